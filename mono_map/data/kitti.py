"""KITTI odometry sequences and raw drives (real or synthetic): a pure validating reader (it never renders
or writes). A raw drive name (``2011_09_26_drive_0013_sync``) opens a :class:`KittiRawSequence` with the
same interface (the raw layout: :mod:`mono_map.data.kitti_raw`); everything below is the odometry layout.

Layout under a data root (the standard KITTI odometry download)::

    sequences/XX/image_2/NNNNNN.png   colour left camera (RGB)
    sequences/XX/velodyne/NNNNNN.bin  float32 x y z reflectance, velodyne frame
    sequences/XX/calib.txt            P0..P3 (3×4 rectified projections), Tr (velodyne → cam0)
    sequences/XX/times.txt            seconds
    sequences/XX/depth_2/NNNNNN.png   optional dense depth of image_2 (synthetic sequences only)
    poses/XX.txt                      T_world_cam0, 3×4 per line; world = first cam0 frame

Every file is validated before use; bad input raises :class:`MonoMapError` naming the
file.  Opening a sequence checks the listing, calibration, poses, times and every image's PNG
header (size, colour) against the calibration. Real and synthetic sequences read alike; a synthetic
one's ``synth.json`` only says how many frames are complete (rendering a missing synthetic sequence
is the commands' job: :mod:`mono_map.data.prepare`).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mono_map import geometry
from mono_map.data import kitti_raw
from mono_map.data.png import PNG_SIGNATURE, decode_image
from mono_map.errors import MonoMapError
from mono_map.paths import data_root

# ---------------------------------------------------------------------------------------------
# Validating parsers (array in / array out).
# ---------------------------------------------------------------------------------------------

REQUIRED_CALIB_KEYS = ("P2", "Tr")


def parse_calib_text(text: str, path: str | os.PathLike = "<calib>") -> dict[str, np.ndarray]:
    """The one KITTI calibration parser: ``KEY: numbers`` lines → ``{key: float64 array}``.

    Tolerant of trailing spaces, blank lines and a missing final newline; a line without ':'
    or with a non-numeric value raises MonoMapError naming ``path`` and the line.
    """
    data: dict[str, np.ndarray] = {}
    for lineno, line in enumerate(text.splitlines(), 1):
        if not line.strip():
            continue
        if ":" not in line:
            raise MonoMapError(f"{path}:{lineno}: malformed calibration line (expected 'KEY: numbers')")
        key, value = line.split(":", 1)
        try:
            data[key.strip()] = np.array([float(x) for x in value.split()], dtype=np.float64)
        except ValueError:
            raise MonoMapError(f"{path}:{lineno}: non-numeric value in calibration entry '{key.strip()}'") from None
    return data


def _read_text(path: Path, what: str) -> str:
    if not path.is_file():
        raise MonoMapError(f"{path}: {what} not found")
    try:
        return path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise MonoMapError(f"{path}: unreadable {what} (not text: {exc.__class__.__name__})") from None


def read_calib_file(path: str | os.PathLike) -> dict[str, np.ndarray]:
    """Parse and check a KITTI odometry ``calib.txt``.

    Returns ``{key: float64 array}``; checks that P2 and Tr hold 12 finite numbers,
    that P2's focal lengths are positive and that Tr's rotation is orthonormal.
    """
    path = Path(path)
    data = parse_calib_text(_read_text(path, "calibration file"), path)
    for key in REQUIRED_CALIB_KEYS:
        if key not in data:
            raise MonoMapError(f"{path}: calibration entry '{key}' missing (need {', '.join(REQUIRED_CALIB_KEYS)})")
        if data[key].size != 12 or not np.all(np.isfinite(data[key])):
            raise MonoMapError(f"{path}: calibration entry '{key}' must hold 12 finite numbers (got {data[key].size})")
    P2 = data["P2"].reshape(3, 4)
    if P2[0, 0] <= 0 or P2[1, 1] <= 0 or abs(P2[2, 2] - 1.0) > 1e-6:
        raise MonoMapError(f"{path}: P2 is not a rectified projection (need fx, fy > 0 and P2[2,2] = 1)")
    R = data["Tr"].reshape(3, 4)[:, :3]
    if np.abs(R @ R.T - np.eye(3)).max() > 1e-3 or np.linalg.det(R) < 0:
        raise MonoMapError(f"{path}: Tr's rotation is not orthonormal (is it a velodyne→cam0 transform?)")
    return data


def read_poses_file(path: str | os.PathLike) -> np.ndarray:
    """Read KITTI poses (12 numbers a line, T_world_cam0 3×4) as float64 (N, 4, 4)."""
    path = Path(path)
    rows = []
    for lineno, line in enumerate(_read_text(path, "poses file").splitlines(), 1):
        if not line.strip():
            continue
        try:
            values = [float(x) for x in line.split()]
        except ValueError:
            raise MonoMapError(f"{path}:{lineno}: non-numeric pose value") from None
        if len(values) != 12:
            raise MonoMapError(f"{path}:{lineno}: a pose needs 12 numbers (got {len(values)})")
        rows.append(values)
    if not rows:
        raise MonoMapError(f"{path}: poses file is empty")
    poses = np.zeros((len(rows), 4, 4))
    poses[:, :3, :] = np.array(rows).reshape(-1, 3, 4)
    poses[:, 3, 3] = 1.0
    if not np.all(np.isfinite(poses)):
        bad = int(np.argwhere(~np.isfinite(poses).all(axis=(1, 2)))[0, 0]) + 1
        raise MonoMapError(f"{path}:{bad}: pose holds NaN or infinity")
    R = poses[:, :3, :3]
    err = np.abs(R @ R.transpose(0, 2, 1) - np.eye(3)).max(axis=(1, 2))
    if err.max() > 1e-3:
        raise MonoMapError(f"{path}:{int(err.argmax()) + 1}: pose rotation is not orthonormal")
    det = np.linalg.det(R)
    if det.min() < 0:
        raise MonoMapError(f"{path}:{int(det.argmin()) + 1}: pose rotation is a reflection (determinant "
                           f"{det.min():.3f}), not a rotation")
    return poses


def read_times_file(path: str | os.PathLike) -> np.ndarray:
    """Read ``times.txt`` (one timestamp in seconds a line) as float64 (N,)."""
    path = Path(path)
    text = _read_text(path, "timestamps file")
    try:
        times = np.array([float(x) for x in text.split()], dtype=np.float64)
    except ValueError:
        raise MonoMapError(f"{path}: non-numeric timestamp") from None
    if not np.all(np.isfinite(times)):
        raise MonoMapError(f"{path}: timestamp is NaN or infinite")
    back = np.flatnonzero(np.diff(times) < 0)
    if len(back):
        raise MonoMapError(f"{path}:{int(back[0]) + 2}: timestamp {times[back[0] + 1]:g} s is earlier than the one "
                           f"before ({times[back[0]]:g} s); frames must be in time order")
    return times


def read_velodyne_bin(path: str | os.PathLike) -> np.ndarray:
    """Read a velodyne scan: float32 (N, 4) x y z reflectance in the velodyne frame (metres)."""
    path = Path(path)
    try:
        size = path.stat().st_size
    except OSError:
        raise MonoMapError(f"{path}: velodyne scan not found") from None
    if size == 0:
        raise MonoMapError(f"{path}: velodyne scan is empty (0 bytes)")
    if size % 16:
        raise MonoMapError(f"{path}: velodyne scan size {size} B is not a multiple of 16 (4 float32 per point)")
    scan = np.fromfile(path, dtype=np.float32).reshape(-1, 4)
    if not np.all(np.isfinite(scan)):
        raise MonoMapError(f"{path}: velodyne scan holds NaN or infinite values")
    far = np.abs(scan[:, :3]).max(axis=1) > MAX_LIDAR_RANGE
    if far.any():
        raise MonoMapError(f"{path}: {int(far.sum())} points lie more than {MAX_LIDAR_RANGE:g} m from the sensor "
                           f"(first: point {int(far.argmax())}); a corrupt scan?")
    return scan


MAX_LIDAR_RANGE = 2000.0  # metres: far beyond any automotive LiDAR (the HDL-64E reaches about 120 m)


def read_image_rgb(path: str | os.PathLike) -> np.ndarray:
    """Read a colour image as H×W×3 uint8 RGB (an alpha channel is dropped; grayscale is refused)."""
    import cv2

    img = decode_image(path)
    if img is None:
        raise MonoMapError(f"{path}: unreadable image")
    if img.ndim == 2 or img.shape[2] == 1:
        raise MonoMapError(f"{path}: grayscale image; a colour (RGB) image is needed (KITTI's image_2)")
    if img.dtype != np.uint8:
        raise MonoMapError(f"{path}: {img.dtype} image; an 8-bit colour image is needed")
    return cv2.cvtColor(img, cv2.COLOR_BGRA2RGB if img.shape[2] == 4 else cv2.COLOR_BGR2RGB)



PNG_GRAY_TYPES = (0, 4)  # IHDR colour types: 0 gray, 2 RGB, 3 palette, 4 gray+alpha, 6 RGBA


def read_png_header(path: str | os.PathLike) -> tuple[int, int, int]:
    """(width, height, colour type) from a PNG's IHDR chunk, without decoding the image."""
    path = Path(path)
    try:
        with open(path, "rb") as fh:
            head = fh.read(26)
    except OSError as exc:
        raise MonoMapError(f"{path}: unreadable image ({exc.strerror})") from None
    if len(head) < 26 or not head.startswith(PNG_SIGNATURE) or head[12:16] != b"IHDR":
        raise MonoMapError(f"{path}: unreadable image (not a PNG file)")
    return int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big"), head[25]


