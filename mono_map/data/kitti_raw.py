"""KITTI *raw* drives: the pure maths and text formats of the raw layout (no file listing, no I/O).

Layout under a raw root (the standard KITTI raw download, ``*_sync`` drives)::

    2011_09_26/calib_cam_to_cam.txt      S_rect_02 (image size), P_rect_02 (3×4), R_rect_00 (3×3), …
    2011_09_26/calib_velo_to_cam.txt     R, T: velodyne → unrectified cam0
    2011_09_26/calib_imu_to_velo.txt     R, T: IMU (OXTS) → velodyne
    2011_09_26/2011_09_26_drive_0013_sync/image_02/data/NNNNNNNNNN.png, image_02/timestamps.txt
    2011_09_26/2011_09_26_drive_0013_sync/velodyne_points/data/NNNNNNNNNN.bin
    2011_09_26/2011_09_26_drive_0013_sync/oxts/data/NNNNNNNNNN.txt   30 numbers: lat lon alt roll pitch yaw …

The reader (:class:`mono_map.data.kitti_raw_reader.KittiRawSequence`) expresses everything in the odometry
convention: velodyne → rectified cam0 is ``T_cam0_velo = R_rect_00 · [R | T]``; poses are rectified cam0
in the first frame's cam0, ``T_world_cam0(i) = T_cam0_imu · T_w_imu(0)⁻¹ · T_w_imu(i) · T_cam0_imu⁻¹``
with ``T_cam0_imu = T_cam0_velo · T_velo_imu`` and ``T_w_imu`` from OXTS by pykitti's formulas
(Mercator projection scaled by the first latitude, ``R = Rz(yaw) · Ry(pitch) · Rx(roll)``).
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass
from datetime import datetime

import numpy as np

from mono_map import geometry
from mono_map.errors import MonoMapError

EARTH_RADIUS = 6378137.0   # metres, pykitti's (and KITTI devkit's) Mercator radius
OXTS_FIELDS = 30           # lat lon alt roll pitch yaw vn ve vf vl vu ax ay az af al au wx wy wz wf wl wu
                           # pos_accuracy vel_accuracy navstat numsats posmode velmode orimode
CALIB_FILES = ("calib_cam_to_cam.txt", "calib_velo_to_cam.txt", "calib_imu_to_velo.txt")
DRIVE_NAME = re.compile(r"^(\d{4}_\d{2}_\d{2})_drive_([A-Za-z0-9]+)_sync$")
EIGEN_SPLIT_SIZE = 697


def drive_date(name: str) -> str | None:
    """The date folder of a raw drive name (``2011_09_26_drive_0013_sync`` → ``2011_09_26``), else None."""
    m = DRIVE_NAME.match(name)
    return m.group(1) if m else None


# ---------------------------------------------------------------------------------------------
# Calibration
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class RawCalibration:
    """The raw calibration of image_02 and the velodyne (metres, 4×4 poses ``T_a_b``: b → a).

    P_rect_02: 3×4 rectified projection of image_02 (in rectified cam0 coordinates).
    R_rect_00: 4×4 rectifying rotation of cam0.  T_cam0unrect_velo: velodyne → unrectified cam0.
    T_velo_imu: IMU → velodyne.  image_size: (H, W) from S_rect_02.
    P_rect_03: 3×4 rectified projection of image_03 (the right colour camera), None if the file has none.
    """

    P_rect_02: np.ndarray
    R_rect_00: np.ndarray
    T_cam0unrect_velo: np.ndarray
    T_velo_imu: np.ndarray
    image_size: tuple[int, int]
    P_rect_03: np.ndarray | None = None

    @property
    def T_cam0_velo(self) -> np.ndarray:
        """Velodyne → rectified cam0 (the odometry layout's ``Tr``)."""
        return self.R_rect_00 @ self.T_cam0unrect_velo

    @property
    def T_cam0_imu(self) -> np.ndarray:
        """IMU → rectified cam0."""
        return self.T_cam0_velo @ self.T_velo_imu


def blank_calib_time(text: str) -> str:
    """The raw calibration files' ``calib_time: 09-Jan-2012 13:57:47`` line (not numbers) made blank,
    keeping the other lines' numbers for error messages."""
    return "\n".join("" if line.strip().startswith("calib_time:") else line for line in text.splitlines())


def _entry(data: dict[str, np.ndarray], key: str, size: int, path) -> np.ndarray:
    if key not in data:
        raise MonoMapError(f"{path}: calibration entry '{key}' missing")
    value = data[key]
    if value.size != size or not np.all(np.isfinite(value)):
        raise MonoMapError(f"{path}: calibration entry '{key}' must hold {size} finite numbers (got {value.size})")
    return value


def _rotation(value: np.ndarray, what: str, path) -> np.ndarray:
    R = value.reshape(3, 3)
    if np.abs(R @ R.T - np.eye(3)).max() > 1e-3 or np.linalg.det(R) < 0:
        raise MonoMapError(f"{path}: {what} is not a rotation (not orthonormal)")
    return R


def raw_calibration(cam_to_cam: dict[str, np.ndarray], velo_to_cam: dict[str, np.ndarray],
                    imu_to_velo: dict[str, np.ndarray], paths: tuple = CALIB_FILES) -> RawCalibration:
    """The checked calibration chain from the three parsed raw files (``paths`` name them in errors)."""
    p_cc, p_vc, p_iv = paths
    P = _entry(cam_to_cam, "P_rect_02", 12, p_cc).reshape(3, 4)
    if P[0, 0] <= 0 or P[1, 1] <= 0 or abs(P[2, 2] - 1.0) > 1e-6:
        raise MonoMapError(f"{p_cc}: P_rect_02 is not a rectified projection (need fx, fy > 0 and P[2,2] = 1)")
    R_rect = _rotation(_entry(cam_to_cam, "R_rect_00", 9, p_cc), "R_rect_00", p_cc)
    size = _entry(cam_to_cam, "S_rect_02", 2, p_cc)
    if np.any(size < 1) or np.any(size != np.round(size)):
        raise MonoMapError(f"{p_cc}: S_rect_02 must be the image size in whole pixels (got {size.tolist()})")
    R_vc = _rotation(_entry(velo_to_cam, "R", 9, p_vc), "R (velodyne → cam0)", p_vc)
    T_vc = _entry(velo_to_cam, "T", 3, p_vc)
    R_iv = _rotation(_entry(imu_to_velo, "R", 9, p_iv), "R (IMU → velodyne)", p_iv)
    T_iv = _entry(imu_to_velo, "T", 3, p_iv)
    P3 = cam_to_cam.get("P_rect_03")   # the right colour camera (optional: image_03 is optional)
    P3 = P3.reshape(3, 4) if P3 is not None and P3.size == 12 else None
    return RawCalibration(P_rect_02=P, R_rect_00=geometry.make_pose(R_rect), P_rect_03=P3,
                          T_cam0unrect_velo=geometry.make_pose(R_vc, T_vc), T_velo_imu=geometry.make_pose(R_iv, T_iv),
                          image_size=(int(size[1]), int(size[0])))


# ---------------------------------------------------------------------------------------------
# OXTS ↔ poses
# ---------------------------------------------------------------------------------------------


def parse_oxts_text(text: str, path: str | os.PathLike = "<oxts>") -> np.ndarray:
    """One OXTS file (one line of exactly 30 numbers) → float64 (30,)."""
    lines = [line for line in text.splitlines() if line.strip()]
    if len(lines) != 1:
        raise MonoMapError(f"{path}: an OXTS file holds one line of {OXTS_FIELDS} numbers (found {len(lines)} lines)")
    try:
        values = np.array([float(x) for x in lines[0].split()], dtype=np.float64)
    except ValueError:
        raise MonoMapError(f"{path}: non-numeric OXTS value") from None
    if values.size != OXTS_FIELDS:
        raise MonoMapError(f"{path}: an OXTS line needs {OXTS_FIELDS} numbers (got {values.size})")
    if not np.all(np.isfinite(values[:6])):
        raise MonoMapError(f"{path}: OXTS position or orientation is NaN or infinite")
    if abs(values[0]) >= 90:
        raise MonoMapError(f"{path}: OXTS latitude {values[0]} is not within (-90, 90) degrees")
    return values


def euler_rotation(roll: np.ndarray, pitch: np.ndarray, yaw: np.ndarray) -> np.ndarray:
    """(N, 3, 3) rotations ``Rz(yaw) · Ry(pitch) · Rx(roll)`` (radians), pykitti's convention."""
    cr, sr, cp, sp, cy, sy = np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch), np.cos(yaw), np.sin(yaw)
    R = np.empty(np.shape(roll) + (3, 3))
    R[..., 0, 0], R[..., 0, 1], R[..., 0, 2] = cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr
    R[..., 1, 0], R[..., 1, 1], R[..., 1, 2] = sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr
    R[..., 2, 0], R[..., 2, 1], R[..., 2, 2] = -sp, cp * sr, cp * cr
    return R


