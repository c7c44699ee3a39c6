"""KITTI's files, read and validated (pure: path in, arrays out): the odometry ``calib.txt`` and its
``KEY: numbers`` format, poses, timestamps, velodyne scans, colour images and their PNG headers, frame
listings. Bad input raises :class:`MonoMapError` naming the file (and line). Units: metres, seconds;
poses are float64 4×4 ``T_world_cam0``; scans float32 x y z reflectance in the velodyne frame.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from mono_map.data.png import PNG_SIGNATURE, decode_image
from mono_map.errors import MonoMapError

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


def read_text(path: Path, what: str) -> str:
    """The text of ``path``; MonoMapError naming it (as ``what``) if it is missing or not text."""
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
    data = parse_calib_text(read_text(path, "calibration file"), path)
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
    for lineno, line in enumerate(read_text(path, "poses file").splitlines(), 1):
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
    text = read_text(path, "timestamps file")
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


COLOUR_AGREEMENT_MIN = 0.5   # a camera's R, G and B agree far above this (real KITTI: >= 0.76; synthetic: higher)


def colour_agreement(img: np.ndarray) -> float:
    """The smallest Pearson correlation between two colour channels of an H×W×3 image (1 = grey-like
    agreement, 0 = unrelated). A camera's channels see the same scene and correlate strongly (real KITTI images
    0.76–0.99); a file whose channels were scrambled (three of the shared object/extra frames: 0.24 at best) does
    not. A flat channel counts as agreeing (1)."""
    x = np.asarray(img, dtype=np.float32).reshape(-1, 3)[::7]     # every 7th pixel: plenty, and fast
    x = x - x.mean(axis=0)
    sd = np.sqrt((x * x).mean(axis=0))
    out = 1.0
    for a, b in ((0, 1), (0, 2), (1, 2)):
        if sd[a] > 1e-6 and sd[b] > 1e-6:
            out = min(out, float((x[:, a] * x[:, b]).mean() / (sd[a] * sd[b])))
    return out


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


def listing(folder: Path, suffix: str) -> list[Path]:
    """Files ``folder/*suffix`` in name order (KITTI's NNNNNN names; hidden temporary files are not
    frames); [] if the folder is missing."""
    if not folder.is_dir():
        return []
    found = sorted(p for p in folder.iterdir() if p.suffix == suffix and not p.name.startswith("."))
    for p in found:
        if not p.is_file():
            raise MonoMapError(f"{p}: a folder where a {suffix} frame file belongs")
    return found