def check_images(files: list[Path], P2: np.ndarray, calib_path: Path) -> tuple[int, int]:
    """Check every image_2 PNG header: one size, colour, and the calibration made for that size.

    Returns (H, W). The calibration holds no image size, but its principal point lies near the
    image centre; a point outside the image's middle half means the images were resized (or
    the calibration belongs to other images) and the intrinsics would back-project wrongly.
    """
    from collections import Counter

    headers = [read_png_header(f) for f in files]
    sizes = Counter((w, h) for w, h, _ in headers)
    (W, H), _ = sizes.most_common(1)[0]
    for f, (w, h, colour) in zip(files, headers):
        if (w, h) != (W, H):
            raise MonoMapError(f"{f}: image is {w}×{h}, the sequence's other images are {W}×{H}")
        if colour in PNG_GRAY_TYPES:
            raise MonoMapError(f"{f}: grayscale image; image_2 must be colour (RGB)")
    cx, cy = float(P2[0, 2]), float(P2[1, 2])
    if not (0.25 * W < cx < 0.75 * W and 0.25 * H < cy < 0.75 * H):
        raise MonoMapError(
            f"{files[0].parent}: images are {W}×{H} but {calib_path.name}'s principal point ({cx:.1f}, {cy:.1f}) "
            f"is made for images of about {2 * cx:.0f}×{2 * cy:.0f}: resized images? (scale P2 with them)")
    return H, W


