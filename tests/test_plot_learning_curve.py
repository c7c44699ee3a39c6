"""tools/plot_learning_curve.py: the picture of validation curves, a run drawn after its parent, bad input."""

import json
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
TOOL = REPO / "tools" / "plot_learning_curve.py"


def _run_dir(root: Path, name: str, hours: list[float]) -> Path:
    d = root / name
    d.mkdir()
    rows = [{"step": 1000 * (i + 1), "cpu_hours": h, "abs_rel": 0.2 - 0.01 * i, "delta1": 0.8 + 0.01 * i,
             "auc_are": 0.1, "sky_beyond_acc": None} for i, h in enumerate(hours)]
    (d / "curve.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
    return d


def test_picture_and_a_continued_run(tmp_path):
    a = _run_dir(tmp_path, "parent", [0.1, 0.2, 0.3])
    b = _run_dir(tmp_path, "child", [0.1, 0.2])
    out = tmp_path / "curve.png"
    p = subprocess.run([sys.executable, str(TOOL), str(a), str(b), "--continues", "child=parent", "--out", str(out)],
                       capture_output=True, text=True, cwd=REPO)
    assert p.returncode == 0, p.stderr
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and out.stat().st_size > 10_000


def _png_height(path: Path) -> int:
    return int.from_bytes(path.read_bytes()[20:24], "big")     # the IHDR chunk: width, then height


def test_rows_of_runs_stack_panels(tmp_path):
    a = _run_dir(tmp_path, "a", [0.1, 0.2])
    b = _run_dir(tmp_path, "b", [0.1, 0.2])
    one, two = tmp_path / "one.png", tmp_path / "two.png"
    for out, rows in ((one, []), (two, ["--row", "first=a,b", "--row", "second=b"])):
        p = subprocess.run([sys.executable, str(TOOL), str(a), str(b), *rows, "--out", str(out)],
                           capture_output=True, text=True, cwd=REPO)
        assert p.returncode == 0, p.stderr
    assert _png_height(two) > 1.8 * _png_height(one)


def test_bad_input_is_one_line(tmp_path):
    a = _run_dir(tmp_path, "parent", [0.1, 0.2])
    for extra, needle in (([str(tmp_path / "nope")], "no such file"),
                          ([str(a), "--continues", "child=parent"], "--continues child=parent"),
                          ([str(a), "--row", "heads=parent,other"], "unknown: other"),
                          ([str(a), "--row", "parent"], "--row parent")):
        p = subprocess.run([sys.executable, str(TOOL), *extra, "--out", str(tmp_path / "x.png")],
                           capture_output=True, text=True, cwd=REPO)
        assert p.returncode != 0 and needle in p.stderr and "Traceback" not in p.stderr
        assert not (tmp_path / "x.png").exists()
