#!/usr/bin/env python3
"""Benchmark map integration on the same scans: octomap-python's insertPointCloud vs mono-map's
batched exact path vs OctoMap's C++ graph2tree (Debian octomap-tools), in one run.

    .venv/bin/python benchmarks/bench_mapping.py --seq 00 --source lidar --frames 0:30
    .venv/bin/python benchmarks/bench_mapping.py --seq 00 --source mono --model oracle --frames 0:10
    .venv/bin/python benchmarks/bench_mapping.py --seq 00 --integrate --model shipped --frames 0:10 --repeat 3

With --integrate: ``--integrate keep`` (keep --keep) against ``--integrate distribution`` on the
same predicted frames, back to back, --repeat times: the map update alone (from the prediction to
the synced octree) and the whole build (``build_map``, prediction included); min / median / max
and the frames/s ratio distribution / keep.

All scans are loaded (and, for mono, predicted/selected/back-projected) first; only integration is
timed (for the batched path: from the points to the synced octree). Every method runs with
discretize=True (graph2tree: -discretize) and OctoMap's defaults, --repeat times back to back
(insertPointCloud, batched, graph2tree in each round). Prints s/scan min / median / max per
method, the per-round speed-up ratios (min / median / max), one summary line
``speed-up: <x>x vs insertPointCloud, <y>x vs graph2tree (median of N runs)``, and how far the
maps of the last round agree (cell states at the finest resolution over the union of known cells,
exact log-odds, memoryUsage, leaf count).
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from mono_map.config import OctoMapConfig
from mono_map.cli.options import add_data_root, add_frames, add_model, add_seq
from mono_map.data.prepare import prepare_sequence
from mono_map.frames import first_frames, parse_frames
from mono_map.mapping.distribution import DistributionConfig
from mono_map.mapping.integrate import MapIntegrator
from mono_map.mapping.octree import tree_leaves
from mono_map.mapping.points import camera_origin, pixels_to_world
from mono_map.mapping.reference import lidar_measurement
from mono_map.mapping.scangraph import write_scan_graph
from mono_map.mapping.select import select_pixels


def integrate_timed(integrator: MapIntegrator, scans) -> tuple[MapIntegrator, float]:
    """Insert every scan and bring the octree up to date; returns (integrator, seconds)."""
    t0 = time.perf_counter()
    for pts, origin in scans:
        integrator.insert(pts, origin)
    integrator.sync()
    return integrator, time.perf_counter() - t0


def load_scans(args) -> list[tuple[np.ndarray, np.ndarray]]:
    selection = parse_frames(args.frames, default=first_frames(500))
    seq = prepare_sequence(args.data_root, args.seq, selection)  # renders only the prefix needed
    frames = selection.resolve(len(seq))
    desc = selection.describe(frames)
    print(f"sequence {args.seq}, {desc}, source {args.source}")
    scans = []
    predictor = None
    if args.source == "mono":
        from mono_map.mapping.inputs import load_predictor

        predictor = load_predictor(None if args.model == "shipped" else args.model)
    for i in frames:
        if args.source == "mono":
            image = seq.image(i)
            pred = predictor.predict_frame(seq, i, image) if hasattr(predictor, "predict_frame") else predictor.predict(image)
            mask = select_pixels(pred.depth, pred.entropy, args.keep, 1.0, 80.0, stride=args.stride)
            T = seq.T_world_cam2(i)
            scans.append((pixels_to_world(pred.depth, mask, seq.calib.K2, T), camera_origin(T)))
        else:
            scans.append(lidar_measurement(seq, i, args.source))
    return scans


def run_graph2tree(scans, res: float):
    """OctoMap's C++ graph2tree -discretize on the scans: (tree, insertion seconds it reports, wall seconds)."""
    import octomap

    with tempfile.TemporaryDirectory() as tmp:
        graph = Path(tmp) / "scans.graph"
        write_scan_graph(graph, scans)
        t0 = time.perf_counter()
        out = subprocess.run(["graph2tree", "-i", str(graph), "-o", str(Path(tmp) / "g.bt"), "-res", str(res),
                              "-g", "-discretize"], capture_output=True, text=True, check=True).stdout
        wall = time.perf_counter() - t0
        m = re.search(r"time to insert scans: ([0-9.eE+-]+) sec", out)
        return (octomap.OcTree.read(str(Path(tmp) / "g.bt.ot").encode()), float(m.group(1)) if m else float("nan"),
                wall)


