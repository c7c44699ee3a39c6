"""``mono-map eval --table``: the paper's Table IV for our data, plus a keep sweep.

Builds (or reuses, cached under ``outputs/seq<SEQ>/`` by their parameters) the LiDAR-FOV map and
monocular maps for every keep of the sweep, scores each against the LiDAR-FOV map (``--reference
lidar``: against the whole 360° LiDAR map, as the paper, where LiDAR-FOV is a scored row), and writes
Markdown + JSON + a PNG of accuracy and memory against keep, and the top-down pictures.
"""

from __future__ import annotations

import json
from pathlib import Path

from mono_map.io import prepare_output_dir
from mono_map.paths import sequence_output_dir


def _cached(out_dir: Path, stem: str, build):
    bt = out_dir / f"{stem}.bt"
    js = out_dir / f"{stem}.json"
    if bt.exists() and js.exists():
        print(f"  reusing {bt}")
        return bt, json.loads(js.read_text())["stats"]
    return build()


def run_table(args) -> int:
    from mono_map.data.kitti import open_sequence
    from mono_map.errors import MonoMapError
    from mono_map.eval.map_metrics import evaluate_map, load_tree
    from mono_map.io import write_json_atomic, write_text_atomic
    from mono_map.mapping.build import parse_frames
    from mono_map.mapping.commands import (_frames_needed, _frames_tag, build_and_write, map_stem,
                                           octomap_config)
    from mono_map.mapping.integrate import validate_octomap_config

    cfg = octomap_config(args)
    validate_octomap_config(cfg)
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
    print(f"mono-map eval --table: sequence {args.seq}, {desc}, {cfg.resolution:g} m cells, model "
          f"{args.model or 'shipped binary checkpoint'}")

    rows = []
    fov_stem = map_stem("lidar-fov", 1.0, cfg, _frames_tag(frames), 1, None)
    fov_bt, fov_stats = _cached(out_dir, fov_stem, lambda: build_and_write(
        seq, "lidar-fov", 1.0, cfg, frames, 1, None, out_dir))
    entries = [("LiDAR-FOV", "lidar-fov", None, fov_bt, fov_stats)]
    if reference == "lidar":  # the paper's ground truth: the whole LiDAR map; LiDAR-FOV is then a row to score
        lidar_stem = map_stem("lidar", 1.0, cfg, _frames_tag(frames), 1, None)
        ref_bt, _ = _cached(out_dir, lidar_stem, lambda: build_and_write(
            seq, "lidar", 1.0, cfg, frames, 1, None, out_dir))
    else:
        ref_bt = fov_bt
    ref = load_tree(ref_bt)
    for keep in sorted(keeps, reverse=True):
        stem = map_stem("mono", keep, cfg, _frames_tag(frames), args.stride, args.model)
        bt, stats = _cached(out_dir, stem, lambda keep=keep: build_and_write(
            seq, "mono", keep, cfg, frames, args.stride, args.model, out_dir))
        label = "mono (keep 1.0)" if keep == 1.0 else f"mono keep {keep:g}"
        entries.append((label, "mono", keep, bt, stats))
    trees = {}
    for label, source, keep, bt, stats in entries:
        tree = ref if bt == ref_bt else load_tree(bt)
        trees[label] = tree
        m = evaluate_map(tree, ref)
        rows.append({"method": label, "source": source, "keep": keep, "bt": str(bt),
                     "accuracy": m["accuracy"], "coverage": m["coverage"], "accuracy_covered": m["accuracy_covered"],
                     "precision": m["precision"], "recall": m["recall"], "f1": m["f1"],
                     "memory_mb": stats["memory_mb"], "bt_memory_mb": m["map"]["memory_mb"],
                     "leaf_count": stats["leaf_count"], "bt_bytes": stats.get("bt_bytes"),
                     "frames_per_s": stats["frames_per_s"], "points_kept": stats["points_kept"]})

    md = table_markdown(rows, args.seq, desc, cfg, args.model, reference)
    stem = (f"table_{_frames_tag(frames)}_res{cfg.resolution:g}" + (f"_model-{Path(args.model).stem}" if args.model else "")
            + ("_ref-lidar" if reference == "lidar" else ""))
    write_text_atomic(out_dir / f"{stem}.md", md)
    write_json_atomic(out_dir / f"{stem}.json", {"sequence": args.seq, "frames": [frames.start, frames.stop], "reference": reference,
                                                  "resolution": cfg.resolution, "model": args.model, "rows": rows})
    from mono_map.viz.plots import plot_sweep, render_topdown

    plot_sweep(rows, out_dir / f"{stem}_sweep.png", "LiDAR-FOV" if reference == "lidar-fov" else "LiDAR")

    pics = [("LiDAR-FOV", trees["LiDAR-FOV"]), ("mono (keep 1.0)", trees["mono (keep 1.0)"]),
            ("mono keep 0.8", trees["mono keep 0.8"])]
    render_topdown(pics, out_dir / f"{stem}_topdown.png")
    print(md)
    print(f"wrote {out_dir / (stem + '.md')}, .json, {stem}_sweep.png, {stem}_topdown.png")
    return 0


def table_markdown(rows: list[dict], seq: str, desc: str, cfg, model, reference: str = "lidar-fov") -> str:
    lines = [f"Sequence {seq}, {desc}, {cfg.resolution:g} m cells, model {model or 'shipped binary'}; "
             f"reference = {'LiDAR-FOV' if reference == 'lidar-fov' else 'whole LiDAR (360°)'} map. Accuracy: share of the reference's known cells (volume-weighted, "
             "finest cells) whose free/occupied state the map reproduces, unknown = wrong. Memory: OctoMap "
             "memoryUsage() of the probabilistic tree after the build.",
             "",
             "| Method | Accuracy (%) | Coverage (%) | Acc. covered (%) | Occ. P / R / F1 (%) | Memory (MB) | Leaves |",
             "|---|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(f"| {r['method']} | {100 * r['accuracy']:.1f} | {100 * r['coverage']:.1f} | "
                     f"{100 * r['accuracy_covered']:.1f} | {100 * r['precision']:.1f} / {100 * r['recall']:.1f} / "
                     f"{100 * r['f1']:.1f} | {r['memory_mb']:.1f} | {r['leaf_count']:,} |")
    return "\n".join(lines) + "\n"

