"""Rerun viewer: RerunMapLogger recordings read back with rerun's own reader; `mono-map view`."""

from __future__ import annotations

import types

import numpy as np
import pytest

from mono_map.cli import main as cli_main
from mono_map.errors import MonoMapError
from mono_map.viz.codec import cell_indices, pack, unpack
from mono_map.viz.rerun_stream import RerunMapLogger
from mono_map.viz.stream_options import StreamOptions
from rrd_readback import latest_map_rows, map_cells_at, read_recording, voxel_cells

RES = 0.2
H, W = 24, 80
K = np.array([[60.0, 0.0, 40.0], [0.0, 60.0, 12.0], [0.0, 0.0, 1.0]])


# ----------------------------------------------------------------------------- helpers


def centres(cells):
    return (np.asarray(sorted(cells), dtype=np.float64).reshape(-1, 3) + 0.5) * RES


def make_update(i, added, freed, rng):
    T = np.eye(4)
    T[:3, 3] = [0.0, 0.0, 1.5 * i]
    return types.SimpleNamespace(
        index=i, time=0.1 * i,
        image=rng.integers(0, 255, (H, W, 3), dtype=np.uint8),
        depth=rng.uniform(1, 80, (H, W)).astype(np.float32),
        entropy=rng.uniform(0, 4, (H, W)).astype(np.float32),
        keep_mask=rng.random((H, W)) < 0.8,
        K=K, T_world_cam2=T, points_world=rng.normal(size=(300, 3)) + T[:3, 3], origin=T[:3, 3],
        occupied_keys_changed=centres(added), freed_keys_changed=centres(freed),
        stats=dict(frames_per_s=3.0, memory_mb=1.0 + i, leaf_count=100 + 10 * i, mean_entropy=2.0 - 0.1 * i,
                   kept_fraction=0.8, n_points=300),
    )


def scripted_changes():
    """Per-frame (added, freed) cell sets and the expected map after each frame (a plain set model)."""
    rng = np.random.default_rng(7)
    state, script, expected = set(), [], []
    far_block = {(200, -5, 300), (201, -5, 300)}  # a block only frame 0 and frame 3 touch
    for i in range(5):
        pool = {tuple(c) for c in rng.integers([-40, -10, 5 * i], [40, 10, 5 * i + 60], (400, 3)).tolist()}
        added = pool - state
        freed = set(sorted(state - far_block)[:: 7]) - added if i else set()
        if i == 0:
            added |= far_block
        if i == 3:
            freed |= far_block  # empties that block: must become a Clear
        freed -= {c for c in added}
        state = (state | added) - freed
        script.append((added, freed))
        expected.append(set(state))
    return script, expected


# ----------------------------------------------------------------------------- logger


def test_pack_roundtrip_with_negative_indices():
    idx = np.array([[-5, 0, 7], [0, -1, 0], [1 << 19, -(1 << 19), 3]])
    assert np.array_equal(unpack(pack(idx)), idx)
    c = (idx + 0.5) * RES
    assert np.array_equal(cell_indices(c, RES), idx)
    with pytest.raises(MonoMapError):
        pack(np.array([[1 << 21, 0, 0]]))


