"""``mono-map build`` and ``mono-map eval`` (heavy imports happen inside the run functions)."""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

from mono_map.io import prepare_output_dir
from mono_map.mapping.jobs import (RRD_MIN_FREE, MapJob, build_and_write, check_memory, check_reach,
                                   checkpoint_path, model_digest, read_map_sidecar, reusable)
from mono_map.mapping.select import DEFAULT_KEEP
from mono_map.mapping.strategies import INTEGRATIONS, LIDAR_SOURCES
from mono_map.paths import sequence_output_dir


def _add_octomap_args(p: argparse.ArgumentParser) -> None:
    from mono_map.config import OctoMapConfig

    d = OctoMapConfig()
    g = p.add_argument_group("OctoMap (defaults are OctoMap's own)")
    g.add_argument("--res", type=float, default=d.resolution, help=f"cell size, metres (default {d.resolution})")
    g.add_argument("--max-range", type=float, default=None,
                   help="rays longer than this are cut and mark free space only (metres, > 0; default: unlimited)")
    g.add_argument("--prob-hit", type=float, default=d.prob_hit, help=f"default {d.prob_hit}")
    g.add_argument("--prob-miss", type=float, default=d.prob_miss, help=f"default {d.prob_miss}")
    g.add_argument("--clamp-min", type=float, default=d.clamp_min, help=f"default {d.clamp_min}")
    g.add_argument("--clamp-max", type=float, default=d.clamp_max, help=f"default {d.clamp_max}")


# --fused-* options: FusedConfig's fields, each with what it means (the default is the dataclass's)
FUSED_OPTIONS = (
    ("spread_ref", "log-depth spread at which a pixel's fusion weight halves"),
    ("min_weight", "summed weight a cell needs to be surface (~ confident views)"),
    ("trunc_sigma", "truncation band in metric spreads"),
    ("trunc_min", "narrowest truncation band, cells"),
    ("trunc_max", "widest truncation band, metres"),
    ("max_depth", "pixels farther than this (metres) are not fused"),
    ("max_spread", "pixels with a wider log-depth spread are not fused"),
    ("trunc_behind", "cells up to this many bands behind a pixel's depth are fused"),
    ("lag", "frames after which a frame's pixels are snapped to the fused surface"),
    ("snap_window", "how far (metres) from a pixel's expected depth its ray looks for the fused surface"),
    ("snap_step", "snap every N-th ray of the --ray-step grid"),
    ("multiview", "neighbouring frames (0 = off, 1, 2) whose images sharpen each frame's depth distribution "
                  "(plane-sweep posterior, depth/multiview.py)"),
    ("multiview_temperature", "temperature of the multi-view photometric likelihood"),
    ("subpixel", "1: voxels read the full-resolution depth bilinearly; 0: the nearest ray-grid pixel"),
)

