"""``mono-map eval --table``: the paper's Table IV for our data, plus a keep sweep.

Builds (or reuses, cached under ``outputs/seq<SEQ>/`` by their parameters) the LiDAR-FOV map,
monocular maps for every keep of the sweep and, unless ``paper_only``, the camera ground-truth map
(``depth-gt``, synthetic sequences) and the distribution-integrated map; scores each against the
LiDAR-FOV map (``--reference lidar``: against the whole 360° LiDAR map, as the paper, where LiDAR-FOV
is a scored row) — accuracy, coverage, occupied P/R/F1, memory, surface precision against depth-gt,
and the calibration (ECE, reliability diagram) of the keep 1.0, keep 0.8 and distribution maps from
their probabilistic ``.ot`` trees — and writes Markdown + JSON, a PNG of accuracy and memory against
keep, the accuracy-vs-memory plot (keep sweep a curve, distribution a point), the reliability
diagram and the top-down pictures.
"""

from __future__ import annotations

import json
from pathlib import Path

from mono_map.io import prepare_output_dir
from mono_map.paths import sequence_output_dir


def _cached(out_dir: Path, stem: str, build, need_ot: bool = False):
    bt = out_dir / f"{stem}.bt"
    js = out_dir / f"{stem}.json"
    if bt.exists() and js.exists() and (not need_ot or (out_dir / f"{stem}.ot").exists()):
        print(f"  reusing {bt}")
        return bt, json.loads(js.read_text())["stats"]
    return build()


CALIBRATED = ("mono (keep 1.0)", "mono keep 0.8", "mono, distribution")   # rows with a .ot and an ECE