def oxts_poses(oxts: np.ndarray) -> np.ndarray:
    """(N, 30) OXTS packets → (N, 4, 4) ``T_w_imu``: east-north-up metres from the first packet's position
    (Mercator scaled by the first latitude), orientation from roll, pitch, yaw — pykitti's
    ``load_oxts_packets_and_poses``."""
    oxts = np.asarray(oxts, dtype=np.float64)
    lat, lon, alt = oxts[:, 0], oxts[:, 1], oxts[:, 2]
    scale = np.cos(lat[0] * np.pi / 180.0)
    t = np.stack([scale * lon * np.pi * EARTH_RADIUS / 180.0,
                  scale * EARTH_RADIUS * np.log(np.tan((90.0 + lat) * np.pi / 360.0)), alt], 1)
    T = np.tile(np.eye(4), (len(oxts), 1, 1))
    T[:, :3, :3] = euler_rotation(oxts[:, 3], oxts[:, 4], oxts[:, 5])
    T[:, :3, 3] = t - t[0]
    return T


def oxts_from_poses(T_w_imu: np.ndarray, lat0: float, lon0: float, alt0: float) -> np.ndarray:
    """The inverse of :func:`oxts_poses`: (N, 4, 4) ``T_w_imu`` (the first at the origin) → (N, 30) packets whose
    first position is (lat0, lon0, alt0) degrees / metres; velocities, accelerations and rates 0, flags
    (navstat 4, 10 satellites, modes 5 5 6)."""
    T = np.asarray(T_w_imu, dtype=np.float64)
    if np.abs(T[0, :3, 3]).max() > 1e-9:
        raise ValueError("oxts_from_poses: the first pose must be at the origin")
    scale = np.cos(lat0 * np.pi / 180.0)
    mx0 = scale * lon0 * np.pi * EARTH_RADIUS / 180.0
    my0 = scale * EARTH_RADIUS * np.log(np.tan((90.0 + lat0) * np.pi / 360.0))
    mx, my = T[:, 0, 3] + mx0, T[:, 1, 3] + my0
    out = np.zeros((len(T), OXTS_FIELDS))
    out[:, 0] = 360.0 / np.pi * np.arctan(np.exp(my / (scale * EARTH_RADIUS))) - 90.0
    out[:, 1] = mx * 180.0 / (scale * np.pi * EARTH_RADIUS)
    out[:, 2] = T[:, 2, 3] + alt0
    out[0, :3] = lat0, lon0, alt0     # exactly: the first latitude sets the Mercator scale
    R = T[:, :3, :3]
    out[:, 3] = np.arctan2(R[:, 2, 1], R[:, 2, 2])                # roll
    out[:, 4] = -np.arcsin(np.clip(R[:, 2, 0], -1.0, 1.0))        # pitch
    out[:, 5] = np.arctan2(R[:, 1, 0], R[:, 0, 0])                # yaw
    out[:, 25:30] = 4, 10, 5, 5, 6
    return out


