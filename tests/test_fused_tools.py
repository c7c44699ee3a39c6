"""tools/tune_fused.py --json and tools/plot_fused_noise.py (docs/fused.md, "How good the depth must be")."""

from __future__ import annotations

import json

import numpy as np
import pytest

from tool_loader import load_tool


def test_lognormal_absrel_matches_sampling():
    plot = load_tool("plot_fused_noise")
    z = np.random.default_rng(0).standard_normal(2_000_000)
    for s in (0.01, 0.05, 0.2):
        assert plot.lognormal_absrel(s) == pytest.approx(np.mean(np.abs(np.expm1(s * z))), rel=2e-3)
    assert plot.lognormal_absrel(0.01) == pytest.approx(0.01 * np.sqrt(2 / np.pi), rel=1e-2)


def test_tune_fused_json_rows_and_the_noise_plot(tiny_root, tmp_path, capsys):
    tune = load_tool("tune_fused")
    out = tmp_path / "run.json"
    assert tune.main(["--seq", "tiny", "--frames", "0:4", "--data-root", str(tiny_root), "--model", "oracle",
                      "--oracle-sigma", "0.02", "--oracle-edge-sigma", "0", "--oracle-shared-sigma", "0.05",
                      "--keeps", "0.8,1", "--multiview", "0", "--json", str(out)]) == 0
    run = json.loads(out.read_text())
    assert run["setting"]["oracle_sigma"] == 0.02 and run["setting"]["oracle_shared_sigma"] == 0.05
    names = [r["map"].strip() for r in run["rows"]]
    assert names == ["depth-gt", "mono keep 0.8", "mono keep 1", "mono, distribution", "fused multiview 0"]
    assert all(0 <= r["f1"] <= 1 and r["occupied_cells"] >= 0 for r in run["rows"])
    assert run["rows"][0]["f1"] > run["rows"][-1]["f1"] > 0        # exact depth beats noisy depth fused
    plot = load_tool("plot_fused_noise")
    png = tmp_path / "noise.png"
    assert plot.main([str(png), str(out), "--network", f"{out}:0.05"]) == 0
    assert png.stat().st_size > 10_000
    assert "| network oracle | 0.0500 |" in capsys.readouterr().out


@pytest.mark.parametrize("argv, message", [
    (["--keeps", "0,1"], "--keeps"),
    (["--oracle-shared-sigma", "0.1"], "--oracle-shared-sigma: needs --model oracle"),
    (["--model", "oracle", "--oracle-shared-sigma", "2"], "oracle shared_sigma"),
    (["--model", "oracle", "--json", "rows.txt"], "--json: rows.txt: the file name must end in .json"),
])
def test_tune_fused_bad_options_are_one_line(argv, message):
    tune = load_tool("tune_fused")
    with pytest.raises(SystemExit, match=message):
        tune.main(argv)


def test_plot_fused_noise_bad_inputs(tmp_path):
    plot = load_tool("plot_fused_noise")
    bad = tmp_path / "bad.json"
    bad.write_text("{}")
    with pytest.raises(SystemExit, match="bad.json: not a tools/tune_fused.py --json file"):
        plot.main([str(tmp_path / "x.png"), str(bad)])
    unnamed = tmp_path / "unnamed.json"
    unnamed.write_text(json.dumps({"setting": {"oracle_sigma": 0.03}, "rows": []}))
    with pytest.raises(SystemExit, match="unnamed.json: not a tools/tune_fused.py --json file"):
        plot.main([str(tmp_path / "x.png"), str(unnamed)])
    with pytest.raises(SystemExit, match="must end in .png"):
        plot.main([str(tmp_path / "x.jpg"), str(bad)])
    edge = tmp_path / "edge.json"
    edge.write_text(json.dumps({"setting": {"seq": "06", "frames": [0, 9, 10], "oracle_sigma": 0.03,
                                            "oracle_edge_sigma": 0.5}, "rows": []}))
    with pytest.raises(SystemExit, match="edge noise"):
        plot.main([str(tmp_path / "x.png"), str(edge)])
    assert not (tmp_path / "x.png").exists()


def test_shared_error_tool_tells_a_shared_error_from_noise(tiny_root, capsys):
    tool = load_tool("shared_error")
    common = ["--seq", "tiny", "--frames", "0:3", "--gaps", "1", "--data-root", str(tiny_root), "--model", "oracle",
              "--oracle-edge-sigma", "0"]
    assert tool.main(common + ["--oracle-sigma", "0.0001", "--oracle-shared-sigma", "0.05"]) == 0
    shared = capsys.readouterr().out.splitlines()[-1].split("|")
    assert float(shared[4]) > 0.99
    assert tool.main(common + ["--oracle-sigma", "0.05"]) == 0
    independent = capsys.readouterr().out.splitlines()[-1].split("|")
    assert abs(float(independent[4])) < 0.1 and int(independent[2].replace(",", "")) > 500
    with pytest.raises(SystemExit, match="--gaps"):
        tool.main(common + ["--gaps", "0"])
    with pytest.raises(SystemExit, match="needs --model oracle"):
        tool.main(["--oracle-shared-sigma", "0.1"])

