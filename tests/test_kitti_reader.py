"""The KITTI odometry reader: real calibration and poses, conventions, and every bad-input case."""

from __future__ import annotations

import gzip
from pathlib import Path

import cv2
import numpy as np
import pykitti
import pytest

from mono_map import geometry
from mono_map.cli import main as cli_main
from mono_map.data.kitti_files import read_calib_file, read_poses_file, read_velodyne_bin
from mono_map.data.kitti_odometry import Calibration, KittiSequence, read_object_calibration
from mono_map.errors import MonoMapError
from mono_map.paths import KITTI_ASSETS_DIR


H, W = 24, 40  # tiny images keep the hand-made sequence fast


def scaled_calib_text(w: int, h: int) -> str:
    """Real KITTI 00 calibration with the projections scaled to w×h images (as resizing would need)."""
    lines = []
    for line in (KITTI_ASSETS_DIR / "calib_00.txt").read_text().splitlines():
        key, vals = line.split(":", 1)
        v = np.array([float(x) for x in vals.split()])
        if key.startswith("P"):
            v = v.reshape(3, 4) * np.array([[w / 1241], [h / 376], [1.0]])
        lines.append(f"{key}: " + " ".join(f"{x:.12e}" for x in v.ravel()))
    return "\n".join(lines) + "\n"


