"""Depth on real KITTI, every real source its own row, for any list of checkpoints.

Rows: ``object/training`` (the three object frames the project reports), ``object/extra`` (seven more),
the ten pooled, the pool of those whose colour channels agree (three of object/extra's files have scrambled
colours: ``scrambled_colour``), and the real sequence ``real01`` (every 2nd frame by default) — plus any ``--seq``
(a real sequence under another root, e.g. a raw drive). Columns: AbsRel, RMSE, δ1 of the log-space
expectation, AbsRel after per-frame median scaling (structure, not scale), sparsification AUC of ARE
ranked by entropy (with the oracle's beside it), and the mean entropy; then a second table of the same rows by
LiDAR distance (0–5, 5–10, 10–20, 20–40, 40–80 m: share of the pixels, median predicted ÷ LiDAR depth, AbsRel).
The metric code is ``eval/depth_evaluation.evaluate_model`` (the one ``mono-map eval-depth`` runs); nothing is
re-implemented.

    PYTHONPATH=. .venv/bin/python tools/eval_real.py [--model binary --model PATH ...] \\
        [--real-root ../shared/kitti_real] [--real01-frames 0:78:2] [--seq ROOT:NAME:FRAMES ...] \\
        [--out outputs/eval_real] [--threads 1]

Writes ``<out>/eval_real.json`` and ``<out>/eval_real.md`` (atomically) and prints the table.
Real data is for measuring only: nothing here trains.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Callable, NamedTuple

REPO = Path(__file__).resolve().parents[1]
DEFAULT_REAL_ROOT = REPO.parent / "shared" / "kitti_real"


class Source(NamedTuple):
    """One row group: a name, what it is, and a loader of its (name, RGB image, LiDAR depth m) frames."""

    name: str
    what: str
    load: Callable[[], list]


def object_source(name: str, folders: list[Path], what: str) -> Source:
    from mono_map.eval.depth_evaluation import object_frames

    return Source(name, what, lambda: [f for d in folders for f in object_frames(d)])


def colour_agreeing_source(name: str, folders: list[Path], what: str) -> Source:
    """The object frames of ``folders`` whose colour channels agree (``scrambled_colour`` leaves the others out)."""
    from mono_map.eval.depth_evaluation import object_frames, scrambled_colour

    def load():
        frames = [f for d in folders for f in object_frames(d)]
        bad = {n for n, _ in scrambled_colour(frames)}
        return [f for f in frames if f[0] not in bad]

    return Source(name, what, load)


def sequence_source(root: str | Path, seq: str, frames: str, name: str | None = None) -> Source:
    """Frames ``frames`` (the ``--frames`` grammar) of a real sequence, LiDAR projected into image_2."""
    from mono_map.data.kitti import open_sequence
    from mono_map.frames import parse_frames

    selection = parse_frames(frames)

    def load():
        s = open_sequence(root, seq)
        return [(f"{seq}_{i:06d}", s.image(i), s.lidar_depth(i)) for i in selection.resolve(len(s))]

    return Source(name or f"{seq} ({frames})", f"real sequence {seq}, frames {frames}", load)


def real_sources(real_root: str | Path, real01_frames: str = "0:78:2", extra: list[str] = ()) -> list[Source]:
    """The real sources of ``../shared/kitti_real`` (+ ``extra`` sequences as ``ROOT:NAME:FRAMES``)."""
    from mono_map.errors import MonoMapError

    root = Path(real_root)
    if not (root / "object" / "training").is_dir():
        raise MonoMapError(f"--real-root: {root}: no object/training (expected ../shared/kitti_real)")
    train, more = root / "object" / "training", root / "object" / "extra"
    out = [object_source("object/training", [train], "3 real object frames (the project's first real check)"),
           object_source("object/extra", [more], "7 more real object frames"),
           object_source("object (all 10)", [train, more], "the ten object frames pooled"),
           colour_agreeing_source("object (colour agrees)", [train, more],
                                  "the object frames whose colour channels agree, pooled (scrambled files left out)"),
           sequence_source(root / "odometry", "real01", real01_frames, f"real01 ({real01_frames})")]
    for spec in extra:
        parts = spec.split(":", 2)   # FRAMES may hold ':' itself (0:144:4)
        if len(parts) != 3 or not all(parts):
            raise MonoMapError(f"--seq: {spec!r}: expected ROOT:NAME:FRAMES (e.g. data/kitti:real02:0:144:4)")
        out.append(sequence_source(parts[0], parts[1], parts[2]))
    return out


def evaluate_sources(models: list[str], sources: list[Source], fast: bool = False, flip: bool = False) -> list[dict]:
    """One row per (source, model): the summary numbers of ``evaluate_model`` on that source's frames, and the
    source's frames whose colour channels do not agree (``scrambled_colour``: name, agreement)."""
    from mono_map.depth.inference import DepthPredictor
    from mono_map.eval.depth_evaluation import evaluate_model, scrambled_colour

    predictors = [(m, DepthPredictor.load(m, fast=fast, flip=flip)) for m in models]   # a bad checkpoint fails first
    rows = []
    for src in sources:
        frames = src.load()
        scrambled = [[n, a] for n, a in scrambled_colour(frames)]
        for m, p in predictors:
            r = evaluate_model(p, iter(frames), len(frames), desc=f"{src.name} {Path(m).stem}", time_frames=0)
            s = r["sparsification"]
            rows.append({"source": src.name, "what": src.what, "model": m + (" --flip" if flip else ""), "n_frames": r["n_frames"],
                         "n_pixels": r["n_pixels"], "abs_rel": r["metrics"]["abs_rel"], "rmse": r["metrics"]["rmse"],
                         "a1": r["metrics"]["a1"], "abs_rel_median_scaled": r["metrics_median_scaled"]["abs_rel"],
                         "auc_are": s["auc"]["are"], "auc_are_oracle": s["auc_oracle"]["are"],
                         "mean_entropy": r["mean_entropy"], "by_distance": r["by_distance"], "per_frame": r["per_frame"],
                         "scrambled_colour": scrambled})
    return rows


