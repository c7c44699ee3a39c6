"""Geometry, selection and the build/eval commands on the tiny synthetic sequence; bad inputs."""

from __future__ import annotations

import dataclasses
import json
import os
import shutil

import numpy as np
import pytest

from mono_map import geometry
from mono_map.cli import main as cli_main
from mono_map.config import OctoMapConfig
from mono_map.data.kitti import open_sequence
from mono_map.depth.inference import DepthPrediction
from mono_map.errors import MonoMapError
from mono_map.mapping.pipeline import build_map
from mono_map.mapping.integrate import MapIntegrator
from mono_map.mapping.jobs import MapJob, reusable
from mono_map.mapping.publish import build_and_write
from mono_map.mapping.oracle import NoisyGroundTruthPredictor
from mono_map.mapping import points
from mono_map.mapping.points import camera_origin, in_camera_fov, lidar_to_world, pixels_to_world
from mono_map.mapping.select import confidence_score, select_pixels

K = np.array([[700.0, 0, 600.0], [0, 700.0, 180.0], [0, 0, 1]])


def test_backprojection_inverts_projection():
    rng = np.random.default_rng(0)
    H, W = 40, 60
    depth = rng.uniform(1, 80, (H, W)).astype(np.float32)
    mask = rng.random((H, W)) < 0.5
    pts = pixels_to_world(depth, mask, K, np.eye(4))
    uv, z = geometry.project_points(K, pts)
    v, u = np.nonzero(mask)
    assert np.allclose(uv, np.stack([u, v], 1), atol=1e-6)
    assert np.allclose(z, depth[mask], rtol=1e-6)


def test_compiled_backprojection_gives_the_numpy_bits(monkeypatch):
    """The compiled pixels_to_world: raster order and numpy's float64 bits (skewed K, a rotated and far
    translated pose, a ragged mask); float64 depth and MONO_MAP_NO_C=1 take the numpy path, same result."""
    if points.library() is None:
        assert shutil.which(os.environ.get("CC", "cc")) is None, "a C compiler is here but the kernel did not build"
        pytest.skip("no C compiler on this machine: only the numpy back-projection exists")
    rng = np.random.default_rng(3)
    depth = rng.uniform(0.5, 90, (37, 53)).astype(np.float32)
    mask = rng.random(depth.shape) < 0.6
    Ks = K.copy()
    Ks[0, 1] = 0.7
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    T = geometry.make_pose(q, rng.normal(size=3) * 300)
    ref = points.pixels_to_world_numpy(depth, mask, Ks, T)
    got = pixels_to_world(depth, mask, Ks, T)
    assert got.shape == (mask.sum(), 3) and got.dtype == np.float64
    assert np.array_equal(got, ref)                       # bit for bit, not allclose
    assert np.array_equal(pixels_to_world(depth.astype(np.float64), mask, Ks, T), ref)
    assert pixels_to_world(depth, np.zeros_like(mask), Ks, T).shape == (0, 3)
    with pytest.raises(ValueError, match="one H×W shape"):
        pixels_to_world(depth, mask[:, :-1], Ks, T)
    monkeypatch.setenv("MONO_MAP_NO_C", "1")
    assert points.library() is None
    assert np.array_equal(pixels_to_world(depth, mask, Ks, T), ref)


def test_compiled_lidar_to_world_gives_the_numpy_points(monkeypatch):
    """The compiled lidar_to_world: the same points in the same order and bits as the numpy form, with
    non-finite points, points behind image_2 and outside its view in the scan; with and without fov_only."""
    if points.library() is None:
        assert shutil.which(os.environ.get("CC", "cc")) is None, "a C compiler is here but the kernel did not build"
        pytest.skip("no C compiler on this machine: only the numpy form exists")
    rng = np.random.default_rng(5)
    scan = np.concatenate([rng.uniform(-60, 60, (4000, 4)), rng.uniform(2, 40, (2000, 4)) * [1, 0.2, 0.05, 1]])
    scan = scan.astype(np.float32)
    scan[::97, 1] = np.nan
    scan[::131, 2] = np.inf
    T_cam2_velo = geometry.make_pose(np.array([[0, -1, 0], [0, 0, -1], [1, 0, 0]], float), [0.06, -0.08, -0.27])
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    T_world_cam2 = geometry.make_pose(q, rng.normal(size=3) * 200)
    for fov in (True, False):
        got, origin = lidar_to_world(scan, T_world_cam2, T_cam2_velo, fov_only=fov, K=K, image_size=(360, 1200))
        ref, ref_origin = points.lidar_to_world_numpy(scan, T_world_cam2, T_cam2_velo, fov, K, (360, 1200))
        assert np.array_equal(got, ref) and np.array_equal(origin, ref_origin)
        assert 0 < len(got) < len(scan) and np.isfinite(got).all()
    in_view = lidar_to_world(scan, T_world_cam2, T_cam2_velo, fov_only=True, K=K, image_size=(360, 1200))[0]
    assert 500 < len(in_view) < 3000            # the forward band is mostly in view, the cube mostly not
    monkeypatch.setenv("MONO_MAP_NO_C", "1")
    assert np.array_equal(lidar_to_world(scan, T_world_cam2, T_cam2_velo, fov_only=True, K=K,
                                         image_size=(360, 1200))[0], in_view)


