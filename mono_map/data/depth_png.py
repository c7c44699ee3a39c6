"""KITTI depth PNGs: uint16, value = depth in metres × 256, 0 = no value."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from mono_map.errors import MonoMapError

DEPTH_SCALE = 256.0
MAX_DEPTH_PNG = 65535 / DEPTH_SCALE  # 255.996 m, the largest depth a KITTI PNG holds


def encode_depth(depth_m: np.ndarray) -> np.ndarray:
    """Metres (H, W) -> uint16 KITTI depth; non-finite or <= 0 become 0 (no value)."""
    d = np.asarray(depth_m, dtype=np.float64)
    out = np.where(np.isfinite(d) & (d > 0), np.clip(np.round(d * DEPTH_SCALE), 1, 65535), 0)
    return out.astype(np.uint16)


def decode_depth(png: np.ndarray) -> np.ndarray:
    """uint16 KITTI depth -> metres float32 (0 = no value)."""
    return png.astype(np.float32) / DEPTH_SCALE


def write_depth_png(path: str | os.PathLike, depth_m: np.ndarray) -> None:
    """Write a KITTI uint16 depth PNG atomically."""
    import cv2

    from mono_map.io import atomic_path

    with atomic_path(path) as tmp:
        if not cv2.imwrite(str(tmp), encode_depth(depth_m)):
            raise MonoMapError(f"{path}: could not write depth PNG")


def read_depth_png(path: str | os.PathLike) -> np.ndarray:
    """Read a KITTI uint16 depth PNG as metres float32 (H, W); 0 = no value."""
    from mono_map.data.png import decode_image

    img = decode_image(path)
    if img is None:
        raise MonoMapError(f"{path}: not a readable depth PNG")
    if img.dtype != np.uint16 or img.ndim != 2:
        raise MonoMapError(f"{Path(path)}: depth PNG must be single-channel uint16 (got {img.dtype}, shape {img.shape})")
    return decode_depth(img)