# ---------------------------------------------------------------------------------------------
# Calibration, frames, sequences
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Calibration:
    """Calibration of image_2 and the velodyne, from an odometry ``calib.txt``.

    P2: 3×4 rectified projection of image_2 (P2 = K2·[I | t2]).
    K2: 3×3 intrinsics of image_2 (pixels).
    T_cam0_velo: Tr, velodyne → cam0.  T_cam2_cam0: [I | t2] with t2 = K2⁻¹·P2[:, 3]
    (≈ +0.06 m along x).  T_cam2_velo = T_cam2_cam0 · T_cam0_velo.
    """

    P2: np.ndarray
    T_cam0_velo: np.ndarray

    @classmethod
    def from_file(cls, path: str | os.PathLike) -> "Calibration":
        data = read_calib_file(path)
        return cls(P2=data["P2"].reshape(3, 4), T_cam0_velo=geometry.make_pose(
            data["Tr"].reshape(3, 4)[:, :3], data["Tr"].reshape(3, 4)[:, 3]))

    @property
    def K2(self) -> np.ndarray:
        return geometry.intrinsics_from_projection(self.P2)

    @property
    def T_cam2_cam0(self) -> np.ndarray:
        return geometry.T_cam_cam0_from_projection(self.P2)

    @property
    def T_cam2_velo(self) -> np.ndarray:
        return self.T_cam2_cam0 @ self.T_cam0_velo


