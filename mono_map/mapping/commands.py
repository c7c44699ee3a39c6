"""``mono-map build`` and ``mono-map eval`` (heavy imports happen inside the run functions)."""

from __future__ import annotations

import argparse
from pathlib import Path

from mono_map.io import prepare_output_dir
from mono_map.paths import sequence_output_dir

SOURCES = ("mono", "depth-gt", "lidar", "lidar-fov")


def _add_octomap_args(p: argparse.ArgumentParser) -> None:
    from mono_map.config import OctoMapConfig

    d = OctoMapConfig()
    g = p.add_argument_group("OctoMap (defaults are OctoMap's own)")
    g.add_argument("--res", type=float, default=d.resolution, help=f"cell size, metres (default {d.resolution})")
    g.add_argument("--max-range", type=float, default=d.max_range,
                   help="rays longer than this are cut and mark free space only (metres; default: unlimited)")
    g.add_argument("--prob-hit", type=float, default=d.prob_hit, help=f"default {d.prob_hit}")
    g.add_argument("--prob-miss", type=float, default=d.prob_miss, help=f"default {d.prob_miss}")
    g.add_argument("--clamp-min", type=float, default=d.clamp_min, help=f"default {d.clamp_min}")
    g.add_argument("--clamp-max", type=float, default=d.clamp_max, help=f"default {d.clamp_max}")


def _add_integration_args(p: argparse.ArgumentParser) -> None:
    from mono_map.mapping.distribution import DistributionConfig

    d = DistributionConfig()
    g = p.add_argument_group("integration of monocular depth")
    g.add_argument("--integrate", default="keep", choices=("keep", "distribution"),
                   help="keep: the paper's cut, the --keep lowest-entropy pixels' expected depths as end points "
                        "(default); distribution: every valid pixel's whole depth distribution sets the expected "
                        "OctoMap update of each cell along its ray (--keep ignored)")
    g.add_argument("--eps", type=float, default=d.eps,
                   help=f"distribution: rays stop where P(surface beyond) < eps (default {d.eps:g})")
    g.add_argument("--temperature", type=float, default=d.temperature,
                   help=f"distribution: probabilities p^(1/T), renormalised (default {d.temperature:g} = as predicted)")
    g.add_argument("--min-update", type=float, default=d.min_update,
                   help=f"distribution: drop per-cell updates weaker than this log-odds magnitude (default {d.min_update:g})")
    g.add_argument("--bin-spread", type=float, default=d.bin_spread,
                   help=f"distribution: spread each bin's mass over this central fraction of the bin, placed at the "
                        f"pixel's local mean (default {d.bin_spread:g} = whole bins)")
    g.add_argument("--ray-step", type=int, default=d.ray_step,
                   help=f"distribution: one ray every N-th pixel row and column (default {d.ray_step})")


def distribution_config(args):
    from mono_map.mapping.distribution import DistributionConfig, check_distribution_config

    d = DistributionConfig()
    return check_distribution_config(DistributionConfig(
        eps=getattr(args, "eps", d.eps), temperature=getattr(args, "temperature", d.temperature),
        ray_step=getattr(args, "ray_step", d.ray_step), min_update=getattr(args, "min_update", d.min_update),
        bin_spread=getattr(args, "bin_spread", d.bin_spread)))


