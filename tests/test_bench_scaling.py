"""benchmarks/bench_scaling.py: the growth exponents and ratios it reports, its report files, its bad input."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
from tool_loader import load_tool, script_path

REPO = Path(__file__).resolve().parents[1]
TOOL = script_path("bench_scaling")


def _tool():
    return load_tool("bench_scaling")


def _run(source, n, build_s, rss, map_mb, frame_s):
    return {"source": source, "n_frames": n, "build_s": build_s, "frames_per_s": n / build_s, "cpu_s": build_s,
            "peak_rss_mb": rss, "map_mb": map_mb, "leaves": 10 * n, "load_start": 1.0, "load_end": 1.0,
            "frame_s": frame_s, "process_wall_s": build_s + 1}


def test_exponents_ratios_and_report(tmp_path):
    bs = _tool()
    n = np.array([500, 1000, 2000, 4541.0])
    assert abs(bs.loglog_slope(n, 0.3 * n) - 1.0) < 1e-9
    assert abs(bs.loglog_slope(n, 0.3 * n ** 2) - 2.0) < 1e-9
    assert abs(bs.tail_ratio([0.2] * 100) - 1.0) < 1e-12
    growing = list(np.linspace(0.1, 1.0, 100))
    assert bs.tail_ratio(growing) > 3                      # per-frame cost growing with the map
    results = {"lidar-fov:1": _run("lidar-fov", 1, 0.5, 80.0, 5.0, [0.5])}
    for k in n.astype(int):
        results[f"lidar-fov:{k}"] = _run("lidar-fov", int(k), 0.2 * k, 3.0 * k / 10, k / 10, [0.2] * int(k))
    text = bs.table(results)
    assert "| lidar-fov | 4,541 |" in text and "| 3.00 |" in text      # RSS / map
    assert "frames^1.00 (wall)" in text and "1-frame build peak RSS 80 MB" in text
    bs.write_report(tmp_path, results)
    assert (tmp_path / "scaling.md").read_text() == text and (tmp_path / "scaling.png").stat().st_size > 0
    path = tmp_path / "scaling.json"
    bs.save_result(path, "a:1", {"x": 1})
    assert bs.save_result(path, "b:2", {"x": 2}) == {"a:1": {"x": 1}, "b:2": {"x": 2}}
    assert json.loads(path.read_text())["a:1"] == {"x": 1}


def test_bad_sizes_and_missing_sequence(tmp_path):
    for extra, needle in ((["--sizes", "500,x"], "--sizes"), (["--sizes", "0"], "--sizes"),
                          ([], "no such sequence directory")):
        p = subprocess.run([sys.executable, str(TOOL), "--data-root", str(tmp_path), "--out", str(tmp_path / "o")]
                           + extra, capture_output=True, text=True)
        assert p.returncode != 0 and needle in p.stderr and "Traceback" not in p.stderr
