"""KITTI odometry layout on disk, written atomically (temp file + rename).

root/sequences/XX/image_2/NNNNNN.png   RGB (stored BGR by OpenCV), 1241×376
root/sequences/XX/image_3/NNNNNN.png   right colour camera (P3), as image_2; only with synth --stereo
root/sequences/XX/depth_2/NNNNNN.png   dense z-depth of image_2, uint16 metres × 256, 0 = sky / none
root/sequences/XX/velodyne/NNNNNN.bin  float32 x y z reflectance (velodyne frame)
root/sequences/XX/calib.txt            real KITTI 00 calibration (P0..P3, Tr), copied verbatim
root/sequences/XX/times.txt            seconds
root/poses/XX.txt                      T_world_cam0, 3×4 row-major per line
root/sequences/XX/synth.json           marker: recipe name + hash, n_frames, generator version (written last)
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from mono_map.errors import MonoMapError
from mono_map.io import atomic_path, write_json_atomic, write_text_atomic
from mono_map.paths import KITTI_ASSETS_DIR

MARKER = "synth.json"
PARTIAL_MARKER = ".synth_partial.json"      # present while a generation is under way / was interrupted


# PNG encoder settings (lossless either way; measured on frames of 00, one thread, cv2 5.0): the noisy RGB
# image gains nothing from zlib's string matching, so Huffman-only coding after the AVG filter writes it 2.5×
# faster and 12 % smaller than zlib level 1 with adaptive filters (13.5 vs 34.1 ms, 0.77 vs 0.87 MB); the
# smooth uint16 depth keeps zlib with the UP filter only (5.8 vs 10.2 ms, 0.15 vs 0.13 MB). The pixels
# decode identically to before; only the files' bytes changed (benchmarks/bench_synth.py --compare decodes).
def png_params(kind: str) -> list[int]:
    """cv2.imwrite parameters for an ``"image"`` (RGB) or ``"depth"`` (uint16) PNG."""
    import cv2

    if kind == "image":
        return [cv2.IMWRITE_PNG_COMPRESSION, 1, cv2.IMWRITE_PNG_STRATEGY, cv2.IMWRITE_PNG_STRATEGY_HUFFMAN_ONLY,
                cv2.IMWRITE_PNG_FILTER, cv2.IMWRITE_PNG_FILTER_AVG]
    if kind == "depth":
        return [cv2.IMWRITE_PNG_COMPRESSION, 1, cv2.IMWRITE_PNG_FILTER, cv2.IMWRITE_PNG_FILTER_UP]
    raise ValueError(f"png_params: unknown kind {kind!r}")


def calib_text() -> str:
    return (KITTI_ASSETS_DIR / "calib_00.txt").read_text()


def read_calib() -> dict[str, np.ndarray]:
    """The calibration synthetic sequences are written with (real KITTI 00's), through the reader's
    parser: {'P0'..'P3': 3×4, 'Tr': 4×4 (velodyne → cam0)}."""
    from mono_map.data.kitti_files import read_calib_file

    out = {key: value.reshape(3, 4) for key, value in read_calib_file(KITTI_ASSETS_DIR / "calib_00.txt").items()}
    Tr = np.eye(4)
    Tr[:3] = out["Tr"]
    out["Tr"] = Tr
    return out


def frame_paths(seq_dir: Path, i: int) -> dict[str, Path]:
    name = f"{i:06d}"
    return {"image": seq_dir / "image_2" / f"{name}.png", "depth": seq_dir / "depth_2" / f"{name}.png",
            "velodyne": seq_dir / "velodyne" / f"{name}.bin"}


def frame_complete(seq_dir: Path, i: int) -> bool:
    return all(p.is_file() for p in frame_paths(seq_dir, i).values())


def right_path(seq_dir: Path, i: int) -> Path:
    """The right colour camera's image of frame ``i`` (``image_3``; written only with synth --stereo)."""
    return seq_dir / "image_3" / f"{i:06d}.png"


def right_complete(seq_dir: Path, i: int) -> bool:
    return right_path(seq_dir, i).is_file()


def leading_right_frames(seq_dir: Path, n: int) -> int:
    """How many of the first ``n`` frames have their ``image_3`` file, counted from frame 0 to the first gap."""
    return next((i for i in range(n) if not right_complete(seq_dir, i)), n)


def _write_png(path: Path, rgb: np.ndarray) -> None:
    import cv2

    with atomic_path(path) as tmp:
        if not cv2.imwrite(str(tmp), np.ascontiguousarray(rgb[..., ::-1]), png_params("image")):
            raise MonoMapError(f"{path}: could not write PNG")


def write_frame(seq_dir: Path, i: int, rgb: np.ndarray, depth_m: np.ndarray, points: np.ndarray) -> None:
    import cv2

    from mono_map.data.depth_png import encode_depth

    paths = frame_paths(seq_dir, i)
    _write_png(paths["image"], rgb)
    with atomic_path(paths["depth"]) as tmp:
        if not cv2.imwrite(str(tmp), encode_depth(depth_m), png_params("depth")):
            raise MonoMapError(f"{paths['depth']}: could not write depth PNG")
    with atomic_path(paths["velodyne"]) as tmp:
        np.ascontiguousarray(points, dtype=np.float32).tofile(tmp)


def write_right(seq_dir: Path, i: int, rgb: np.ndarray) -> None:
    """The right colour camera's image of frame ``i`` (``image_3``), written as image_2 is."""
    _write_png(right_path(seq_dir, i), rgb)


def write_sequence_files(root: Path, name: str, pose_lines: list[str], times: np.ndarray) -> None:
    seq_dir = root / "sequences" / name
    write_text_atomic(seq_dir / "calib.txt", calib_text())
    write_text_atomic(seq_dir / "times.txt", "".join(f"{t:.6e}\n" for t in times))
    write_text_atomic(root / "poses" / f"{name}.txt", "".join(line + "\n" for line in pose_lines))


def remove_frames_from(seq_dir: Path, n: int, image_3_from: int | None = None) -> None:
    """Delete frame files with index >= n (a shorter regeneration leaves no strays); ``image_3`` files from
    index ``image_3_from`` on (default n; 0 drops every right image a re-render without --stereo made stale)."""
    for sub, ext, first in (("image_2", ".png", n), ("depth_2", ".png", n), ("velodyne", ".bin", n),
                            ("image_3", ".png", n if image_3_from is None else image_3_from)):
        d = seq_dir / sub
        if not d.is_dir():
            continue
        for p in d.iterdir():
            if p.suffix == ext and p.stem.isdigit() and int(p.stem) >= first:
                p.unlink()


def read_marker(seq_dir: Path, partial: bool = False) -> dict | None:
    """The sequence's marker (``synth.json``, or with ``partial`` the in-progress one), None if absent.

    A malformed ``synth.json`` raises MonoMapError naming it (``synth --force`` re-renders); a
    malformed partial marker is what an interrupted write leaves, read as an interrupted
    generation without an owner ({}).
    """
    p = seq_dir / (PARTIAL_MARKER if partial else MARKER)
    if not p.is_file():
        return None
    try:
        text = p.read_text()
    except OSError as exc:
        if partial:
            return {}
        # unreadable is not malformed: re-rendering (synth --force) would not be the fix
        raise MonoMapError(f"{p}: cannot read the synthetic-sequence marker ({exc.strerror}); "
                           "check its permissions") from None
    try:
        info = json.loads(text)
    except (json.JSONDecodeError, UnicodeDecodeError):
        info = None
    if partial:
        return info if isinstance(info, dict) else {}
    n = info.get("n_frames") if isinstance(info, dict) else None
    if isinstance(n, int) and not isinstance(n, bool) and n >= 1:
        return info
    raise MonoMapError(f"{p}: malformed synthetic-sequence marker (no positive integer n_frames); "
                       f"re-render with mono-map synth --seq {seq_dir.name} --force")


def write_marker(seq_dir: Path, info: dict, partial: bool = False) -> None:
    write_json_atomic(seq_dir / (PARTIAL_MARKER if partial else MARKER), info)