def register(subparsers) -> None:
    b = subparsers.add_parser(
        "build", help="build an OctoMap (.bt + stats JSON) from monocular depth or LiDAR",
        description="Integrate a sequence into an OctoMap: per frame, keep the --keep fraction of valid pixels "
                    "with the lowest predicted entropy, back-project them and ray-cast them into the map "
                    "(or use the LiDAR scans). Writes <out>/<name>.bt and <out>/<name>.json atomically.")
    b.add_argument("--seq", required=True, help="sequence name, e.g. 00")
    b.add_argument("--keep", type=float, default=0.8, help="fraction of valid pixels kept per frame, in (0, 1] (default 0.8)")
    b.add_argument("--source", default="mono", help="mono | depth-gt | lidar | lidar-fov (default mono); depth-gt: "
                   "the synthetic ground-truth depth_2 back-projected like a keep-1.0 mono map (upper bound)")
    _add_integration_args(b)
    _add_octomap_args(b)
    b.add_argument("--stride", type=int, default=1, help="use every S-th pixel row and column (default 1)")
    b.add_argument("--frames", default=None,
                   help="a:b, n (first n) or 'all' (default: the first 500 frames)")
    b.add_argument("--model", default=None,
                   help="depth checkpoint (default: the shipped binary model); 'oracle' = noisy ground truth "
                        "(synthetic sequences only, for development)")
    b.add_argument("--data-root", default=None, help="KITTI odometry root (default $MONO_MAP_DATA or ./data/kitti)")
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
    e.add_argument("--keep", type=float, default=0.8, help="with no --map: the keep of that default map (default 0.8)")
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
    from mono_map.config import OctoMapConfig

    return OctoMapConfig(resolution=args.res, prob_hit=args.prob_hit, prob_miss=args.prob_miss,
                         clamp_min=args.clamp_min, clamp_max=args.clamp_max, max_range=args.max_range)


def map_stem(source: str, keep: float, cfg, frames_desc: str, stride: int, model: str | None,
             integrate: str = "keep", dcfg=None) -> str:
    """A file stem that encodes every parameter changing the map (used as the cache key)."""
    from mono_map.config import OctoMapConfig
    from mono_map.mapping.distribution import DistributionConfig

    if source == "mono" and integrate == "distribution":
        dd, dcfg = DistributionConfig(), dcfg or DistributionConfig()
        parts = ["mono-dist" + (f"-eps{dcfg.eps:g}" if dcfg.eps != dd.eps else "")
                 + (f"-temp{dcfg.temperature:g}" if dcfg.temperature != dd.temperature else "")
                 + (f"-step{dcfg.ray_step}" if dcfg.ray_step != dd.ray_step else "")
                 + (f"-min{dcfg.min_update:g}" if dcfg.min_update != dd.min_update else "")
                 + (f"-spread{dcfg.bin_spread:g}" if dcfg.bin_spread != dd.bin_spread else "")]
    else:
        parts = [source if source != "mono" else f"mono-keep{keep:g}"]
    if source == "mono" and model:
        parts.append("model-" + Path(str(model)).stem)
    if source in ("mono", "depth-gt") and stride != 1:
        parts.append(f"stride{stride}")
    parts.append(f"res{cfg.resolution:g}")
    d = OctoMapConfig()
    if cfg.max_range != d.max_range:
        parts.append(f"maxrange{cfg.max_range:g}")
    for name in ("prob_hit", "prob_miss", "clamp_min", "clamp_max"):
        if getattr(cfg, name) != getattr(d, name):
            parts.append(f"{name.replace('_', '')}{getattr(cfg, name):g}")
    parts.append(frames_desc)
    return "_".join(parts)


def _frames_tag(frames: range) -> str:
    return f"f{frames.start}-{frames.stop}"


