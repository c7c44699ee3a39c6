#!/usr/bin/env python3
"""Keep sweep against distribution integration in ONE pass over the frames (each frame predicted once).

Tuning (on a training town, never on 00) — a grid of distribution settings:

    .venv/bin/python tools/compare_integrations.py --seq 05 --frames 0:60 --model shipped --tune

Measuring (any sequence) — the chosen settings (the DistributionConfig defaults unless given):

    .venv/bin/python tools/compare_integrations.py --seq 00 --frames 0:500 --model shipped --out DIR

Every candidate gets its own integrator fed from the same predictions; each map is scored exactly as
``mono-map eval --table`` scores it (the same metric functions on the same trees: accuracy, coverage,
acc. on covered cells and occupied P/R/F1 against the LiDAR-FOV map, surface precision against the
depth-gt map, ECE of the probabilistic tree, OctoMap memoryUsage), but ``eval --table`` would predict
every frame once per map. LiDAR-FOV and depth-gt maps are read from ``--refs DIR`` when built there
(``mono-map build --source lidar-fov|depth-gt --out DIR``), else built. With ``--out``: Markdown, JSON,
the accuracy-vs-memory plot and the reliability diagram (:mod:`mono_map.mapping.table`'s plots).
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import sys
from pathlib import Path

from mono_map.cli.options import add_data_root, add_frames, add_model, add_seq  # noqa: E402
from mono_map.config import OctoMapConfig  # noqa: E402
from mono_map.data.kitti import open_sequence  # noqa: E402
from mono_map.eval.map_metrics import calibration, compare_leaves, surface_precision  # noqa: E402
from mono_map.frames import frames_tag, parse_frames  # noqa: E402
from mono_map.mapping.inputs import load_predictor  # noqa: E402
from mono_map.mapping.pipeline import build_map, make_builders, run_builders  # noqa: E402
from mono_map.mapping.jobs import MapJob  # noqa: E402
from mono_map.mapping.distribution import DistributionConfig  # noqa: E402
from mono_map.mapping.octree import load_tree, tree_leaves  # noqa: E402
from mono_map.mapping.oracle import NoisyGroundTruthPredictor  # noqa: E402
from mono_map.mapping.select import check_rank  # noqa: E402
from mono_map.errors import MonoMapError  # noqa: E402


def reference_leaves(seq, source: str, frames, cfg, refs: Path | None):
    bt = MapJob(seq.name, None, source, tuple(frames), octomap=cfg).path(refs) if refs is not None else None
    if bt is not None and bt.exists():
        return tree_leaves(load_tree(bt))
    return tree_leaves(build_map(seq, MapJob.spec(source, frames, octomap=cfg), show_progress=False).tree)


def parse_max_ranges(text: str) -> list[float]:
    """'none,40,30' -> [-1.0, 40.0, 30.0] (OctoMap's convention: < 0 = unlimited); one line naming the option."""
    out = []
    for v in text.split(","):
        v = v.strip().lower()
        try:
            r = -1.0 if v == "none" else float(v)
        except ValueError:
            raise SystemExit(f"--max-ranges: {v!r} is neither 'none' nor a number of metres")
        if v != "none" and not (r > 0 and r < float("inf")):
            raise SystemExit(f"--max-ranges: {v!r} must be a positive number of metres or 'none'")
        out.append(r)
    return out


def main(argv=None) -> int:
    d = DistributionConfig()
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_seq(p, default="05")
    add_frames(p, default="0:60")
    add_model(p, oracle=True)
    p.add_argument("--oracle-sigma", type=float, default=None,
                   help="with --model oracle: its log-depth noise on smooth surfaces (default 0.03)")
    add_data_root(p)
    p.add_argument("--keeps", default="0.8,1.0")
    p.add_argument("--tune", action="store_true", help="a grid: --eps x --min-update x --ray-step x --temperature")
    p.add_argument("--eps", default=str(d.eps))
    p.add_argument("--min-update", default=str(d.min_update))
    p.add_argument("--ray-step", default=str(d.ray_step))
    p.add_argument("--temperature", default=str(d.temperature))
    p.add_argument("--bin-spread", default=str(d.bin_spread))
    p.add_argument("--quantum", default=str(d.quantum))
    p.add_argument("--snap-free", default=str(int(d.snap_free)), help="0, 1 or 0,1 (free updates snapped to {miss, 0})")
    p.add_argument("--prob-hit", type=float, default=0.7)
    p.add_argument("--prob-miss", type=float, default=0.4)
    p.add_argument("--max-ranges", default="none",
                   help="comma list of OctoMap max ranges for the mono maps, metres or 'none' (unlimited): every "
                        "candidate is built once per value (the references stay unlimited)")
    p.add_argument("--keeps-only", action="store_true", help="no distribution candidates")
    p.add_argument("--ranks", default="entropy",
                   help="how keep maps rank pixels: entropy, metric or entropy,metric (mono_map.mapping.select)")
    p.add_argument("--refs", default=None, help="directory with built lidar-fov / depth-gt maps of these frames")
    p.add_argument("--out", default=None, help="write Markdown, JSON and plots here")
    args = p.parse_args(argv)
    if args.oracle_sigma is not None and (args.model != "oracle" or not 0 < args.oracle_sigma < 1):
        raise SystemExit("--oracle-sigma: needs --model oracle and a noise in (0, 1)")
    if args.tune and args.seq == "00":
        raise SystemExit("tune on a training town, never on 00")
    cfg = OctoMapConfig(prob_hit=args.prob_hit, prob_miss=args.prob_miss)
    max_ranges = parse_max_ranges(args.max_ranges)
    try:
        ranks = [check_rank(r.strip(), "--ranks") for r in args.ranks.split(",")]
    except MonoMapError as exc:
        raise SystemExit(str(exc)) from None
    selection = parse_frames(args.frames)
    seq = open_sequence(args.data_root, args.seq)
    frames = selection.resolve(len(seq))
    desc = selection.describe(frames)
    refs = Path(args.refs) if args.refs else None
    print(f"sequence {args.seq}, {desc}, model {args.model or 'shipped'}, prob_hit {cfg.prob_hit}, prob_miss {cfg.prob_miss}",
          flush=True)
    ref = reference_leaves(seq, "lidar-fov", frames, OctoMapConfig(), refs)    # references: default sensor model
    surf = reference_leaves(seq, "depth-gt", frames, OctoMapConfig(), refs)
    if args.oracle_sigma is not None:
        predictor = NoisyGroundTruthPredictor(sigma=args.oracle_sigma)
    else:
        predictor = load_predictor(None if args.model == "shipped" else args.model)
    grid = [DistributionConfig(eps=float(e), min_update=float(m), ray_step=int(s), temperature=float(t),
                               bin_spread=float(b), quantum=float(q), snap_free=bool(int(f)))
            for e, m, s, t, b, q, f in itertools.product(args.eps.split(","), args.min_update.split(","),
                                                         args.ray_step.split(","), args.temperature.split(","),
                                                         args.bin_spread.split(","), args.quantum.split(","),
                                                         args.snap_free.split(","))]
    cands = {}   # name -> the map's settings (MapJob.spec) and rank; one builder each, fed from one prediction per frame
    for r in max_ranges:
        octomap = dataclasses.replace(cfg, max_range=r)
        tag = "" if r < 0 else f", max range {r:g} m"
        for k in sorted({float(k) for k in args.keeps.split(",")}, reverse=True):
            for rank in ranks if k < 1.0 else ranks[:1]:         # keep 1.0 keeps every pixel whatever the ranking
                rtag = "" if rank == "entropy" else f", ranked by {rank}"
                cands[("mono (keep 1.0)" if k == 1.0 else f"mono keep {k:g}") + rtag + tag] = dict(
                    keep=k, octomap=octomap, rank=rank)
        for g in [] if args.keeps_only else grid:
            name = "mono, distribution" if len(grid) == 1 else (
                f"dist eps {g.eps:g} min {g.min_update:g} step {g.ray_step} T {g.temperature:g} "
                f"spread {g.bin_spread:g} q {g.quantum:g}" + (" snap" if g.snap_free else ""))
            cands[name + tag] = dict(integrate="distribution", distribution=g, octomap=octomap)
    settings = [{k: v for k, v in kw.items() if k != "rank"} for kw in cands.values()]
    builders = make_builders(seq, [dict(job=MapJob.spec("mono", frames, **s), rank=kw.get("rank", "entropy"),
                                        predictor=predictor, stats_every=10**9)
                                   for s, kw in zip(settings, cands.values())])
    run_builders(seq, builders, frames)
    rows, reliability = [], {}
    for name, kw in cands.items():
        b = builders.pop(0)
        integration_s = sum(f["frame_s"] for f in b.per_frame) / len(frames)
        tree = b.result(frames).tree
        leaves = tree_leaves(tree)
        m = compare_leaves(leaves, ref)
        s = surface_precision(leaves, surf)
        e = calibration(leaves, ref)
        reliability[name] = e
        dist = kw.get("distribution")
        rows.append({"method": name, "source": "mono" if dist is None else "mono-distribution",
                     "keep": kw.get("keep"), "rank": kw.get("rank"), "settings": None if dist is None else dist.__dict__,
                     "max_range": kw["octomap"].max_range,
                     "accuracy": m["accuracy"], "coverage": m["coverage"], "accuracy_covered": m["accuracy_covered"],
                     "precision": m["precision"], "recall": m["recall"], "f1": m["f1"],
                     "surface_precision": s["surface_precision"], "occupied_cells": s["occupied_cells"],
                     "ece": e["ece"], "memory_mb": tree.memoryUsage() / 2**20, "leaf_count": tree.getNumLeafNodes(),
                     "integration_s_per_frame": integration_s})
        del b, tree
    lines = ["| map | acc. (%) | cov. (%) | acc. covered (%) | occ. P / R / F1 (%) | surface prec. (%) | occupied cells | "
             "ECE | memory (MB) | integration s/frame |", "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(f"| {r['method']} | {100 * r['accuracy']:.1f} | {100 * r['coverage']:.1f} | "
                     f"{100 * r['accuracy_covered']:.1f} | {100 * r['precision']:.1f} / {100 * r['recall']:.1f} / "
                     f"{100 * r['f1']:.1f} | {100 * r['surface_precision']:.1f} | {r['occupied_cells']:,} | "
                     f"{r['ece']:.3f} | {r['memory_mb']:.1f} | {r['integration_s_per_frame']:.2f} |")
    md = "\n".join(lines) + "\n"
    print(md)
    if args.out:
        from mono_map.io import write_json_atomic, write_text_atomic
        from mono_map.viz.plots import plot_accuracy_memory, plot_reliability

        out = Path(args.out)
        out.mkdir(parents=True, exist_ok=True)
        stem = f"compare_{args.seq}_{frames_tag(frames)}_{Path(args.model or 'shipped').stem}" + (
            f"_sigma{args.oracle_sigma:g}" if args.oracle_sigma is not None else "")
        write_text_atomic(out / f"{stem}.md", md)
        write_json_atomic(out / f"{stem}.json", {"sequence": args.seq, "frames": [frames[0], frames[-1] + 1],
                                                 "model": args.model, "rows": rows, "reliability": reliability})
        plot_accuracy_memory(rows, out / f"{stem}_acc_memory.png")
        calib = {k: v for k, v in reliability.items() if k in ("mono (keep 1.0)", "mono keep 0.8", "mono, distribution")}
        plot_reliability(calib, out / f"{stem}_reliability.png")
        print(f"wrote {out / stem}.md, .json, _acc_memory.png, _reliability.png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
