"""tools/compare_integrations.py: a max-range sweep of the keep maps in one pass, and its bad input."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
TOOL = REPO / "tools" / "compare_integrations.py"


def bad_input_line(tmp_path, *args) -> str:
    """The tool on a data root that does not exist: it must stop on ``args`` first, with one line and no
    traceback (the data root is never reached, so the check runs before any work). Returns that line."""
    p = subprocess.run([sys.executable, str(TOOL), "--seq", "tiny", "--data-root", str(tmp_path / "none"), *args],
                       capture_output=True, text=True, cwd=REPO)
    assert p.returncode != 0 and "Traceback" not in p.stderr, p.stderr
    lines = p.stderr.strip().splitlines()
    assert len(lines) == 1, p.stderr
    return lines[0]


def test_bad_max_ranges_one_line_before_any_work(tmp_path):
    for bad, why in (("30,abc", "neither 'none' nor a number"), ("0", "positive number"), ("inf", "positive number")):
        line = bad_input_line(tmp_path, "--max-ranges", bad)
        assert line.startswith("--max-ranges:") and why in line, line


def test_bad_ranks_one_line_before_any_work(tmp_path):
    line = bad_input_line(tmp_path, "--ranks", "entropy,mode")
    assert line.startswith("--ranks: unknown ranking 'mode'"), line


def test_bad_oracle_sigma_one_line_before_any_work(tmp_path):
    for extra in (["--model", "shipped", "--oracle-sigma", "0.05"], ["--model", "oracle", "--oracle-sigma", "0"]):
        line = bad_input_line(tmp_path, *extra)
        assert line.startswith("--oracle-sigma: needs --model oracle"), line


def test_max_range_sweep_builds_each_keep_map_per_range(tiny_root, tmp_path):
    """Every keep map once per max range from one prediction pass; the range-limited map has fewer occupied
    cells (end points beyond the range are not inserted); keep 0.8 at most as many as keep 1.0; a range-limited
    row equals a plain build of the same map with that max_range."""
    out = tmp_path / "out"
    p = subprocess.run([sys.executable, str(TOOL), "--seq", "tiny", "--frames", "0:3", "--data-root", str(tiny_root),
                        "--model", "oracle", "--keeps", "0.8,1.0", "--max-ranges", "none,8", "--keeps-only",
                        "--out", str(out)], capture_output=True, text=True, cwd=REPO)
    assert p.returncode == 0, p.stderr
    rows = {r["method"]: r for r in json.loads(next(out.glob("compare_tiny_*.json")).read_text())["rows"]}
    assert sorted(rows) == ["mono (keep 1.0)", "mono (keep 1.0), max range 8 m", "mono keep 0.8",
                            "mono keep 0.8, max range 8 m"]
    for k in ("mono (keep 1.0)", "mono keep 0.8"):
        assert rows[k]["max_range"] < 0 and rows[k + ", max range 8 m"]["max_range"] == 8.0
        assert 0 < rows[k + ", max range 8 m"]["occupied_cells"] < rows[k]["occupied_cells"]
    assert rows["mono keep 0.8"]["occupied_cells"] <= rows["mono (keep 1.0)"]["occupied_cells"]

    from mono_map.config import OctoMapConfig
    from mono_map.data.kitti import open_sequence
    from mono_map.eval.map_metrics import surface_precision
    from mono_map.mapping.pipeline import build_map
    from mono_map.mapping.jobs import MapJob
    from mono_map.mapping.oracle import NoisyGroundTruthPredictor
    from mono_map.mapping.octree import tree_leaves

    seq = open_sequence(tiny_root, "tiny")
    plain = build_map(seq, MapJob.spec("mono", [0, 1, 2], keep=0.8, octomap=OctoMapConfig(max_range=8.0)),
                      predictor=NoisyGroundTruthPredictor(), show_progress=False)
    surf = build_map(seq, MapJob.spec("depth-gt", [0, 1, 2]), show_progress=False)
    s = surface_precision(tree_leaves(plain.tree), tree_leaves(surf.tree))
    assert s["occupied_cells"] == rows["mono keep 0.8, max range 8 m"]["occupied_cells"]
    assert np.isclose(s["surface_precision"], rows["mono keep 0.8, max range 8 m"]["surface_precision"])


def test_oracle_sigma_is_the_noise_of_the_oracle(tiny_root, tmp_path):
    """--oracle-sigma sets the oracle's log-depth noise: 30 % noise puts fewer of keep 1.0's occupied cells on a
    true surface than the default 3 %; its files carry the sigma in their name."""
    sp = {}
    for extra, tag in (([], ""), (["--oracle-sigma", "0.3"], "_sigma0.3")):
        out = tmp_path / f"out{tag}"
        p = subprocess.run([sys.executable, str(TOOL), "--seq", "tiny", "--frames", "0:2", "--data-root", str(tiny_root),
                            "--model", "oracle", "--keeps", "1.0", "--keeps-only", "--out", str(out)] + extra,
                           capture_output=True, text=True, cwd=REPO)
        assert p.returncode == 0, p.stderr
        f = out / f"compare_tiny_f0-2_oracle{tag}.json"
        sp[tag] = json.loads(f.read_text())["rows"][0]["surface_precision"]
    assert sp["_sigma0.3"] < sp[""] - 0.05
