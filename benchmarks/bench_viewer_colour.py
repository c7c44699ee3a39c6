#!/usr/bin/env python
"""Cost of ``RerunMapLogger(colour="probability")`` against the default height colours, in one run.

Builds frames a:b once (capturing every ``FrameUpdate``), then replays the updates through the logger,
alternating height / probability for ``--repeats`` pairs, and reports the logger's seconds per frame
(min / median / max) and the recording size of each. Builds do not report probabilities yet, so the
probability updates are synthetic but shaped like an integration's: every cell that became occupied
(p in [0.5, 1)), every freed cell (p < 0.5), a quarter of the occupied cells refreshed, and
``--free-cells`` random cells that stay free (which the logger must look at and ignore).

    python benchmarks/bench_viewer_colour.py --seq 00 --frames 0:40 --source mono
"""

from __future__ import annotations

import argparse
import copy
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def with_probabilities(updates, resolution: float, free_cells: int, seed: int = 0):
    """Copies of ``updates`` carrying synthetic ``updated_cells`` / ``updated_probability``."""
    from mono_map.viz.codec import cell_indices, pack

    rng = np.random.default_rng(seed)
    occupied = np.zeros((0, 3))
    out = []
    for u in updates:
        occ, freed = np.asarray(u.occupied_keys_changed).reshape(-1, 3), np.asarray(u.freed_keys_changed).reshape(-1, 3)
        if len(freed):
            occupied = occupied[~np.isin(pack(cell_indices(occupied, resolution)), pack(cell_indices(freed, resolution)))]
        occupied = np.concatenate([occupied, occ])
        refresh = occupied[rng.random(len(occupied)) < 0.25]
        lo, hi = occupied.min(0) if len(occupied) else np.zeros(3), occupied.max(0) if len(occupied) else np.ones(3)
        free = (np.floor(rng.uniform(lo, hi, (free_cells, 3)) / resolution) + 0.5) * resolution
        cells = np.concatenate([occ, freed, refresh, free])
        prob = np.concatenate([rng.uniform(0.5, 1.0, len(occ)), rng.uniform(0.0, 0.5, len(freed)),
                               rng.uniform(0.5, 1.0, len(refresh)), rng.uniform(0.0, 0.5, free_cells)])
        v = copy.copy(u)
        v.updated_cells, v.updated_probability = cells, prob.astype(np.float32)
        out.append(v)
    return out


def main(argv=None) -> int:
    from mono_map.cli.options import add_data_root, add_frames, add_seq
    from mono_map.frames import parse_frames

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_seq(ap)
    add_data_root(ap)
    add_frames(ap, default="0:20")
    ap.add_argument("--source", default="lidar-fov", help="mono | lidar | lidar-fov (default lidar-fov)")
    ap.add_argument("--repeats", type=int, default=3, help="alternating pairs (default 3)")
    ap.add_argument("--free-cells", type=int, default=200_000, help="free cells per frame in the update")
    args = ap.parse_args(argv)

    from mono_map.data.kitti import open_sequence
    from mono_map.mapping.pipeline import build_map
    from mono_map.mapping.jobs import MapJob
    from mono_map.viz.rerun_stream import RerunMapLogger
    from mono_map.viz.stream_options import StreamOptions

    sel = parse_frames(args.frames)
    if sel.indices is not None or sel.step != 1 or sel.stop is None:
        ap.error(f"--frames: a range A:B of frames, got {args.frames!r}")
    a, b = sel.start, sel.stop
    seq = open_sequence(args.data_root, args.seq, frames=b)
    updates = []
    build_map(seq, MapJob.spec(args.source, range(a, b)), observers=[lambda u: updates.append(copy.deepcopy(u))],
              show_progress=False)
    res = 0.2
    prob_updates = with_probabilities(updates, res, args.free_cells)
    times = {"height": [], "probability": []}
    sizes = {}
    with tempfile.TemporaryDirectory() as tmp:
        for rep in range(args.repeats + 1):   # the first pair warms up (imports, colour tables) and is not timed
            for colour, ups in (("height", updates), ("probability", prob_updates)):
                rrd = Path(tmp) / f"{colour}.rrd"
                t0 = time.perf_counter()
                logger = RerunMapLogger(rrd=rrd, options=StreamOptions(resolution=res, image_size=seq.image_size,
                                                                      colour=colour))
                for u in ups:
                    logger(u)
                logger.close()
                if rep:
                    times[colour].append((time.perf_counter() - t0) / len(ups))
                sizes[colour] = rrd.stat().st_size
    n_upd = np.mean([len(u.updated_probability) for u in prob_updates])
    print(f"{args.seq} frames {a}:{b} {args.source}: {len(updates)} frames, {n_upd:,.0f} probability updates/frame")
    for colour, t in times.items():
        print(f"  {colour:11s} {1000 * min(t):7.1f} / {1000 * statistics.median(t):7.1f} / {1000 * max(t):7.1f} "
              f"ms per frame (min / median / max of {len(t)}), recording {sizes[colour] / 1e6:.1f} MB")
    print(f"  median ratio probability / height: {statistics.median(times['probability']) / statistics.median(times['height']):.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