def test_hand_built_pose_places_point():
    # camera 2 m above the world origin looking along world +x: cam z -> world x, cam x -> world -y,
    # cam y (down) -> world -z
    R = np.array([[0, 0, 1], [-1, 0, 0], [0, -1, 0]], dtype=float)
    T = geometry.make_pose(R, [0, 0, 2.0])
    depth = np.zeros((360, 1200), np.float32)
    depth[180, 600] = 10.0            # principal point
    depth[180, 670] = 10.0            # 70 px right = 1 m right at 10 m
    mask = depth > 0
    pts = pixels_to_world(depth, mask, K, T)
    assert np.allclose(pts, [[10, 0, 2], [10, -1, 2]], atol=1e-9)
    assert np.allclose(camera_origin(T), [0, 0, 2])


def test_lidar_fov_and_origin():
    T_cam2_velo = geometry.make_pose(np.array([[0, -1, 0], [0, 0, -1], [1, 0, 0]], float), [0.1, -0.2, -0.3])
    scan = np.array([[10, 0, 0, 1], [-10, 0, 0, 1], [10, 30, 0, 1]], np.float32)  # ahead, behind, far left
    ok = in_camera_fov(scan, T_cam2_velo, K, 360, 1200)
    assert ok.tolist() == [True, False, False]
    T_world_cam2 = geometry.make_pose(None, [5, 0, 0])
    pts, origin = lidar_to_world(scan, T_world_cam2, T_cam2_velo, fov_only=True, K=K, image_size=(360, 1200))
    assert len(pts) == 1
    assert np.allclose(origin, (T_world_cam2 @ T_cam2_velo)[:3, 3])


def test_wall_ten_metres_ahead():
    """A wall 10 m ahead: free cells before it, occupied at it, unknown behind."""
    H, W = 360, 1200
    depth = np.full((H, W), 10.0, np.float32)
    mask = np.zeros((H, W), bool)
    mask[150:210:4, 560:640:4] = True
    integ = MapIntegrator(OctoMapConfig(resolution=0.2))
    T = geometry.make_pose(None, [0.05, 0.03, 0.07])
    pts = pixels_to_world(depth, mask, K, T)
    integ.insert(pts, camera_origin(T))
    z = np.arange(0.5, 12.0, 0.2) + 0.07
    labels = integ.tree.getLabels(np.stack([np.full_like(z, 0.05), np.full_like(z, 0.03), z], 1))
    assert (labels[z < 9.8] == 0).all()
    assert labels[np.argmin(np.abs(z - 10.07))] == 1
    assert (labels[z > 10.4] == -1).all()


@pytest.mark.parametrize("keep", [0.3, 0.8, 1.0, 0.123])
def test_keep_fraction_exact(keep):
    rng = np.random.default_rng(1)
    depth = rng.uniform(0.5, 90, (50, 70)).astype(np.float32)
    depth[0, :10] = np.nan
    entropy = rng.random((50, 70)).astype(np.float32)
    kept, valid = select_pixels(depth, entropy, keep, 1.0, 80.0, return_valid=True)
    assert kept.sum() == round(keep * valid.sum())
    assert not (kept & ~valid).any()
    if keep < 1:  # the kept pixels are the lowest-entropy ones
        assert entropy[kept].max() <= entropy[valid & ~kept].min()
    kept2 = select_pixels(depth, entropy, keep, 1.0, 80.0, stride=3)
    grid = np.zeros_like(kept2)
    grid[::3, ::3] = True
    assert not (kept2 & ~grid).any()


