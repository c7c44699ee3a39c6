"""``mono-map build`` and ``mono-map eval`` (heavy imports happen inside the run functions)."""

from __future__ import annotations

import argparse
from pathlib import Path

from mono_map.io import prepare_output_dir
from mono_map.paths import sequence_output_dir

SOURCES = ("mono", "lidar", "lidar-fov")


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


def register(subparsers) -> None:
    b = subparsers.add_parser(
        "build", help="build an OctoMap (.bt + stats JSON) from monocular depth or LiDAR",
        description="Integrate a sequence into an OctoMap: per frame, keep the --keep fraction of valid pixels "
                    "with the lowest predicted entropy, back-project them and ray-cast them into the map "
                    "(or use the LiDAR scans). Writes <out>/<name>.bt and <out>/<name>.json atomically.")
    b.add_argument("--seq", required=True, help="sequence name, e.g. 00")
    b.add_argument("--keep", type=float, default=0.8, help="fraction of valid pixels kept per frame, in (0, 1] (default 0.8)")
    b.add_argument("--source", default="mono", help="mono | lidar | lidar-fov (default mono)")
    _add_octomap_args(b)
    b.add_argument("--stride", type=int, default=1, help="use every S-th pixel row and column (default 1)")
    b.add_argument("--frames", default=None,
                   help="N (the first N), A:B[:S], I,J,... or 'all' (default: the first 500 frames)")
    b.add_argument("--model", default=None,
                   help="depth checkpoint (default: the shipped binary model); 'oracle' = noisy ground truth "
                        "(synthetic sequences only, for development)")
    b.add_argument("--data-root", default=None, help="KITTI odometry root (default $MONO_MAP_DATA or ./data/kitti)")
    b.add_argument("--out", default=None, help="output directory (default outputs/seq<SEQ>)")
    b.add_argument("--name", default=None, help="output file stem (default from source/keep/res)")
    b.add_argument("--viewer", action="store_true", help="stream the build to a spawned rerun viewer")
    b.add_argument("--rrd", default=None, help="save a rerun recording to this file")
    b.add_argument("--reference-map", default=None, help="a .bt shown beside the build in the viewer")
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
    e.add_argument("--keeps", default="0.3,0.4,0.5,0.6,0.7,0.8,0.9,1.0", help="keep sweep for --table")
    e.add_argument("--frames", default=None, help="frames for built maps (default: the first 500)")
    e.add_argument("--stride", type=int, default=1, help="pixel stride for built mono maps")
    e.add_argument("--model", default=None, help="depth checkpoint for built mono maps ('oracle' = noisy GT)")
    e.add_argument("--data-root", default=None)
    e.add_argument("--out", default=None, help="directory for cached maps and the table (default outputs/seq<SEQ>)")
    e.add_argument("--json", default=None, help="write the metrics JSON here")
    _add_octomap_args(e)
    e.set_defaults(func=run_eval)


def octomap_config(args):
    """The OctoMap settings of the options, checked (MonoMapError naming the option)."""
    import math

    from mono_map.config import OctoMapConfig
    from mono_map.errors import MonoMapError
    from mono_map.mapping.integrate import validate_octomap_config

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
    return name


def checkpoint_path(model: str | None) -> Path | None:
    """The checkpoint file ``--model`` names (None: the shipped binary model; a bare head name: its
    shipped checkpoint; 'oracle': none); MonoMapError if it does not exist."""
    from mono_map.depth.inference import default_checkpoint
    from mono_map.errors import MonoMapError

    if model == "oracle":
        return None
    if model is None:
        path = default_checkpoint("binary")
    elif not Path(model).suffix and not Path(model).exists():
        path = default_checkpoint(str(model))
    else:
        path = Path(model)
    if not path.is_file():
        raise MonoMapError(f"--model: {model}: checkpoint not found")
    return path


def model_digest(model: str | None) -> str:
    """What identifies the depth model: sha256 of its checkpoint file (first 16 hex), or 'oracle'."""
    import hashlib

    path = checkpoint_path(model)
    if path is None:
        return "oracle"
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()[:16]