def cell_table(tree):
    leaves = tree_leaves(tree)
    codes, leaf = leaves.expand()
    return codes, leaves.value[leaf]


def agreement(a, b) -> dict:
    ca, va = cell_table(a)
    cb, vb = cell_table(b)
    union = np.union1d(ca, cb)
    sa = np.full(len(union), -1, np.int8)
    sb = np.full(len(union), -1, np.int8)
    sa[np.searchsorted(union, ca)] = (va >= 0).astype(np.int8)
    sb[np.searchsorted(union, cb)] = (vb >= 0).astype(np.int8)
    same_values = len(ca) == len(cb) and np.array_equal(ca, cb) and np.array_equal(va, vb)
    ma, mb = a.memoryUsage(), b.memoryUsage()
    return {"cells": len(union), "state_agreement": float((sa == sb).mean()), "identical_log_odds": bool(same_values),
            "memory_a": ma, "memory_b": mb, "memory_diff": abs(ma - mb) / mb,
            "leaves_a": a.getNumLeafNodes(), "leaves_b": b.getNumLeafNodes()}


def bench_integrations(args) -> int:
    """--integrate: keep vs distribution, back to back, on the same frames (see the module docstring)."""
    from mono_map.mapping.build import make_builder
    from mono_map.mapping.jobs import MapJob

    from mono_map.mapping.inputs import FrameInputs, load_predictor

    from mono_map.mapping.pipeline import build_map

    selection = parse_frames(args.frames, default=first_frames(500))
    seq = prepare_sequence(args.data_root, args.seq, selection)
    frames = selection.resolve(len(seq))
    desc = selection.describe(frames)
    predictor = load_predictor(None if args.model == "shipped" else args.model)
    dcfg = DistributionConfig(eps=args.eps, min_update=args.min_update, ray_step=args.ray_step)
    cfg = OctoMapConfig(resolution=args.res)
    print(f"sequence {args.seq}, {desc}, model {args.model}, keep {args.keep} vs distribution {dcfg}")
    # every frame's image and prediction (with the rays' probabilities) once, shared by both integrations
    inputs = [FrameInputs(seq, i, {id(predictor): dcfg.ray_step}) for i in frames]
    for fi in inputs:
        fi.prediction(predictor)

    def updates(integrate):
        """The map update alone: the builder's per-frame step on the predicted frames, then the octree."""
        def run():
            b = make_builder(seq,
                             MapJob.spec("mono", frames, keep=args.keep, octomap=cfg,
                                         stride=args.stride, integrate=integrate, distribution=dcfg),
                             predictor=predictor)
            for i, fi in zip(frames, inputs):
                b.step(i, fi)
            b.integrator.sync()
        return run

    def builds(integrate):
        return lambda: build_map(seq,
                                 MapJob.spec("mono", frames, keep=args.keep, octomap=cfg, stride=args.stride,
                                             integrate=integrate, distribution=dcfg),
                                 predictor=predictor, show_progress=False)

    for what, keep_fn, dist_fn in (("map update", updates("keep"), updates("distribution")),
                                   ("whole build", builds("keep"), builds("distribution"))):
        times = {"keep": [], "distribution": []}
        for _ in range(args.repeat):
            for name, fn in (("keep", keep_fn), ("distribution", dist_fn)):
                t0 = time.perf_counter()
                fn()
                times[name].append(time.perf_counter() - t0)
        fps = {k: [len(frames) / t for t in v] for k, v in times.items()}
        ratios = [d / k for k, d in zip(fps["keep"], fps["distribution"])]
        for name, v in fps.items():
            print(f"{what:12s} {name:13s} frames/s min {min(v):.2f} median {statistics.median(v):.2f} max {max(v):.2f}")
        print(f"{what:12s} distribution / keep frames/s: min {min(ratios):.2f} median {statistics.median(ratios):.2f} "
              f"max {max(ratios):.2f}  ({args.repeat} back-to-back pairs)")
    return 0


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_seq(p)
    add_data_root(p)
    p.add_argument("--source", default="lidar", choices=["lidar", "lidar-fov", "mono"])
    add_frames(p, default="0:20")
    p.add_argument("--keep", type=float, default=0.8)
    p.add_argument("--stride", type=int, default=1)
    add_model(p, oracle=True, help="mono only: depth checkpoint (default: the shipped binary model; 'shipped' "
                                   "names it too)")
    p.add_argument("--res", type=float, default=0.2)
    p.add_argument("--numpy", action="store_true", help="also time the numpy DDA (no compiled kernel)")
    p.add_argument("--integrate", action="store_true", help="keep vs distribution integration (see above)")
    p.add_argument("--repeat", type=int, default=3, help="back-to-back runs of every method (>= 1)")
    d = DistributionConfig()
    p.add_argument("--eps", type=float, default=d.eps)
    p.add_argument("--min-update", type=float, default=d.min_update)
    p.add_argument("--ray-step", type=int, default=d.ray_step)
    args = p.parse_args(argv)
    if args.repeat < 1:
        p.error(f"--repeat: must be at least 1, got {args.repeat}")
    if args.integrate:
        return bench_integrations(args)
    cfg = OctoMapConfig(resolution=args.res)

    scans = load_scans(args)
    n_pts = sum(len(s[0]) for s in scans)
    print(f"{len(scans)} scans, {n_pts:,} points ({n_pts / len(scans):,.0f} per scan), {args.res} m cells\n")

    results: dict[str, list[float]] = {}
    ref = fast = g2t = None
    for _ in range(args.repeat):       # baseline and candidates back to back, every repeat
        ref, t_ref = integrate_timed(MapIntegrator(cfg, method="insertPointCloud"), scans)
        fast, t_fast = integrate_timed(MapIntegrator(cfg), scans)
        results.setdefault("insertPointCloud", []).append(t_ref)
        results.setdefault("batched", []).append(t_fast)
        results.setdefault("batched: octree updates", []).append(fast.sync_seconds)
        if args.numpy:
            os.environ["MONO_MAP_NO_C"] = "1"
            _, t_np = integrate_timed(MapIntegrator(cfg), scans)
            del os.environ["MONO_MAP_NO_C"]
            results.setdefault("batched (numpy DDA)", []).append(t_np)
        if shutil.which("graph2tree"):
            g2t, t_ins, t_wall = run_graph2tree(scans, args.res)
            results.setdefault("graph2tree (insertion)", []).append(t_ins)
            results.setdefault("graph2tree (whole run)", []).append(t_wall)
    if g2t is None:
        print("graph2tree not installed (apt-get install octomap-tools): skipped")
    fast_tree = fast.tree

    med = {name: statistics.median(v) for name, v in results.items()}
    print(f"{'method':28s} {'s/scan min':>10s} {'median':>8s} {'max':>8s} {'median / batched':>17s}")
    for name, v in results.items():
        n = len(scans)
        print(f"{name:28s} {min(v) / n:10.4f} {med[name] / n:8.4f} {max(v) / n:8.4f} {med[name] / med['batched']:16.2f}x")
    ratios = {"insertPointCloud": [a / b for a, b in zip(results["insertPointCloud"], results["batched"])]}
    if g2t is not None:
        ratios["graph2tree"] = [a / b for a, b in zip(results["graph2tree (insertion)"], results["batched"])]
    for name, r in ratios.items():
        print(f"speed-up vs {name:16s}: min {min(r):.1f}x, median {statistics.median(r):.1f}x, max {max(r):.1f}x "
              f"({len(r)} back-to-back runs)")
    print(f"speed-up: {statistics.median(ratios['insertPointCloud']):.1f}x vs insertPointCloud, "
          + (f"{statistics.median(ratios['graph2tree']):.1f}x vs graph2tree" if g2t is not None else "graph2tree n/a")
          + f" (median of {args.repeat} runs)")

    for name, other in (("insertPointCloud", ref.tree), ("graph2tree", g2t)):
        if other is None:
            continue
        a = agreement(fast_tree, other)
        print(f"batched vs {name}: {a['cells']:,} cells, state agreement {100 * a['state_agreement']:.4f} %, "
              f"identical log-odds: {a['identical_log_odds']}, memory {a['memory_a'] / 2**20:.2f} vs "
              f"{a['memory_b'] / 2**20:.2f} MB (diff {100 * a['memory_diff']:.3f} %), leaves {a['leaves_a']:,} vs "
              f"{a['leaves_b']:,}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
