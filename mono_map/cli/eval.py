"""``mono-map eval``: score a map against a LiDAR reference, or the paper's Table IV (``--table``; heavy
imports inside the run functions)."""

from __future__ import annotations

from pathlib import Path

from mono_map.cli.build import DEFAULT_FRAMES
from mono_map.cli.options import (add_data_root, add_flip, add_frames, add_integration, add_model, add_octomap, add_out,
                                  check_flip,
                                  add_seq, distribution_config, fused_config, octomap_config)
from mono_map.io import prepare_output_dir
from mono_map.mapping.jobs import MapJob, read_map_sidecar, reusable
from mono_map.mapping.limits import check_reach
from mono_map.mapping.publish import build_and_write
from mono_map.mapping.select import DEFAULT_KEEP
from mono_map.mapping.strategies import LIDAR_SOURCES
from mono_map.paths import sequence_output_dir


def register(subparsers) -> None:
    e = subparsers.add_parser(
        "eval", help="score a map against a LiDAR reference, or print the paper's Table IV (--table)",
        description="Cell-state accuracy (unknown cells in the map count as wrong), coverage, accuracy over "
                    "covered cells, occupied precision/recall/F1, memory and leaf count. With --table: build "
                    "whatever is missing and print LiDAR-FOV, mono, mono keep 0.8 and a keep sweep.")
    e.add_argument("--map", default=None,
                   help="map to score (.bt); default: the map `mono-map build --seq SEQ --keep KEEP` wrote under --out")
    e.add_argument("--keep", type=float, default=DEFAULT_KEEP,
                   help=f"with no --map: the keep of that default map (default {DEFAULT_KEEP:g})")
    e.add_argument("--reference", default="lidar-fov", help="lidar-fov | lidar | path to a .bt (default lidar-fov); "
                   "with --table: lidar-fov, or lidar (the whole 360° LiDAR map, LiDAR-FOV then a scored row)")
    add_seq(e, help="sequence for a built reference / the table")
    e.add_argument("--table", action="store_true", help="build missing maps and print Table IV + keep sweep")
    e.add_argument("--paper-only", action="store_true",
                   help="with --table: only the paper's rows (LiDAR-FOV, keep sweep): no depth-gt, distribution "
                        "map or calibration")
    e.add_argument("--keeps", default="0.3,0.4,0.5,0.6,0.7,0.8,0.9,1.0", help="keep sweep for --table")
    add_frames(e, says=f"the first {DEFAULT_FRAMES}", what="frames for built maps")
    e.add_argument("--stride", type=int, default=1, help="pixel stride for built mono maps")
    add_model(e, oracle=True, help="depth checkpoint for built mono maps (default: the shipped binary model)")
    add_flip(e)
    add_data_root(e)
    add_out(e, help="directory for cached maps and the table (default outputs/seq<SEQ>)")
    e.add_argument("--json", default=None, help="write the metrics JSON here")
    add_integration(e)
    add_octomap(e)
    e.set_defaults(func=run_eval)


def reference_path(ref: str, seq, cfg, frames, out_dir: Path) -> Path:
    """The reference .bt: a path, or the LiDAR(-FOV) map of the sequence (built if missing or stale)."""
    from mono_map.errors import MonoMapError

    if ref in ("lidar", "lidar-fov"):
        job = MapJob.of(seq, ref, frames, octomap=cfg)
        bt = job.path(out_dir)
        ok, why = reusable(bt, job)
        if not ok:
            check_reach(seq, job)
            print(f"{'rebuilding' if bt.exists() else 'building'} the {ref} reference map {bt}: {why}", flush=True)
            build_and_write(job, seq, out_dir)
        return bt
    path = Path(ref)
    if not path.is_file():
        raise MonoMapError(f"--reference: {ref} is neither lidar, lidar-fov nor an existing .bt file")
    return path


