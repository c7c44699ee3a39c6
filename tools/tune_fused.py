#!/usr/bin/env python3
"""Fused maps: a grid of fused-surface settings against keep 0.8 and the distribution map, in ONE pass.

Tuning (on a training town, never on 00):

    PYTHONPATH=. python tools/tune_fused.py --seq 06 --frames 0:200 --data-root DIR \\
        --spread-ref 0.05,0.1 --min-weight 1,2,4

Every frame is predicted once and every map is a real builder (:mod:`mono_map.mapping.build`) fed from
that prediction. Each map is scored as ``mono-map eval --table`` scores it: accuracy, coverage, occupied
P/R/F1 against the LiDAR-FOV map, surface precision against the depth-gt map (synthetic sequences; the
depth-gt map is also a row), occupied cells, OctoMap memoryUsage. ``--model oracle [--oracle-sigma S]``:
the noisy ground-truth stand-in (:mod:`mono_map.mapping.oracle`).
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import sys
from pathlib import Path


from mono_map.cli.options import add_data_root, add_frames, add_model, add_oracle_noise, add_seq, oracle_predictor  # noqa: E402
from mono_map.config import OctoMapConfig  # noqa: E402
from mono_map.errors import MonoMapError  # noqa: E402
from mono_map.io import check_output_file, write_json_atomic  # noqa: E402
from mono_map.data.kitti import open_sequence  # noqa: E402
from mono_map.eval.map_metrics import compare_leaves, surface_precision  # noqa: E402
from mono_map.frames import parse_frames  # noqa: E402
from mono_map.mapping.inputs import load_predictor  # noqa: E402
from mono_map.mapping.jobs import MapJob  # noqa: E402
from mono_map.mapping.pipeline import build_map, make_builders, run_builders  # noqa: E402
from mono_map.depth.multiview import MultiviewConfig  # noqa: E402
from mono_map.mapping.distribution import DistributionConfig  # noqa: E402
from mono_map.mapping.fused import FusedConfig  # noqa: E402
from mono_map.mapping.octree import tree_leaves  # noqa: E402

GRID = tuple(f.name for f in dataclasses.fields(FusedConfig))      # every fused setting is a --NAME comma list


def score(tree, ref, surf) -> dict:
    leaves = tree_leaves(tree)
    m = compare_leaves(leaves, ref)
    out = {k: m[k] for k in ("accuracy", "coverage", "precision", "recall", "f1")}
    out["memory_mb"] = tree.memoryUsage() / 2**20
    out["surface_precision"] = surface_precision(leaves, surf)["surface_precision"] if surf is not None else None
    out["occupied_cells"] = int(leaves.length[leaves.occupied].sum())
    out["freed"] = m["missed_occupied_cells"]      # the reference's occupied cells this map holds free
    return out


def row(name: str, m: dict) -> str:
    sp = "–" if m["surface_precision"] is None else f"{100 * m['surface_precision']:.1f}"
    return (f"| {name} | {100 * m['accuracy']:.1f} | {100 * m['coverage']:.1f} | {100 * m['precision']:.1f} / "
            f"{100 * m['recall']:.1f} / {100 * m['f1']:.1f} | {sp} | {m['occupied_cells']:,} | {m['freed']:,} | "
            f"{m['memory_mb']:.1f} |")


def main(argv=None) -> int:
    d = FusedConfig()
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_seq(p, default="06", help="a training town to tune on")
    add_frames(p, default="0:60")
    add_data_root(p)
    add_model(p, oracle=True)
    add_oracle_noise(p)
    for name in GRID:
        p.add_argument("--" + name.replace("_", "-"), default=str(getattr(d, name)), help="comma list")
    p.add_argument("--ray-step", type=int, default=None,
                   help="the distribution half's and the fused surface's ray grid (default: DistributionConfig's)")
    p.add_argument("--eps", default=None,
                   help="comma list: the free half's eps (rays stop where P(surface beyond) < eps; default: "
                        "DistributionConfig's)")
    p.add_argument("--no-baselines", action="store_true", help="no keep / distribution / depth-gt rows")
    p.add_argument("--keeps", default="0.8", help="comma list: the keep maps among the baselines (default 0.8)")
    p.add_argument("--json", default=None, help="also write the rows here (a JSON list of {map, metrics})")
    p.add_argument("--keep-multiview", action="store_true",
                   help="also a keep 0.8 map of the multi-view posterior (depth/multiview.py, its defaults)")
    p.add_argument("--allow-00", action="store_true", help="measure (not tune) on 00: one setting only")
    args = p.parse_args(argv)
    values = [[type(getattr(d, n))(float(v)) for v in getattr(args, n).split(",")] for n in GRID]
    grid = [FusedConfig(**dict(zip(GRID, combo))) for combo in itertools.product(*values)]
    try:
        keeps = [float(v) for v in args.keeps.split(",")]
    except ValueError:
        keeps = []
    if not keeps or not all(0 < k <= 1 for k in keeps):
        raise SystemExit(f"--keeps: a comma list of fractions in (0, 1], got {args.keeps!r}")
    if args.seq == "00" and (not args.allow_00 or len(grid) > 1 or (args.eps or "").count(",")):
        raise SystemExit("tune on a training town, never on 00 (--allow-00 measures one setting)")
    if args.json:
        try:
            check_output_file(args.json, "--json", ".json")
        except MonoMapError as e:
            raise SystemExit(str(e))
    try:
        predictor = oracle_predictor(args)
    except MonoMapError as e:
        raise SystemExit(str(e))
    seq = open_sequence(args.data_root, args.seq)
    frames = parse_frames(args.frames).resolve(len(seq))
    if predictor is None:
        predictor = load_predictor(None if args.model == "shipped" else args.model)
    cfg = OctoMapConfig()
    synthetic = seq.depth(frames[0]) is not None
    print(f"sequence {args.seq}, frames {frames[0]}-{frames[-1]}, model {args.model or 'shipped'}", flush=True)
    ref = tree_leaves(build_map(seq, MapJob.spec("lidar-fov", frames, octomap=cfg), show_progress=False).tree)
    gt_tree = build_map(seq, MapJob.spec("depth-gt", frames, octomap=cfg), show_progress=False).tree if synthetic else None
    surf = tree_leaves(gt_tree) if synthetic else None
    names, maps = [], []
    dd = DistributionConfig()
    try:
        epss = [dd.eps] if args.eps is None else [float(v) for v in args.eps.split(",")]
    except ValueError:
        raise SystemExit(f"--eps: a comma list of numbers, got {args.eps!r}")
    dists = [DistributionConfig(ray_step=dd.ray_step if args.ray_step is None else args.ray_step, eps=e) for e in epss]
    if not args.no_baselines:
        names += [f"mono keep {k:g}" for k in keeps] + ["mono, distribution"]
        maps += [dict(keep=k) for k in keeps] + [dict(integrate="distribution")]
    if args.keep_multiview:
        names.append("mono keep 0.8, multiview posterior")
        maps.append(dict(keep=0.8, multiview=MultiviewConfig()))
    for g, dc in itertools.product(grid, dists):
        names.append("fused " + " ".join(f"{n} {getattr(g, n):g}" for n in GRID if getattr(g, n) != getattr(d, n))
                     + ("" if args.ray_step is None else f" ray_step {args.ray_step}")
                     + ("" if dc.eps == dd.eps else f" eps {dc.eps:g}"))
        maps.append(dict(integrate="fused", fused=g, distribution=dc))
    builders = make_builders(seq, [dict(job=MapJob.spec("mono", frames, **{k: v for k, v in kw.items() if k != "multiview"}),
                                        multiview=kw.get("multiview"), predictor=predictor, stats_every=10**9)
                                   for kw in maps])
    run_builders(seq, builders, frames)
    lines = ["| map | acc. | cov. | occ. P / R / F1 | surface prec. | occupied cells | reference's occupied cells freed | "
             "memory (MB) |", "|---|---:|---:|---:|---:|---:|---:|---:|"]
    rows = []
    if gt_tree is not None and not args.no_baselines:
        rows.append({"map": "depth-gt", **score(gt_tree, ref, surf)})
        lines.append(row("depth-gt", rows[-1]))
        print(lines[-1], flush=True)
    for name in names:
        b = builders.pop(0)
        fps = len(frames) / sum(f["frame_s"] for f in b.per_frame)
        rows.append({"map": name, **score(b.result(frames).tree, ref, surf), "map_work_fps": fps})
        lines.append(row(name, rows[-1]) + f" {fps:.1f} fr/s map work |")
        print(lines[-1], flush=True)
        del b
    print("\n".join(lines))
    if args.json:
        setting = {"seq": args.seq, "frames": [int(frames[0]), int(frames[-1]), len(frames)],
                   "model": args.model or "shipped", "oracle_sigma": getattr(predictor, "sigma", None),
                   "oracle_edge_sigma": getattr(predictor, "edge_sigma", None),
                   "oracle_shared_sigma": getattr(predictor, "shared_sigma", None),
                   "oracle_shared_wavelength": getattr(predictor, "shared_wavelength", None)}
        write_json_atomic(args.json, {"setting": setting, "rows": rows})
    return 0


if __name__ == "__main__":
    try:
        sys.exit(main())
    except MonoMapError as exc:           # bad data: one line
        sys.exit(f"tune_fused: error: {exc}")
