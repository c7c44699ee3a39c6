"""What ``--flip`` costs: the shipped checkpoint's predictions of a KITTI-sized image with and without the mirrored
second pass, back to back in one process, repeated; min / median / max of each and of their ratio.

    .venv/bin/python benchmarks/bench_flip.py [--model binary] [--repeats 5] [--per-run 10] [--threads 2] [--fast]

``--fast``: statistics at the decoder's stride 4 (the map builds' predictor). Run it on an idle machine.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np


def per_frame_ms(predictor, image: np.ndarray, frames: int) -> float:
    t0 = time.perf_counter()
    for _ in range(frames):
        predictor.predict(image)
    return 1000 * (time.perf_counter() - t0) / frames


def main() -> None:
    import torch

    from mono_map.cli.options import add_model, add_threads
    from mono_map.depth.inference import DepthPredictor, default_precision

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_model(ap)
    ap.add_argument("--repeats", type=int, default=5, help="alternating timed runs of each (default 5)")
    ap.add_argument("--per-run", type=int, default=10, help="predictions per timed run (default 10)")
    ap.add_argument("--fast", action="store_true", help="statistics at stride 4 (as map builds predict)")
    add_threads(ap, default=2)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    precision = default_precision()
    plain = DepthPredictor.load(args.model, fast=args.fast, precision=precision)
    flip = DepthPredictor.load(args.model, fast=args.fast, precision=precision, flip=True)
    image = (np.random.default_rng(0).random((376, 1241, 3)) * 255).astype(np.uint8)
    for p in (plain, flip):          # warm-up
        p.predict(image)
    a, b = [], []
    for _ in range(args.repeats):
        a.append(per_frame_ms(plain, image, args.per_run))
        b.append(per_frame_ms(flip, image, args.per_run))
    ratio = np.array(b) / np.array(a)

    def mmm(x):
        return [round(float(np.min(x)), 2), round(float(np.median(x)), 2), round(float(np.max(x)), 2)]

    print(json.dumps({"model": args.model or "binary", "precision": precision, "threads": args.threads,
                      "fast": args.fast, "repeats": args.repeats, "frames_per_run": args.per_run,
                      "plain_ms_min_median_max": mmm(a), "flip_ms_min_median_max": mmm(b),
                      "ratio_min_median_max": mmm(ratio)}, indent=1))


if __name__ == "__main__":
    main()
