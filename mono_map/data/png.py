"""PNG files read whole and checked (chunk lengths, CRC-32) before OpenCV decodes them: a corrupt or
truncated file is one MonoMapError naming it, never libpng's own lines on stderr."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from mono_map.errors import MonoMapError

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def check_png_chunks(path: str | os.PathLike, data: bytes) -> None:
    """MonoMapError naming ``path`` unless ``data`` is a whole PNG: every chunk's length and CRC-32 right,
    up to IEND. Checked before decoding, so libpng never prints its own warnings for a corrupt file."""
    import zlib

    if not data.startswith(PNG_SIGNATURE):
        raise MonoMapError(f"{path}: unreadable image (not a PNG file)")
    pos, n = len(PNG_SIGNATURE), len(data)
    while True:
        if pos + 12 > n:
            raise MonoMapError(f"{path}: unreadable image (truncated PNG: ends inside a chunk at byte {pos})")
        length = int.from_bytes(data[pos:pos + 4], "big")
        kind = data[pos + 4:pos + 8]
        end = pos + 8 + length
        if length > 2**31 - 1 or end + 4 > n:
            raise MonoMapError(f"{path}: unreadable image (truncated PNG: chunk {kind!r} at byte {pos} runs past "
                               f"the end)")
        if zlib.crc32(data[pos + 4:end]) != int.from_bytes(data[end:end + 4], "big"):
            raise MonoMapError(f"{path}: unreadable image (corrupt PNG: chunk {kind!r} at byte {pos} fails its CRC)")
        if kind == b"IEND":
            return
        pos = end + 4


def decode_image(path: str | os.PathLike, flags: int | None = None):
    """The decoded image (cv2, BGR order, ``IMREAD_UNCHANGED`` by default) or None if OpenCV cannot; a PNG
    is checked chunk by chunk first (:func:`check_png_chunks`: MonoMapError, no libpng noise)."""
    import cv2

    try:
        data = Path(path).read_bytes()
    except OSError as exc:
        raise MonoMapError(f"{path}: unreadable image ({exc.strerror})") from None
    if data.startswith(PNG_SIGNATURE) or str(path).lower().endswith(".png"):
        check_png_chunks(path, data)
    return cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED if flags is None else flags)
