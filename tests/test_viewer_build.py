"""A short real build (tiny synthetic sequence, LiDAR-FOV source) streamed to an .rrd."""

from __future__ import annotations

import numpy as np

from mono_map.viz.codec import cell_indices, occupied_cells_from_bt
from mono_map.viz.rerun_stream import RerunMapLogger
from mono_map.viz.stream_options import StreamOptions
from rrd_readback import map_cells_at, read_recording


def test_short_build_writes_recording_with_expected_paths_and_frames(tiny_root, tmp_path):
    from mono_map.data.kitti import open_sequence
    from mono_map.mapping.pipeline import build_map
    from mono_map.mapping.jobs import MapJob
    from mono_map.mapping.octree import write_tree_bt

    seq = open_sequence(tiny_root, "tiny")
    frames = list(range(min(4, len(seq))))
    rrd = tmp_path / "build.rrd"
    logger = RerunMapLogger(rrd=rrd, options=StreamOptions(resolution=0.2, image_size=seq.image_size))
    result = build_map(seq, MapJob.spec("lidar-fov", frames), observers=[logger], show_progress=False)
    assert rrd.is_file(), "build_map closes its observers: the recording must be complete"

    rows = read_recording(rrd)
    for p in ("/world/camera", "/world/points", "/world/trajectory/seg_0000",
              "/stats/frames_per_s", "/stats/memory_mb", "/stats/leaf_count", "/stats/kept_fraction"):
        assert p in rows, p
    assert "/frame/depth" not in rows  # a LiDAR source has no predicted depth
    # leaf count / memory only where measured (first and last frame here, stats_every 100): no stale values
    assert sorted(f for f, _ in rows["/stats/leaf_count"] if f is not None) == [frames[0], frames[-1]]
    assert sorted(f for f, _ in rows["/stats/frames_per_s"] if f is not None) == frames
    if "/world/camera/image" in rows:  # LiDAR builds may or may not pass image_2 along
        assert sorted(f for f, _ in rows["/world/camera/image"]) == frames
    pinhole = [e for _, e in rows["/world/camera"] if e.get("Pinhole:resolution")]
    assert len(pinhole) == 1 and pinhole[0]["Pinhole:resolution"][0] == [seq.image_size[1], seq.image_size[0]]
    assert sorted(f for f, _ in rows["/world/points"]) == frames
    assert any(p.startswith("/world/map/occupied/b") for p in rows)
    # the camera pose logged for the last frame is the sequence's T_world_cam2
    last = max((r for r in rows["/world/camera"] if r[1].get("Transform3D:translation")), key=lambda r: r[0])
    assert np.allclose(last[1]["Transform3D:translation"][0], seq.T_world_cam2(frames[-1])[:3, 3], atol=1e-4)

    # The streamed map at the last frame is exactly the finished map's occupied cells.
    bt = tmp_path / "map.bt"
    write_tree_bt(result.tree, bt)
    centres, res = occupied_cells_from_bt(bt)
    expected = {tuple(c) for c in cell_indices(centres, res).tolist()}
    assert len(expected) > 100
    assert map_cells_at(rows, frames[-1], res) == expected


def test_build_cli_rrd_uses_the_build_resolution(tiny_root, tmp_path):
    """`mono-map build --rrd` at --res 0.4: the streamed cells are the written map's 0.4 m cells."""
    from mono_map.cli import main as cli_main

    rrd = tmp_path / "cli.rrd"
    code = cli_main(["build", "--seq", "tiny", "--data-root", str(tiny_root), "--source", "lidar-fov",
                     "--frames", "0:3", "--res", "0.4", "--out", str(tmp_path), "--name", "m", "--rrd", str(rrd)])
    assert code == 0 and rrd.is_file()
    rows = read_recording(rrd)
    assert sorted(f for f, e in rows["/world/camera"] if e.get("Transform3D:translation")) == [0, 1, 2]
    centres, res = occupied_cells_from_bt(tmp_path / "m.bt")
    assert res == 0.4
    assert map_cells_at(rows, 2, res) == {tuple(c) for c in cell_indices(centres, res).tolist()}
