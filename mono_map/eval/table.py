"""The paper's Table IV for our data, plus a keep sweep (``mono-map eval --table``).

Builds (or reuses, cached under ``outputs/seq<SEQ>/``; a map is reused only if its .json records the
same job: data root, model digest, settings, integration and frames) the LiDAR-FOV map, monocular maps
for every keep of the sweep and, unless ``paper_only``, the camera ground-truth map (``depth-gt``,
synthetic sequences) and the distribution-integrated map; scores each against the LiDAR-FOV map
(``--reference lidar``: against the whole 360° LiDAR map, as the paper, where LiDAR-FOV is a scored
row) — accuracy, coverage, occupied P/R/F1, memory, surface precision against depth-gt, and the
calibration (ECE, reliability diagram) of the keep 1.0, keep 0.8 and distribution maps from their
probabilistic ``.ot`` trees — and writes Markdown + JSON. The pictures (:func:`mono_map.viz.plots.plot_table`:
accuracy and memory against keep, accuracy vs memory, the reliability diagram, top-down maps) are drawn
by the command from the returned :class:`Table`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from mono_map.config import OctoMapConfig
from mono_map.frames import FrameSelection
from mono_map.io import prepare_output_dir
from mono_map.mapping.distribution import DistributionConfig
from mono_map.mapping.fused import FusedConfig
from mono_map.mapping.jobs import MapJob
from mono_map.mapping.limits import check_reach
from mono_map.mapping.strategies import source_of
from mono_map.paths import sequence_output_dir

CALIBRATED = ("mono (keep 1.0)", "mono keep 0.8", "mono, distribution")   # rows with a .ot and an ECE


@dataclass(frozen=True)
class TableJob:
    """What ``eval --table`` scores: sequence, data root, frames, maps' settings, reference.

    paper_only: only the paper's rows (LiDAR-FOV, keep sweep), no depth-gt, distribution or fused map or
    calibration; distribution: the settings of the distribution-integrated row (and the fused row's free
    space); fused: the fused row's surface settings; flip: every mono map's images predicted mirrored too."""

    seq: str
    data_root: str | None
    frames: FrameSelection
    out: str | None
    keeps: tuple[float, ...]
    stride: int
    model: str | None
    octomap: OctoMapConfig
    reference: str = "lidar-fov"
    paper_only: bool = False
    distribution: DistributionConfig = field(default_factory=DistributionConfig)
    fused: FusedConfig = field(default_factory=FusedConfig)
    flip: bool = False


@dataclass
class Table:
    """What :func:`run_table` scored and wrote: the rows, their Markdown, where they went, and what the
    pictures need (reliability per calibrated row, (label, Leaves) pairs for the top-down maps)."""

    rows: list[dict]
    markdown: str
    out_dir: Path
    stem: str
    reference: str
    reliability: dict
    topdown: list[tuple[str, object]]
    extended: bool
    pictures: list[str] = field(default_factory=list)   # file names of the pictures written beside it


def missing_maps(jobs: list[tuple[MapJob, bool]], out_dir: Path) -> list[tuple[MapJob, bool]]:
    """The (job, needs .ot) pairs whose map under ``out_dir`` cannot be reused — its .json must say it was
    built by exactly that job (data root, model digest, settings, frames) and, with the .ot flag, its
    .ot must be there; says which are reused and why the others are (re)built."""
    from mono_map.mapping.jobs import reusable

    todo = []
    for job, need_ot in jobs:
        bt = job.path(out_dir)
        ok, why = reusable(bt, job)
        if ok and need_ot and not bt.with_suffix(".ot").is_file():
            ok, why = False, f"{bt.with_suffix('.ot').name} missing"
        if ok:
            print(f"  reusing {bt}")
            continue
        if bt.exists():
            print(f"  rebuilding {bt}: {why}")
        todo.append((job, need_ot))
    return todo


# Peak memory of one map in a shared build pass, per frame (measured: mono keep 1.0 on frames 0–499 of
# 00, memoryUsage 366 MB, 1.96–3.0× that in peak RSS): the pass groups at most as many maps as fit in
# half the memory a build may use.
PASS_BYTES_PER_MAP_FRAME = 1.5e6


def build_missing(todo: list[tuple[MapJob, bool]], seq, out_dir: Path, predictor) -> None:
    """Build the missing maps in as few passes over the frames as memory allows (every map of a pass
    shares each frame's prediction: the keep sweep costs one prediction pass, not one per keep)."""
    from mono_map.mapping.limits import memory_limit
    from mono_map.mapping.publish import MapRequest, build_and_write_all

    if not todo:
        return
    limit, _ = memory_limit()
    per_pass = max(1, int(limit / 2 // (PASS_BYTES_PER_MAP_FRAME * len(todo[0][0].frames))))
    for a in range(0, len(todo), per_pass):
        group = todo[a:a + per_pass]
        print(f"  building {len(group)} map{'s' if len(group) > 1 else ''} in one pass: "
              + ", ".join(job.stem() for job, _ in group), flush=True)
        build_and_write_all([MapRequest(job, write_ot=need_ot) for job, need_ot in group], seq, out_dir,
                            predictor=predictor)


def run_table(job: TableJob, pictures=None) -> Table:
    """Build (or reuse) every map of the table, score them, write ``<stem>.md``, ``<stem>.json`` and the
    pictures ``pictures(table, folder)`` draws into ``folder`` (returning their file names) as one set."""
    from mono_map.data.prepare import prepare_sequence
    from mono_map.eval.map_metrics import calibration, compare_leaves, surface_precision, tree_summary
    from mono_map.frames import frames_tag
    from mono_map.io import staged_dir, write_json_atomic, write_text_atomic
    from mono_map.mapping.inputs import load_predictor
    from mono_map.depth.inference import model_digest
    from mono_map.mapping.jobs import read_map_sidecar
    from mono_map.mapping.octree import load_tree, tree_leaves

    cfg = job.octomap
    dcfg = job.distribution
    reference = job.reference
    keeps = job.keeps
    out_dir = prepare_output_dir(sequence_output_dir(job.out, job.seq))
    digest = model_digest(job.model)
    predictor = load_predictor(job.model, flip=job.flip)  # a bad checkpoint is refused before any data is read
    seq = prepare_sequence(job.data_root, job.seq, job.frames, stereo=bool(job.fused.stereo))   # synthetic: image_3 too
    frames = job.frames.resolve(len(seq))
    desc = job.frames.describe(frames)
    tag = frames_tag(frames)
    print(f"mono-map eval --table: sequence {job.seq}, {desc}, {cfg.resolution:g} m cells, model "
          f"{job.model or 'shipped binary checkpoint'}" + (", each image mirrored too (--flip)" if job.flip else ""))
    extended = not job.paper_only
    calibrated = CALIBRATED if extended else ()

    def job_of(source, keep=1.0, stride=1, model=None, integrate="keep"):
        mono = source_of(source).predicted
        return MapJob.of(seq, source, frames, keep=keep, integrate=integrate, distribution=dcfg, octomap=cfg,
                         stride=stride, model=model, digest=digest if mono else None, fused=job.fused,
                         flip=job.flip)

    fov = job_of("lidar-fov")
    entries = [("LiDAR-FOV", "lidar-fov", None, fov)]
    ref = job_of("lidar") if reference == "lidar" else fov   # the paper's ground truth: the whole LiDAR map
    gt = None
    if extended and seq.depth(frames[0]) is not None:  # synthetic: the camera ground-truth map (upper bound, surfaces)
        gt = job_of("depth-gt")                        # every pixel, whatever --stride: the true surfaces, dense
        entries.append(("camera ground truth (depth-gt)", "depth-gt", None, gt))
    for keep in sorted(keeps, reverse=True):
        label = "mono (keep 1.0)" if keep == 1.0 else f"mono keep {keep:g}"
        entries.append((label, "mono", keep, job_of("mono", keep, job.stride, job.model)))
    if extended:
        entries.append(("mono, distribution", "mono-distribution", None,
                        job_of("mono", 1.0, job.stride, job.model, integrate="distribution")))
        entries.append(("mono, fused", "mono-fused", None,
                        job_of("mono", 1.0, job.stride, job.model, integrate="fused")))
    jobs = [(mj, label in calibrated) for label, _, _, mj in entries]
    if ref is not fov:
        jobs.insert(1, (ref, False))
    for mj, _ in jobs:
        check_reach(seq, mj)  # a pose beyond the map's reach is named before any map is built
    build_missing(missing_maps(jobs, out_dir), seq, out_dir, predictor)
    ref_bt = ref.path(out_dir)
    gt_bt = None if gt is None else gt.path(out_dir)

    ref_tree = load_tree(ref_bt)                 # read once: its leaves are every row's reference
    ref_leaves = tree_leaves(ref_tree)
    gt_leaves = tree_leaves(load_tree(gt_bt)) if gt_bt is not None else None
    pictured = ["LiDAR-FOV", "mono (keep 1.0)", "mono keep 0.8"] + (["mono, distribution", "mono, fused"]
                                                                       if extended else [])
    rows, pics, reliability = [], {}, {}
    for label, source, keep, mj in entries:
        bt = mj.path(out_dir)
        stats = read_map_sidecar(bt)["stats"]
        tree = ref_tree if bt == ref_bt else load_tree(bt)
        leaves = ref_leaves if bt == ref_bt else tree_leaves(tree)
        if label in pictured:
            pics[label] = leaves
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

    md = table_markdown(rows, job.seq, desc, cfg, f"{job.model or 'shipped binary'} (--flip)" if job.flip else job.model,
                        reference, dcfg if extended else None,
                        job.fused if extended else None)
    stem = (f"table_{tag}_res{cfg.resolution:g}" + (f"_model-{Path(job.model).stem}" if job.model else "")
            + ("_flip" if job.flip else "") + ("_ref-lidar" if reference == "lidar" else ""))
    table = Table(rows=rows, markdown=md, out_dir=out_dir, stem=stem, reference=reference, reliability=reliability,
                  topdown=[(label, pics[label]) for label in pictured], extended=extended)
    # the table, its JSON and its pictures are published as one set: all of them or (a failure, a signal) none
    with staged_dir(out_dir) as stage:
        write_text_atomic(stage / f"{stem}.md", md)
        write_json_atomic(stage / f"{stem}.json", {"sequence": job.seq, "frames": [frames[0], frames[-1] + 1],
                                                   "reference": reference, "resolution": cfg.resolution,
                                                   "model": job.model, "model_digest": digest, "rows": rows,
                                                   "distribution": dcfg.__dict__ if extended else None,
                                                   "fused": job.fused.__dict__ if extended else None,
                                                   "reliability": reliability, "data": fov.key()["data"]})
        table.pictures = list(pictures(table, stage)) if pictures is not None else []
    return table


def _pct(v) -> str:
    return "–" if v is None else f"{100 * v:.1f}"


def table_markdown(rows: list[dict], seq: str, desc: str, cfg, model, reference: str = "lidar-fov",
                   dcfg=None, fcfg=None) -> str:
    dist = "" if dcfg is None else (f" Distribution map: eps {dcfg.eps:g}, min update {dcfg.min_update:g}, "
                                    f"ray step {dcfg.ray_step}, temperature {dcfg.temperature:g}.")
    if fcfg is not None:
        dist += (f" Fused map: the distribution map's free space + surface hits snapped to the fused TSDF "
                 f"(spread ref {fcfg.spread_ref:g}, min weight {fcfg.min_weight:g}, lag {fcfg.lag}, snap window "
                 f"{fcfg.snap_window:g} m; multi-view posterior from {fcfg.multiview} neighbours; surface at each "
                 f"pixel's {'mode' if fcfg.mode else 'expected depth'}).")
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