def _add_integration_args(p: argparse.ArgumentParser) -> None:
    from mono_map.mapping.distribution import DistributionConfig

    d = DistributionConfig()
    g = p.add_argument_group("integration of monocular depth")
    g.add_argument("--integrate", default="keep", choices=INTEGRATIONS,
                   help="keep: the paper's cut, the --keep lowest-entropy pixels' expected depths as end points "
                        "(default); distribution: every valid pixel's whole depth distribution sets the expected "
                        "OctoMap update of each cell along its ray (--keep ignored); fused: the distribution's free "
                        "space + a thin surface fused across views (uncertainty-weighted TSDF; docs/fused.md)")
    g.add_argument("--eps", type=float, default=d.eps,
                   help=f"distribution: rays stop where P(surface beyond) < eps (default {d.eps:g})")
    g.add_argument("--temperature", type=float, default=d.temperature,
                   help=f"distribution: probabilities p^(1/T), renormalised (default {d.temperature:g}; 1 = as predicted)")
    g.add_argument("--min-update", type=float, default=d.min_update,
                   help=f"distribution: drop per-cell updates weaker than this log-odds magnitude (default {d.min_update:g})")
    g.add_argument("--bin-spread", type=float, default=d.bin_spread,
                   help=f"distribution: spread each bin's mass over this central fraction of the bin, placed at the "
                        f"pixel's local mean (default {d.bin_spread:g} = whole bins)")
    g.add_argument("--quantum", type=float, default=d.quantum,
                   help=f"distribution: round per-cell updates to multiples of this log-odds step, so free space "
                        f"prunes (default {d.quantum:g}; 0 = off)")
    g.add_argument("--snap-free", action=argparse.BooleanOptionalAction, default=d.snap_free,
                   help="distribution: snap free-space updates to the sensor model's {miss, 0} (a whole miss where "
                        "the expected update is at least half a miss), so free space prunes as in a keep map "
                        f"(default {'on' if d.snap_free else 'off'})")
    g.add_argument("--ray-step", type=int, default=d.ray_step,
                   help=f"distribution: one ray every N-th pixel row and column (default {d.ray_step})")
    from mono_map.mapping.fused import FusedConfig

    f = FusedConfig()
    g = p.add_argument_group("fused surface (--integrate fused; the free space uses the distribution options)")
    kinds = {fld.name: {"int": int, "float": float}[str(fld.type)] for fld in dataclasses.fields(FusedConfig)}
    for name, what in FUSED_OPTIONS:
        default = getattr(f, name)
        g.add_argument("--fused-" + name.replace("_", "-"), type=kinds[name], default=default,
                       help=f"{what} (default {default:g})")

def distribution_config(args):
    """The ``--integrate distribution`` settings of the options, checked (MonoMapError naming the option)."""
    from mono_map.mapping.distribution import DistributionConfig, check_distribution_config

    return check_distribution_config(DistributionConfig(eps=args.eps, temperature=args.temperature,
                                                        ray_step=args.ray_step, min_update=args.min_update,
                                                        bin_spread=args.bin_spread, quantum=args.quantum,
                                                        snap_free=args.snap_free))


def fused_config(args):
    """The ``--integrate fused`` surface settings of the options, checked (MonoMapError naming the option)."""
    from mono_map.mapping.fused import FusedConfig, check_fused_config

    return check_fused_config(FusedConfig(**{name: getattr(args, "fused_" + name) for name, _ in FUSED_OPTIONS}))


def register(subparsers) -> None:
    b = subparsers.add_parser(
        "build", help="build an OctoMap (.bt + stats JSON) from monocular depth or LiDAR",
        description="Integrate a sequence into an OctoMap: per frame, keep the --keep fraction of valid pixels "
                    "with the lowest predicted entropy, back-project them and ray-cast them into the map "
                    "(or use the LiDAR scans). Writes <out>/<name>.bt and <out>/<name>.json atomically.")
    b.add_argument("--seq", required=True, help="sequence name, e.g. 00")
    b.add_argument("--keep", type=float, default=DEFAULT_KEEP,
                   help=f"fraction of valid pixels kept per frame, in (0, 1] (default {DEFAULT_KEEP:g})")
    b.add_argument("--source", default="mono", help="mono | depth-gt | lidar | lidar-fov (default mono); depth-gt: "
                   "the synthetic ground-truth depth_2 back-projected like a keep-1.0 mono map (upper bound)")
    _add_integration_args(b)
    _add_octomap_args(b)
    b.add_argument("--stride", type=int, default=1, help="use every S-th pixel row and column (default 1)")
    b.add_argument("--frames", default=None,
                   help="N (the first N), A:B[:S], I,J,... or 'all' (default: the first 500 frames)")
    b.add_argument("--model", default=None,
                   help="depth checkpoint (default: the shipped binary model); 'oracle' = noisy ground truth "
                        "(synthetic sequences only, for development)")
    b.add_argument("--data-root", default=None, help="KITTI root: odometry layout, or raw (then --seq YYYY_MM_DD_drive_NNNN_sync) (default $MONO_MAP_DATA or ./data/kitti)")
    b.add_argument("--out", default=None, help="output directory (default outputs/seq<SEQ>)")
    b.add_argument("--name", default=None, help="output file stem (default from source/keep/res)")
    b.add_argument("--viewer", action="store_true", help="stream the build to a spawned rerun viewer")
    b.add_argument("--rrd", default=None, help="save a rerun recording to this file")
    b.add_argument("--reference-map", default=None, help="a .bt shown beside the build in the viewer")
    b.add_argument("--ot", action="store_true", help="also write the probabilistic tree <name>.ot (for calibration)")
    b.set_defaults(func=run_build)

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
    e.add_argument("--seq", default="00", help="sequence for a built reference / the table (default 00)")
    e.add_argument("--table", action="store_true", help="build missing maps and print Table IV + keep sweep")
    e.add_argument("--paper-only", action="store_true",
                   help="with --table: only the paper's rows (LiDAR-FOV, keep sweep): no depth-gt, distribution "
                        "map or calibration")
    e.add_argument("--keeps", default="0.3,0.4,0.5,0.6,0.7,0.8,0.9,1.0", help="keep sweep for --table")
    e.add_argument("--frames", default=None, help="frames for built maps (default: the first 500)")
    e.add_argument("--stride", type=int, default=1, help="pixel stride for built mono maps")
    e.add_argument("--model", default=None, help="depth checkpoint for built mono maps ('oracle' = noisy GT)")
    e.add_argument("--data-root", default=None)
    e.add_argument("--out", default=None, help="directory for cached maps and the table (default outputs/seq<SEQ>)")
    e.add_argument("--json", default=None, help="write the metrics JSON here")
    _add_integration_args(e)
    _add_octomap_args(e)
    e.set_defaults(func=run_eval)


