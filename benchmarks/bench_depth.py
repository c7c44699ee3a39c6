"""Benchmark the depth network on this machine: network forward at the model input size (192×640
for `small`) and the full DepthPredictor.predict on a KITTI-sized 376×1241 image.

    .venv/bin/python benchmarks/bench_depth.py [--arch small] [--head binary] [--threads 2] [--frames 20]
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
import torch

from mono_map.depth.inference import DepthPredictor
from mono_map.depth.networks import DepthNet, named_config


def timeit(fn, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Wall-clock and process-CPU seconds per call (CPU time is what a shared machine cannot hide)."""
    fn()  # warm-up
    wall, cpu = [], []
    for _ in range(n):
        t0, c0 = time.perf_counter(), time.process_time()
        fn()
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return np.array(wall), np.array(cpu)


def main() -> None:
    from mono_map.cli.options import add_threads

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--arch", default="small")
    ap.add_argument("--head", default="binary")
    add_threads(ap, default=2)
    ap.add_argument("--frames", type=int, default=20, help="timed repetitions of each forward pass (default 20)")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    cfg = named_config(args.arch, head=args.head)
    net = DepthNet(cfg).eval()
    params = sum(p.numel() for p in net.parameters())
    x = torch.rand(1, 3, cfg.input_height, cfg.input_width)
    with torch.inference_mode():
        t_net, c_net = timeit(lambda: net(x), args.frames)
    pred = DepthPredictor(net)
    img = (np.random.default_rng(0).random((376, 1241, 3)) * 255).astype(np.uint8)
    t_pred, c_pred = timeit(lambda: pred.predict(img), args.frames)
    fast = DepthPredictor(net, fast=True)
    t_fast, c_fast = timeit(lambda: fast.predict(img), args.frames)
    res = {
        "arch": args.arch, "head": args.head, "threads": args.threads, "params_M": round(params / 1e6, 3),
        "input": [cfg.input_height, cfg.input_width],
        "net_ms_median": round(1000 * float(np.median(t_net)), 1),
        "net_fps": round(1 / float(np.median(t_net)), 1),
        "predict_376x1241_ms_median": round(1000 * float(np.median(t_pred)), 1),
        "predict_fps": round(1 / float(np.median(t_pred)), 1),
        "predict_fast_376x1241_ms_median": round(1000 * float(np.median(t_fast)), 1),
        "cpu_ms_per_frame": {"net": round(1000 * float(np.median(c_net)), 1),
                             "predict": round(1000 * float(np.median(c_pred)), 1),
                             "predict_fast": round(1000 * float(np.median(c_fast)), 1)},
        "load_average": open("/proc/loadavg").read().split()[:3],
    }
    print(json.dumps(res, indent=2))


if __name__ == "__main__":
    main()