def test_metric_ranking_prefers_near_pixels_of_equal_relative_spread():
    """rank "metric" = entropy + log(depth): of two pixels with the same entropy (same spread in log-depth)
    the nearer one is more confident, and a far pixel needs log(d_far / d_near) nats less entropy to tie; rank
    "entropy" is the entropy itself; an unknown ranking is one line naming the argument."""
    depth = np.array([[5.0, 40.0, 40.0]], dtype=np.float32)
    entropy = np.array([[1.0, 1.0, 1.0 - np.log(8.0)]], dtype=np.float32)
    assert np.array_equal(confidence_score(depth, entropy, "entropy"), entropy)
    m = confidence_score(depth, entropy, "metric")
    assert m[0, 0] < m[0, 1] and np.isclose(m[0, 0], m[0, 2], atol=1e-6)
    kept = select_pixels(depth, confidence_score(depth, entropy[:, [0, 1, 1]], "metric"), 1 / 3, 1.0, 80.0)
    assert kept.tolist() == [[True, False, False]]
    with pytest.raises(MonoMapError, match="^rank: unknown ranking 'mode'"):
        confidence_score(depth, entropy, "mode")


def test_build_ranked_by_metric_keeps_nearer_points(tiny_root):
    """The same keep 0.5 map of the oracle ranked by metric entropy keeps end points nearer the camera on
    average than ranked by entropy, and as many of them."""
    from mono_map.mapping.build import make_builder

    from mono_map.mapping.pipeline import run_builders

    seq = open_sequence(tiny_root, "tiny")
    kept = {}
    for rank in ("entropy", "metric"):
        rec = Recorder()
        b = make_builder(seq, MapJob.spec("mono", range(1), keep=0.5), predictor=NoisyGroundTruthPredictor(),
                         rank=rank, observers=[rec])
        run_builders(seq, [b], [0], show_progress=False)
        kept[rank] = rec.updates[0]
    dist = {r: np.linalg.norm(u.points_world - u.origin, axis=1) for r, u in kept.items()}
    assert len(dist["metric"]) == len(dist["entropy"]) > 0
    assert dist["metric"].mean() < 0.9 * dist["entropy"].mean()


class Recorder:
    def __init__(self):
        self.updates, self.closed = [], False

    def __call__(self, upd):
        self.updates.append(upd)

    def close(self):
        self.closed = True


def test_build_mono_oracle_observers(tiny_root):
    seq = open_sequence(tiny_root, "tiny")
    rec = Recorder()
    res = build_map(seq, MapJob.spec("mono", range(0, 2), keep=0.5, stride=4),
                    predictor=NoisyGroundTruthPredictor(), observers=[rec], show_progress=False)
    assert rec.closed and [u.index for u in rec.updates] == [0, 1]
    u = rec.updates[0]
    assert u.keep_mask.shape == seq.image_size and u.depth.shape == seq.image_size
    assert len(u.points_world) == u.keep_mask.sum() == u.stats["n_points"]
    assert abs(u.stats["kept_fraction"] - 0.5) < 1e-3
    assert np.allclose(u.origin, seq.T_world_cam2(0)[:3, 3])
    assert len(u.occupied_keys_changed) > 0
    # every cell reported as newly occupied in frame 0 is occupied after frame 0 ... and in the end
    # unless freed later
    freed = {tuple(np.round(c, 3)) for c in rec.updates[1].freed_keys_changed}
    still = [c for c in u.occupied_keys_changed if tuple(np.round(c, 3)) not in freed]
    assert (res.tree.getLabels(np.array(still)) == 1).all()
    assert res.stats["points_kept"] == sum(len(x.points_world) for x in rec.updates)
    assert res.stats["memory_mb"] > 0 and res.stats["leaf_count"] == res.tree.getNumLeafNodes()


