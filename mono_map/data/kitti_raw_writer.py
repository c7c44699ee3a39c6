"""Write an odometry-layout sequence (synthetic or real) as a KITTI *raw* drive: the round trip's other half.

The odometry layout holds neither the rectifying rotation nor the IMU, so a :class:`RawRig` supplies them
(small made-up rotations, so the reader's chain ``R_rect_00 · [R|T] · T_velo_imu`` is really exercised):

- ``calib_velo_to_cam.txt``: ``[R|T] = R_rect_00⁻¹ · Tr``, so that ``R_rect_00 · [R|T]`` is ``Tr`` again;
- ``calib_cam_to_cam.txt``: ``P_rect_0X`` = the odometry ``P0…P3``, ``R_rect_00`` = the rig's, ``S_rect_0X`` =
  the image size (``K``, ``D``, ``R``, ``T`` of the unrectified cameras are placeholders);
- ``calib_imu_to_velo.txt``: the rig's IMU → velodyne;
- ``oxts/data``: the poses through the IMU chain and the inverse Mercator conversion (velocities,
  accelerations and rates 0); ``*/timestamps.txt`` from ``times.txt``; images and scans copied;
  a synthetic sequence's dense depth goes to ``depth_02/data`` and its ``synth.json`` beside them.
"""

from __future__ import annotations

import json
import os
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mono_map import geometry
from mono_map.data import kitti_raw
from mono_map.data.kitti_files import read_calib_file
from mono_map.data.kitti_odometry import KittiSequence
from mono_map.errors import MonoMapError
from mono_map.io import staged_dir, write_text_atomic

SYNTHETIC_DATE = "2000_01_01"   # the date folder of synthetic raw drives (never a real recording day)


def synthetic_drive_name(recipe_name: str) -> str:
    """The raw drive name of a synthetic sequence: ``2000_01_01_drive_<recipe>_sync``."""
    return f"{SYNTHETIC_DATE}_drive_{recipe_name}_sync"


@dataclass(frozen=True)
class RawRig:
    """What a raw drive has and an odometry sequence lacks (radians, metres, degrees for lat/lon).

    rect: R_rect_00 as roll/pitch/yaw-style angles (≈ 0.6° in all); imu: IMU → velodyne rotation angles;
    imu_t: its translation (the real 2011-09-26 rig's); origin: the first OXTS packet's lat, lon, alt,
    roll, pitch, yaw."""

    rect: tuple[float, float, float] = (0.006, -0.008, 0.004)
    imu: tuple[float, float, float] = (0.012, -0.02, 0.015)
    imu_t: tuple[float, float, float] = (-0.8086759, 0.3195559, -0.7997231)
    origin: tuple[float, float, float, float, float, float] = (49.015003, 8.434280, 116.4, 0.02, -0.01, 0.7)

    def R_rect_00(self) -> np.ndarray:
        return geometry.make_pose(kitti_raw.euler_rotation(*map(np.float64, self.rect)))

    def T_velo_imu(self) -> np.ndarray:
        return geometry.make_pose(kitti_raw.euler_rotation(*map(np.float64, self.imu)), np.array(self.imu_t))


def fmt(values) -> str:
    """Numbers as text that parses back to the same float64 (``repr`` precision)."""
    return " ".join(repr(float(x)) for x in np.ravel(values))


def calib_texts(P: dict[str, np.ndarray], T_cam0_velo: np.ndarray, image_size: tuple[int, int],
                rig: RawRig) -> dict[str, str]:
    """The three raw calibration files' text from odometry projections ``P`` ({"P0".."P3": 3×4}), ``Tr``
    (velodyne → rectified cam0) and the image size (H, W)."""
    H, W = image_size
    R_rect = rig.R_rect_00()
    T_unrect = geometry.pose_inverse(R_rect) @ T_cam0_velo
    stamp = "calib_time: 01-Jan-2000 00:00:00\n"
    cc = [stamp, "corner_dist: 9.950000e-02\n"]
    for c in range(4):
        Pc = P.get(f"P{c}", P["P2"])
        cc += [f"S_{c:02d}: {fmt([W, H])}\n", f"K_{c:02d}: {fmt(Pc[:, :3])}\n", f"D_{c:02d}: {fmt(np.zeros(5))}\n",
               f"R_{c:02d}: {fmt(np.eye(3))}\n", f"T_{c:02d}: {fmt(np.zeros(3))}\n", f"S_rect_{c:02d}: {fmt([W, H])}\n",
               f"R_rect_{c:02d}: {fmt(R_rect[:3, :3] if c == 0 else np.eye(3))}\n", f"P_rect_{c:02d}: {fmt(Pc)}\n"]
    T_vi = rig.T_velo_imu()
    return {
        "calib_cam_to_cam.txt": "".join(cc),
        "calib_velo_to_cam.txt": (f"{stamp}R: {fmt(T_unrect[:3, :3])}\nT: {fmt(T_unrect[:3, 3])}\n"
                                  f"delta_f: {fmt([0, 0])}\ndelta_c: {fmt([0, 0])}\n"),
        "calib_imu_to_velo.txt": f"{stamp}R: {fmt(T_vi[:3, :3])}\nT: {fmt(T_vi[:3, 3])}\n",
    }