def read_object_calibration(path: str | os.PathLike) -> Calibration:
    """Calibration of a KITTI *object*-benchmark frame (P2, R0_rect, Tr_velo_to_cam) as a :class:`Calibration`.

    The object format keeps the rectifying rotation apart: velodyne → rectified cam0 is
    R0_rect · Tr_velo_to_cam, which is what the odometry ``Tr`` already is.
    """
    path = Path(path)
    data = parse_calib_text(_read_text(path, "calibration file"), path)
    sizes = {"P2": 12, "R0_rect": 9, "Tr_velo_to_cam": 12}
    for key, size in sizes.items():
        if key not in data or data[key].size != size:
            raise MonoMapError(f"{path}: object calibration entry '{key}' missing or not {size} numbers")
    R0 = geometry.make_pose(data["R0_rect"].reshape(3, 3))
    Tr = data["Tr_velo_to_cam"].reshape(3, 4)
    return Calibration(P2=data["P2"].reshape(3, 4), T_cam0_velo=R0 @ geometry.make_pose(Tr[:, :3], Tr[:, 3]))


class KittiSequence:
    """A validated KITTI odometry sequence under ``root`` (real or synthetic)."""

    def __init__(self, root: str | os.PathLike, name: str):
        self.root = Path(root)
        self.name = name
        self.path = self.root / "sequences" / name
        if not self.path.is_dir():
            raise MonoMapError(
                f"{self.path}: sequence '{name}' not found (expected KITTI odometry layout "
                f"sequences/{name}/{{image_2,velodyne,calib.txt,times.txt}} under {self.root})")
        self.calib = Calibration.from_file(self.path / "calib.txt")
        times = read_times_file(self.path / "times.txt")
        pose_path = self.root / "poses" / f"{name}.txt"
        poses = read_poses_file(pose_path) if pose_path.is_file() else None
        self.image_files = _listing(self.path / "image_2", ".png")
        self.velodyne_files = _listing(self.path / "velodyne", ".bin")
        # A synthetic prefix being extended in place briefly holds more frames than its
        # marker, poses and times: read only the frames the marker vouches for.
        n_marked = self._synthetic_frame_count()
        if n_marked is not None:
            self.image_files = self.image_files[:n_marked]
            self.velodyne_files = self.velodyne_files[:n_marked]
        n = len(self.image_files)
        if n == 0:
            raise MonoMapError(f"{self.path / 'image_2'}: no PNG images")
        if len(times) != n:
            raise MonoMapError(f"{self.path / 'times.txt'}: {len(times)} timestamps for {n} images in image_2/")
        if poses is not None and len(poses) != n:
            raise MonoMapError(f"{pose_path}: {len(poses)} poses for {n} images in {self.path / 'image_2'}")
        if self.velodyne_files and len(self.velodyne_files) != n:
            raise MonoMapError(
                f"{self.path / 'velodyne'}: {len(self.velodyne_files)} scans for {n} images in image_2/")
        self.image_size = check_images(self.image_files, self.calib.P2, self.path / "calib.txt")
        self.times = times
        self.poses_cam0 = poses
        self.pose_path = pose_path

    def _synthetic_frame_count(self) -> int | None:
        """Frame count recorded in ``synth.json`` (synthetic sequences), else None."""
        import json

        marker = self.path / "synth.json"
        if not marker.is_file():
            return None
        try:
            text = marker.read_text()
        except OSError as exc:  # unreadable, not malformed: re-rendering would not be the fix
            raise MonoMapError(f"{marker}: cannot read the synthetic-sequence marker ({exc.strerror}); "
                               "check its permissions") from None
        try:
            n = json.loads(text)["n_frames"]
        except (ValueError, KeyError, TypeError, IndexError, UnicodeDecodeError):
            n = None
        if not isinstance(n, int) or isinstance(n, bool) or n < 1:
            raise MonoMapError(f"{marker}: malformed synthetic-sequence marker (no positive integer n_frames; "
                               f"re-render with mono-map synth --seq {self.name} --force)")
        return n

    def __len__(self) -> int:
        return len(self.image_files)

    def __repr__(self) -> str:
        return f"KittiSequence({str(self.root)!r}, {self.name!r}, frames={len(self)})"

    def _check_index(self, i: int) -> int:
        if not -len(self) <= i < len(self):
            raise MonoMapError(f"{self.path}: frame {i} out of range (sequence has {len(self)} frames)")
        return i % len(self)

    @property
    def is_synthetic(self) -> bool:
        """True for sequences written by mono-map's generator (they carry ``synth.json``)."""
        return (self.path / "synth.json").is_file()

    def T_world_cam0(self, i: int) -> np.ndarray:
        if self.poses_cam0 is None:
            raise MonoMapError(f"{self.pose_path}: poses not available for sequence '{self.name}'")
        return self.poses_cam0[self._check_index(i)]

    def T_world_cam2(self, i: int) -> np.ndarray:
        """Pose of image_2 in the world (first cam0 frame): T_world_cam0 · inv(T_cam2_cam0)."""
        return self.T_world_cam0(i) @ geometry.pose_inverse(self.calib.T_cam2_cam0)

    def image(self, i: int) -> np.ndarray:
        """image_2 of frame i: H×W×3 uint8 RGB."""
        path = self.image_files[self._check_index(i)]
        img = read_image_rgb(path)
        if img.shape[:2] != self.image_size:
            raise MonoMapError(f"{path}: image is {img.shape[1]}×{img.shape[0]}, "
                               f"expected {self.image_size[1]}×{self.image_size[0]} like the sequence's other images")
        return img

    def velodyne(self, i: int) -> np.ndarray:
        """Velodyne scan of frame i: (N, 4) float32 x y z reflectance (velodyne frame, metres)."""
        if not self.velodyne_files:
            raise MonoMapError(f"{self.path / 'velodyne'}: no velodyne scans for sequence '{self.name}'")
        return read_velodyne_bin(self.velodyne_files[self._check_index(i)])

    @property
    def depth_dir(self) -> Path:
        """Where dense ground-truth depth of image_2 would be (synthetic sequences: ``depth_2/``)."""
        return self.path / "depth_2"

    def depth(self, i: int) -> np.ndarray | None:
        """Dense ground-truth depth of image_2 (metres, 0 = none) if :attr:`depth_dir` has it, else None."""
        from mono_map.data.depth_png import read_depth_png

        path = self.depth_dir / self.image_files[self._check_index(i)].name
        if not path.is_file():
            return None
        depth = read_depth_png(path)
        if depth.shape != self.image_size:
            raise MonoMapError(f"{path}: depth is {depth.shape[1]}×{depth.shape[0]}, "
                               f"expected {self.image_size[1]}×{self.image_size[0]}")
        return depth

    def lidar_depth(self, i: int) -> np.ndarray:
        """Sparse depth of image_2 from the velodyne scan (metres, 0 = no value), KITTI's practice."""
        scan = self.velodyne(i)
        pts_cam2 = geometry.transform_points(self.calib.T_cam2_velo, scan[:, :3])
        return geometry.lidar_depth_image(pts_cam2, self.calib.K2, *self.image_size)