def test_cli_build_and_eval(tiny_root, tmp_path, capsys):
    out = tmp_path / "maps"
    common = ["--seq", "tiny", "--data-root", str(tiny_root), "--frames", "0:3", "--out", str(out)]
    assert cli_main(["build", "--source", "lidar-fov", *common]) == 0
    assert cli_main(["build", "--source", "mono", "--model", "oracle", "--keep", "0.8", "--stride", "4", *common]) == 0
    bts = sorted(out.glob("*.bt"))
    assert [p.name for p in bts] == ["lidar-fov_res0.2_f0-3.bt", "mono-keep0.8_model-oracle_stride4_res0.2_f0-3.bt"]
    stats = json.loads(bts[1].with_suffix(".json").read_text())["stats"]
    assert stats["n_frames"] == 3 and stats["points_kept"] > 0 and stats["frames_per_s"] > 0
    assert not list(out.glob(".*tmp*"))
    capsys.readouterr()
    js = tmp_path / "m.json"
    assert cli_main(["eval", "--map", str(bts[1]), "--reference", str(bts[0]), "--json", str(js)]) == 0
    text = capsys.readouterr().out
    assert "accuracy" in text and "coverage" in text
    m = json.loads(js.read_text())
    assert 0 < m["accuracy"] <= m["accuracy_covered"] <= 1 and 0 < m["coverage"] <= 1
    # the reference against itself is perfect
    assert cli_main(["eval", "--map", str(bts[0]), "--reference", str(bts[0]), "--json", str(js)]) == 0
    assert json.loads(js.read_text())["accuracy"] == 1.0
    # no --map: the map `build` wrote for the same options, scored against the cached LiDAR-FOV map
    capsys.readouterr()
    same = [*common, "--model", "oracle", "--stride", "4"]
    assert cli_main(["eval", *same, "--json", str(js)]) == 0
    assert f"scoring {bts[1]}" in capsys.readouterr().out
    assert json.loads(js.read_text())["accuracy"] == m["accuracy"]
    assert cli_main(["eval", *same, "--keep", "0.5"]) == 2
    err = capsys.readouterr().err
    assert "mono-keep0.5" in err and "does not exist" in err and len(err.strip().splitlines()) == 1


def test_map_job_keys_names_and_reuse(tiny_root, tmp_path):
    """A MapJob's key holds only what determines the map; it is what build_and_write stores and
    reusable compares (naming the setting that differs)."""
    seq = open_sequence(tiny_root, "tiny")
    lidar = MapJob.of(seq, "lidar-fov", range(0, 2), keep=0.3, stride=4)
    assert lidar.key() == MapJob.of(seq, "lidar-fov", range(0, 2)).key()   # LiDAR ignores keep and stride
    assert lidar.stem() == "lidar-fov_res0.2_f0-2"
    mono = MapJob.of(seq, "mono", range(0, 2), keep=0.5, stride=4, model="oracle")
    assert mono.stem() == "mono-keep0.5_model-oracle_stride4_res0.2_f0-2"
    assert mono.key()["keep"] == 0.5 and mono.key()["model"] == "oracle" and mono.key()["stride"] == 4
    assert dataclasses.replace(mono, keep=0.9).hash() != mono.hash()
    dist = dataclasses.replace(mono, integrate="distribution")
    assert dist.key()["keep"] is None and dist.stem().startswith("mono-dist_")
    assert dataclasses.replace(dist, keep=0.9).hash() == dist.hash()        # a distribution map ignores keep
    bt, _ = build_and_write(lidar, seq, tmp_path, show_progress=False)
    assert bt == lidar.path(tmp_path)
    side = json.loads(bt.with_suffix(".json").read_text())
    assert side["job"] == lidar.key() and side["job_hash"] == lidar.hash()
    assert reusable(bt, lidar) == (True, "")
    ok, why = reusable(bt, dataclasses.replace(lidar, octomap=OctoMapConfig(prob_hit=0.8)))
    assert not ok and why == "built with other octomap"


class BadPredictor:
    def __init__(self, kind):
        self.kind = kind

    def predict(self, image):
        h, w = image.shape[:2]
        depth = np.full((h, w), 10.0, np.float32)
        if self.kind == "nan":
            depth[5, 5] = np.nan
        if self.kind == "empty":
            depth[:] = 0.0
        return DepthPrediction(depth=depth, entropy=np.ones((h, w), np.float32))


