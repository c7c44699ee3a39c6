"""``mono-map eval --table``: the paper's Table IV for our data, plus a keep sweep.

Builds (or reuses, cached under ``outputs/seq<SEQ>/``; a map is reused only if its .json records the same job: data
root, model digest, settings and frames) the LiDAR-FOV map and
monocular maps for every keep of the sweep, scores each against the LiDAR-FOV map (``--reference
lidar``: against the whole 360° LiDAR map, as the paper, where LiDAR-FOV is a scored row), and writes
Markdown + JSON + a PNG of accuracy and memory against keep, and the top-down pictures.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from mono_map.config import OctoMapConfig
from mono_map.frames import FrameSelection
from mono_map.io import prepare_output_dir
from mono_map.paths import sequence_output_dir


@dataclass(frozen=True)
class TableJob:
    """What ``eval --table`` scores: sequence, data root, frames, maps' settings, reference."""

    seq: str
    data_root: str | None
    frames: FrameSelection
    out: str | None
    keeps: tuple[float, ...]
    stride: int
    model: str | None
    octomap: OctoMapConfig
    reference: str = "lidar-fov"


def _cached(bt: Path, job: dict, build):
    """Reuse ``bt`` if its .json says it was built by exactly ``job`` (data root, model digest,
    settings, frames); else build it again, saying why."""
    from mono_map.mapping.jobs import read_map_sidecar, reusable

    ok, why = reusable(bt, job)
    if ok:
        print(f"  reusing {bt}")
        return bt, read_map_sidecar(bt)["stats"]
    if bt.exists():
        print(f"  rebuilding {bt} ({why})")
    return build()


def run_table(job: TableJob) -> int:
    from mono_map.data.prepare import prepare_sequence
    from mono_map.eval.map_metrics import evaluate_map, load_tree
    from mono_map.frames import frames_tag
    from mono_map.io import write_json_atomic, write_text_atomic
    from mono_map.mapping.build import load_predictor
    from mono_map.mapping.jobs import build_and_write, job_key, map_stem, model_digest

    cfg = job.octomap
    reference = job.reference
    keeps = job.keeps
    out_dir = prepare_output_dir(sequence_output_dir(job.out, job.seq))
    digest = model_digest(job.model)
    predictor = load_predictor(job.model)  # a bad checkpoint is refused before any data is read
    seq = prepare_sequence(job.data_root, job.seq, job.frames)
    frames = job.frames.resolve(len(seq))
    desc = job.frames.describe(frames)
    tag = frames_tag(frames)
    print(f"mono-map eval --table: sequence {job.seq}, {desc}, {cfg.resolution:g} m cells, model "
          f"{job.model or 'shipped binary checkpoint'}")

    def build_mono(keep):
        return build_and_write(seq, "mono", keep, cfg, frames, job.stride, job.model, out_dir,
                               predictor=predictor, digest=digest)

    def lidar_map(source):
        bt = out_dir / f"{map_stem(source, 1.0, cfg, tag, 1, None)}.bt"
        return _cached(bt, job_key(seq, source, 1.0, cfg, frames, 1, None), lambda: build_and_write(
            seq, source, 1.0, cfg, frames, 1, None, out_dir))

    fov_bt, fov_stats = lidar_map("lidar-fov")
    entries = [("LiDAR-FOV", "lidar-fov", None, fov_bt, fov_stats)]
    if reference == "lidar":  # the paper's ground truth: the whole LiDAR map; LiDAR-FOV is then a row to score
        ref_bt, _ = lidar_map("lidar")
    else:
        ref_bt = fov_bt
    ref = load_tree(ref_bt)
    rows = []
    for keep in sorted(keeps, reverse=True):
        bt = out_dir / f"{map_stem('mono', keep, cfg, tag, job.stride, job.model)}.bt"
        bt, stats = _cached(bt, job_key(seq, "mono", keep, cfg, frames, job.stride, job.model, digest),
                            lambda keep=keep: build_mono(keep))
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

    md = table_markdown(rows, job.seq, desc, cfg, job.model, reference)
    stem = (f"table_{tag}_res{cfg.resolution:g}" + (f"_model-{Path(job.model).stem}" if job.model else "")
            + ("_ref-lidar" if reference == "lidar" else ""))
    write_text_atomic(out_dir / f"{stem}.md", md)
    write_json_atomic(out_dir / f"{stem}.json", {"sequence": job.seq, "frames": [frames[0], frames[-1] + 1],
                                                  "reference": reference, "resolution": cfg.resolution,
                                                  "model": job.model, "model_digest": digest, "rows": rows})
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

