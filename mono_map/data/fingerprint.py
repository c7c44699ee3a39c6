"""What a sequence's frames hold, as short hashes: outputs made from them are reused only if these are unchanged.

Small data is hashed whole (the frames' poses, timestamps, the calibration); large data is fingerprinted
by its listing — each frame file's name, size and modification time (ns) — so editing, replacing or
re-rendering an image, scan or depth file changes the fingerprint without reading it. Measured cost
for 4541 frames (13,623 files): ``benchmarks/bench_fingerprint.py``, docs/reliability.md.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

import numpy as np

PARTS = ("poses", "times", "calibration", "images", "scans", "depth")  # in the order "X changed" is said


def _digest(*chunks: bytes) -> str:
    h = hashlib.sha256()
    for c in chunks:
        h.update(c)
    return h.hexdigest()[:16]


def listing_digest(files: list[Path]) -> str:
    """sha256 (16 hex) of the files' names, sizes and modification times; a missing file counts as such."""
    h = hashlib.sha256()
    for f in files:
        try:
            st = os.stat(f)
            h.update(f"{f.name}\0{st.st_size}\0{st.st_mtime_ns}\n".encode())
        except OSError:
            h.update(f"{f.name}\0missing\n".encode())
    return h.hexdigest()[:16]


def sequence_fingerprint(seq, frames, parts: tuple[str, ...] = PARTS) -> dict[str, str]:
    """{part: hash} of what frames ``frames`` of the open sequence ``seq`` (:class:`KittiSequence`) hold:
    ``poses`` (their T_world_cam0), ``times``, ``calibration`` (P2, Tr), and the listings of their
    ``images`` (image_2), ``scans`` (velodyne) and ``depth`` (``seq.depth_dir``, where present). ``parts`` picks
    the ones an output depends on."""
    idx = np.asarray(list(frames), dtype=np.int64)
    out: dict[str, str] = {}
    if "poses" in parts:
        poses = getattr(seq, "poses_cam0", None)
        out["poses"] = "none" if poses is None else _digest(np.ascontiguousarray(poses[idx]).tobytes())
    if "times" in parts:
        out["times"] = _digest(np.ascontiguousarray(np.asarray(seq.times)[idx]).tobytes())
    if "calibration" in parts:
        c = seq.calib
        out["calibration"] = _digest(np.asarray(c.P2, np.float64).tobytes(),
                                     np.asarray(c.T_cam0_velo, np.float64).tobytes())
    if "images" in parts:
        out["images"] = listing_digest([seq.image_files[i] for i in idx])
    if "scans" in parts and seq.velodyne_files:
        out["scans"] = listing_digest([seq.velodyne_files[i] for i in idx])
    if "depth" in parts:
        d = seq.depth_dir   # depth_2/, or a raw drive's depth_02/data/
        if d.is_dir():
            out["depth"] = listing_digest([d / seq.image_files[i].name for i in idx])
    return out


def changed(old: dict | None, new: dict) -> list[str]:
    """The parts whose hash differs (in :data:`PARTS` order); every part if ``old`` holds none."""
    if not isinstance(old, dict):
        return list(new)
    return [p for p in PARTS if p in set(old) | set(new) and old.get(p) != new.get(p)]


def describe_change(old: dict | None, new: dict) -> str:
    """"poses changed", "images, scans changed", or "no data fingerprint recorded" for old outputs."""
    if not isinstance(old, dict):
        return "no data fingerprint recorded (made by an older mono-map)"
    parts = changed(old, new)
    return f"{', '.join(parts)} changed" if parts else "data unchanged"