@pytest.mark.parametrize("argv, message", [
    (["--keep", "0"], "--keep"),
    (["--keep", "1.5"], "--keep"),
    (["--source", "radar"], "--source"),
    (["--model", "/nonexistent/model.pt"], "model.pt"),
    (["--res", "-1"], "--res"),
    (["--integrate", "distribution", "--eps", "0"], "--eps"),
    (["--integrate", "distribution", "--eps", "1.5"], "--eps"),
    (["--integrate", "distribution", "--temperature", "-1"], "--temperature"),
    (["--integrate", "distribution", "--ray-step", "0"], "--ray-step"),
    (["--integrate", "distribution", "--min-update", "0.5"], "--min-update"),
    (["--integrate", "distribution", "--bin-spread", "0"], "--bin-spread"),
])
def test_cli_bad_inputs_write_nothing(tiny_root, tmp_path, capsys, argv, message):
    out = tmp_path / "maps"
    rc = cli_main(["build", "--seq", "tiny", "--data-root", str(tiny_root), "--frames", "0:2", "--out", str(out), *argv])
    assert rc == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert not out.exists() or not any(out.iterdir())


def test_cli_depth_gt_without_ground_truth_is_one_line(tiny_root, tmp_path, capsys, monkeypatch):
    """--source depth-gt on a sequence without depth_2 (real KITTI): one line naming it, nothing written."""
    from mono_map.data.kitti import KittiSequence

    monkeypatch.setattr(KittiSequence, "depth", lambda self, i: None)
    out = tmp_path / "maps"
    rc = cli_main(["build", "--seq", "tiny", "--data-root", str(tiny_root), "--frames", "0:2", "--out", str(out),
                   "--source", "depth-gt"])
    err = capsys.readouterr().err
    assert rc == 2 and "depth_2" in err and "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert not out.exists() or not any(out.iterdir())


@pytest.mark.parametrize("kind, message", [("nan", "NaN"), ("empty", "empty frame")])
def test_bad_predictions(tiny_root, kind, message):
    seq = open_sequence(tiny_root, "tiny")
    rec = Recorder()
    with pytest.raises(MonoMapError, match=message):
        build_map(seq, MapJob.spec("mono", range(0, 1), keep=0.8), predictor=BadPredictor(kind), observers=[rec],
                  show_progress=False)
    assert rec.closed


def test_eval_bad_map(tmp_path):
    bad = tmp_path / "x.bt"
    bad.write_text("not a tree")
    assert cli_main(["eval", "--map", str(bad), "--reference", str(bad)]) == 2
    assert cli_main(["eval", "--map", str(tmp_path / "missing.bt"), "--reference", str(bad)]) == 2


def test_cli_table_and_sweep(tiny_root, tmp_path, capsys):
    """`eval --table`: builds the maps it lacks, scores them, writes Markdown, JSON and both pictures;
    against the whole LiDAR map (the paper's ground truth) the LiDAR-FOV map becomes a scored row."""
    out = tmp_path / "table"
    common = ["eval", "--seq", "tiny", "--data-root", str(tiny_root), "--frames", "0:3", "--out", str(out),
              "--table", "--keeps", "0.5", "--model", "oracle", "--stride", "4"]
    assert cli_main(common) == 0
    text = capsys.readouterr().out
    assert "building 7 maps in one pass" in text   # LiDAR-FOV, depth-gt, keeps 1.0/0.8/0.5, distribution, fused
    assert "| mono keep 0.8 |" in text and "| mono (keep 1.0) |" in text and "| mono keep 0.5 |" in text
    stem = "table_f0-3_res0.2_model-oracle"
    rows = json.loads((out / f"{stem}.json").read_text())["rows"]
    assert [r["method"] for r in rows] == ["LiDAR-FOV", "camera ground truth (depth-gt)", "mono (keep 1.0)",
                                           "mono keep 0.8", "mono keep 0.5", "mono, distribution", "mono, fused"]
    assert rows[0]["accuracy"] == 1.0 and rows[0]["coverage"] == 1.0
    kept = [r["points_kept"] for r in rows[2:5]]
    assert kept[0] > kept[1] > kept[2] > 0  # keep 1.0 > 0.8 > 0.5
    for r in rows[1:]:
        assert 0 < r["accuracy"] <= r["accuracy_covered"] <= 1 and r["memory_mb"] > 0
        assert 0 < r["surface_precision"] <= 1
    assert rows[1]["surface_precision"] == 1.0                  # depth-gt is its own surface
    assert [r["ece"] is not None for r in rows] == [False, False, True, True, False, True, False]
    for suffix in (".md", "_sweep.png", "_topdown.png", "_acc_memory.png", "_reliability.png"):
        assert (out / f"{stem}{suffix}").stat().st_size > 0
    n_bt = len(list(out.glob("*.bt")))
    assert n_bt == 7 and len(list(out.glob("*.ot"))) == 3

    assert cli_main(common + ["--reference", "lidar"]) == 0
    capsys.readouterr()
    table = json.loads((out / f"{stem}_ref-lidar.json").read_text())
    assert table["reference"] == "lidar"
    fov = table["rows"][0]
    assert fov["method"] == "LiDAR-FOV" and fov["coverage"] < 1.0 and 0 < fov["accuracy"] < 1.0
    assert len(list(out.glob("*.bt"))) == n_bt + 1  # only the whole-LiDAR map was added; the rest reused

    # the job key carries the integration: another --eps is another distribution map, the rest is reused
    dist = json.loads(next(out.glob("mono-dist_*.json")).read_text())["job"]
    assert dist["integration"]["mode"] == "distribution" and dist["keep"] is None
    assert dist["integration"]["distribution"]["eps"] == 0.5
    assert cli_main(common + ["--eps", "0.3"]) == 0
    assert "rebuilding" not in capsys.readouterr().out
    # (the fused map's free half is the distribution integration: another --eps is another fused map too)
    assert len(list(out.glob("*.bt"))) == n_bt + 3 and len(list(out.glob("mono-dist-eps0.3_*.ot"))) == 1
    assert len(list(out.glob("mono-fused-eps0.3_*.bt"))) == 1

    assert cli_main(common + ["--reference", "radar"]) == 2
    assert "--reference" in capsys.readouterr().err


