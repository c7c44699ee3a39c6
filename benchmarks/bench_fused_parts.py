"""Where a fused build's time goes: each part of ``mono-map build --integrate fused`` (shipped model, default
settings) timed per frame with the build run frame by frame on one thread of control (no prefetch, so the parts
do not compete): the network (with its bin probabilities), the multi-view posterior, the free half, the TSDF
update and the snap (with the hits), and the map step as a whole.

    .venv/bin/python benchmarks/bench_fused_parts.py --data-root DATA [--seq 06] [--frames 40:70]

Prints each part's mean seconds a frame (the first three frames left out: start-up; a mean, since a frame's
pixels are snapped ``lag`` frames later and the last frame snaps the rest). Run it on an idle machine.
"""

from __future__ import annotations

import argparse
import time
from collections import defaultdict

import numpy as np

from mono_map.cli import options
from mono_map.data.kitti import open_sequence
from mono_map.errors import MonoMapError
from mono_map.frames import parse_frames
from mono_map.mapping import build
from mono_map.mapping.inputs import FrameInputs, probs_steps
from mono_map.mapping.jobs import MapJob
from mono_map.mapping.pipeline import make_builders


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    options.add_data_root(ap, required=True)
    options.add_seq(ap, default="06")
    options.add_frames(ap, default="40:70")
    args = ap.parse_args(argv)

    times: dict[str, list[float]] = defaultdict(list)

    def timed(name, f):
        def g(*a, **k):
            t = time.perf_counter()
            out = f(*a, **k)
            times[name].append(time.perf_counter() - t)
            return out
        return g

    try:
        seq = open_sequence(args.data_root, args.seq)
        frames = parse_frames(args.frames).resolve(len(seq))
    except MonoMapError as exc:
        raise SystemExit(f"bench_fused_parts: {exc}")
    if len(frames) < 4:
        raise SystemExit(f"bench_fused_parts: --frames {args.frames}: need 4 or more frames")
    build.distribution_frame = timed("free half", build.distribution_frame)
    build.fuse_prediction = timed("TSDF update", build.fuse_prediction)
    build.due_surface_points = timed("snap", build.due_surface_points)
    b = make_builders(seq, [dict(job=MapJob.spec("mono", frames, integrate="fused"))])[0]
    b.multiview.refine = timed("posterior", b.multiview.refine)
    steps = probs_steps([b])
    for i in frames:
        inputs = FrameInputs(seq, i, steps)
        t = time.perf_counter()
        inputs.prediction(b.predictor)
        times["network"].append(time.perf_counter() - t)
        b.prepare(i, inputs)
        t = time.perf_counter()
        b.step(i, inputs)
        times["map step (free half + TSDF + snap + hits)"].append(time.perf_counter() - t)
    n = len(frames) - 3
    print(f"seq {args.seq} frames {args.frames}: mean seconds a frame (the {n} frames after the first three)")
    for name in ("network", "posterior", "map step (free half + TSDF + snap + hits)", "free half", "TSDF update", "snap"):
        print(f"  {name:44s} {sum(times[name][3:]) / n:.3f}")


if __name__ == "__main__":
    main()