def build_and_write(seq, source: str, keep: float, cfg, frames: range, stride: int, model: str | None,
                    out_dir: Path, name: str | None = None, observers=(), show_progress: bool = True,
                    integrate: str = "keep", dcfg=None, write_ot: bool = False) -> tuple[Path, dict]:
    """Build one map and write ``<name>.bt`` + ``<name>.json`` atomically (and, with write_ot, the
    probabilistic ``<name>.ot``, which calibration needs: .bt keeps max-likelihood states only);
    returns (bt path, stats)."""
    from mono_map.io import write_json_atomic
    from mono_map.mapping.build import build_map, load_predictor, write_tree_bt, write_tree_ot

    predictor = load_predictor(model) if source == "mono" else None
    name = name or map_stem(source, keep, cfg, _frames_tag(frames), stride, model, integrate, dcfg)
    result = build_map(seq, source=source, keep=keep, frames=frames, octomap=cfg, stride=stride,
                       predictor=predictor, observers=observers, show_progress=show_progress,
                       integrate=integrate, distribution=dcfg)
    stats = dict(result.stats)
    stats["model"] = (model or "shipped binary checkpoint") if source == "mono" else None
    bt = out_dir / f"{name}.bt"
    if write_ot:                     # before the .bt: writeBinary turns the tree max-likelihood in memory
        write_tree_ot(result.tree, out_dir / f"{name}.ot")
        stats["ot"] = str(out_dir / f"{name}.ot")
    write_tree_bt(result.tree, bt)
    stats["bt"] = str(bt)
    stats["bt_bytes"] = bt.stat().st_size
    write_json_atomic(out_dir / f"{name}.json", {"stats": stats, "per_frame": result.per_frame})
    return bt, stats


def run_build(args) -> int:
    from mono_map.data.kitti import open_sequence
    from mono_map.errors import MonoMapError
    from mono_map.mapping.build import SOURCES as BUILD_SOURCES, parse_frames
    from mono_map.mapping.integrate import validate_octomap_config
    from mono_map.mapping.select import check_keep

    if args.source not in BUILD_SOURCES:
        raise MonoMapError(f"--source: unknown source {args.source!r} (choose from {', '.join(BUILD_SOURCES)})")
    dcfg = distribution_config(args)
    if args.source == "mono":
        if args.integrate == "keep":
            check_keep(args.keep)
        if args.model not in (None, "oracle") and not Path(args.model).exists() and Path(args.model).suffix:
            raise MonoMapError(f"{args.model}: checkpoint not found")
    if args.stride < 1:
        raise MonoMapError(f"--stride: must be a positive integer, got {args.stride}")
    cfg = octomap_config(args)
    validate_octomap_config(cfg)
    out_dir = prepare_output_dir(sequence_output_dir(args.out, args.seq))
    seq = open_sequence(args.data_root, args.seq, frames=_frames_needed(args.frames))
    frames, desc = parse_frames(args.frames, len(seq))
    how = ""
    if args.source == "mono":
        how = (f", keep {args.keep:g}" if args.integrate == "keep" else
               f", distribution integration (eps {dcfg.eps:g}, temperature {dcfg.temperature:g})")
    print(f"mono-map build: sequence {args.seq}, {desc}, source {args.source}{how}, {cfg.resolution:g} m cells")
    observers = []
    if args.viewer or args.rrd:
        from mono_map.viz.rerun_stream import RerunMapLogger

        observers.append(RerunMapLogger(rrd=args.rrd, spawn=args.viewer, reference_map=args.reference_map,
                                        resolution=cfg.resolution, image_size=seq.image_size))
    bt, stats = build_and_write(seq, args.source, args.keep, cfg, frames, args.stride, args.model, out_dir,
                                name=args.name, observers=observers, integrate=args.integrate, dcfg=dcfg,
                                write_ot=args.ot)
    print(f"wrote {bt} ({stats['bt_bytes'] / 2**20:.1f} MB on disk) and {bt.with_suffix('.json')}")
    print(f"  frames {stats['n_frames']}, points kept {stats['points_kept']:,}, rays cast {stats['rays_cast']:,}, "
          f"leaves {stats['leaf_count']:,}, memory {stats['memory_mb']:.1f} MB (OctoMap memoryUsage), "
          f"{stats['wall_s']:.1f} s = {stats['frames_per_s']:.2f} frames/s")
    return 0


def _frames_needed(spec: str | None) -> int | None:
    """How many frames a synthetic sequence must have for --frames (None = all / unknown)."""
    from mono_map.mapping.build import DEFAULT_FRAMES

    if spec is None:
        return DEFAULT_FRAMES
    s = str(spec).strip()
    if s == "all":
        return None
    try:
        return int(s.split(":", 1)[1]) if ":" in s and s.split(":", 1)[1].strip() else (None if ":" in s else int(s))
    except ValueError:
        return None