def test_logger_writes_incremental_map_that_reads_back(tmp_path):
    script, expected = scripted_changes()
    rrd = tmp_path / "rec.rrd"
    rng = np.random.default_rng(0)
    logger = RerunMapLogger(rrd=rrd, options=StreamOptions(resolution=RES, block_cells=16))
    for i, (added, freed) in enumerate(script):
        logger(make_update(i, added, freed, rng))
        assert not rrd.exists(), "the recording must appear only when complete"
    logger.close()
    assert rrd.stat().st_size > 0

    rows = read_recording(rrd)
    paths = set(rows)
    for p in ("/world", "/world/camera", "/world/camera/image", "/frame/depth", "/frame/entropy",
              "/frame/kept_mask", "/world/points", "/world/trajectory/seg_0000", "/stats/frames_per_s",
              "/stats/memory_mb", "/stats/leaf_count", "/stats/mean_entropy", "/stats/kept_fraction",
              "/stats/map_cells"):
        assert p in paths, p
    n = len(script)
    for p in ("/world/camera/image", "/frame/depth", "/frame/entropy", "/frame/kept_mask", "/world/points"):
        assert sorted(f for f, _ in rows[p]) == list(range(n)), p
    assert sorted(f for f, e in rows["/world/camera"] if e.get("Transform3D:translation")) == list(range(n))
    # the time timeline carries the sequence timestamps (ns durations)
    times = sorted(e["time"] for _, e in rows["/world/camera/image"])
    assert np.allclose([t.total_seconds() for t in times], 0.1 * np.arange(n))
    # stats: one value per frame
    vals = [e["Scalars:scalars"][0] for f, e in sorted(rows["/stats/leaf_count"], key=lambda r: r[0] or -1)
            if f is not None]
    assert vals == [100 + 10 * i for i in range(n)]

    # The union of block entities, latest-at, equals the true map after every frame.
    for i in range(n):
        assert map_cells_at(rows, i, RES) == expected[i], f"map differs after frame {i}"
    # Untouched blocks are not re-sent: the far block has rows only at frames 0 and 3 (clear).
    far = [p for p in paths if p.startswith("/world/map/occupied/b12_-1_18")]
    assert far == ["/world/map/occupied/b12_-1_18"]
    far_rows = sorted(rows[far[0]], key=lambda r: r[0])
    assert [f for f, _ in far_rows] == [0, 3]
    assert far_rows[1][1].get("Clear:is_recursive") is not None
    # Each frame sends far fewer cells than "whole map every frame" would.
    total_map = sum(len(s) for s in expected)
    assert logger.cells_logged < total_map
    assert logger.map_cells == len(expected[-1])


def test_logger_map_every_batches_and_close_flushes(tmp_path):
    script, expected = scripted_changes()
    rrd = tmp_path / "batched.rrd"
    rng = np.random.default_rng(1)
    with RerunMapLogger(rrd=rrd, options=StreamOptions(resolution=RES, block_cells=16, map_every=2)) as logger:
        for i, (added, freed) in enumerate(script):
            logger(make_update(i, added, freed, rng))
    rows = read_recording(rrd)
    map_frames = {f for p, es in rows.items() if p.startswith("/world/map/") for f, _ in es}
    assert map_frames == {1, 3, 4}  # every 2nd frame, plus the final flush at the last frame
    assert map_cells_at(rows, 4, RES) == expected[-1]
    assert map_cells_at(rows, 1, RES) == expected[1]


def test_logger_without_depth_or_images_and_with_reference_map(tmp_path, small_bt):
    bt, cells = small_bt
    rrd = tmp_path / "lidar.rrd"
    logger = RerunMapLogger(rrd=rrd, reference_map=bt, options=StreamOptions(resolution=RES))
    rng = np.random.default_rng(2)
    u = make_update(0, {(1, 2, 3)}, set(), rng)
    u.depth = u.entropy = u.keep_mask = None  # a LiDAR source
    logger(u)
    logger.close()
    rows = read_recording(rrd)
    assert "/frame/depth" not in rows and "/frame/entropy" not in rows
    ref = rows["/world/reference_map"]
    assert len(ref) == 1 and ref[0][0] is None  # static
    assert voxel_cells(ref[0][1], RES) == cells
    assert logger.reference_cells == len(cells)


def test_logger_rejects_bad_options(tmp_path):
    with pytest.raises(MonoMapError, match="--rrd"):
        RerunMapLogger(rrd=None, spawn=False)
    with pytest.raises(MonoMapError, match="cells"):
        RerunMapLogger(rrd=tmp_path / "x.rrd", options=StreamOptions(cells="spheres"))
    with pytest.raises(MonoMapError, match="nope.bt"):
        RerunMapLogger(rrd=tmp_path / "x.rrd", reference_map=tmp_path / "nope.bt")


def test_logger_rejects_cells_of_another_resolution(tmp_path):
    # the "build" below uses 0.2 m cells
    logger = RerunMapLogger(rrd=tmp_path / "r.rrd", options=StreamOptions(resolution=0.1))
    with pytest.raises(MonoMapError, match="resolution"):
        logger(make_update(0, {(1, 2, 3), (4, 5, 6)}, set(), np.random.default_rng(5)))
    logger.abort()