def oxts_packets(poses: np.ndarray, T_cam0_velo: np.ndarray, rig: RawRig) -> np.ndarray:
    """(N, 30) OXTS packets of odometry poses (rectified cam0 in the first cam0) on ``rig``."""
    T_cam0_imu = T_cam0_velo @ rig.T_velo_imu()
    lat, lon, alt, roll, pitch, yaw = rig.origin
    T_w_imu0 = geometry.make_pose(kitti_raw.euler_rotation(np.float64(roll), np.float64(pitch), np.float64(yaw)))
    T_w_imu = kitti_raw.imu_poses(poses, T_cam0_imu, T_w_imu0)
    T_w_imu[0, :3, 3] = 0.0   # rounding only: the first IMU pose is the origin
    return kitti_raw.oxts_from_poses(T_w_imu, lat, lon, alt)


def check_raw_target(root: str | os.PathLike, drive: str, force: bool = False) -> Path:
    """The folder raw drive ``drive`` would be written to under ``root``, refused if it exists (unless ``force``
    and it is a drive this writer made: ``synth.json``; real data is never overwritten)."""
    date = kitti_raw.drive_date(drive)
    if date is None:
        raise MonoMapError(f"--drive: '{drive}' is not a raw drive name (YYYY_MM_DD_drive_NAME_sync, NAME letters "
                           "and digits)")
    drive_dir = Path(root) / date / drive
    if drive_dir.exists() and not force:
        raise MonoMapError(f"{drive_dir}: raw drive exists (pass --force to rewrite it)")
    if drive_dir.exists() and not (drive_dir / "synth.json").is_file():
        raise MonoMapError(f"{drive_dir}: a raw drive that mono-map did not write (no synth.json) is never "
                           "overwritten; choose another --drive or remove it yourself")
    return drive_dir


def write_raw_drive(seq: KittiSequence, root: str | os.PathLike, drive: str, frames: list[int] | None = None,
                    rig: RawRig = RawRig(), force: bool = False) -> Path:
    """Write frames ``frames`` (default all) of the odometry sequence ``seq`` as raw drive ``drive`` under the
    raw root ``root`` (``root/<date>/<drive>``; the date folder's calibration files are written, or must
    already say the same). Poses are re-based on the first written frame. ``force`` rewrites a drive this
    writer made from a synthetic sequence (``synth.json``); any other existing drive is refused. Returns the
    drive folder."""
    from mono_map.progress import progress

    if seq.poses_cam0 is None:
        raise MonoMapError(f"{seq.pose_path}: poses needed to write OXTS for a raw drive")
    idx = list(range(len(seq))) if frames is None else [int(i) for i in frames]
    if any(not 0 <= i < len(seq) for i in idx):
        raise MonoMapError(f"{seq.path}: frames {min(idx)}..{max(idx)} out of range (sequence has {len(seq)} frames)")
    if not idx:
        raise MonoMapError(f"{seq.path}: no frames to write")
    drive_dir = check_raw_target(root, drive, force)
    date_dir = drive_dir.parent
    calib_src = seq.path / "calib.txt"
    P = {k: v.reshape(3, 4) for k, v in read_calib_file(calib_src).items() if k in ("P0", "P1", "P2", "P3")}
    texts = calib_texts(P, seq.calib.T_cam0_velo, seq.image_size, rig)
    for name, text in texts.items():   # one rig per date folder
        path = date_dir / name
        if path.is_file() and path.read_text() != text:
            raise MonoMapError(f"{path}: the date folder holds another rig's calibration; write the drive under "
                               f"another date or root")
    poses = seq.poses_cam0[idx]
    poses = geometry.pose_inverse(poses[0]) @ poses
    oxts = oxts_packets(poses, seq.calib.T_cam0_velo, rig)
    times = kitti_raw.format_timestamps(seq.times[idx] - seq.times[idx[0]])
    for name, text in texts.items():
        if not (date_dir / name).is_file():
            write_text_atomic(date_dir / name, text)
    if drive_dir.exists():
        shutil.rmtree(drive_dir)
    with staged_dir(drive_dir) as stage:
        for sub in ("image_02", "velodyne_points", "oxts"):
            (stage / sub / "data").mkdir(parents=True)
            (stage / sub / "timestamps.txt").write_text(times)
        for k, i in enumerate(progress(idx, total=len(idx), desc=f"raw {drive}", unit="frame")):
            stem = f"{k:010d}"
            shutil.copyfile(seq.image_files[i], stage / "image_02" / "data" / f"{stem}.png")
            if seq.velodyne_files:
                shutil.copyfile(seq.velodyne_files[i], stage / "velodyne_points" / "data" / f"{stem}.bin")
            (stage / "oxts" / "data" / f"{stem}.txt").write_text(fmt(oxts[k][:25]) + " " +
                                                                 " ".join(str(int(x)) for x in oxts[k][25:]) + "\n")
            depth = seq.depth_dir / seq.image_files[i].name
            if depth.is_file():
                (stage / "depth_02" / "data").mkdir(parents=True, exist_ok=True)
                shutil.copyfile(depth, stage / "depth_02" / "data" / f"{stem}.png")
        marker = seq.path / "synth.json"
        if marker.is_file():
            info = json.loads(marker.read_text())
            info.update(n_frames=len(idx), raw_frames=[int(i) for i in idx], odometry_sequence=seq.name)
            (stage / "synth.json").write_text(json.dumps(info, indent=1))
    return drive_dir