def test_topdown_picture_has_no_gaps_between_adjacent_cells():
    """A contiguous row of 0.2 m cells fills every pixel of its picture row (no moire gaps)."""
    from mono_map.viz.plots import height_image, picture_extent

    res = 0.2
    k = np.arange(-300, 300)
    pts = np.stack([(k + 0.5) * res, np.full(k.shape, -1.0), np.full(k.shape, 7.3)], axis=1)  # OctoMap centres
    extent = picture_extent(pts, res)
    img = height_image(pts, extent, res)
    row = img[np.isfinite(img).any(axis=1)]
    assert row.shape[0] == 1
    filled = np.flatnonzero(np.isfinite(row[0]))
    assert len(filled) == len(k) and np.all(np.diff(filled) == 1)
    assert np.allclose(row[0, filled], 1.0)  # height = -y


def test_cli_output_directory_that_is_a_file(tiny_root, tmp_path, capsys):
    blocker = tmp_path / "not_a_dir"
    blocker.write_text("x")
    rc = cli_main(["build", "--seq", "tiny", "--data-root", str(tiny_root), "--source", "lidar-fov",
                   "--frames", "0:1", "--out", str(blocker)])
    err = capsys.readouterr().err
    assert rc == 2 and err.strip() == f"mono-map: error: --out: {blocker} is a file, not a directory"
    assert blocker.read_text() == "x"


