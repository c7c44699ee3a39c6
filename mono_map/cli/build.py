"""``mono-map build``: one map of a sequence, its settings made into one :class:`~mono_map.mapping.jobs.MapJob`
and passed whole to :func:`~mono_map.mapping.publish.build_and_write` (heavy imports inside the run function)."""

from __future__ import annotations

from pathlib import Path

from mono_map.cli.options import (add_data_root, add_flip, add_frames, add_integration, add_model, add_octomap, add_out,
                                  check_flip,
                                  add_seq, distribution_config, fused_config, octomap_config)
from mono_map.io import prepare_output_dir
from mono_map.mapping.jobs import MapJob
from mono_map.mapping.limits import check_memory, check_reach
from mono_map.mapping.publish import RRD_MIN_FREE, build_and_write
from mono_map.mapping.select import DEFAULT_KEEP
from mono_map.paths import sequence_output_dir

DEFAULT_FRAMES = 500  # build and eval: the first 500 frames unless --frames says otherwise


def register(subparsers) -> None:
    b = subparsers.add_parser(
        "build", help="build an OctoMap (.bt + stats JSON) from monocular depth or LiDAR",
        description="Integrate a sequence into an OctoMap: per frame, keep the --keep fraction of valid pixels "
                    "with the lowest predicted entropy, back-project them and ray-cast them into the map "
                    "(or use the LiDAR scans). Writes <out>/<name>.bt and <out>/<name>.json atomically.")
    add_seq(b, required=True)
    b.add_argument("--keep", type=float, default=DEFAULT_KEEP,
                   help=f"fraction of valid pixels kept per frame, in (0, 1] (default {DEFAULT_KEEP:g})")
    b.add_argument("--source", default="mono", help="mono | depth-gt | lidar | lidar-fov (default mono); depth-gt: "
                   "the synthetic ground-truth depth_2 back-projected like a keep-1.0 mono map (upper bound)")
    add_integration(b)
    add_octomap(b)
    b.add_argument("--stride", type=int, default=1, help="use every S-th pixel row and column (default 1)")
    add_frames(b, says=f"the first {DEFAULT_FRAMES} frames")
    add_model(b, oracle=True)
    add_flip(b)
    add_data_root(b)
    add_out(b, help="output directory (default outputs/seq<SEQ>)")
    b.add_argument("--name", default=None, help="output file stem (default from source/keep/res)")
    b.add_argument("--viewer", action="store_true", help="stream the build to a spawned rerun viewer")
    b.add_argument("--rrd", default=None, help="save a rerun recording to this file")
    b.add_argument("--reference-map", default=None, help="a .bt shown beside the build in the viewer")
    b.add_argument("--ot", action="store_true", help="also write the probabilistic tree <name>.ot (for calibration)")
    b.set_defaults(func=run_build)


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
    check_flip(args)
    if source.predicted:
        from mono_map.depth.inference import checkpoint_path   # torch: only for a predicted source

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
        from mono_map.viz.screenshot import check_display

        check_display("--viewer", "use --rrd OUT.rrd and open it with mono-map view where there is one")
    if args.reference_map is not None and not Path(args.reference_map).is_file():
        raise MonoMapError(f"--reference-map: {args.reference_map}: no such file")
    check_data_root(args.data_root)
    out_dir = prepare_output_dir(sequence_output_dir(args.out, args.seq))
    predictor = digest = None
    if source.predicted:
        from mono_map.depth.inference import model_digest

        predictor = load_predictor(args.model, flip=args.flip)  # a bad checkpoint fails here
        digest = model_digest(args.model)
    # then the data
    stereo = bool(fcfg.stereo) and integration_of(args.integrate, source).fused   # a synthetic one renders image_3
    seq = prepare_sequence(args.data_root, args.seq, selection, stereo=stereo)
    frames = selection.resolve(len(seq))
    if source.ground_truth and seq.depth(frames[0]) is None:
        raise MonoMapError(f"--source depth-gt: {seq.depth_dir} has no ground-truth depth for frame "
                           f"{frames[0]} (a synthetic sequence has it)")
    job = MapJob.of(seq, args.source, frames, keep=args.keep, integrate=args.integrate, distribution=dcfg,
                    octomap=cfg, stride=args.stride, model=args.model, digest=digest, fused=fcfg, flip=args.flip)
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