def poses_cam0(T_w_imu: np.ndarray, T_cam0_imu: np.ndarray) -> np.ndarray:
    """IMU poses (N, 4, 4) → rectified cam0 in the first frame's cam0 (the odometry convention).

    Full matrix inverses, as pykitti: a calibration's rotation printed to 9 digits is orthonormal only to
    ~1e-9, and a transposed rotation would move poses 100 m away by ~1e-7 m."""
    return T_cam0_imu @ np.linalg.inv(T_w_imu[0]) @ T_w_imu @ np.linalg.inv(T_cam0_imu)


def imu_poses(poses: np.ndarray, T_cam0_imu: np.ndarray, T_w_imu0: np.ndarray) -> np.ndarray:
    """The inverse of :func:`poses_cam0` for a chosen first IMU pose ``T_w_imu0`` (at the origin)."""
    return T_w_imu0 @ np.linalg.inv(T_cam0_imu) @ poses @ T_cam0_imu


# ---------------------------------------------------------------------------------------------
# Timestamps
# ---------------------------------------------------------------------------------------------


def parse_timestamps(text: str, path: str | os.PathLike = "<timestamps>") -> np.ndarray:
    """Raw ``timestamps.txt`` (``2011-09-26 13:02:25.964389445`` a line) → float64 seconds since the first."""
    ns = []
    for lineno, line in enumerate(text.splitlines(), 1):
        if not line.strip():
            continue
        whole, _, frac = line.strip().partition(".")
        try:
            t = datetime.strptime(whole, "%Y-%m-%d %H:%M:%S")
            if frac and not frac.isdigit():
                raise ValueError
        except ValueError:
            raise MonoMapError(f"{path}:{lineno}: malformed timestamp (expected 'YYYY-MM-DD HH:MM:SS.fffffffff')") from None
        seconds = int((t - datetime(2000, 1, 1)).total_seconds())   # whole seconds: exact
        ns.append(seconds * 10**9 + int((frac or "0").ljust(9, "0")[:9]))
    if not ns:
        raise MonoMapError(f"{path}: no timestamps")
    ns = np.array(ns, dtype=np.int64)
    return (ns - ns[0]).astype(np.float64) * 1e-9