class SkyTopPredictor:
    """The oracle's depth, with the top half of every image declared "no surface within range"."""

    def __init__(self):
        self.oracle = NoisyGroundTruthPredictor()

    def predict_frame(self, seq, i, image=None):
        p = self.oracle.predict_frame(seq, i, image)
        p.p_beyond = np.zeros_like(p.depth)
        p.p_beyond[: p.depth.shape[0] // 2] = 0.9
        p.entropy = np.where(np.isfinite(p.entropy), 0.0, p.entropy).astype(np.float32)  # sky top most confident
        return p


def test_build_never_inserts_beyond_range_pixels(tiny_root):
    seq = open_sequence(tiny_root, "tiny")
    rec = Recorder()
    build_map(seq, MapJob.spec("mono", range(0, 1), keep=0.5, stride=4), predictor=SkyTopPredictor(),
              observers=[rec], show_progress=False)
    mask = rec.updates[0].keep_mask
    h = mask.shape[0] // 2
    assert mask.any() and not mask[:h].any()
    with pytest.raises(MonoMapError, match="p_beyond"):
        select_pixels(np.ones((4, 4)), np.zeros((4, 4)), 1.0, p_beyond=np.zeros((3, 4)))


class CountingOracle(NoisyGroundTruthPredictor):
    """The oracle, counting its predictions per frame (and whether bin probabilities were asked for)."""

    def __init__(self):
        super().__init__()
        self.calls = []

    def predict_frame(self, seq, i, image=None, with_probs=False, probs_step=1):
        self.calls.append((int(i), bool(with_probs)))
        return super().predict_frame(seq, i, image, with_probs=with_probs, probs_step=probs_step)


def test_maps_of_one_pass_equal_maps_built_alone_and_predict_once(tiny_root, tmp_path):
    from mono_map.mapping.pipeline import build_maps
    from mono_map.mapping.publish import MapRequest, build_and_write_all
    from mono_map.mapping.octree import tree_leaves

    seq = open_sequence(tiny_root, "tiny")
    frames = range(0, 3)
    specs = [MapJob.spec("mono", frames, keep=1.0, stride=4), MapJob.spec("mono", frames, keep=0.5, stride=4),
             MapJob.spec("mono", frames, integrate="distribution", stride=4), MapJob.spec("lidar-fov", frames)]
    shared = CountingOracle()
    together = build_maps(seq, [dict(job=s, predictor=shared) for s in specs], show_progress=False)
    assert shared.calls == [(0, True), (1, True), (2, True)]     # one prediction per frame for three mono maps
    for spec, res in zip(specs, together):
        alone = build_map(seq, spec, predictor=NoisyGroundTruthPredictor(), show_progress=False)
        a, b = tree_leaves(res.tree), tree_leaves(alone.tree)
        assert np.array_equal(a.start, b.start) and np.array_equal(a.length, b.length), spec
        assert np.array_equal(a.value, b.value) and a.occupied.any(), spec
        assert res.stats["memory_bytes"] == alone.stats["memory_bytes"]
        assert res.stats["points_kept"] == alone.stats["points_kept"]
    # published together, each map byte-identical to the one built and written alone
    jobs = [MapJob.of(seq, "mono", range(0, 3), keep=k, stride=4, model="oracle") for k in (1.0, 0.5)]
    written = build_and_write_all([MapRequest(j) for j in jobs], seq, tmp_path / "pass",
                                  predictor=NoisyGroundTruthPredictor(), show_progress=False)
    for job, (bt, stats) in zip(jobs, written):
        alone, _ = build_and_write(job, seq, tmp_path / "alone", predictor=NoisyGroundTruthPredictor(),
                                   show_progress=False)
        assert bt == job.path(tmp_path / "pass") and bt.read_bytes() == alone.read_bytes()
        assert reusable(bt, job) == (True, "") and stats["bt_bytes"] == bt.stat().st_size
    with pytest.raises(ValueError, match="share their frames"):
        build_and_write_all([MapRequest(jobs[0]), MapRequest(MapJob.of(seq, "lidar-fov", range(0, 2)))], seq,
                            tmp_path / "bad", show_progress=False)
    assert not (tmp_path / "bad").exists()


@pytest.mark.parametrize("which", [0, 1])
def test_a_rename_failing_in_a_pass_publishes_none_of_its_maps(tiny_root, tmp_path, monkeypatch, which):
    """build_and_write_all publishes every map of the pass or none: one map's .json failing to rename leaves
    neither map (whichever files were renamed already are removed again)."""
    import os

    from mono_map.mapping.publish import MapRequest, build_and_write_all

    seq = open_sequence(tiny_root, "tiny")
    jobs = [MapJob.of(seq, "lidar-fov", range(0, 2)), MapJob.of(seq, "lidar", range(0, 2))]
    failing = jobs[which].path(tmp_path).with_suffix(".json")
    real = os.replace

    def replace(src, dst):
        if os.fspath(dst) == os.fspath(failing):
            raise OSError(28, "No space left on device", os.fspath(dst))
        return real(src, dst)

    monkeypatch.setattr(os, "replace", replace)
    with pytest.raises(OSError):
        build_and_write_all([MapRequest(j) for j in jobs], seq, tmp_path, show_progress=False)
    assert jobs[0].path(tmp_path).parent == tmp_path and not list(tmp_path.iterdir())


class ThreadRecordingOracle(NoisyGroundTruthPredictor):
    """The oracle, recording which thread predicts each frame; fails on frame ``fail_at`` (if given)."""

    def __init__(self, fail_at=None):
        super().__init__()
        self.threads, self.fail_at = {}, fail_at

    def predict_frame(self, seq, i, image=None, with_probs=False, probs_step=1):
        import threading

        self.threads[int(i)] = threading.current_thread().name
        if i == self.fail_at:
            raise MonoMapError(f"frame {i}: predictor failed")
        return super().predict_frame(seq, i, image, with_probs=with_probs, probs_step=probs_step)


def test_look_ahead_prediction_gives_the_frame_by_frame_maps(tiny_root):
    """run_builders predicts frame n+1 in a second thread while the maps integrate frame n: the maps are
    those of stepping each builder frame by frame in one thread; a predictor error stops the pass with that
    error, at most one frame ahead, observers closed."""
    import threading

    from mono_map.mapping.pipeline import make_builders, run_builders
    from mono_map.mapping.octree import tree_leaves

    seq = open_sequence(tiny_root, "tiny")
    frames = [0, 1, 2, 3]
    specs = [MapJob.spec("mono", frames, keep=1.0, stride=4), MapJob.spec("mono", frames, keep=0.5, stride=4)]
    ahead = ThreadRecordingOracle()
    piped = make_builders(seq, [dict(job=s, predictor=ahead) for s in specs])
    run_builders(seq, piped, frames, show_progress=False)
    assert sorted(ahead.threads) == frames
    assert all(name != threading.main_thread().name for name in ahead.threads.values())
    plain = make_builders(seq, [dict(job=s, predictor=NoisyGroundTruthPredictor()) for s in specs])
    for i in frames:
        for b in plain:
            b.step(i)              # no shared inputs: predicts in this thread, frame by frame
    for p, q in zip(piped, plain):
        a, b = tree_leaves(p.result(frames).tree), tree_leaves(q.result(frames).tree)
        assert np.array_equal(a.start, b.start) and np.array_equal(a.value, b.value) and a.occupied.any()

    failing, rec = ThreadRecordingOracle(fail_at=2), Recorder()
    builders = make_builders(seq, [dict(job=specs[0], predictor=failing, observers=[rec])])
    with pytest.raises(MonoMapError, match="frame 2: predictor failed"):
        run_builders(seq, builders, frames, show_progress=False)
    assert sorted(failing.threads) == [0, 1, 2] and rec.closed
    assert [u.index for u in rec.updates] == [0, 1]


def test_maps_built_in_threads_at_once_equal_maps_built_alone(tiny_root):
    """The integrators' per-frame buffers (visited bitmap, accumulators) are per thread: maps built at the
    same time in several threads are those built one after another (keep, distribution and LiDAR maps)."""
    from concurrent.futures import ThreadPoolExecutor

    from mono_map.mapping.octree import tree_leaves

    seq = open_sequence(tiny_root, "tiny")
    frames = range(0, 4)
    specs = [MapJob.spec("mono", frames, keep=1.0), MapJob.spec("mono", frames, integrate="distribution"),
             MapJob.spec("mono", frames, keep=0.5), MapJob.spec("lidar", frames)]

    def build(spec):
        res = build_map(seq, spec, predictor=NoisyGroundTruthPredictor(), show_progress=False)
        return tree_leaves(res.tree)

    alone = [build(s) for s in specs]
    for _ in range(2):
        with ThreadPoolExecutor(len(specs)) as ex:
            together = list(ex.map(build, specs))
        for spec, a, b in zip(specs, alone, together):
            assert np.array_equal(a.start, b.start) and np.array_equal(a.length, b.length), spec
            assert np.array_equal(a.value, b.value), spec


def test_demo_end_to_end_on_the_tiny_sequence(tiny_root, tmp_path, capsys):
    """`mono-map demo` with the shipped model on 3 frames: the three maps, the table, the recording, and a
    last line with the time of each phase; run again, it reuses every map."""
    out = tmp_path / "out"
    argv = ["demo", "--seq", "tiny", "--data-root", str(tiny_root), "--frames", "3", "--out", str(out)]
    assert cli_main(argv) == 0
    text = capsys.readouterr().out
    last = text.strip().splitlines()[-1]
    assert last.startswith("demo finished in ")
    for phase in ("model and sequence", "LiDAR-FOV", "monocular maps", "table"):
        assert f"{phase} " in last, last
    names = {p.name for p in out.iterdir()}
    assert {"lidar-fov_res0.2_f0-3.bt", "mono-keep0.8_res0.2_f0-3.bt", "mono-keep1_res0.2_f0-3.bt",
            "demo_mono-keep0.8_f0-3.rrd", "table_f0-3_res0.2.md"} <= names, names
    assert "| mono keep 0.8 |" in text
    assert cli_main(argv) == 0
    again = capsys.readouterr().out
    assert "[1/3]" not in again and "[2/3]" not in again
    assert "LiDAR-FOV" not in again.strip().splitlines()[-1]