def test_aborted_logger_leaves_no_file(tmp_path):
    rrd = tmp_path / "aborted.rrd"
    with pytest.raises(RuntimeError):
        with RerunMapLogger(rrd=rrd) as logger:
            logger(make_update(0, {(0, 0, 0)}, set(), np.random.default_rng(3)))
            raise RuntimeError("build failed")
    assert not rrd.exists()
    assert not list(tmp_path.iterdir())


# ----------------------------------------------------------------------------- mono-map view


@pytest.fixture
def small_bt(tmp_path):
    """A .bt with a ground patch, a wall and an aligned 8×8×8-cell cube OctoMap prunes into one node."""
    import octomap

    ground = {(x, 8, z) for x in range(-10, 10) for z in range(0, 30)}
    wall = {(x, y, 50) for x in range(-10, 10) for y in range(-8, 8)}
    cube = {(16 + x, -16 + y, 16 + z) for x in range(8) for y in range(8) for z in range(8)}
    cells = ground | wall | cube
    tree = octomap.OcTree(RES)
    tree.updateNodes(centres(cells), True)
    tree.updateInnerOccupancy()
    path = tmp_path / "small.bt"
    assert tree.writeBinary(str(path).encode())
    check = octomap.OcTree(RES)
    check.readBinary(str(path).encode())
    assert check.getNumLeafNodes() < len(cells)  # the cube really was pruned
    return path, cells


def test_view_bt_save_writes_valid_rrd(tmp_path, small_bt, capsys):
    bt, cells = small_bt
    out = tmp_path / "view.rrd"
    assert cli_main(["view", str(bt), "--save", str(out)]) == 0
    rows = read_recording(out)
    got = set()
    for p, es in rows.items():
        if p.startswith("/world/map/occupied/"):
            assert len(es) == 1 and es[0][0] is None  # static
            got |= voxel_cells(es[0][1], RES)
    assert got == cells  # pruned nodes expanded back to finest cells, nothing lost or invented
    assert "/world" in rows
    assert f"{len(cells)} occupied cells" in capsys.readouterr().err

    # a saved recording opens through `view --save` again (validated copy)
    again = tmp_path / "again.rrd"
    assert cli_main(["view", str(out), "--save", str(again)]) == 0
    assert again.read_bytes() == out.read_bytes()


def test_view_without_display_asks_for_save(tmp_path, small_bt, monkeypatch, capsys):
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    assert cli_main(["view", str(small_bt[0])]) == 2
    assert "--save" in capsys.readouterr().err


@pytest.mark.parametrize("case", ["missing", "suffix", "corrupt_rrd", "corrupt_bt", "bad_save"])
def test_view_bad_paths_give_one_line_errors(tmp_path, case, small_bt, capsys):
    if case == "missing":
        target, extra = tmp_path / "nothing.rrd", []
    elif case == "suffix":
        target, extra = tmp_path / "map.txt", []
        target.write_text("x")
    elif case == "corrupt_rrd":
        target, extra = tmp_path / "broken.rrd", ["--save", str(tmp_path / "o.rrd")]
        target.write_bytes(b"not a recording at all")
    elif case == "corrupt_bt":
        target, extra = tmp_path / "broken.bt", ["--save", str(tmp_path / "o.rrd")]
        target.write_bytes(b"# Octomap OcTree binary file\ngarbage")
    else:
        target, extra = small_bt[0], ["--save", str(tmp_path / "o.png")]
    assert cli_main(["view", str(target)] + extra) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("mono-map: error: ") and "\n" not in err and "Traceback" not in err
    named = "o.png" if case == "bad_save" else target.name
    assert named in err
    assert not (tmp_path / "o.rrd").exists()


def test_close_during_an_exception_discards_the_recording(tmp_path):
    """build_map closes observers in `finally`: a failing build must not leave a partial .rrd."""
    rrd = tmp_path / "failed.rrd"
    logger = RerunMapLogger(rrd=rrd)
    logger(make_update(0, {(0, 0, 0)}, set(), np.random.default_rng(4)))
    with pytest.raises(ValueError):
        try:
            raise ValueError("frame 1: empty frame")
        finally:
            logger.close()
    assert not rrd.exists() and not list(tmp_path.iterdir())