def octomap_config(args):
    """The OctoMap settings of the options, checked (MonoMapError naming the option)."""
    import math

    from mono_map.config import OctoMapConfig
    from mono_map.errors import MonoMapError
    from mono_map.mapping.octree import validate_octomap_config

    if args.max_range is not None and not (math.isfinite(args.max_range) and args.max_range > 0):
        raise MonoMapError(f"--max-range: must be a positive number of metres, got {args.max_range} "
                           "(leave it out for unlimited rays)")
    if math.isfinite(args.res) and args.res > MAX_RESOLUTION:
        raise MonoMapError(f"--res: {args.res:g} m cells are coarser than this tool supports "
                           f"(<= {MAX_RESOLUTION:g} m; a street is about 20 m wide)")
    cfg = OctoMapConfig(resolution=args.res, prob_hit=args.prob_hit, prob_miss=args.prob_miss,
                        clamp_min=args.clamp_min, clamp_max=args.clamp_max,
                        max_range=-1.0 if args.max_range is None else float(args.max_range))
    validate_octomap_config(cfg)
    return cfg


MAX_RESOLUTION = 10.0            # metres


def check_name(name: str | None) -> str | None:
    """``--name``: a plain file stem, so every output stays inside ``--out``."""
    from mono_map.errors import MonoMapError

    if name is None:
        return None
    if not name or name in (".", "..") or "/" in name or "\\" in name or name.startswith(".") or "\0" in name:
        raise MonoMapError(f"--name: {name!r} must be a plain file name (no '/', not starting with '.'), "
                           "so the outputs stay inside --out")
    if len(name.encode()) > NAME_MAX - len(".json"):
        raise MonoMapError(f"--name: {len(name.encode())} bytes is too long for a file name "
                           f"(at most {NAME_MAX - len('.json')}, so that {name[:12]}….json fits in 255)")
    return name


NAME_MAX = 255  # bytes in a file name (Linux file systems)


