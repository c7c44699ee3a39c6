"""KITTI raw drives: the same frames read through the raw and the odometry layout agree (poses, frames,
depth targets, maps cell for cell), against pykitti; every command on a raw drive; bad drives and splits
in one line naming the file; Eigen's ground truth as monodepth2 makes it; real01 written as a raw drive."""

from __future__ import annotations

import json
import os
import shutil
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

from mono_map import geometry
from mono_map.cli import main as cli_main
from mono_map.data import kitti_raw
from mono_map.data.kitti import open_sequence
from mono_map.data.kitti_raw_reader import KittiRawSequence
from mono_map.data.kitti_raw_writer import RawRig, synthetic_drive_name, write_raw_drive
from mono_map.errors import MonoMapError
from tiny_net import write_tiny_checkpoint

DRIVE = synthetic_drive_name("tiny")    # 2000_01_01_drive_tiny_sync
DATE = DRIVE[:10]


def copy_odometry(src: Path, dst: Path, name: str = "tiny") -> None:
    """The odometry sequence ``name`` of ``src`` under ``dst`` (files hard-linked: replace, never edit, them)."""
    shutil.copytree(src / "sequences" / name, dst / "sequences" / name, copy_function=os.link)
    (dst / "poses").mkdir(parents=True, exist_ok=True)
    shutil.copyfile(src / "poses" / f"{name}.txt", dst / "poses" / f"{name}.txt")


def orthonormal(poses: np.ndarray) -> np.ndarray:
    """Poses with their rotations projected onto SO(3) (the 7-digit poses file is orthonormal to ~2e-7 only)."""
    out = poses.copy()
    u, _, vt = np.linalg.svd(poses[:, :3, :3])
    out[:, :3, :3] = u @ vt
    return out


@pytest.fixture(scope="session")
def raw_root(tiny_root, tmp_path_factory):
    """tiny in both layouts under one root: the odometry files as rendered, and written as raw drive DRIVE."""
    root = tmp_path_factory.mktemp("raw")
    copy_odometry(tiny_root, root)
    write_raw_drive(open_sequence(root, "tiny"), root, DRIVE)
    return root


@pytest.fixture(scope="session")
def exact_root(tiny_root, tmp_path_factory):
    """tiny with full-precision orthonormal poses in both layouts: the same frames, poses equal to rounding."""
    root = tmp_path_factory.mktemp("raw_exact")
    copy_odometry(tiny_root, root)
    poses = orthonormal(open_sequence(root, "tiny").poses_cam0)
    (root / "poses" / "tiny.txt").write_text("".join(" ".join(repr(float(x)) for x in p[:3].ravel()) + "\n"
                                                     for p in poses))
    write_raw_drive(open_sequence(root, "tiny"), root, DRIVE)
    return root