def check_map_data(map_path: Path, side: dict | None, seq, frames) -> None:
    """Refuse to score ``map_path`` against a reference of ``seq``'s frames when the map's .json says it was
    built from this sequence's frames as they were before (poses, images, scans ... changed since)."""
    from mono_map.data.fingerprint import describe_change
    from mono_map.errors import MonoMapError
    from mono_map.mapping.jobs import data_fingerprint

    job = (side or {}).get("job")
    if not isinstance(job, dict) or not isinstance(job.get("data"), dict) or job.get("sequence") != seq.name:
        return
    from mono_map.frames import frames_tag

    if str(Path(seq.root).resolve()) != job.get("data_root") or job.get("frames") != frames_tag(list(frames)):
        return  # another copy of the data (modification times differ) or other frames: nothing to compare
    now = dict(data_fingerprint(seq, str(job.get("source")), frames))
    if {k: job["data"].get(k) for k in now} != now:
        raise MonoMapError(f"--map: {map_path} was built from sequence {seq.name} before its data changed "
                           f"({describe_change(job['data'], now)}); rebuild it to score it")


def check_eval_options(args):
    """eval's options, checked before any data or map is read: (OctoMap config, distribution config,
    frame selection)."""
    from mono_map.depth.inference import checkpoint_path
    from mono_map.errors import MonoMapError
    from mono_map.frames import first_frames, parse_frames
    from mono_map.io import check_output_file
    from mono_map.mapping.select import check_keep

    check_keep(args.keep)
    cfg = octomap_config(args)
    dcfg = distribution_config(args)
    fused_config(args)
    check_flip(args)
    selection = parse_frames(args.frames, default=first_frames(DEFAULT_FRAMES))
    if args.stride < 1:
        raise MonoMapError(f"--stride: must be a positive integer, got {args.stride}")
    checkpoint_path(args.model)
    if args.json:
        check_output_file(args.json, "--json", ".json")
    if args.map is not None and not Path(args.map).is_file():
        raise MonoMapError(f"--map: {args.map}: map file not found")
    if args.table:
        parse_keeps(args.keeps)
    if args.reference not in LIDAR_SOURCES and not Path(args.reference).is_file():
        raise MonoMapError(f"--reference: {args.reference} is neither lidar, lidar-fov nor an existing .bt file")
    return cfg, dcfg, selection


def default_map_path(args, cfg, dcfg, selection) -> Path:
    """The .bt ``mono-map build --seq SEQ --keep KEEP`` (same --frames/--stride/--model/--out/OctoMap/
    --integrate options) writes; MonoMapError if it is not there yet or was built from other data or another model."""
    from mono_map.data.prepare import prepare_sequence
    from mono_map.errors import MonoMapError

    seq = prepare_sequence(args.data_root, args.seq, selection, render=False)
    frames = selection.resolve(len(seq))
    job = MapJob.of(seq, "mono", frames, keep=args.keep, integrate=args.integrate, distribution=dcfg, octomap=cfg,
                    stride=args.stride, model=args.model, fused=fused_config(args), flip=args.flip)
    path = job.path(sequence_output_dir(args.out, args.seq))
    how = f"--keep {args.keep:g}" if job.integration.end_points else f"--integrate {args.integrate}"
    if not path.is_file():
        raise MonoMapError(f"--map: none given, and {path} does not exist yet "
                           f"(build it: mono-map build --seq {args.seq} {how}, or pass --map)")
    ok, why = reusable(path, job)
    if not ok:
        raise MonoMapError(f"--map: none given, and {path} is stale ({why}); rebuild it with mono-map build "
                           f"--seq {args.seq} {how}, or pass --map")
    print(f"scoring {path}")
    return path


def parse_keeps(text: str) -> tuple[float, ...]:
    """``--keeps`` "0.3,0.5" → the sorted keeps, with 0.8 and 1.0 (the table's rows) always in."""
    import math

    from mono_map.errors import MonoMapError

    try:
        keeps = {float(k) for k in text.split(",") if k.strip()}
    except ValueError:
        raise MonoMapError(f"--keeps: expected comma-separated numbers, got {text!r}") from None
    for k in keeps:
        if not (math.isfinite(k) and 0 < k <= 1):
            raise MonoMapError(f"--keeps: {k} is outside (0, 1]")
    return tuple(sorted(keeps | {0.8, 1.0}))