def format_timestamps(times: np.ndarray, start: datetime = datetime(2011, 9, 26, 13, 0, 0)) -> str:
    """Seconds since the first frame → raw ``timestamps.txt`` text (nanoseconds), starting at ``start``."""
    from datetime import timedelta

    lines = []
    for t in np.asarray(times, dtype=np.float64):
        ns = int(round(float(t) * 1e9))
        stamp = start + timedelta(seconds=ns // 10**9)
        lines.append(f"{stamp:%Y-%m-%d %H:%M:%S}.{ns % 10**9:09d}")
    return "\n".join(lines) + "\n"


# ---------------------------------------------------------------------------------------------
# The Eigen split and its ground truth
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class SplitFrame:
    """One line of a split file: ``date/drive frame side`` (e.g. ``2011_09_26/2011_09_26_drive_0002_sync 0000000069 l``)."""

    date: str
    drive: str
    frame: int
    side: str


def parse_split(text: str, path: str | os.PathLike = "<split>") -> list[SplitFrame]:
    """A split file's lines (left camera only) → [SplitFrame]; a malformed line names ``path:line``."""
    out = []
    for lineno, line in enumerate(text.splitlines(), 1):
        if not line.strip():
            continue
        parts = line.split()
        if len(parts) != 3 or parts[0].count("/") != 1:
            raise MonoMapError(f"{path}:{lineno}: a split line is 'DATE/DRIVE FRAME SIDE' (got {line.strip()!r})")
        date, drive = parts[0].split("/")
        if drive_date(drive) != date:
            raise MonoMapError(f"{path}:{lineno}: {parts[0]!r} is no raw drive 'YYYY_MM_DD/YYYY_MM_DD_drive_NNNN_sync'")
        if not parts[1].isdigit():
            raise MonoMapError(f"{path}:{lineno}: frame {parts[1]!r} is not a frame number")
        if parts[2] not in ("l", "r"):
            raise MonoMapError(f"{path}:{lineno}: side {parts[2]!r} is neither 'l' nor 'r'")
        if parts[2] == "r":
            raise MonoMapError(f"{path}:{lineno}: right-camera frames (side 'r') are not supported; image_02 only")
        out.append(SplitFrame(date, drive, int(parts[1]), parts[2]))
    if not out:
        raise MonoMapError(f"{path}: the split lists no frames")
    return out


def eigen_depth_map(scan: np.ndarray, P_rect_02: np.ndarray, T_cam0_velo: np.ndarray,
                    height: int, width: int) -> np.ndarray:
    """LiDAR depth of image_02 as Eigen's protocol makes it (monodepth2's ``generate_depth_map``):
    points ahead of the velodyne (x ≥ 0) projected by ``P_rect_02 · R_rect_00 · [R|T]``; depth is the
    projection's third coordinate (rectified cam0 z + P_rect_02[2,3]); pixels ``round(u) - 1``,
    ``round(v) - 1``; the nearest point wins a pixel. (H, W) float32 metres, 0 = none."""
    scan = np.asarray(scan)
    pts = scan[scan[:, 0] >= 0, :3].astype(np.float64)
    hom = np.concatenate([pts, np.ones((len(pts), 1))], 1)
    proj = hom @ (P_rect_02 @ T_cam0_velo).T
    z = proj[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = np.round(proj[:, 0] / z) - 1
        v = np.round(proj[:, 1] / z) - 1
    ok = np.isfinite(u) & np.isfinite(v) & (u >= 0) & (v >= 0) & (u < width) & (v < height) & (z > 0)
    idx = v[ok].astype(np.int64) * width + u[ok].astype(np.int64)
    depth = np.full(height * width, np.inf)
    np.minimum.at(depth, idx, z[ok])
    depth[~np.isfinite(depth)] = 0.0
    return depth.reshape(height, width).astype(np.float32)