# ----------------------------------------------------------------------------- colour by probability


def test_logger_colours_cells_by_occupancy_probability(tmp_path):
    """colour="probability": every drawn cell carries its latest probability, also when only its
    probability changed (its block is re-logged then); free cells in the update are ignored."""
    from mono_map.viz.codec import PROBABILITY_RANGE

    rng = np.random.default_rng(11)
    prob: dict = {}
    rrd = tmp_path / "prob.rrd"
    logger = RerunMapLogger(rrd=rrd, options=StreamOptions(resolution=RES, block_cells=16, colour="probability"))
    expected = []
    for i in range(4):
        if i == 2:   # only probabilities of occupied cells change: no cell appears or disappears
            cells = sorted(c for c, p in prob.items() if p >= 0.5)[:50]
            new = {c: float(rng.uniform(0.5, 1.0)) for c in cells}
        else:
            cells = {tuple(c) for c in rng.integers([-30, -5, 0], [30, 5, 60], (300, 3)).tolist()}
            new = {c: float(rng.uniform(0.0, 1.0)) for c in cells}
        before = {c for c, p in prob.items() if p >= 0.5}
        prob.update(new)
        after = {c for c, p in prob.items() if p >= 0.5}
        u = make_update(i, after - before, before - after, rng)
        u.updated_cells = centres(new)
        u.updated_probability = np.array([new[c] for c in sorted(new)], dtype=np.float32)
        logger(u)
        expected.append({c: np.float32(prob[c]) for c in after})
    logger.close()

    rows = read_recording(rrd)
    for i, want in enumerate(expected):
        shown = {}
        for row in latest_map_rows(rows, i).values():
            assert row["VoxelGridMap:value_range"][0] == list(PROBABILITY_RANGE)
            cells = np.asarray(row["VoxelGridMap:voxel_indices"]).reshape(-1, 3) + np.round(
                np.asarray(row["VoxelGridMap:translation"][0]) / RES).astype(np.int64)
            shown.update(zip(map(tuple, cells.tolist()), row["VoxelGridMap:values"]))
        assert set(shown) == set(want), f"cells differ after frame {i}"
        assert all(np.isclose(shown[c], want[c]) for c in want), f"probabilities differ after frame {i}"
    # frame 2 changed no occupancy, yet re-logged the blocks of the cells whose probability changed
    assert any(f == 2 for p, es in rows.items() if p.startswith("/world/map/") for f, _ in es)


def test_probability_colours_match_the_point_style(tmp_path):
    from mono_map.viz.codec import probability_colours

    rrd = tmp_path / "pts.rrd"
    logger = RerunMapLogger(rrd=rrd, options=StreamOptions(resolution=RES, cells="points", colour="probability"))
    u = make_update(0, {(1, 2, 3), (4, 5, 6)}, set(), np.random.default_rng(12))
    u.updated_cells, u.updated_probability = centres({(1, 2, 3), (4, 5, 6)}), np.array([0.55, 0.95])
    logger(u)
    logger.close()
    (row,) = [e for p, es in read_recording(rrd).items() if p.startswith("/world/map/") for _, e in es]
    got = np.array(row["Points3D:colors"], dtype=np.uint32)
    want = probability_colours(np.array([0.55, 0.95]))
    packed = (want[:, 0].astype(np.uint32) << 24) | (want[:, 1].astype(np.uint32) << 16) | (
        want[:, 2].astype(np.uint32) << 8) | 255
    assert np.array_equal(got, packed)
    assert not np.array_equal(want[0], want[1])  # the scale tells 0.55 from 0.95


def test_probability_colour_needs_probabilities(tmp_path):
    logger = RerunMapLogger(rrd=tmp_path / "p.rrd", options=StreamOptions(resolution=RES, colour="probability"))
    with pytest.raises(MonoMapError, match="updated_probability"):
        logger(make_update(0, {(1, 2, 3)}, set(), np.random.default_rng(13)))
    logger.abort()
    with pytest.raises(MonoMapError, match="colour"):
        RerunMapLogger(rrd=tmp_path / "q.rrd", options=StreamOptions(colour="rainbow"))
    assert not list(tmp_path.iterdir())
