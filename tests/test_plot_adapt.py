"""tools/plot_adapt.py changes: which pixels' δ1 failures an adapted model adds or fixes, and the picture."""

import numpy as np

from tool_loader import load_tool


def test_failure_changes_classify_each_pixel():
    tool = load_tool("plot_adapt")
    gt = np.array([[10.0, 10.0, 10.0, 10.0, 10.0, 0.0]])
    before = np.array([[10.0, 10.0, 20.0, 20.0, 10.0, 10.0]])
    after = np.array([[7.0, 14.0, 10.0, 5.0, 11.0, 1.0]])
    ch = tool.failure_changes(gt, before, after)
    assert ch["new, too near"].tolist() == [[True, False, False, False, False, False]]
    assert ch["new, too far"].tolist() == [[False, True, False, False, False, False]]
    assert ch["fixed"].tolist() == [[False, False, True, False, False, False]]
    assert ch["failing in both"].tolist() == [[False, False, False, True, False, False]]
    # no ground truth (last pixel): in none of them
    assert not any(m[0, 5] for m in ch.values())


def test_changes_picture_and_bad_input(tiny_root, tmp_path, capsys):
    tool = load_tool("plot_adapt")
    out = tmp_path / "c.png"
    base = ["changes", "--seq", "tiny", "--data-root", str(tiny_root), "--frames", "0,3", "--out", str(out)]
    assert tool.main(base + ["--model", "binary", "--model", "v2/binary-wide-12000"]) == 0
    assert out.stat().st_size > 10_000
    capsys.readouterr()
    assert tool.main(base + ["--model", "binary"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--model" in err[0]
