"""tools/archive/surface_by_distance.py: distances to the path, the per-bin table, bad input in one line."""

import subprocess
import sys
from pathlib import Path

import numpy as np
from tool_loader import load_tool, script_path

REPO = Path(__file__).resolve().parents[1]
TOOL = script_path("surface_by_distance")


def _tool():
    return load_tool("surface_by_distance")


def test_distance_to_the_path_and_the_table():
    t = _tool()
    path = np.array([[0.0, 0.0], [0.0, 10.0]])
    xz = np.array([[3.0, 4.0], [0.0, 25.0], [-5.0, 10.0]])
    np.testing.assert_allclose(t.path_distance(xz, path, chunk=2), [5.0, 15.0, 5.0])
    near = {"m": np.array([True, False, False])}
    md = t.table("distance (m)", (0, 10, 20), {"m": np.array([5.0, 15.0, 5.0])}, near)
    assert "| 0–10 | 2 / 50.0 |" in md and "| 10–20 | 1 / 0.0 |" in md and "| all | 3 / 33.3 |" in md


def test_bad_input_one_line(tmp_path):
    for args, msg in ((["--surface", str(tmp_path / "gt.bt"), "nameless.bt"], "expected NAME=MAP.bt"),
                      (["--surface", str(tmp_path / "gt.bt"), f"a={tmp_path / 'a.bt'}"], "no such map")):
        p = subprocess.run([sys.executable, str(TOOL), *args], capture_output=True, text=True, cwd=REPO)
        lines = p.stderr.strip().splitlines()
        assert p.returncode != 0 and len(lines) == 1 and msg in lines[0], p.stderr


def test_maps_of_another_resolution_than_the_surface_one_line(tiny_root, tmp_path):
    import octomap

    for res, name in ((0.2, "gt.bt"), (0.4, "a.bt")):
        tree = octomap.OcTree(res)
        tree.updateNode(np.array([1.0, 0.0, 5.0]), True)
        tree.writeBinary(str(tmp_path / name).encode())
    p = subprocess.run([sys.executable, str(TOOL), "--seq", "tiny", "--frames", "0:3", "--data-root", str(tiny_root),
                        "--surface", str(tmp_path / "gt.bt"), f"a={tmp_path / 'a.bt'}"],
                       capture_output=True, text=True, cwd=REPO)
    lines = p.stderr.strip().splitlines()
    assert p.returncode != 0 and len(lines) == 1 and "a.bt: 0.4 m cells" in lines[0], p.stderr