DEFAULT_FRAMES = 500  # build and eval: the first 500 frames unless --frames says otherwise
def run_build(args) -> int:
    from mono_map.data.prepare import check_data_root, prepare_sequence
    from mono_map.errors import MonoMapError
    from mono_map.frames import first_frames, parse_frames
    from mono_map.io import check_output_file
    from mono_map.mapping.inputs import load_predictor
    from mono_map.mapping.select import check_keep
    from mono_map.mapping.strategies import integration_of, source_of

    # every option first: nothing is opened, rendered or written before they all pass
    source = source_of(args.source)
    dcfg = distribution_config(args)
    fcfg = fused_config(args)
    if source.predicted:
        if integration_of(args.integrate, source).end_points:
            check_keep(args.keep)
        checkpoint_path(args.model)
    if args.stride < 1:
        raise MonoMapError(f"--stride: must be a positive integer, got {args.stride}")
    cfg = octomap_config(args)
    selection = parse_frames(args.frames, default=first_frames(DEFAULT_FRAMES))
    check_name(args.name)
    rrd = check_output_file(args.rrd, "--rrd", ".rrd", min_free=RRD_MIN_FREE) if args.rrd else None
    if args.viewer:
        from mono_map.viz.commands import check_display

        check_display("--viewer", "use --rrd OUT.rrd and open it with mono-map view where there is one")
    if args.reference_map is not None and not Path(args.reference_map).is_file():
        raise MonoMapError(f"--reference-map: {args.reference_map}: no such file")
    check_data_root(args.data_root)
    out_dir = prepare_output_dir(sequence_output_dir(args.out, args.seq))
    predictor = load_predictor(args.model) if source.predicted else None  # a bad checkpoint fails here
    digest = model_digest(args.model) if source.predicted else None
    # then the data
    seq = prepare_sequence(args.data_root, args.seq, selection)
    frames = selection.resolve(len(seq))
    if source.ground_truth and seq.depth(frames[0]) is None:
        raise MonoMapError(f"--source depth-gt: {seq.depth_dir} has no ground-truth depth for frame "
                           f"{frames[0]} (a synthetic sequence has it)")
    job = MapJob.of(seq, args.source, frames, keep=args.keep, integrate=args.integrate, distribution=dcfg,
                    octomap=cfg, stride=args.stride, model=args.model, digest=digest, fused=fcfg)
    check_reach(seq, job)
    check_memory(seq, job)
    how = ""
    if source.predicted:
        how = (f", keep {args.keep:g}" if job.integration.end_points else
               f", {args.integrate} integration (eps {dcfg.eps:g}, temperature {dcfg.temperature:g})")
    print(f"mono-map build: sequence {args.seq}, {selection.describe(frames)}, source {args.source}{how}, "
          f"{cfg.resolution:g} m cells", flush=True)
    logger = None
    observers = []
    if rrd is not None or args.viewer:
        from mono_map.viz.rerun_stream import RerunMapLogger
        from mono_map.viz.stream_options import StreamOptions

        def logger(path=None):
            return RerunMapLogger(rrd=path, spawn=args.viewer, reference_map=args.reference_map,
                                  options=StreamOptions(resolution=cfg.resolution, image_size=seq.image_size))
        if rrd is None:
            observers.append(logger())
    bt, stats = build_and_write(job, seq, out_dir, name=args.name, observers=observers, predictor=predictor,
                                rrd=rrd, logger=logger, write_ot=args.ot)
    print(f"wrote {bt} ({stats['bt_bytes'] / 2**20:.1f} MB on disk) and {bt.with_suffix('.json')}"
          + (f" and {bt.with_suffix('.ot')}" if args.ot else "") + (f" and {rrd}" if rrd is not None else ""))
    print(f"  frames {stats['n_frames']}, points kept {stats['points_kept']:,}, rays cast {stats['rays_cast']:,}, "
          f"leaves {stats['leaf_count']:,}, memory {stats['memory_mb']:.1f} MB (OctoMap memoryUsage), "
          f"{stats['wall_s']:.1f} s = {stats['frames_per_s']:.2f} frames/s")
    return 0


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
    from mono_map.errors import MonoMapError
    from mono_map.frames import first_frames, parse_frames
    from mono_map.io import check_output_file
    from mono_map.mapping.select import check_keep

    check_keep(args.keep)
    cfg = octomap_config(args)
    dcfg = distribution_config(args)
    fused_config(args)
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
                    stride=args.stride, model=args.model, fused=fused_config(args))
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
                                  distribution=dcfg, fused=fused_config(args)))
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