def job_key(seq, source: str, keep: float, cfg, frames, stride: int, model: str | None,
            digest: str | None = None) -> dict:
    """Everything that determines a map: stored in its .json, compared before a map is reused."""
    import dataclasses

    from mono_map.frames import frames_tag

    marker = {}
    if seq is not None and (seq.path / "synth.json").is_file():
        import json

        try:
            info = json.loads((seq.path / "synth.json").read_text())
            marker = {k: info.get(k) for k in ("recipe_hash", "generator_version", "n_frames")}
        except (ValueError, UnicodeDecodeError):
            marker = {}
    mono = source == "mono"
    return {"data_root": str(Path(seq.root).resolve()) if seq is not None else None,
            "sequence": getattr(seq, "name", None), "synthetic": marker or None,
            "source": source, "keep": float(keep) if mono else None, "stride": int(stride) if mono else None,
            "model": (digest or model_digest(model)) if mono else None,
            "frames": frames_tag(frames), "octomap": dataclasses.asdict(cfg), "integration": "batched"}


def read_map_sidecar(path: Path) -> dict | None:
    """The ``.json`` a build wrote beside ``<name>.bt``: {"stats", "job", ...}; None if absent;
    MonoMapError naming it if it is not one."""
    import json

    from mono_map.errors import MonoMapError

    side = Path(path).with_suffix(".json")
    if not side.is_file():
        return None
    try:
        data = json.loads(side.read_text())
    except (ValueError, UnicodeDecodeError, OSError) as exc:
        raise MonoMapError(f"{side}: unreadable map statistics ({exc.__class__.__name__}); "
                           "delete it or rebuild the map") from None
    if not isinstance(data, dict) or not isinstance(data.get("stats"), dict):
        raise MonoMapError(f"{side}: not a mono-map build's statistics (no 'stats' object); "
                           "delete it or rebuild the map")
    return data


def reusable(bt: Path, job: dict) -> tuple[bool, str]:
    """Whether ``bt`` (with its .json) was built by exactly ``job``; (False, why) otherwise."""
    from mono_map.errors import MonoMapError

    if not bt.is_file():
        return False, "not built yet"
    try:
        side = read_map_sidecar(bt)
    except MonoMapError as exc:
        return False, str(exc)
    if side is None:
        return False, f"{bt.with_suffix('.json').name} missing"
    if side.get("job") != job:
        stored = side.get("job") or {}
        diff = sorted(k for k in set(job) | set(stored) if job.get(k) != stored.get(k))
        return False, f"built with other {', '.join(diff) or 'settings'}"
    if side["stats"].get("bt_bytes") not in (None, bt.stat().st_size):
        return False, f"{bt.name} does not match its .json"
    return True, ""


def memory_limit() -> tuple[float, str]:
    """Bytes a build may use, and where the figure comes from: ``$MONO_MAP_MEMORY_GB``, else the
    smaller of the available RAM (/proc/meminfo) and the address-space limit (ulimit -v)."""
    import os
    import resource

    env = os.environ.get("MONO_MAP_MEMORY_GB")
    if env:
        try:
            return float(env) * 2**30, "$MONO_MAP_MEMORY_GB"
        except ValueError:
            from mono_map.errors import MonoMapError

            raise MonoMapError(f"$MONO_MAP_MEMORY_GB: expected a number of GB, got {env!r}") from None
    limit, where = float("inf"), "no limit known"
    try:
        for line in open("/proc/meminfo"):
            if line.startswith("MemAvailable:"):
                limit, where = float(line.split()[1]) * 1024, "available RAM"
    except OSError:
        pass
    soft = resource.getrlimit(resource.RLIMIT_AS)[0]
    if soft != resource.RLIM_INFINITY and soft < limit:
        limit, where = float(soft), "ulimit -v"
    return limit, where


# Peak memory of one frame's integration, measured on tiny frame 0 (peak RSS above the start-up):
# LiDAR ≈ 90 B per ray-cell visit (0.05 m: 22 M visits, 1.9 GB); mono (shipped model, keep 0.8,
# 1241×376) ≈ 150 MB at 0.2 m, growing as (0.2 / res)^2.5 (0.1 m: 0.58 GB, 0.05 m: 3.3 GB).
BYTES_PER_VISIT = 90
MONO_BYTES_AT_02 = 150e6