def reference_path(args, seq, cfg, frames: range, out_dir: Path) -> Path:
    """The reference .bt: a path, or the cached LiDAR(-FOV) map of the sequence (built if missing)."""
    from mono_map.errors import MonoMapError

    ref = args.reference
    if ref in ("lidar", "lidar-fov"):
        stem = map_stem(ref, 1.0, cfg, _frames_tag(frames), 1, None)
        bt = out_dir / f"{stem}.bt"
        if not bt.exists():
            print(f"building the {ref} reference map ({bt})")
            build_and_write(seq, ref, 1.0, cfg, frames, 1, None, out_dir)
        return bt
    path = Path(ref)
    if not path.exists():
        raise MonoMapError(f"--reference: {ref} is neither lidar, lidar-fov nor an existing .bt file")
    return path


def default_map_path(args) -> Path:
    """The .bt ``mono-map build --seq SEQ --keep KEEP`` (same --frames/--stride/--model/--out/OctoMap
    options) writes; MonoMapError if it is not there yet."""
    from mono_map.data.kitti import open_sequence
    from mono_map.errors import MonoMapError
    from mono_map.mapping.build import parse_frames
    from mono_map.mapping.select import check_keep

    check_keep(args.keep)
    cfg = octomap_config(args)
    seq = open_sequence(args.data_root, args.seq, frames=_frames_needed(args.frames), generate=False)
    frames, _ = parse_frames(args.frames, len(seq))
    out_dir = sequence_output_dir(args.out, args.seq)
    path = out_dir / f"{map_stem('mono', args.keep, cfg, _frames_tag(frames), args.stride, args.model)}.bt"
    if not path.is_file():
        raise MonoMapError(f"--map: none given, and {path} does not exist yet "
                           f"(build it: mono-map build --seq {args.seq} --keep {args.keep:g}, or pass --map)")
    print(f"scoring {path}")
    return path


def run_eval(args) -> int:
    from mono_map.errors import MonoMapError

    if args.table:
        from mono_map.mapping.table import run_table

        return run_table(args)
    if not args.map:
        args.map = str(default_map_path(args))
    import json

    from mono_map.data.kitti import open_sequence
    from mono_map.eval.map_metrics import evaluate_map, load_tree
    from mono_map.io import write_json_atomic
    from mono_map.mapping.build import parse_frames

    map_path = Path(args.map)
    tree = load_tree(map_path)
    if args.reference in ("lidar", "lidar-fov"):
        cfg = octomap_config(args)
        # the reference is built with the map's resolution and frames (from the map's stats JSON if present)
        side = map_path.with_suffix(".json")
        meta = json.loads(side.read_text())["stats"] if side.exists() else {}
        cfg = cfg.__class__(**{**cfg.__dict__, "resolution": float(tree.getResolution())})
        seq = open_sequence(args.data_root, args.seq, frames=_frames_needed(args.frames))
        if meta.get("frames") and args.frames is None:
            frames = range(*meta["frames"])
        else:
            frames, _ = parse_frames(args.frames, len(seq))
        out_dir = Path(args.out) if args.out else map_path.parent
        ref_path = reference_path(args, seq, cfg, frames, out_dir)
    else:
        ref_path = reference_path(args, None, None, range(0), Path("."))
    ref = load_tree(ref_path)
    metrics = evaluate_map(tree, ref)
    metrics["map_path"] = str(map_path)
    metrics["reference_path"] = str(ref_path)
    side = map_path.with_suffix(".json")
    if side.exists():
        metrics["build"] = json.loads(side.read_text()).get("stats", {})
    print(format_metrics(metrics))
    if args.json:
        write_json_atomic(args.json, metrics)
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
