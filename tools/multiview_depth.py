#!/usr/bin/env python3
"""Depth accuracy of the multi-view posterior (mono_map/depth/multiview.py) against the network's prior.

    PYTHONPATH=. python tools/multiview_depth.py --seq 06 --frames 10:200:10 --data-root DIR \\
        --temperature 0.02,0.05,0.1 [--model PATH|oracle]

Per setting: AbsRel and δ<1.25 of the expected depth (prior and posterior) over the pixels with
ground-truth depth in the bins' range, at the prior's pixels (every ``--probs-step``-th), and the fraction
of pixels the sweep changed. Ground truth: dense depth_2 (synthetic) or, with ``--gt lidar``, the projected LiDAR (real sequences). Choose settings on a training town,
never on 00 (``--allow-00`` measures one setting).
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np

from mono_map.data.kitti import open_sequence
from mono_map.depth.bins import DepthBins
from mono_map.depth.multiview import MultiviewConfig, MultiviewPosterior
from mono_map.eval.depth_metrics import distance_bands
from mono_map.eval.sparsification import sparsification
from mono_map.frames import parse_frames
from mono_map.cli.options import add_data_root, add_frames, add_model, add_seq
from mono_map.mapping.inputs import load_predictor, run_predictor


def metrics(d: np.ndarray, gt: np.ndarray) -> tuple[float, float]:
    r = np.maximum(d / gt, gt / d)
    return float(np.mean(np.abs(d - gt) / gt)), float(np.mean(r < 1.25))


def summary(per_frame: list[tuple[np.ndarray, np.ndarray, np.ndarray]]) -> tuple[float, float, float, dict]:
    """Pooled AbsRel and δ<1.25 over every pixel, AbsRel as eval-depth reports it (the mean of frames) and the
    sparsification AUCs of the entropy (ARE %, RMSE m, 1−δ1 %; pooled pixels, as eval-depth)."""
    d, g, e = (np.concatenate(x) for x in zip(*per_frame))
    a, b = metrics(d, g)
    auc = sparsification(g, d, e)["auc"]
    return a, b, float(np.mean([metrics(x, y)[0] for x, y, _ in per_frame if len(y)])), auc


def auc_cells(auc: dict) -> str:
    return f"{100 * auc['are']:.2f} / {auc['rmse']:.2f} / {100 * auc['1-d1']:.2f}"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_seq(p, default="06")
    add_frames(p, default="10:200:10")
    add_data_root(p)
    add_model(p)
    p.add_argument("--probs-step", type=int, default=2)
    d = MultiviewConfig()   # defaults: the builder's (comma lists make a grid)
    p.add_argument("--temperature", default=f"{d.temperature:g}")
    p.add_argument("--sources", default=str(d.sources))
    p.add_argument("--prior-power", default=f"{d.prior_power:g}")
    p.add_argument("--min-baseline", default=f"{d.min_baseline:g}")
    p.add_argument("--window", default=str(d.window))
    p.add_argument("--scale", default=str(d.scale), help="the cost's grid: 1/scale of the image (comma list)")
    p.add_argument("--max-baseline", default=f"{d.max_baseline:g}")
    p.add_argument("--allow-00", action="store_true")
    p.add_argument("--stereo", default="0", help="1: the frame's right image (image_3) is one more source (comma list)")
    p.add_argument("--gt", choices=("dense", "lidar"), default="dense",
                   help="ground truth: dense depth_2 (synthetic) or the projected LiDAR (any sequence with velodyne)")
    args = p.parse_args(argv)
    grid = [MultiviewConfig(sources=int(s), temperature=float(t), prior_power=float(a), min_baseline=float(b),
                            window=int(wn), scale=int(sc), max_baseline=float(mb), stereo=bool(int(st)))
            for s in args.sources.split(",") for t in args.temperature.split(",") for a in args.prior_power.split(",")
            for b in args.min_baseline.split(",") for wn in args.window.split(",") for sc in args.scale.split(",")
            for mb in args.max_baseline.split(",") for st in args.stereo.split(",")]
    if args.seq == "00" and (not args.allow_00 or len(grid) > 1):
        raise SystemExit("choose settings on a training town, never on 00 (--allow-00 measures one setting)")
    seq = open_sequence(args.data_root, args.seq)
    frames = parse_frames(args.frames).resolve(len(seq))
    predictor = load_predictor(args.model)
    bins = getattr(predictor, "bins", None) or DepthBins()
    refiners = [MultiviewPosterior(g, bins) for g in grid]
    acc = {"prior": []} | {k: [] for k in range(len(grid))}
    informative = {k: [] for k in range(len(grid))}
    secs = {k: 0.0 for k in range(len(grid))}
    s = args.probs_step
    for i in frames:
        gt = seq.depth(i) if args.gt == "dense" else seq.lidar_depth(i)
        if gt is None:
            raise SystemExit(f"{args.seq}: no ground-truth depth ({'synthetic sequences only; --gt lidar for real ones' if args.gt == 'dense' else 'no velodyne scans'})")
        pred = run_predictor(predictor, seq, i, seq.image(i), with_probs=True, probs_step=s)
        g = gt[::s, ::s]
        ok = (g >= bins.min_depth) & (g <= bins.max_depth)
        acc["prior"].append((pred.depth[::s, ::s][ok], g[ok], pred.entropy[::s, ::s][ok]))
        for k, r in enumerate(refiners):
            t = time.perf_counter()
            q = r.refine(seq, i, pred)
            secs[k] += time.perf_counter() - t
            acc[k].append((q.depth[::s, ::s][ok], g[ok], q.entropy[::s, ::s][ok]))
            informative[k].append(r.last_informative)
        print(f"frame {i}", file=sys.stderr, flush=True)
    print(f"{args.seq}, frames {frames[0]}-{frames[-1]} ({len(frames)}), model {args.model or 'shipped'}, "
          f"pixels every {s}")
    print("| depth | AbsRel | δ<1.25 | AbsRel (mean of frames) | AUC ARE % / RMSE m / 1−δ1 % (entropy) "
          "| pixels changed | s/frame (loaded host) |\n|---|---:|---:|---:|---:|---:|---:|")
    a, b, f, auc = summary(acc["prior"])
    print(f"| prior (network) | {a:.3f} | {b:.3f} | {f:.3f} | {auc_cells(auc)} | – | – |")
    names = {}
    for k, cfg in enumerate(grid):
        a, b, f, auc = summary(acc[k])
        names[k] = (f"posterior, {cfg.sources} sources ≥ {cfg.min_baseline:g} m, τ {cfg.temperature:g}, a {cfg.prior_power:g}, "
                    f"window {cfg.window}, scale {cfg.scale}, max baseline {cfg.max_baseline:g} m{', + image_3' if cfg.stereo else ''}")
        print(f"| {names[k]} | {a:.3f} | "
              f"{b:.3f} | {f:.3f} | {auc_cells(auc)} | {100 * np.mean(informative[k]):.0f} % | {secs[k] / len(frames):.2f} |")
    print("\nAbsRel by true depth (eval-depth's bands; pooled pixels; share of the pixels in the header)\n")
    bands = {key: distance_bands(np.concatenate([g for _, g, _ in v]), np.concatenate([d for d, _, _ in v]))
             for key, v in acc.items()}
    print("| depth | " + " | ".join(f"{b['lo']:g}–{b['hi']:g} m ({100 * b['share']:.0f} %)" for b in bands["prior"])
          + " |\n|---|" + "---:|" * len(bands["prior"]))
    for key, name in [("prior", "prior (network)")] + list(names.items()):
        print(f"| {name} | " + " | ".join("–" if b["abs_rel"] is None else f"{b['abs_rel']:.3f}" for b in bands[key]) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