def markdown(rows: list[dict]) -> str:
    L = ["| source | model | frames | AbsRel | RMSE (m) | δ1 | AbsRel median-scaled | AUC ARE (%) | oracle AUC ARE (%) "
         "| entropy (nats) |", "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        L.append(f"| {r['source']} | {r['model']} | {r['n_frames']} | {r['abs_rel']:.3f} | {r['rmse']:.2f} | "
                 f"{r['a1']:.3f} | {r['abs_rel_median_scaled']:.3f} | {100 * r['auc_are']:.1f} | "
                 f"{100 * r['auc_are_oracle']:.1f} | {r['mean_entropy']:.2f} |")
    return "\n".join(L) + "\n"


def markdown_by_distance(rows: list[dict]) -> str:
    """Per row, by LiDAR distance: share of the pixels / median predicted ÷ LiDAR depth / AbsRel."""
    from mono_map.eval.depth_evaluation import distance_table

    lines = distance_table(["source", "model"], [([r["source"], r["model"]], r["by_distance"]) for r in rows])
    return "\n".join(lines) + "\n" if lines else ""


def main(argv: list[str] | None = None) -> int:
    from mono_map.cli.options import add_flip, add_model, add_out, add_threads

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_model(ap, repeat=True)
    ap.add_argument("--real-root", default=str(DEFAULT_REAL_ROOT), help="the kitti_real folder (default ../shared/kitti_real)")
    ap.add_argument("--real01-frames", default="0:78:2", help="frames of real01 (default every 2nd: 0:78:2)")
    ap.add_argument("--seq", action="append", default=[], help="another real sequence as ROOT:NAME:FRAMES (repeatable)")
    ap.add_argument("--only", action="append", default=None, help="evaluate only the sources with these names")
    add_out(ap, default="outputs/eval_real")
    add_threads(ap, default=1)
    ap.add_argument("--fast", action="store_true", help="statistics at the decoder's stride 4")
    add_flip(ap)
    args = ap.parse_args(argv)

    import torch

    from mono_map.errors import MonoMapError
    from mono_map.io import prepare_output_dir, write_json_atomic, write_text_atomic

    try:
        torch.set_num_threads(max(1, args.threads))
        sources = real_sources(args.real_root, args.real01_frames, args.seq)
        if args.only:
            sources = [s for s in sources if s.name in args.only or s.name.split(" ")[0] in args.only]
            if not sources:
                raise MonoMapError(f"--only: no source named {args.only}")
        out = prepare_output_dir(args.out)
        rows = evaluate_sources(args.model or ["binary"], sources, fast=args.fast, flip=args.flip)
    except MonoMapError as exc:
        print(f"eval_real: error: {exc}", file=sys.stderr)
        return 2
    md = markdown(rows)
    md += ("\nBy LiDAR distance (share of the pixels / median of predicted ÷ LiDAR depth, below 1 too near / "
           "AbsRel):\n\n" + markdown_by_distance(rows))
    scrambled = sorted({n: a for r in rows for n, a in r["scrambled_colour"]}.items())
    if scrambled:
        md += ("\nColour channels that do not agree (smallest correlation; scored in the rows above except "
               "'object (colour agrees)'): " + ", ".join(f"{n} ({a:.2f})" for n, a in scrambled) + "\n")
    write_json_atomic(out / "eval_real.json", {"args": vars(args), "rows": rows,
                                               "scrambled_colour": [list(x) for x in scrambled]})
    write_text_atomic(out / "eval_real.md", md)
    print(md)
    print(f"wrote {out}/eval_real.(json|md)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