def make_sequence(root: Path, name: str = "42", n: int = 5, velodyne: bool = True) -> Path:
    """A hand-made KITTI-layout sequence: real 00 calib (scaled to the tiny images) and poses, small scans."""
    seq = root / "sequences" / name
    (seq / "image_2").mkdir(parents=True)
    (seq / "calib.txt").write_text(scaled_calib_text(W, H))
    (root / "poses").mkdir(exist_ok=True)
    lines = gzip.decompress((KITTI_ASSETS_DIR / "poses" / "00.txt.gz").read_bytes()).decode().splitlines()
    (root / "poses" / f"{name}.txt").write_text("\n".join(lines[:n]) + "\n")
    (seq / "times.txt").write_text("".join(f"{0.1 * i:e}\n" for i in range(n)))
    rng = np.random.default_rng(0)
    if velodyne:
        (seq / "velodyne").mkdir()
    for i in range(n):
        img = np.zeros((H, W, 3), np.uint8)
        img[..., 0] = 200  # red in RGB
        cv2.imwrite(str(seq / "image_2" / f"{i:06d}.png"), cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
        if velodyne:
            rng.normal(size=(100, 4)).astype(np.float32).tofile(seq / "velodyne" / f"{i:06d}.bin")
    return seq


def test_real_calibration_conventions():
    calib = Calibration.from_file(KITTI_ASSETS_DIR / "calib_00.txt")
    assert calib.K2[0, 0] == pytest.approx(718.856)
    # image_2 sits ~6 cm from cam0: t2 = K2^-1 P2[:, 3] (x dominates, y/z are millimetres)
    t2 = calib.T_cam2_cam0[:3, 3]
    assert t2[0] == pytest.approx(0.0599, abs=5e-4)
    assert abs(t2[1]) < 0.01 and abs(t2[2]) < 0.01
    # P2 reprojects cam0 points exactly like K2 · (T_cam2_cam0 · X)
    X = np.array([[1.0, -0.5, 12.0], [-3.0, 1.2, 30.0]])
    uvw = (calib.P2 @ np.c_[X, np.ones(2)].T).T
    uv_p2 = uvw[:, :2] / uvw[:, 2:]
    uv, _ = geometry.project_points(calib.K2, geometry.transform_points(calib.T_cam2_cam0, X))
    np.testing.assert_allclose(uv, uv_p2, atol=1e-9)
    # Tr maps velodyne forward (x) to cam0 forward (z)
    fwd = geometry.transform_points(calib.T_cam0_velo, np.array([[10.0, 0, 0]]))[0]
    assert fwd[2] > 9.5 and abs(fwd[0]) < 0.5


def test_reader_agrees_with_pykitti(tmp_path):
    make_sequence(tmp_path, n=5)
    seq = KittiSequence(tmp_path, "42")
    ref = pykitti.odometry(str(tmp_path), "42")
    assert len(seq) == len(ref) == 5
    np.testing.assert_allclose(seq.poses_cam0, np.array(ref.poses))
    np.testing.assert_allclose(seq.calib.T_cam0_velo, ref.calib.T_cam0_velo)
    np.testing.assert_allclose(seq.calib.K2, ref.calib.K_cam2)
    # pykitti keeps only the x part of t2; ours keeps the mm-size y/z parts too
    np.testing.assert_allclose(seq.calib.T_cam2_velo, ref.calib.T_cam2_velo, atol=5e-3)
    np.testing.assert_array_equal(seq.image(2), np.asarray(ref.get_cam2(2)))
    np.testing.assert_array_equal(seq.velodyne(1), ref.get_velo(1))
    assert seq.image(0)[0, 0].tolist() == [200, 0, 0]  # RGB order
    assert seq.image_size == (H, W)
    assert seq.depth(0) is None


def test_frame_poses_use_cam2_offset(tmp_path):
    make_sequence(tmp_path, n=3)
    seq = KittiSequence(tmp_path, "42")
    assert seq.image(2).shape == (H, W, 3) and seq.velodyne(2).shape == (100, 4)
    # camera centre of image_2 in the world = cam0 centre moved by -t2 along cam0's axes
    T0 = seq.poses_cam0[2]
    c2 = seq.T_world_cam2(2)[:3, 3]
    expected = T0[:3, :3] @ (-seq.calib.T_cam2_cam0[:3, 3]) + T0[:3, 3]
    np.testing.assert_allclose(c2, expected, atol=1e-12)
    assert 0.055 < np.linalg.norm(c2 - T0[:3, 3]) < 0.065
    # first pose is the identity: the world is the first cam0 frame
    np.testing.assert_allclose(seq.poses_cam0[0], np.eye(4), atol=1e-6)


def test_real_poses_and_calib_files(kitti_real):
    poses = read_poses_file(kitti_real / "odometry" / "poses" / "00.txt")
    assert poses.shape == (4541, 4, 4)
    steps = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
    assert 5 < steps.mean() * 10 < 12  # ~8 m/s at 10 Hz
    data = read_calib_file(kitti_real / "odometry" / "sequences" / "00" / "calib.txt")  # trailing spaces, no newline
    assert set(data) >= {"P0", "P1", "P2", "P3", "Tr"}


@pytest.mark.parametrize("frame", ["000000", "000001", "000002"])
def test_real_lidar_projects_onto_real_image(frame, kitti_real):
    """Real HDL-64E scan through real object calibration into the real image: geometry is consistent."""
    obj = kitti_real / "object" / "training"
    calib = read_object_calibration(obj / "calib" / f"{frame}.txt")
    scan = read_velodyne_bin(obj / "velodyne" / f"{frame}.bin")
    assert 100_000 < len(scan) < 130_000
    img = cv2.imread(str(obj / "image_2" / f"{frame}.png"))
    h, w = img.shape[:2]
    pts = geometry.transform_points(calib.T_cam2_velo, scan[:, :3])
    depth = geometry.lidar_depth_image(pts, calib.K2, h, w)
    valid = depth > 0
    assert 10_000 < valid.sum() < 30_000  # about a sixth of the scan lies in the camera's view
    assert depth[valid].max() < 120 and depth[valid].min() > 1.0
    # Road in the lower image: depth shrinks towards the bottom rows (the ground plane)
    rows = [int(h * f) for f in (0.8, 0.87, 0.95)]
    med = [np.median(depth[r - 3:r + 3][valid[r - 3:r + 3]]) for r in rows]
    assert med[0] > med[1] > med[2]
    # Ground points in view: camera height above them ≈ 1.65 m (KITTI's mount)
    near = valid[int(h * 0.9):, w // 3: 2 * w // 3]
    assert near.sum() > 50
    vv, uu = np.nonzero(valid[int(h * 0.9):, w // 3: 2 * w // 3])
    z = depth[int(h * 0.9):, w // 3: 2 * w // 3][vv, uu]
    y = geometry.backproject_pixels(calib.K2, uu + w // 3, vv + int(h * 0.9), z)[:, 1]
    assert 1.4 < np.median(y) < 1.9


# ------------------------------------------------------------------ bad input: one clear error line


def expect_error(match: str, fn, *args):
    with pytest.raises(MonoMapError, match=match):
        fn(*args)


def test_missing_sequence(tmp_path):
    expect_error(r"sequences/77: sequence '77' not found", KittiSequence, tmp_path, "77")


def test_malformed_calib(tmp_path):
    seq = make_sequence(tmp_path)
    (seq / "calib.txt").write_text("P2: 1 2 3\nTr: " + " ".join(["0"] * 12))
    expect_error(r"calib.txt: calibration entry 'P2' must hold 12", KittiSequence, tmp_path, "42")
    (seq / "calib.txt").write_text("P0: 1 0 0 0 0 1 0 0 0 0 1 0\n")
    expect_error(r"calib.txt: calibration entry 'P2' missing", KittiSequence, tmp_path, "42")
    (seq / "calib.txt").write_text("P2: 7 0 6 0 0 7 1 0 0 0 1 x\nTr: 1 0 0 0 0 1 0 0 0 0 1 0")
    expect_error(r"calib.txt:1: non-numeric", KittiSequence, tmp_path, "42")


def test_malformed_poses(tmp_path):
    make_sequence(tmp_path)
    poses = tmp_path / "poses" / "42.txt"
    lines = poses.read_text().splitlines()
    poses.write_text("\n".join(lines[:2] + ["1 0 0"] + lines[3:]))
    expect_error(r"42.txt:3: a pose needs 12 numbers", KittiSequence, tmp_path, "42")
    poses.write_text("\n".join(lines[:1] + [lines[1].replace(lines[1].split()[3], "nan")] + lines[2:]))
    expect_error(r"42.txt:2: pose holds NaN", KittiSequence, tmp_path, "42")


def test_pose_count_mismatch(tmp_path):
    make_sequence(tmp_path, n=5)
    poses = tmp_path / "poses" / "42.txt"
    poses.write_text("\n".join(poses.read_text().splitlines()[:4]) + "\n")
    expect_error(r"42.txt: 4 poses for 5 images", KittiSequence, tmp_path, "42")


def test_unreadable_and_wrong_size_images(tmp_path):
    """Every image's header is checked when the sequence is opened, before any work."""
    seq_dir = make_sequence(tmp_path)
    good = (seq_dir / "image_2" / "000003.png").read_bytes()
    (seq_dir / "image_2" / "000003.png").write_bytes(b"not a png")
    expect_error(r"000003.png: unreadable image", KittiSequence, tmp_path, "42")
    (seq_dir / "image_2" / "000003.png").write_bytes(good)
    cv2.imwrite(str(seq_dir / "image_2" / "000000.png"), np.zeros((H + 1, W, 3), np.uint8))
    expect_error(r"000000.png: image is 40×25, the sequence's other images are 40×24", KittiSequence, tmp_path, "42")


def test_images_resized_against_the_calibration_refused(tmp_path):
    seq_dir = make_sequence(tmp_path)
    (seq_dir / "calib.txt").write_text(scaled_calib_text(2 * W, 2 * H))
    expect_error(r"image_2: images are 40×24 but calib.txt's principal point .* about 78×47",
                 KittiSequence, tmp_path, "42")


def test_grayscale_image_refused(tmp_path):
    seq_dir = make_sequence(tmp_path)
    cv2.imwrite(str(seq_dir / "image_2" / "000002.png"), np.zeros((H, W), np.uint8))
    expect_error(r"000002.png: grayscale image", KittiSequence, tmp_path, "42")


def test_bad_velodyne_size(tmp_path):
    seq_dir = make_sequence(tmp_path)
    (seq_dir / "velodyne" / "000002.bin").write_bytes(b"\0" * 20)
    seq = KittiSequence(tmp_path, "42")
    expect_error(r"000002.bin: velodyne scan size 20 B is not a multiple of 16", seq.velodyne, 2)


def test_cli_prints_one_line_error(tmp_path, capsys):
    code = cli_main(["demo", "--data-root", str(tmp_path), "--seq", "nosuchseq"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2
    assert len(err) == 1 and err[0].startswith("mono-map: error: ") and "nosuchseq" in err[0]
    assert "Traceback" not in err[0]


def test_synthetic_prefix_being_extended_reads_only_marked_frames(tmp_path):
    """While a synthetic prefix grows in place, image_2/ holds frames beyond the marker: ignore them."""
    import json

    seq_dir = make_sequence(tmp_path, n=5)
    (seq_dir / "synth.json").write_text(json.dumps({"n_frames": 4}))
    poses = tmp_path / "poses" / "42.txt"
    poses.write_text("\n".join(poses.read_text().splitlines()[:4]) + "\n")
    (seq_dir / "times.txt").write_text("".join(f"{0.1 * i:e}\n" for i in range(4)))
    seq = KittiSequence(tmp_path, "42")
    assert len(seq) == 4 and seq.is_synthetic
    (seq_dir / "synth.json").write_text("{}")
    expect_error(r"synth.json: malformed synthetic-sequence marker", KittiSequence, tmp_path, "42")