def run_table(args) -> int:
    from mono_map.data.kitti import open_sequence
    from mono_map.errors import MonoMapError
    from mono_map.eval.map_metrics import (calibration, compare_leaves, load_tree, surface_precision, tree_leaves,
                                           tree_summary)
    from mono_map.io import write_json_atomic, write_text_atomic
    from mono_map.mapping.build import parse_frames
    from mono_map.mapping.commands import (_frames_needed, _frames_tag, build_and_write, distribution_config,
                                           map_stem, octomap_config)
    from mono_map.mapping.integrate import validate_octomap_config

    cfg = octomap_config(args)
    validate_octomap_config(cfg)
    dcfg = distribution_config(args)
    reference = getattr(args, "reference", "lidar-fov")
    if reference not in ("lidar", "lidar-fov"):
        raise MonoMapError(f"--reference: the table is scored against 'lidar-fov' or 'lidar', not {reference!r}")
    try:
        keeps = sorted({float(k) for k in args.keeps.split(",") if k.strip()})
    except ValueError:
        raise MonoMapError(f"--keeps: expected comma-separated numbers, got {args.keeps!r}") from None
    for k in keeps:
        if not 0 < k <= 1:
            raise MonoMapError(f"--keeps: {k} is outside (0, 1]")
    keeps = sorted(set(keeps) | {0.8, 1.0})
    out_dir = prepare_output_dir(sequence_output_dir(args.out, args.seq))
    seq = open_sequence(args.data_root, args.seq, frames=_frames_needed(args.frames))
    frames, desc = parse_frames(args.frames, len(seq))
    tag = _frames_tag(frames)
    print(f"mono-map eval --table: sequence {args.seq}, {desc}, {cfg.resolution:g} m cells, model "
          f"{args.model or 'shipped binary checkpoint'}")

    rows = []
    fov_stem = map_stem("lidar-fov", 1.0, cfg, tag, 1, None)
    fov_bt, fov_stats = _cached(out_dir, fov_stem, lambda: build_and_write(
        seq, "lidar-fov", 1.0, cfg, frames, 1, None, out_dir))
    entries = [("LiDAR-FOV", "lidar-fov", None, fov_bt, fov_stats)]
    if reference == "lidar":  # the paper's ground truth: the whole LiDAR map; LiDAR-FOV is then a row to score
        lidar_stem = map_stem("lidar", 1.0, cfg, tag, 1, None)
        ref_bt, _ = _cached(out_dir, lidar_stem, lambda: build_and_write(
            seq, "lidar", 1.0, cfg, frames, 1, None, out_dir))
    else:
        ref_bt = fov_bt
    extended = not getattr(args, "paper_only", False)
    calibrated = CALIBRATED if extended else ()
    gt_bt = None
    if extended and seq.depth(frames[0]) is not None:  # synthetic: the camera ground-truth map (upper bound, surfaces)
        gt_stem = map_stem("depth-gt", 1.0, cfg, tag, 1, None)      # every pixel: the true surfaces, dense
        gt_bt, gt_stats = _cached(out_dir, gt_stem, lambda: build_and_write(
            seq, "depth-gt", 1.0, cfg, frames, 1, None, out_dir))
        entries.append(("camera ground truth (depth-gt)", "depth-gt", None, gt_bt, gt_stats))
    for keep in sorted(keeps, reverse=True):
        label = "mono (keep 1.0)" if keep == 1.0 else f"mono keep {keep:g}"
        stem = map_stem("mono", keep, cfg, tag, args.stride, args.model)
        bt, stats = _cached(out_dir, stem, lambda keep=keep, label=label: build_and_write(
            seq, "mono", keep, cfg, frames, args.stride, args.model, out_dir, write_ot=label in calibrated),
            need_ot=label in calibrated)
        entries.append((label, "mono", keep, bt, stats))
    if extended:
        stem = map_stem("mono", 1.0, cfg, tag, args.stride, args.model, "distribution", dcfg)
        bt, stats = _cached(out_dir, stem, lambda: build_and_write(
            seq, "mono", 1.0, cfg, frames, args.stride, args.model, out_dir, integrate="distribution", dcfg=dcfg,
            write_ot=True), need_ot=True)
        entries.append(("mono, distribution", "mono-distribution", None, bt, stats))

    ref_leaves = tree_leaves(load_tree(ref_bt))
    gt_leaves = tree_leaves(load_tree(gt_bt)) if gt_bt is not None else None
    trees, reliability = {}, {}
    for label, source, keep, bt, stats in entries:
        tree = load_tree(bt)
        trees[label] = tree
        leaves = tree_leaves(tree)
        m = compare_leaves(leaves, ref_leaves)
        row = {"method": label, "source": source, "keep": keep, "bt": str(bt),
               "accuracy": m["accuracy"], "coverage": m["coverage"], "accuracy_covered": m["accuracy_covered"],
               "precision": m["precision"], "recall": m["recall"], "f1": m["f1"],
               "memory_mb": stats["memory_mb"], "bt_memory_mb": tree_summary(tree)["memory_mb"],
               "leaf_count": stats["leaf_count"], "bt_bytes": stats.get("bt_bytes"),
               "frames_per_s": stats["frames_per_s"], "points_kept": stats["points_kept"],
               "occupied_cells": int(leaves.length[leaves.occupied].sum()),
               "surface_precision": None, "ece": None}
        if gt_leaves is not None:
            row["surface_precision"] = surface_precision(leaves, gt_leaves)["surface_precision"]
        if label in calibrated:
            cal = calibration(tree_leaves(load_tree(bt.with_suffix(".ot"))), ref_leaves)
            reliability[label] = cal
            row["ece"] = cal["ece"]
        rows.append(row)

    md = table_markdown(rows, args.seq, desc, cfg, args.model, reference, dcfg)
    stem = (f"table_{tag}_res{cfg.resolution:g}" + (f"_model-{Path(args.model).stem}" if args.model else "")
            + ("_ref-lidar" if reference == "lidar" else ""))
    write_text_atomic(out_dir / f"{stem}.md", md)
    write_json_atomic(out_dir / f"{stem}.json", {"sequence": args.seq, "frames": [frames.start, frames.stop], "reference": reference,
                                                  "resolution": cfg.resolution, "model": args.model, "rows": rows,
                                                  "distribution": dcfg.__dict__, "reliability": reliability})
    ref_label = "LiDAR-FOV" if reference == "lidar-fov" else "LiDAR"
    plot_sweep(rows, out_dir / f"{stem}_sweep.png", ref_label)
    pngs = [f"{stem}_sweep.png"]
    if extended:
        plot_accuracy_memory(rows, out_dir / f"{stem}_acc_memory.png", ref_label)
        plot_reliability(reliability, out_dir / f"{stem}_reliability.png", ref_label)
        pngs += [f"{stem}_acc_memory.png", f"{stem}_reliability.png"]
    from mono_map.viz.topdown import render_topdown

    pics = [("LiDAR-FOV", trees["LiDAR-FOV"]), ("mono (keep 1.0)", trees["mono (keep 1.0)"]),
            ("mono keep 0.8", trees["mono keep 0.8"])]
    if extended:
        pics.append(("mono, distribution", trees["mono, distribution"]))
    render_topdown(pics, out_dir / f"{stem}_topdown.png")
    print(md)
    print(f"wrote {out_dir / (stem + '.md')}, .json, {', '.join(pngs)}, {stem}_topdown.png")
    return 0


