"""Cost of the content fingerprint that keys map, reference, table and training-cache reuse
(mono_map/data/fingerprint.py), at KITTI 00's size: 4541 frames, each with image_2, velodyne and
depth_2 files (13,623 files), plus poses, times and calibration.

    .venv/bin/python benchmarks/bench_fingerprint.py [--frames 4541] [--runs 5] [--root DIR]

Without --root it lays out empty stand-in files in a temporary folder (the fingerprint reads names,
sizes and modification times, never the contents, so file sizes do not change its cost); with --root
DIR --seq S it fingerprints a real or rendered sequence. Prints min / median / max seconds of the
whole fingerprint (all parts) over --runs runs, the file metadata warm in the OS's cache (a cold
first read after dropping the caches is not measured: it needs root and a quiet machine).
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np

from mono_map.data.fingerprint import PARTS, sequence_fingerprint


def stand_in_sequence(folder: Path, n: int) -> SimpleNamespace:
    """A sequence-like object over ``n`` frames of empty files in the KITTI layout under ``folder``."""
    seq_dir = folder / "sequences" / "big"
    files = {}
    for sub, ext in (("image_2", ".png"), ("velodyne", ".bin"), ("depth_2", ".png")):
        (seq_dir / sub).mkdir(parents=True)
        files[sub] = [seq_dir / sub / f"{i:06d}{ext}" for i in range(n)]
        for f in files[sub]:
            f.touch()
    rng = np.random.default_rng(0)
    poses = np.tile(np.eye(4), (n, 1, 1))
    poses[:, :3, 3] = rng.normal(size=(n, 3)).cumsum(0)
    calib = SimpleNamespace(P2=rng.normal(size=(3, 4)), T_cam0_velo=np.eye(4))
    return SimpleNamespace(path=seq_dir, image_files=files["image_2"], velodyne_files=files["velodyne"],
                           poses_cam0=poses, times=np.arange(n) * 0.1, calib=calib)


def main() -> None:
    from mono_map.cli.options import add_seq

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=4541, help="stand-in frames to write and fingerprint (default 4541)")
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--root", default=None, help="a KITTI root to fingerprint instead of stand-in files")
    add_seq(ap, help="with --root: the sequence to fingerprint")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        if args.root:
            from mono_map.data.kitti import open_sequence

            seq = open_sequence(args.root, args.seq)
        else:
            seq = stand_in_sequence(Path(tmp), args.frames)
        frames = range(len(seq.image_files))
        n_files = 2 * len(frames) + (len(frames) if (seq.path / "depth_2").is_dir() else 0)
        times = []
        for _ in range(args.runs):
            t0 = time.perf_counter()
            fp = sequence_fingerprint(seq, frames, PARTS)
            times.append(time.perf_counter() - t0)
    t = np.array(times)
    print(json.dumps({"frames": len(frames), "files": n_files, "parts": sorted(fp), "runs": args.runs,
                      "seconds": {"min": round(float(t.min()), 4), "median": round(float(np.median(t)), 4),
                                  "max": round(float(t.max()), 4)}}, indent=1))


if __name__ == "__main__":
    main()