def run_eval(args) -> int:
    from mono_map.errors import MonoMapError
    from mono_map.frames import FrameSelection

    cfg, dcfg, selection = check_eval_options(args)
    if args.table:
        from mono_map.eval.table import TableJob

        if args.reference not in ("lidar", "lidar-fov"):
            raise MonoMapError(f"--reference: the table is scored against 'lidar-fov' or 'lidar', "
                               f"not {args.reference!r}")
        return run_table(TableJob(seq=args.seq, data_root=args.data_root, frames=selection, out=args.out,
                                  keeps=parse_keeps(args.keeps), stride=args.stride, model=args.model,
                                  octomap=cfg, reference=args.reference, paper_only=args.paper_only,
                                  distribution=dcfg, fused=fused_config(args), flip=args.flip))
    from mono_map.data.prepare import prepare_sequence
    from mono_map.eval.map_metrics import evaluate_map
    from mono_map.mapping.octree import load_tree
    from mono_map.io import write_json_atomic

    map_path = Path(args.map) if args.map else default_map_path(args, cfg, dcfg, selection)
    side = read_map_sidecar(map_path)  # a corrupt sidecar is refused before any scoring
    tree = load_tree(map_path)
    if args.reference in ("lidar", "lidar-fov"):
        # the reference is built with the map's resolution and frames (from the map's stats JSON if present)
        meta = side["stats"] if side else {}
        cfg = cfg.__class__(**{**cfg.__dict__, "resolution": float(tree.getResolution())})
        out_dir = prepare_output_dir(Path(args.out) if args.out else map_path.parent)
        try:
            if args.frames is None and isinstance(meta.get("frame_indices"), list):
                selection = FrameSelection(f"{map_path.name}'s frames", option=str(map_path.with_suffix(".json")),
                                           indices=tuple(int(i) for i in meta["frame_indices"]))
            elif args.frames is None and isinstance(meta.get("frames"), list) and len(meta["frames"]) == 2:
                a, b = (int(x) for x in meta["frames"])
                selection = FrameSelection(f"{map_path.name}'s frames {a}:{b}", option=str(map_path.with_suffix(".json")),
                                           start=a, stop=b)
        except (TypeError, ValueError):
            raise MonoMapError(f"{map_path.with_suffix('.json')}: malformed 'frames' in the map's statistics") from None
        if side is None and args.frames is None:
            raise MonoMapError(f"--map: {map_path.with_suffix('.json')} is missing, so the frames {map_path.name} "
                               f"was built from are unknown; pass --frames for them (or rebuild the map)")
        seq = prepare_sequence(args.data_root, args.seq, selection)
        frames = selection.resolve(len(seq))
        check_map_data(map_path, side, seq, frames)
        ref_path = reference_path(args.reference, seq, cfg, frames, out_dir)
    else:
        ref_path = reference_path(args.reference, None, None, [], Path("."))
    ref = load_tree(ref_path)
    metrics = evaluate_map(tree, ref)
    metrics["map_path"] = str(map_path)
    metrics["reference_path"] = str(ref_path)
    if side:
        metrics["build"] = side["stats"]
    print(format_metrics(metrics))
    if args.json:
        write_json_atomic(args.json, metrics)
    return 0


def run_table(job) -> int:
    """``eval --table``: build what is missing, score, write the table and its pictures, print it."""
    from mono_map.eval.table import run_table as score_table
    from mono_map.viz.plots import plot_table

    table = score_table(job, pictures=plot_table)  # the table and its pictures are published together
    pngs = table.pictures
    print(table.markdown)
    print(f"wrote {table.out_dir / (table.stem + '.md')}, .json, {', '.join(pngs)}")
    return 0


def format_metrics(m: dict) -> str:
    build = m.get("build") or {}
    lines = [
        f"map        {m['map_path']}",
        f"reference  {m['reference_path']}",
        f"accuracy   {100 * m['accuracy']:.2f} %  (share of the reference's {m['ref_known_cells']:,} known "
        f"{m['map']['resolution']:g} m cells whose free/occupied state the map reproduces; unknown in the map = wrong)",
        f"coverage   {100 * m['coverage']:.2f} %  (reference cells the map knows)",
        f"acc. (covered cells) {100 * m['accuracy_covered']:.2f} %",
        f"occupied   precision {100 * m['precision']:.2f} %  recall {100 * m['recall']:.2f} %  F1 {100 * m['f1']:.2f} %",
        f"map size   {m['map']['leaf_count']:,} leaves, {m['map']['memory_mb']:.2f} MB as loaded from .bt "
        f"(max-likelihood)" + (f"; {build['memory_mb']:.2f} MB while building" if "memory_mb" in build else ""),
    ]
    return "\n".join(lines)