def read_raw_calibration(date_dir: str | os.PathLike) -> kitti_raw.RawCalibration:
    """The three calibration files of a raw date folder, parsed and checked (:func:`kitti_raw.raw_calibration`)."""
    paths = tuple(Path(date_dir) / f for f in kitti_raw.CALIB_FILES)
    parsed = [parse_calib_text(kitti_raw.blank_calib_time(_read_text(p, "raw calibration file")), p) for p in paths]
    return kitti_raw.raw_calibration(*parsed, paths=paths)


class KittiRawSequence(KittiSequence):
    """A validated KITTI raw drive (``YYYY_MM_DD_drive_NNNN_sync``) with the odometry sequence's interface.

    ``root`` is a raw root (holding ``YYYY_MM_DD/``) or the date folder itself. Calibration from the
    date folder (``calib.P2`` = P_rect_02, ``calib.T_cam0_velo`` = R_rect_00 · [R|T]); poses from OXTS as
    rectified cam0 in the first frame's cam0 (:mod:`mono_map.data.kitti_raw`); ``times`` from
    ``image_02/timestamps.txt`` in seconds since the first frame. ``raw_calib`` keeps the whole chain.
    """

    def __init__(self, root: str | os.PathLike, name: str):
        self.root = Path(root)
        self.name = name
        date = kitti_raw.drive_date(name)
        if date is None:
            raise MonoMapError(f"'{name}' is not a raw drive name (YYYY_MM_DD_drive_NNNN_sync)")
        candidates = (self.root / date / name, self.root / name)
        self.path = next((p for p in candidates if p.is_dir()), candidates[0])
        if not self.path.is_dir():
            raise MonoMapError(
                f"{self.path}: raw drive '{name}' not found (expected the KITTI raw layout "
                f"{date}/{name}/{{image_02,velodyne_points,oxts}} and {date}/calib_*.txt under {self.root})")
        self.raw_calib = read_raw_calibration(self.path.parent)
        rc = self.raw_calib
        self.calib = Calibration(P2=rc.P_rect_02, T_cam0_velo=rc.T_cam0_velo)
        self.image_files = _listing(self.path / "image_02" / "data", ".png")
        self.velodyne_files = _listing(self.path / "velodyne_points" / "data", ".bin")
        oxts_files = _listing(self.path / "oxts" / "data", ".txt")
        n = len(self.image_files)
        if n == 0:
            raise MonoMapError(f"{self.path / 'image_02' / 'data'}: no PNG images")
        stamp_path = self.path / "image_02" / "timestamps.txt"
        times = kitti_raw.parse_timestamps(_read_text(stamp_path, "timestamps file"), stamp_path)
        if len(times) != n:
            raise MonoMapError(f"{stamp_path}: {len(times)} timestamps for {n} images in image_02/data")
        for folder, files, what in ((self.path / "oxts" / "data", oxts_files, "OXTS packets"),
                                    (self.path / "velodyne_points" / "data", self.velodyne_files, "scans")):
            if files or what != "scans":   # OXTS is required, scans are optional
                if len(files) != n:
                    raise MonoMapError(f"{folder}: {len(files)} {what} for {n} images in image_02/data")
                bad = next((f for f, g in zip(files, self.image_files) if f.stem != g.stem), None)
                if bad is not None:
                    raise MonoMapError(f"{bad}: no image of that frame in image_02/data (frames must match by name)")
        calib_path = self.path.parent / kitti_raw.CALIB_FILES[0]
        self.image_size = check_images(self.image_files, rc.P_rect_02, calib_path)
        if self.image_size != rc.image_size:
            raise MonoMapError(f"{self.image_files[0]}: image is {self.image_size[1]}×{self.image_size[0]}, but "
                               f"{calib_path}'s S_rect_02 says {rc.image_size[1]}×{rc.image_size[0]}")
        oxts = np.stack([kitti_raw.parse_oxts_text(_read_text(f, "OXTS file"), f) for f in oxts_files])
        self.times = times
        self.poses_cam0 = kitti_raw.poses_cam0(kitti_raw.oxts_poses(oxts), rc.T_cam0_imu)
        self.pose_path = self.path / "oxts"

    def __repr__(self) -> str:
        return f"KittiRawSequence({str(self.root)!r}, {self.name!r}, frames={len(self)})"

    @property
    def depth_dir(self) -> Path:
        """Dense ground-truth depth of image_02 (mono-map's synthetic drives only): ``depth_02/data/``."""
        return self.path / "depth_02" / "data"