def estimate_frame_bytes(seq, i: int, source: str, cfg, stride: int, keep: float) -> float:
    """Peak bytes to integrate frame ``i`` alone (see the constants above; an estimate, not a bound)."""
    import numpy as np

    if source == "mono":
        h, w = seq.image_size
        pixels = (-(-h // stride)) * (-(-w // stride)) * keep
        return MONO_BYTES_AT_02 * (0.2 / cfg.resolution) ** 2.5 * pixels / (376 * 1241 * 0.8)
    from mono_map.mapping.reference import lidar_measurement

    pts, origin = lidar_measurement(seq, i, source)
    lengths = np.linalg.norm(pts - origin, axis=1)
    if cfg.max_range > 0:
        lengths = np.minimum(lengths, cfg.max_range)
    return float(np.sum(lengths / cfg.resolution + 1)) * BYTES_PER_VISIT


def check_memory(seq, frames, source: str, cfg, stride: int, keep: float) -> None:
    """Refuse, before building, settings whose first frame alone would not fit in memory."""
    from mono_map.errors import MonoMapError

    need = estimate_frame_bytes(seq, frames[0], source, cfg, stride, keep)
    limit, where = memory_limit()
    if need > limit:
        raise MonoMapError(f"--res: {cfg.resolution:g} m cells: integrating frame {frames[0]} alone would need about "
                           f"{need / 2**30:.1f} GB, more than the {limit / 2**30:.1f} GB allowed ({where}); "
                           "use a coarser --res, a --max-range or a larger --stride")


def map_stem(source: str, keep: float, cfg, frames_desc: str, stride: int, model: str | None) -> str:
    """A file stem that encodes every parameter changing the map (the .json's job key decides reuse)."""
    from mono_map.config import OctoMapConfig

    parts = [source if source != "mono" else f"mono-keep{keep:g}"]
    if source == "mono":
        if model:
            parts.append("model-" + Path(str(model)).stem)
        if stride != 1:
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


def build_and_write(seq, source: str, keep: float, cfg, frames, stride: int, model: str | None,
                    out_dir: Path, name: str | None = None, observers=(), show_progress: bool = True,
                    predictor=None, rrd: Path | None = None, logger=None, digest: str | None = None
                    ) -> tuple[Path, dict]:
    """Build one map and publish ``<name>.bt``, ``<name>.json`` (and ``rrd``) together; (bt path, stats).

    ``logger(rrd_path)`` makes the recording observer, given the temporary path the recording is
    written to (renamed with the map only if the whole build succeeds). Nothing is published
    if the build fails.
    """
    from mono_map.errors import MonoMapError
    from mono_map.frames import frames_tag
    from mono_map.io import atomic_outputs, quiet_native_output, write_json_atomic
    from mono_map.mapping.build import build_map, load_predictor, write_tree_bt

    frames = list(frames)
    job = job_key(seq, source, keep, cfg, frames, stride, model, digest)
    if source == "mono" and predictor is None:
        predictor = load_predictor(model)
    name = name or map_stem(source, keep, cfg, frames_tag(frames), stride, model)
    bt = out_dir / f"{name}.bt"
    targets = [bt] + ([Path(rrd)] if rrd is not None else []) + [bt.with_suffix(".json")]
    with atomic_outputs(*targets) as temps:
        observers = list(observers)
        if rrd is not None:
            observers = [DiskSpaceGuard(Path(rrd))] + observers + [logger(temps[1])]
        try:
            result = build_map(seq, source=source, keep=keep, frames=frames, octomap=cfg, stride=stride,
                               predictor=predictor, observers=observers, show_progress=show_progress)
        except RuntimeError as exc:  # rerun's flush timing out: its sink could not write the recording
            if rrd is None:
                raise
            raise MonoMapError(f"{rrd}: rerun could not write the recording ({exc})") from None
        stats = dict(result.stats)
        stats["model"] = (model or "shipped binary checkpoint") if source == "mono" else None
        if frames != list(range(frames[0], frames[-1] + 1)):
            stats["frame_indices"] = frames
        with _naming(bt), quiet_native_output():  # OctoMap's own warning on a full disk: reported below
            write_tree_bt(result.tree, temps[0])
        stats["bt"] = str(bt)
        stats["bt_bytes"] = temps[0].stat().st_size
        with _naming(bt.with_suffix(".json")):
            write_json_atomic(temps[-1], {"stats": stats, "job": job, "per_frame": result.per_frame})
    return bt, stats


def _naming(target: Path):
    """Errors while writing a temporary file are reported under the output's own name."""
    import contextlib

    from mono_map.errors import MonoMapError
    from mono_map.io import free_bytes

    @contextlib.contextmanager
    def ctx():
        try:
            yield
        except (OSError, MonoMapError) as exc:
            why = getattr(exc, "strerror", None) or "write failed"
            if free_bytes(target.parent) < (1 << 20):
                why = "No space left on device" if why == "write failed" else why
            raise MonoMapError(f"{target}: could not write it ({why}); nothing was published") from None
    return ctx()


DEFAULT_FRAMES = 500  # build and eval: the first 500 frames unless --frames says otherwise
# rerun's file sink blocks for good on a full disk: a recording stops while this much is still free
RRD_MIN_FREE = 32 << 20


class DiskSpaceGuard:
    """Observer that stops a build before the disk under ``path`` fills (MonoMapError naming it)."""

    def __init__(self, path: Path, min_free: int = RRD_MIN_FREE):
        self.path, self.min_free = Path(path), min_free

    def __call__(self, update) -> None:
        from mono_map.errors import MonoMapError
        from mono_map.io import free_bytes

        free = free_bytes(self.path.parent)
        if free < self.min_free:
            raise MonoMapError(f"{self.path}: the disk is nearly full ({free / 2**20:.1f} MB left) at frame "
                               f"{update.index}; nothing was written")


def run_build(args) -> int:
    from mono_map.data.prepare import check_data_root, prepare_sequence
    from mono_map.errors import MonoMapError
    from mono_map.frames import first_frames, parse_frames
    from mono_map.io import check_output_file
    from mono_map.mapping.build import SOURCES as BUILD_SOURCES, load_predictor
    from mono_map.mapping.select import check_keep

    # every option first: nothing is opened, rendered or written before they all pass
    if args.source not in BUILD_SOURCES:
        raise MonoMapError(f"--source: unknown source {args.source!r} (choose from {', '.join(BUILD_SOURCES)})")
    if args.source == "mono":
        check_keep(args.keep)
        checkpoint_path(args.model)
    if args.stride < 1:
        raise MonoMapError(f"--stride: must be a positive integer, got {args.stride}")
    cfg = octomap_config(args)
    selection = parse_frames(args.frames, default=first_frames(DEFAULT_FRAMES))
    check_name(args.name)
    rrd = check_output_file(args.rrd, "--rrd", ".rrd", min_free=RRD_MIN_FREE) if args.rrd else None
    if args.reference_map is not None and not Path(args.reference_map).is_file():
        raise MonoMapError(f"--reference-map: {args.reference_map}: no such file")
    check_data_root(args.data_root)
    out_dir = prepare_output_dir(sequence_output_dir(args.out, args.seq))
    predictor = load_predictor(args.model) if args.source == "mono" else None  # a bad checkpoint fails here
    digest = model_digest(args.model) if args.source == "mono" else None
    # then the data
    seq = prepare_sequence(args.data_root, args.seq, selection)
    frames = selection.resolve(len(seq))
    check_memory(seq, frames, args.source, cfg, args.stride, args.keep)
    print(f"mono-map build: sequence {args.seq}, {selection.describe(frames)}, source {args.source}"
          + (f", keep {args.keep:g}" if args.source == "mono" else "") + f", {cfg.resolution:g} m cells", flush=True)
    logger = None
    observers = []
    if rrd is not None or args.viewer:
        from mono_map.viz.rerun_stream import RerunMapLogger

        def logger(path=None):
            return RerunMapLogger(rrd=path, spawn=args.viewer, reference_map=args.reference_map,
                                  resolution=cfg.resolution, image_size=seq.image_size)
        if rrd is None:
            observers.append(logger())
    bt, stats = build_and_write(seq, args.source, args.keep, cfg, frames, args.stride, args.model, out_dir,
                                name=args.name, observers=observers, predictor=predictor, rrd=rrd,
                                logger=logger, digest=digest)
    print(f"wrote {bt} ({stats['bt_bytes'] / 2**20:.1f} MB on disk) and {bt.with_suffix('.json')}"
          + (f" and {rrd}" if rrd is not None else ""))
    print(f"  frames {stats['n_frames']}, points kept {stats['points_kept']:,}, rays cast {stats['rays_cast']:,}, "
          f"leaves {stats['leaf_count']:,}, memory {stats['memory_mb']:.1f} MB (OctoMap memoryUsage), "
          f"{stats['wall_s']:.1f} s = {stats['frames_per_s']:.2f} frames/s")
    return 0


def reference_path(args, seq, cfg, frames, out_dir: Path) -> Path:
    """The reference .bt: a path, or the LiDAR(-FOV) map of the sequence (built if missing or stale)."""
    from mono_map.errors import MonoMapError
    from mono_map.frames import frames_tag

    ref = args.reference
    if ref in ("lidar", "lidar-fov"):
        stem = map_stem(ref, 1.0, cfg, frames_tag(frames), 1, None)
        bt = out_dir / f"{stem}.bt"
        ok, why = reusable(bt, job_key(seq, ref, 1.0, cfg, frames, 1, None))
        if not ok:
            print(f"building the {ref} reference map ({bt}: {why})", flush=True)
            build_and_write(seq, ref, 1.0, cfg, frames, 1, None, out_dir)
        return bt
    path = Path(ref)
    if not path.is_file():
        raise MonoMapError(f"--reference: {ref} is neither lidar, lidar-fov nor an existing .bt file")
    return path


def check_eval_options(args):
    """eval's options, checked before any data or map is read: (OctoMap config, frame selection)."""
    from mono_map.errors import MonoMapError
    from mono_map.frames import first_frames, parse_frames
    from mono_map.io import check_output_file
    from mono_map.mapping.select import check_keep

    check_keep(args.keep)
    cfg = octomap_config(args)
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
    if args.reference not in ("lidar", "lidar-fov") and not Path(args.reference).is_file():
        raise MonoMapError(f"--reference: {args.reference} is neither lidar, lidar-fov nor an existing .bt file")
    return cfg, selection


def default_map_path(args, cfg, selection) -> Path:
    """The .bt ``mono-map build --seq SEQ --keep KEEP`` (same --frames/--stride/--model/--out/OctoMap
    options) writes; MonoMapError if it is not there yet or was built from other data or another model."""
    from mono_map.data.prepare import prepare_sequence
    from mono_map.errors import MonoMapError
    from mono_map.frames import frames_tag

    seq = prepare_sequence(args.data_root, args.seq, selection, render=False)
    frames = selection.resolve(len(seq))
    out_dir = sequence_output_dir(args.out, args.seq)
    path = out_dir / f"{map_stem('mono', args.keep, cfg, frames_tag(frames), args.stride, args.model)}.bt"
    if not path.is_file():
        raise MonoMapError(f"--map: none given, and {path} does not exist yet "
                           f"(build it: mono-map build --seq {args.seq} --keep {args.keep:g}, or pass --map)")
    ok, why = reusable(path, job_key(seq, "mono", args.keep, cfg, frames, args.stride, args.model))
    if not ok:
        raise MonoMapError(f"--map: none given, and {path} is stale ({why}); rebuild it with mono-map build "
                           f"--seq {args.seq} --keep {args.keep:g}, or pass --map")
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

    cfg, selection = check_eval_options(args)
    if args.table:
        from mono_map.mapping.table import TableJob, run_table

        if args.reference not in ("lidar", "lidar-fov"):
            raise MonoMapError(f"--reference: the table is scored against 'lidar-fov' or 'lidar', "
                               f"not {args.reference!r}")
        return run_table(TableJob(seq=args.seq, data_root=args.data_root, frames=selection, out=args.out,
                                  keeps=parse_keeps(args.keeps), stride=args.stride, model=args.model,
                                  octomap=cfg, reference=args.reference))
    from mono_map.data.prepare import prepare_sequence
    from mono_map.eval.map_metrics import evaluate_map, load_tree
    from mono_map.io import write_json_atomic

    map_path = Path(args.map) if args.map else default_map_path(args, cfg, selection)
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
        seq = prepare_sequence(args.data_root, args.seq, selection)
        frames = selection.resolve(len(seq))
        ref_path = reference_path(args, seq, cfg, frames, out_dir)
    else:
        ref_path = reference_path(args, None, None, [], Path("."))
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