def _pct(v) -> str:
    return "–" if v is None else f"{100 * v:.1f}"


def table_markdown(rows: list[dict], seq: str, desc: str, cfg, model, reference: str = "lidar-fov",
                   dcfg=None) -> str:
    dist = "" if dcfg is None else (f" Distribution map: eps {dcfg.eps:g}, min update {dcfg.min_update:g}, "
                                    f"ray step {dcfg.ray_step}, temperature {dcfg.temperature:g}.")
    lines = [f"Sequence {seq}, {desc}, {cfg.resolution:g} m cells, model {model or 'shipped binary'}; "
             f"reference = {'LiDAR-FOV' if reference == 'lidar-fov' else 'whole LiDAR (360°)'} map. Accuracy: share of the reference's known cells (volume-weighted, "
             "finest cells) whose free/occupied state the map reproduces, unknown = wrong. Memory: OctoMap "
             "memoryUsage() of the probabilistic tree after the build. Surface precision: share of the map's "
             "occupied cells within one cell of an occupied depth-gt cell. ECE: expected calibration error of "
             "the probabilistic tree's occupancy probabilities over the cells the reference knows (10 bins)." + dist,
             "",
             "| Method | Accuracy (%) | Coverage (%) | Acc. covered (%) | Occ. P / R / F1 (%) | Surface prec. (%) | "
             "Occupied cells | ECE | Memory (MB) | Leaves |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        ece = "–" if r.get("ece") is None else f"{r['ece']:.3f}"
        lines.append(f"| {r['method']} | {100 * r['accuracy']:.1f} | {100 * r['coverage']:.1f} | "
                     f"{100 * r['accuracy_covered']:.1f} | {100 * r['precision']:.1f} / {100 * r['recall']:.1f} / "
                     f"{100 * r['f1']:.1f} | {_pct(r.get('surface_precision'))} | {r.get('occupied_cells', 0):,} | "
                     f"{ece} | {r['memory_mb']:.1f} | {r['leaf_count']:,} |")
    return "\n".join(lines) + "\n"


def plot_accuracy_memory(rows: list[dict], path: Path, reference_label: str = "LiDAR-FOV") -> None:
    """Accuracy (and accuracy on covered cells) against memory: the keep sweep a curve, the distribution map a point."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from mono_map.io import atomic_path

    sweep = sorted((r for r in rows if r["source"] == "mono"), key=lambda r: r["memory_mb"])
    dist = [r for r in rows if r["source"] == "mono-distribution"]
    fig, ax = plt.subplots(figsize=(6.4, 4.6))
    for key, style, name in (("accuracy", "o-", "accuracy"), ("accuracy_covered", "s--", "acc. on covered cells")):
        ax.plot([r["memory_mb"] for r in sweep], [100 * r[key] for r in sweep], style, color="tab:blue",
                label=f"keep sweep: {name}", alpha=1.0 if key == "accuracy" else 0.6)
        for r in dist:
            ax.plot(r["memory_mb"], 100 * r[key], "*" if key == "accuracy" else "P", color="tab:red", ms=14,
                    label=f"distribution: {name}", alpha=1.0 if key == "accuracy" else 0.6)
    for r in sweep:
        ax.annotate(f"{r['keep']:g}", (r["memory_mb"], 100 * r["accuracy"]), textcoords="offset points",
                    xytext=(4, -10), fontsize=7, color="tab:blue")
    ax.set_xlabel("memory (MB, OctoMap memoryUsage)")
    ax.set_ylabel(f"accuracy vs {reference_label} map (%)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.16), ncol=2, frameon=False)
    fig.tight_layout()
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=130)
    plt.close(fig)


def plot_reliability(reliability: dict, path: Path, reference_label: str = "LiDAR-FOV") -> None:
    """Reliability diagram: per map, the share of cells the reference has occupied against the map's
    occupancy probability (binned), with the bins' weights below."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from mono_map.io import atomic_path

    fig, (ax, axw) = plt.subplots(2, 1, figsize=(5.6, 6.2), sharex=True, gridspec_kw={"height_ratios": [3, 1]})
    ax.plot([0, 1], [0, 1], ":", color="grey", lw=1, label="perfectly calibrated")
    n = max(len(reliability), 1)
    for j, (label, cal) in enumerate(reliability.items()):
        conf, freq, w = (np.asarray(cal[k], dtype=float) for k in ("confidence", "frequency", "weight"))
        ok = w > 0
        ax.plot(conf[ok], freq[ok], "o-", label=f"{label} (ECE {cal['ece']:.3f})")
        edges = np.asarray(cal["bin_edges"])
        width = (edges[1] - edges[0]) / (n + 1)
        axw.bar(edges[:-1] + (j + 0.5) * width, w, width=width, align="edge", label=label)
    ax.set_ylabel(f"share occupied in the {reference_label} map")
    ax.set_xlim(0, 1)
    ax.set_ylim(0, 1)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    axw.set_xlabel("map's occupancy probability (cells both maps know)")
    axw.set_ylabel("share of cells")
    axw.set_yscale("log")
    fig.tight_layout()
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=130)
    plt.close(fig)


