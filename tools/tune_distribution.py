#!/usr/bin/env python3
"""Choose the settings of ``--integrate distribution`` on a TRAINING town (never on 00).

    .venv/bin/python tools/tune_distribution.py --seq 05 --frames 0:60 --model shipped
    .venv/bin/python tools/tune_distribution.py --seq 05 --frames 0:60 --model oracle

Predicts every frame once and feeds it to one integrator per candidate (keep 0.8, keep 1.0 and a
grid of eps / min-update / ray-step / temperature), then scores each map against the sequence's
LiDAR-FOV map (accuracy, coverage, acc. on covered cells, occupied F1, ECE of the probabilistic
tree) and its depth-gt map (surface precision), with OctoMap's memoryUsage. Prints a Markdown table.
"""

from __future__ import annotations

import argparse
import itertools
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from mono_map.config import OctoMapConfig  # noqa: E402
from mono_map.data.kitti import open_sequence  # noqa: E402
from mono_map.eval.map_metrics import calibration, compare_leaves, surface_precision, tree_leaves  # noqa: E402
from mono_map.mapping.build import build_map, distribution_frame, load_predictor, parse_frames  # noqa: E402
from mono_map.mapping.build import bin_edges, run_predictor  # noqa: E402
from mono_map.mapping.distribution import DistributionConfig  # noqa: E402
from mono_map.mapping.integrate import MapIntegrator  # noqa: E402
from mono_map.mapping.points import camera_origin, pixels_to_world  # noqa: E402
from mono_map.mapping.select import select_pixels  # noqa: E402


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--seq", default="05")
    p.add_argument("--frames", default="0:60")
    p.add_argument("--model", default="shipped", help="'shipped', 'oracle' or a checkpoint")
    p.add_argument("--data-root", default=None)
    p.add_argument("--eps", default="0.05,0.1,0.2")
    p.add_argument("--min-update", default="0,0.05")
    p.add_argument("--ray-step", default="2")
    p.add_argument("--temperature", default="1")
    p.add_argument("--extra", default="", help="more candidates 'eps:min:step:T', separated by ';'")
    p.add_argument("--prob-hit", type=float, default=0.7)
    args = p.parse_args(argv)
    if args.seq == "00":
        raise SystemExit("tune on a training town, never on 00")
    cfg = OctoMapConfig(prob_hit=args.prob_hit)
    seq = open_sequence(args.data_root, args.seq, generate=False)
    frames, desc = parse_frames(args.frames, len(seq))
    print(f"sequence {args.seq}, {desc}, model {args.model}, prob_hit {cfg.prob_hit}")
    lidar = build_map(seq, "lidar-fov", frames=frames, octomap=cfg, show_progress=False).tree
    gt = build_map(seq, "depth-gt", frames=frames, octomap=cfg, show_progress=False).tree
    ref, surf = tree_leaves(lidar), tree_leaves(gt)
    predictor = load_predictor(None if args.model == "shipped" else args.model)
    edges = bin_edges(predictor)
    grid = [DistributionConfig(eps=float(e), min_update=float(m), ray_step=int(s), temperature=float(t))
            for e, m, s, t in itertools.product(args.eps.split(","), args.min_update.split(","),
                                                args.ray_step.split(","), args.temperature.split(","))]
    for c in filter(None, args.extra.split(";")):
        e, m, st, t = c.split(":")
        grid.append(DistributionConfig(eps=float(e), min_update=float(m), ray_step=int(st), temperature=float(t)))
    cands = {f"keep {k:g}": (k, MapIntegrator(cfg), [0.0]) for k in (0.8, 1.0)}
    for d in grid:
        cands[f"dist eps {d.eps:g} min {d.min_update:g} step {d.ray_step} T {d.temperature:g}"] = (d, MapIntegrator(cfg), [0.0])
    K = seq.calib.K2
    for i in frames:
        image = seq.image(i)
        pred = run_predictor(predictor, seq, i, image, with_probs=True)
        T = seq.T_world_cam2(i)
        for name, (c, integ, sec) in cands.items():
            t0 = time.perf_counter()
            if isinstance(c, float):
                mask = select_pixels(pred.depth, pred.entropy, c, 1.0, 80.0)
                integ.insert(pixels_to_world(pred.depth, mask, K, T), camera_origin(T))
            else:
                _, valid = select_pixels(pred.depth, pred.entropy, 1.0, 1.0, 80.0, return_valid=True)
                distribution_frame(integ, pred, valid, K, T, edges, c, i)
            sec[0] += time.perf_counter() - t0
    print("\n| map | acc. (%) | cov. (%) | acc. covered (%) | occ. F1 (%) | surface prec. (%) | occupied cells | "
          "ECE | memory (MB) | integration s/frame |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for name, (c, integ, sec) in cands.items():
        tree = integ.tree
        leaves = tree_leaves(tree)
        m = compare_leaves(leaves, ref)
        s = surface_precision(leaves, surf)
        e = calibration(leaves, ref)
        print(f"| {name} | {100 * m['accuracy']:.1f} | {100 * m['coverage']:.1f} | {100 * m['accuracy_covered']:.1f} | "
              f"{100 * m['f1']:.1f} | {100 * s['surface_precision']:.1f} | {s['occupied_cells']:,} | {e['ece']:.3f} | "
              f"{tree.memoryUsage() / 2**20:.1f} | {sec[0] / len(frames):.2f} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