def open_sequence(root: str | os.PathLike | None, name: str) -> KittiSequence:
    """Open and validate sequence ``name`` under ``root`` (``None`` → :func:`mono_map.paths.data_root`):
    a raw drive name (``2011_09_26_drive_0013_sync``) opens a :class:`KittiRawSequence`, any other an
    odometry :class:`KittiSequence`; both read alike downstream.

    Only reads; a command that may render a missing synthetic sequence calls
    :func:`mono_map.data.prepare.prepare_sequence` instead.
    """
    if kitti_raw.drive_date(name) is not None:
        return KittiRawSequence(data_root(root), name)
    if name.endswith("_extract") and kitti_raw.drive_date(name.removesuffix("_extract") + "_sync") is not None:
        raise MonoMapError(f"--seq: {name}: an unsynced, unrectified raw drive; mono-map reads the synced and "
                           f"rectified download ({name.removesuffix('_extract')}_sync)")
    return KittiSequence(data_root(root), name)


def _listing(folder: Path, suffix: str) -> list[Path]:
    """Files ``folder/*suffix`` in name order (KITTI's NNNNNN names; hidden temporary files are not
    frames); [] if the folder is missing."""
    if not folder.is_dir():
        return []
    found = sorted(p for p in folder.iterdir() if p.suffix == suffix and not p.name.startswith("."))
    for p in found:
        if not p.is_file():
            raise MonoMapError(f"{p}: a folder where a {suffix} frame file belongs")
    return found