def plot_sweep(rows: list[dict], path: Path, reference_label: str = "LiDAR-FOV") -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from mono_map.io import atomic_path

    mono = sorted((r for r in rows if r["source"] == "mono"), key=lambda r: r["keep"])
    ref = next(r for r in rows if r["source"] == "lidar-fov")
    keeps = [r["keep"] for r in mono]
    fig, ax1 = plt.subplots(figsize=(6, 4.6))
    ax1.plot(keeps, [100 * r["accuracy"] for r in mono], "o-", color="tab:blue", label="accuracy")
    ax1.plot(keeps, [100 * r["accuracy_covered"] for r in mono], "s--", color="tab:cyan", label="accuracy (covered cells)")
    ax1.set_xlabel("keep (fraction of lowest-entropy pixels)")
    ax1.set_ylabel(f"accuracy vs {reference_label} map (%)", color="tab:blue")
    ax2 = ax1.twinx()
    ax2.plot(keeps, [r["memory_mb"] for r in mono], "^-", color="tab:red", label="memory")
    ax2.axhline(ref["memory_mb"], color="tab:red", ls=":", lw=1, label="LiDAR-FOV memory")
    ax2.set_ylabel("memory (MB, OctoMap memoryUsage)", color="tab:red")
    h1, l1 = ax1.get_legend_handles_labels()
    h2, l2 = ax2.get_legend_handles_labels()
    ax1.legend(h1 + h2, l1 + l2, fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.16), ncol=2,
               frameon=False)  # below the axes: the curves use the whole plot
    ax1.grid(alpha=0.3)
    fig.tight_layout()
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=130)
    plt.close(fig)