def pose_errors(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """Largest translation (m) and rotation angle (rad) of inv(a)·b over the poses."""
    d = np.linalg.inv(a) @ b
    cos = np.clip((np.trace(d[:, :3, :3], axis1=1, axis2=2) - 1) / 2, -1, 1)
    ang = np.arccos(cos)
    # arccos loses precision near 0: the skew part's norm is the better small angle
    skew = np.stack([d[:, 2, 1] - d[:, 1, 2], d[:, 0, 2] - d[:, 2, 0], d[:, 1, 0] - d[:, 0, 1]], 1)
    ang = np.where(ang < 1e-3, np.linalg.norm(skew, axis=1) / 2, ang)
    return float(np.abs(d[:, :3, 3]).max()), float(ang.max())


# ------------------------------------------------------------------------------------- round trip


def test_raw_drive_reads_like_the_odometry_sequence(raw_root):
    odo, raw = open_sequence(raw_root, "tiny"), open_sequence(raw_root, DRIVE)
    assert isinstance(raw, KittiRawSequence) and len(raw) == len(odo) == 6
    t, r = pose_errors(odo.poses_cam0, raw.poses_cam0)
    assert t <= 1e-3 and r <= 1e-6, (t, r)
    assert np.abs(odo.times - raw.times).max() < 1e-9
    assert raw.image_size == odo.image_size
    assert np.array_equal(raw.calib.P2, odo.calib.P2)
    assert np.abs(raw.calib.T_cam0_velo - odo.calib.T_cam0_velo).max() < 1e-12
    assert raw.is_synthetic and json.loads((raw.path / "synth.json").read_text())["n_frames"] == 6
    # the chain is really exercised: R_rect_00 is not the identity, [R|T] is not Tr
    assert np.abs(raw.raw_calib.R_rect_00 - np.eye(4)).max() > 5e-3
    assert np.abs(raw.raw_calib.T_cam0unrect_velo - raw.calib.T_cam0_velo).max() > 5e-3


def test_exact_poses_round_trip_to_rounding(exact_root):
    t, r = pose_errors(open_sequence(exact_root, "tiny").poses_cam0, open_sequence(exact_root, DRIVE).poses_cam0)
    assert t < 1e-8 and r < 1e-8, (t, r)   # ~2e-9: Tr itself is orthonormal to ~1e-7 only


def test_frames_and_depth_targets_bit_identical(raw_root):
    odo, raw = open_sequence(raw_root, "tiny"), open_sequence(raw_root, DRIVE)
    for i in range(len(odo)):
        assert np.array_equal(odo.image(i), raw.image(i))
        assert np.array_equal(odo.velodyne(i), raw.velodyne(i))
        assert np.array_equal(odo.depth(i), raw.depth(i))
        assert np.array_equal(odo.lidar_depth(i), raw.lidar_depth(i))


def test_poses_and_calibration_as_pykitti_reads_them(raw_root):
    pykitti = pytest.importorskip("pykitti")
    ds = pykitti.raw(str(raw_root), DATE, "tiny")
    raw = open_sequence(raw_root, DRIVE)
    T = np.array([o.T_w_imu for o in ds.oxts])
    c = ds.calib
    expect = c.T_cam0_imu @ np.linalg.inv(T[0]) @ T @ np.linalg.inv(c.T_cam0_imu)
    assert np.abs(expect - raw.poses_cam0).max() < 1e-12
    assert np.abs(c.T_cam0_velo - raw.calib.T_cam0_velo).max() < 1e-15
    assert np.abs(c.T_velo_imu - raw.raw_calib.T_velo_imu).max() == 0
    assert np.abs(c.P_rect_20 - raw.calib.P2).max() == 0
    assert len(ds.timestamps) == len(raw)
    # pykitti's cam0 → cam2 shift is P[0,3]/fx along x only; ours is K⁻¹·P[:,3], the whole offset
    P = raw.calib.P2
    shift = np.linalg.solve(P[:, :3], P[:, 3]) - [P[0, 3] / P[0, 0], 0, 0]
    assert np.abs(raw.calib.T_cam2_velo[:3, 3] - c.T_cam2_velo[:3, 3] - shift).max() < 1e-12
    assert np.abs(raw.calib.T_cam2_velo[:3, :3] - c.T_cam2_velo[:3, :3]).max() < 1e-15


def test_oxts_conversion_inverts_over_the_globe():
    """oxts_from_poses then oxts_poses gives the IMU poses back, north and south, at any heading."""
    rng = np.random.default_rng(3)
    for lat0, lon0 in ((49.0, 8.4), (-33.9, 151.2), (64.1, -21.9)):
        n = 50
        ang = rng.uniform([-0.3, -0.3, -np.pi], [0.3, 0.3, np.pi], (n, 3))
        T = np.tile(np.eye(4), (n, 1, 1))
        T[:, :3, :3] = kitti_raw.euler_rotation(*ang.T)
        T[:, :3, 3] = rng.uniform(-2000, 2000, (n, 3))
        T[0, :3, 3] = 0
        back = kitti_raw.oxts_poses(kitti_raw.oxts_from_poses(T, lat0, lon0, 100.0))
        assert np.abs(back[:, :3, 3] - T[:, :3, 3]).max() < 1e-6
        assert np.abs(back[:, :3, :3] - T[:, :3, :3]).max() < 1e-12


def test_timestamps_round_trip_to_the_nanosecond():
    times = np.array([0.0, 0.103456789, 1.5, 86399.999999999, 86400.25])   # across midnight
    assert np.abs(kitti_raw.parse_timestamps(kitti_raw.format_timestamps(times)) - times).max() < 1e-9


def leaves_of(result):
    from mono_map.mapping.octree import tree_leaves

    lv = tree_leaves(result.tree)
    return lv.start, lv.length, lv.occupied


@pytest.mark.parametrize("source", ["lidar-fov", "lidar", "depth-gt", "mono"])
def test_maps_cell_for_cell(exact_root, source):
    from mono_map.config import OctoMapConfig
    from mono_map.mapping.jobs import MapJob
    from mono_map.mapping.pipeline import build_map
    from mono_map.mapping.oracle import NoisyGroundTruthPredictor

    out = []
    for name in ("tiny", DRIVE):
        seq = open_sequence(exact_root, name)
        mono = source == "mono"
        job = MapJob.spec(source, range(6), keep=0.8, octomap=OctoMapConfig(resolution=0.2), stride=4 if mono else 1)
        out.append(leaves_of(build_map(seq, job, predictor=NoisyGroundTruthPredictor() if mono else None,
                                       show_progress=False)))
    (s0, l0, o0), (s1, l1, o1) = out
    assert l0.sum() > 1000
    assert np.array_equal(s0, s1) and np.array_equal(l0, l1) and np.array_equal(o0, o1)


# ------------------------------------------------------------------------------------- commands


@pytest.fixture(scope="module")
def ckpt(tmp_path_factory):
    """An untrained tiny network: fast, and enough to run the commands."""
    return write_tiny_checkpoint(tmp_path_factory.mktemp("ckpt") / "tiny.pt")


def test_every_command_on_a_raw_drive(raw_root, tmp_path, capsys, ckpt, monkeypatch):
    monkeypatch.setenv("MONO_MAP_CACHE", str(tmp_path / "cache"))   # adapt's resumable state
    R, out = str(raw_root), tmp_path / "out"
    common = ["--seq", DRIVE, "--data-root", R]
    assert cli_main(["predict", *common, "--frames", "0:2", "--model", str(ckpt), "--out", str(out / "p")]) == 0
    assert sorted(p.name for p in (out / "p" / "depth").iterdir()) == ["000000.png", "000001.png"]
    assert cli_main(["eval-depth", *common, "--frames", "0:2", "--model", str(ckpt), "--threads", "1",
                     "--out", str(out / "e")]) == 0
    assert json.loads((out / "e" / f"depth_seq{DRIVE}.json").read_text())["results"]
    build = ["build", *common, "--frames", "0:2", "--res", "0.4", "--out", str(out / "m")]
    assert cli_main([*build, "--source", "lidar-fov", "--name", "ref", "--rrd", str(out / "r.rrd")]) == 0
    assert cli_main([*build, "--source", "depth-gt", "--name", "gt"]) == 0
    assert cli_main([*build, "--source", "mono", "--model", "oracle", "--stride", "8", "--name", "mono"]) == 0
    assert cli_main(["eval", "--map", str(out / "m" / "gt.bt"), "--reference", str(out / "m" / "ref.bt")]) == 0
    assert cli_main(["eval", "--table", *common, "--frames", "0:2", "--res", "0.4", "--model", "oracle",
                     "--stride", "8", "--keeps", "0.8,1.0", "--out", str(out / "t")]) == 0
    assert cli_main(["adapt", *common, "--model", str(ckpt), "--steps", "1", "--out", str(out / "a")]) == 0
    (adapted,) = (out / "a").glob(f"*-adapted-{DRIVE}-*.pt")
    assert cli_main(["view", str(out / "r.rrd"), "--save", str(out / "v.rrd")]) == 0
    assert (out / "v.rrd").stat().st_size > 0
    capsys.readouterr()


def test_build_on_raw_and_odometry_layout_same_bytes(raw_root, tmp_path):
    for name in ("tiny", DRIVE):
        assert cli_main(["build", "--seq", name, "--data-root", str(raw_root), "--source", "lidar-fov",
                         "--res", "0.4", "--out", str(tmp_path / name), "--name", "m"]) == 0
    assert (tmp_path / "tiny" / "m.bt").read_bytes() == (tmp_path / DRIVE / "m.bt").read_bytes()


def test_a_date_folder_as_the_root(raw_root):
    seq = open_sequence(raw_root / DATE, DRIVE)
    assert len(seq) == 6 and seq.path == raw_root / DATE / DRIVE
    with pytest.raises(MonoMapError, match="unsynced, unrectified"):
        open_sequence(raw_root, DRIVE.replace("_sync", "_extract"))


def test_synth_layout_raw(tiny_root, tmp_path, capsys):
    root = tmp_path / "d"
    copy_odometry(tiny_root, root)
    assert cli_main(["synth", "--seq", "tiny", "--layout", "raw", "--drive", "2011_01_02_drive_0007_sync",
                     "--data-root", str(root)]) == 0
    seq = open_sequence(root, "2011_01_02_drive_0007_sync")
    assert len(seq) == 6 and np.array_equal(seq.image(5), open_sequence(root, "tiny").image(5))
    assert cli_main(["synth", "--seq", "tiny", "--layout", "raw", "--drive", "drive7", "--data-root", str(root)]) == 2
    assert cli_main(["synth", "--seq", "tiny", "--drive", "2011_01_02_drive_0008_sync", "--data-root", str(root)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-2].startswith("mono-map: error: --drive:") and err[-1].startswith("mono-map: error: --drive:")
    # a drive it did not write (no synth.json: real data, say) is never overwritten, even with --force
    (root / "2011_01_02" / "2011_01_02_drive_0007_sync" / "synth.json").unlink()
    assert cli_main(["synth", "--seq", "tiny", "--layout", "raw", "--drive", "2011_01_02_drive_0007_sync",
                     "--data-root", str(root)]) == 2
    assert "never overwritten" in capsys.readouterr().err
    assert len(open_sequence(root, "2011_01_02_drive_0007_sync")) == 6


# ------------------------------------------------------------------------------------- bad drives


def replace(path: Path, text: str | bytes) -> None:
    path.unlink()
    (path.write_bytes if isinstance(text, bytes) else path.write_text)(text)


def edit_calib(name: str, key: str, value: str):
    def setup(d: Path):
        p = d / DATE / name
        lines = [f"{key}: {value}" if line.startswith(f"{key}:") else line for line in p.read_text().splitlines()]
        replace(p, "\n".join(line for line in lines if value != "DROP" or not line.startswith(f"{key}:")) + "\n")
    return setup


def drive_file(rel: str) -> Path:
    return Path(DATE) / DRIVE / rel


BAD_DRIVES = [  # (id, setup(root), the file the line must name, what it must say)
    ("no-cam-to-cam", lambda d: (d / DATE / "calib_cam_to_cam.txt").unlink(), "calib_cam_to_cam.txt", "not found"),
    ("no-velo-to-cam", lambda d: (d / DATE / "calib_velo_to_cam.txt").unlink(), "calib_velo_to_cam.txt", "not found"),
    ("no-imu-to-velo", lambda d: (d / DATE / "calib_imu_to_velo.txt").unlink(), "calib_imu_to_velo.txt", "not found"),
    ("no-P_rect_02", edit_calib("calib_cam_to_cam.txt", "P_rect_02", "DROP"), "calib_cam_to_cam.txt", "P_rect_02"),
    ("short-R_rect_00", edit_calib("calib_cam_to_cam.txt", "R_rect_00", "1 0 0 0 1 0"), "calib_cam_to_cam.txt",
     "R_rect_00"),
    ("R-not-rotation", edit_calib("calib_velo_to_cam.txt", "R", "1 0 0 0 2 0 0 0 1"), "calib_velo_to_cam.txt",
     "not a rotation"),
    ("T-non-numeric", edit_calib("calib_imu_to_velo.txt", "T", "0.1 x 0.3"), "calib_imu_to_velo.txt", "non-numeric"),
    ("S_rect-size", edit_calib("calib_cam_to_cam.txt", "S_rect_02", "1242 375"), "0000000000.png", "S_rect_02"),
    ("oxts-29-fields", lambda d: replace(d / drive_file("oxts/data/0000000003.txt"),
                                         " ".join(["1"] * 29) + "\n"), "0000000003.txt", "30 numbers (got 29)"),
    ("oxts-31-fields", lambda d: replace(d / drive_file("oxts/data/0000000002.txt"),
                                         " ".join(["1"] * 31) + "\n"), "0000000002.txt", "30 numbers (got 31)"),
    ("oxts-non-numeric", lambda d: replace(d / drive_file("oxts/data/0000000001.txt"),
                                           "49 8 a" + " 0" * 27 + "\n"), "0000000001.txt", "non-numeric"),
    ("oxts-missing", lambda d: (d / drive_file("oxts/data/0000000005.txt")).unlink(), "oxts/data",
     "5 OXTS packets for 6 images"),
    ("oxts-empty", lambda d: replace(d / drive_file("oxts/data/0000000000.txt"), ""), "0000000000.txt", "one line"),
    ("image-missing", lambda d: (d / drive_file("image_02/data/0000000004.png")).unlink(), "timestamps.txt",
     "6 timestamps for 5 images"),
    ("scan-missing", lambda d: (d / drive_file("velodyne_points/data/0000000004.bin")).unlink(),
     "velodyne_points/data", "5 scans for 6 images"),
    ("image-not-png", lambda d: replace(d / drive_file("image_02/data/0000000002.png"), b"GIF89a" + bytes(40)),
     "0000000002.png", "not a PNG"),
    ("no-timestamps", lambda d: (d / drive_file("image_02/timestamps.txt")).unlink(), "image_02/timestamps.txt",
     "not found"),
    ("bad-timestamp", lambda d: replace(d / drive_file("image_02/timestamps.txt"), "yesterday\n" * 6),
     "timestamps.txt:1", "malformed timestamp"),
    ("no-drive", lambda d: shutil.rmtree(d / DATE / DRIVE), DRIVE, "not found"),
]


@pytest.mark.parametrize("case", BAD_DRIVES, ids=[c[0] for c in BAD_DRIVES])
def test_bad_raw_drive_one_line_naming_the_file(raw_root, tmp_path, capsys, case):
    _, setup, names, says = case
    root = tmp_path / "root"
    shutil.copytree(raw_root / DATE, root / DATE, copy_function=os.link)
    setup(root)
    out = tmp_path / "out"
    assert cli_main(["build", "--seq", DRIVE, "--data-root", str(root), "--source", "lidar", "--res", "0.4",
                     "--out", str(out)]) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("mono-map: error: "), lines
    assert names in lines[0] and says in lines[0], lines[0]
    assert not out.exists()    # checked before any work


# ------------------------------------------------------------------------------------- the Eigen split


def write_split(tmp_path: Path, lines: list[str]) -> Path:
    p = tmp_path / "split.txt"
    p.write_text("\n".join(lines) + "\n")
    return p


def test_eval_depth_split_counts_and_protocols(raw_root, tmp_path, capsys, ckpt):
    split = write_split(tmp_path, [f"{DATE}/{DRIVE} 0000000001 l", f"{DATE}/{DRIVE} 0000000004 l",
                                   f"{DATE}/{DRIVE} 0000000009 l", "2011_09_26/2011_09_26_drive_0002_sync 0000000069 l"])
    out = tmp_path / "out"
    assert cli_main(["eval-depth", "--data-root", str(raw_root), "--split", str(split), "--threads", "1",
                     "--model", str(ckpt), "--out", str(out)]) == 0
    cap = capsys.readouterr()
    assert "2 of the 4 frames of split.txt found" in cap.err
    rep = json.loads((out / "depth_split_split.json").read_text())
    assert (rep["n_found"], rep["n_listed"], rep["missing_drives"]) == (2, 4, ["2011_09_26_drive_0002_sync"])
    (eig,) = rep["results"].values()
    assert eig["frames"] == [f"{DRIVE}_0000000001", f"{DRIVE}_0000000004"]
    # the Garg crop keeps fewer ground-truth pixels than the full image; the three rows are numbers and differ
    assert 0 < eig["n_pixels"] < eig["n_pixels_full_image"]
    rows = (eig["metrics"], eig["metrics_median_scaled"], eig["metrics_full_image"])
    for m in rows:
        assert np.isfinite(m["abs_rel"]) and m["abs_rel"] > 0 and 0 <= m["a1"] <= 1
    assert len({m["abs_rel"] for m in rows}) == 3
    assert eig["median_ratio"]["median"] > 0 and eig["median_ratio"]["median"] != 1
    assert "Eigen: raw-calibration LiDAR, Garg crop" in (out / "depth_split_split.md").read_text()
    # one pass scores both ground truths: the full-image row is what a pass over the full image alone gives
    from mono_map.depth.inference import DepthPredictor
    from mono_map.eval.depth_evaluation import eigen_frames, evaluate_model, split_frames

    sel = split_frames(raw_root, str(split))
    alone = evaluate_model(DepthPredictor.load(str(ckpt)), ((n, im, full) for n, im, _, full in eigen_frames(sel)),
                           cap=80.0, garg_crop=False)
    assert alone["metrics"] == eig["metrics_full_image"] and alone["n_pixels"] == eig["n_pixels_full_image"]


def test_eigen_split_is_packaged_and_lists_697_frames():
    from mono_map.eval.depth_evaluation import split_path

    lines = kitti_raw.parse_split(split_path("eigen").read_text())
    assert len(lines) == kitti_raw.EIGEN_SPLIT_SIZE == 697
    assert len({(f.drive, f.frame) for f in lines}) == 697 and {f.side for f in lines} == {"l"}


BAD_SPLITS = [  # (id, split lines or None for a missing file, extra options, what the line must name)
    ("two-fields", ["2000_01_01/2000_01_01_drive_tiny_sync 0000000001"], [], "split.txt:1"),
    ("not-a-drive", ["2000_01_01/tiny 0000000001 l"], [], "split.txt:1"),
    ("date-mismatch", ["2000_01_02/2000_01_01_drive_tiny_sync 0000000001 l"], [], "split.txt:1"),
    ("frame-not-number", [f"{DATE}/{DRIVE} 1a l"], [], "split.txt:1"),
    ("right-camera", [f"{DATE}/{DRIVE} 0000000001 l", f"{DATE}/{DRIVE} 0000000002 r"], [], "split.txt:2"),
    ("empty", [""], [], "split.txt"),
    ("missing-file", None, [], "--split"),
    ("none-found", ["2011_09_26/2011_09_26_drive_0002_sync 0000000069 l"], [], "none of the 1 frames"),
    ("eigen-none-found", "eigen", [], "none of the 697 frames of"),
    ("with-frames", [f"{DATE}/{DRIVE} 0000000001 l"], ["--frames", "0:2"], "--frames"),
    ("with-dense", [f"{DATE}/{DRIVE} 0000000001 l"], ["--gt", "dense"], "--gt dense"),
    ("no-scans", [f"{DATE}/{DRIVE} 0000000001 l"], ["--data-root", "{noscans}"], "velodyne_points/data: no velodyne"),
]


@pytest.mark.parametrize("case", BAD_SPLITS, ids=[c[0] for c in BAD_SPLITS])
def test_bad_split_one_line(raw_root, tmp_path, capsys, case):
    _, lines, extra, names = case
    split = tmp_path / "split.txt" if lines is None else "eigen" if lines == "eigen" else write_split(tmp_path, lines)
    out = tmp_path / "out"
    if "{noscans}" in extra:   # a drive without velodyne_points: its scans are the ground truth
        shutil.copytree(raw_root / DATE, tmp_path / "noscans" / DATE, copy_function=os.link)
        shutil.rmtree(tmp_path / "noscans" / DATE / DRIVE / "velodyne_points")
        extra = [str(tmp_path / "noscans") if e == "{noscans}" else e for e in extra]
    assert cli_main(["eval-depth", "--data-root", str(raw_root), "--split", str(split), "--model", "oracle-none",
                     "--out", str(out), *extra]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and names in err[0], err
    assert not out.exists()


def monodepth2_depth_map(velo: np.ndarray, P_rect_02: np.ndarray, T_cam0_velo: np.ndarray, H: int, W: int):
    """monodepth2's generate_depth_map (kitti_utils.py), its loop over duplicates included, as a reference."""
    P_velo2im = (P_rect_02 @ T_cam0_velo)[:3]
    velo = velo[velo[:, 0] >= 0, :].astype(np.float64)
    velo[:, 3] = 1.0
    pts = velo @ P_velo2im.T
    pts[:, :2] = pts[:, :2] / pts[:, 2][..., None]
    pts[:, 0] = np.round(pts[:, 0]) - 1
    pts[:, 1] = np.round(pts[:, 1]) - 1
    ok = (pts[:, 0] >= 0) & (pts[:, 1] >= 0) & (pts[:, 0] < W) & (pts[:, 1] < H)
    pts = pts[ok]
    depth = np.zeros((H, W))
    depth[pts[:, 1].astype(int), pts[:, 0].astype(int)] = pts[:, 2]
    inds = pts[:, 1].astype(int) * W + pts[:, 0].astype(int)
    for dd in [item for item, count in Counter(inds).items() if count > 1]:
        where = np.where(inds == dd)[0]
        depth[int(pts[where[0], 1]), int(pts[where[0], 0])] = pts[where, 2].min()
    depth[depth < 0] = 0
    return depth


@pytest.fixture(scope="session")
def real01_raw(kitti_real, tmp_path_factory):
    """Frames 0-7 of the real sequence real01 written as a raw drive of 2011-09-26 (its recording day)."""
    root = tmp_path_factory.mktemp("real01_raw")
    odo = open_sequence(kitti_real / "odometry", "real01")
    write_raw_drive(odo, root, "2011_09_26_drive_9901_sync", frames=list(range(8)))
    return odo, open_sequence(root, "2011_09_26_drive_9901_sync")


def test_real01_as_a_raw_drive_reads_back(real01_raw):
    odo, raw = real01_raw
    assert len(raw) == 8 and raw.image_size == (375, 1242) and not raw.is_synthetic
    t, r = pose_errors(odo.poses_cam0[:8], raw.poses_cam0)
    assert t <= 1e-3 and r <= 1e-6, (t, r)
    for i in (0, 7):
        assert np.array_equal(odo.image(i), raw.image(i))
        assert np.array_equal(odo.lidar_depth(i), raw.lidar_depth(i))


def test_eigen_ground_truth_as_monodepth2_makes_it(real01_raw):
    """On real scans: bit for bit monodepth2's map; against mono-map's projection, the same depths one
    pixel up and left (monodepth2's round(u) - 1)."""
    _, raw = real01_raw
    rc = raw.raw_calib
    H, W = raw.image_size
    for i in (0, 5):
        scan = raw.velodyne(i)
        ours = kitti_raw.eigen_depth_map(scan, rc.P_rect_02, rc.T_cam0_velo, H, W)
        ref = monodepth2_depth_map(scan, rc.P_rect_02, rc.T_cam0_velo, H, W)
        assert (ours > 0).sum() > 10000
        assert np.array_equal(ours, ref.astype(np.float32))
        own = raw.lidar_depth(i)
        both = (ours[:-1, :-1] > 0) & (own[1:, 1:] > 0)
        assert both.sum() > 0.97 * (ours > 0).sum()
        diff = ours[:-1, :-1][both] - own[1:, 1:][both]
        assert np.median(np.abs(diff)) < 1e-4


def test_depth_gt_on_a_real_raw_drive_one_line(real01_raw, tmp_path, capsys):
    """A real drive has no dense depth: --source depth-gt names depth_02/data, nothing written."""
    _, raw = real01_raw
    out = tmp_path / "out"
    assert cli_main(["build", "--seq", raw.name, "--data-root", str(raw.root), "--source", "depth-gt",
                     "--frames", "0:2", "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "depth_02/data" in err[0], err
    assert not out.exists()


def test_a_raw_drive_fingerprints_like_its_odometry_twin(raw_root):
    """Outputs are keyed by what the frames hold: a raw drive's fingerprint has the same parts, its dense
    depth (depth_02/data) included; editing a depth file changes it."""
    from mono_map.data.fingerprint import sequence_fingerprint

    odo, raw = open_sequence(raw_root, "tiny"), open_sequence(raw_root, DRIVE)
    fo, fr = sequence_fingerprint(odo, range(6)), sequence_fingerprint(raw, range(6))
    assert set(fr) == set(fo) and "depth" in fr


def test_editing_a_raw_drives_depth_changes_its_fingerprint(raw_root, tmp_path):
    from mono_map.data.fingerprint import sequence_fingerprint

    root = tmp_path / "r"
    shutil.copytree(raw_root / DATE, root / DATE, copy_function=os.link)
    before = sequence_fingerprint(open_sequence(root, DRIVE), range(6))
    f = root / drive_file("depth_02/data/0000000003.png")
    replace(f, f.read_bytes())
    os.utime(f, ns=(1, 1))
    after = sequence_fingerprint(open_sequence(root, DRIVE), range(6))
    assert [k for k in after if after[k] != before[k]] == ["depth"]
