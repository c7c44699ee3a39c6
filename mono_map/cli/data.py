"""``mono-map synth``, ``mono-map render-trainset`` (registered by mono_map.cli.app)."""

from __future__ import annotations

import argparse
import os
import sys

from mono_map.cli.options import add_data_root, add_frames, add_seq


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "synth", help="render a synthetic KITTI sequence from its recipe (sequences/NAME.toml)",
        description="Render a synthetic sequence in the KITTI odometry layout (image_2, velodyne, dense depth_2, "
                    "calib.txt, times.txt, poses/NAME.txt) from its recipe.  Existing frames of the same recipe are "
                    "kept, so asking for more frames extends a prefix.")
    add_seq(p, required=True, help="recipe name (sequences/NAME.toml, e.g. 00) or path to a .toml")
    add_frames(p, says="all of the recipe's",
               what="frames to have (the prefix up to the last one is rendered)")
    add_data_root(p, help="KITTI root (default $MONO_MAP_DATA or ./data/kitti)")
    p.add_argument("--workers", type=int, default=2, help="parallel render processes (default 2)")
    p.add_argument("--force", action="store_true", help="re-render every frame even if present")
    p.add_argument("--stereo", action="store_true",
                   help="also render KITTI's right colour camera (image_3, projection P3 of calib.txt) of the frames "
                        "asked for; of frames already rendered, only their missing image_3")
    p.add_argument("--layout", choices=("odometry", "raw"), default="odometry",
                   help="raw: also write the rendered frames as a KITTI raw drive (OXTS, the three date-folder "
                        "calibration files; docs/data.md), e.g. <root>/2000_01_01/2000_01_01_drive_NAME_sync")
    p.add_argument("--drive", default=None,
                   help="with --layout raw: the drive's name (default 2000_01_01_drive_<recipe>_sync)")
    p.set_defaults(func=run_synth)

    p = subparsers.add_parser(
        "render-trainset", help="render the randomised training towns (and val09) into the training cache",
        description="Render the validation town val09 and the randomised training towns straight at training "
                    "resolution (192x634, memory-mapped) into the training cache. Resumable: frames already done "
                    "are kept; training reads the frames that exist while the rest render.")
    p.add_argument("--root", default=None, help="cache directory (default $MONO_MAP_TRAINSET or ~/.cache/mono-map/trainset)")
    p.add_argument("--workers", type=int, default=2, help="parallel render processes, one town each (default 2)")
    p.add_argument("--towns", type=int, default=0, help="only the first N training towns (default 0 = all)")
    p.add_argument("--traffic", type=int, default=0,
                   help="also the first N towns with lane traffic and large vehicles (h01_0a, ...; default 0)")
    p.add_argument("--kerb-trucks", type=int, default=0,
                   help="also the first N towns with lane traffic and large vehicles parked at the kerbs too "
                        "(k01_0a, ...; default 0)")
    p.add_argument("--jams", type=int, default=0,
                   help="also the first N traffic-jam towns: the next lane full, large vehicles beside and at the kerbs, a "
                        "vehicle close ahead, painted vehicle details (j01_0a, ...; default 0)")
    p.add_argument("--detailed", action="store_true",
                   help="also the twins of the training, traffic and kerb-truck towns asked for with painted details on "
                        "their vehicles (lights, plates, stripes, lettering, grime): p01_0a, d01_0a, v01_0a, ...")
    p.add_argument("--greenery", action="store_true",
                   help="with --detailed: also the twins of those painted towns with hedges along the frontages and "
                        "canopy trees over the road: q01_0a, g01_0a, e01_0a, ...")
    p.set_defaults(func=run_render_trainset)


def run_synth(args: argparse.Namespace) -> int:
    import time

    from mono_map.data.prepare import check_data_root
    from mono_map.data.synth import generate_sequence, load_recipe
    from mono_map.errors import MonoMapError
    from mono_map.frames import parse_frames

    frames = parse_frames(args.frames)
    if args.workers < 1:
        raise MonoMapError(f"--workers: must be >= 1, got {args.workers}")
    if args.stereo and args.layout == "raw":
        raise MonoMapError("--stereo: the raw layout (--layout raw) carries image_02 only; render --stereo "
                           "without --layout raw")
    recipe = load_recipe(args.seq)
    n = frames.needed()
    if n is not None and n > recipe.frames:
        raise MonoMapError(f"--frames: {frames.text!r} needs {n} frames; recipe {recipe.name} has {recipe.frames}")
    root = check_data_root(args.data_root)
    if args.drive is not None and args.layout != "raw":
        raise MonoMapError("--drive: names a raw drive; pass --layout raw")
    drive = None
    if args.layout == "raw":
        from mono_map.data.kitti_raw_writer import check_raw_target, synthetic_drive_name

        drive = args.drive or synthetic_drive_name(recipe.name)
        check_raw_target(root, drive, force=True)   # before any rendering
    t0 = time.perf_counter()
    seq_dir = generate_sequence(recipe, root, frames=n, workers=args.workers, force=args.force,
                                 stereo=args.stereo)
    dt = time.perf_counter() - t0
    from mono_map.data.synth.writer import read_marker

    marker = read_marker(seq_dir)
    n = marker["n_frames"]
    size = sum(p.stat().st_size for p in seq_dir.rglob("*") if p.is_file())
    right = f" (image_3 of the first {marker['image_3']})" if "image_3" in marker else ""
    print(f"sequence {recipe.name}: {n} frames{right} in {seq_dir} ({size / 1e6:.0f} MB), {dt:.1f} s",
          file=sys.stderr)
    if drive is not None:
        from mono_map.data.kitti_odometry import KittiSequence
        from mono_map.data.kitti_raw_writer import write_raw_drive

        seq = KittiSequence(root, recipe.name)
        out = write_raw_drive(seq, root, drive, frames=list(range(n)), force=True)
        print(f"raw drive {drive}: {n} frames in {out} (open it with --seq {drive})", file=sys.stderr)
    return 0


def run_render_trainset(args: argparse.Namespace) -> int:
    from pathlib import Path

    from mono_map.data.synth.randomize import (detailed_towns, greenery_towns, jam_towns, traffic_towns, training_towns,
                                               validation_town)
    from mono_map.data.synth.trainset import default_root, render_trainset
    from mono_map.errors import MonoMapError

    specs = training_towns()
    if args.workers < 1:
        raise MonoMapError(f"--workers: must be >= 1, got {args.workers}")
    if not 0 <= args.towns <= len(specs):
        raise MonoMapError(f"--towns: must be 0 (all) to {len(specs)}, got {args.towns}")
    if not 0 <= args.traffic <= len(specs):
        raise MonoMapError(f"--traffic: must be 0 (none) to {len(specs)}, got {args.traffic}")
    if not 0 <= args.kerb_trucks <= len(specs):
        raise MonoMapError(f"--kerb-trucks: must be 0 (none) to {len(specs)}, got {args.kerb_trucks}")
    if not 0 <= args.jams <= len(specs):
        raise MonoMapError(f"--jams: must be 0 (none) to {len(specs)}, got {args.jams}")
    if args.greenery and not args.detailed:
        raise MonoMapError("--greenery: makes twins of the painted towns; pass --detailed too")
    root = Path(args.root).expanduser() if args.root else default_root()
    if root.exists() and not root.is_dir():
        raise MonoMapError(f"--root: {root}: not a directory")
    if root.is_dir() and not os.access(root, os.W_OK):
        raise MonoMapError(f"--root: {root}: not writable")
    towns = (specs[:args.towns] if args.towns else specs) + traffic_towns(args.traffic) \
        + traffic_towns(args.kerb_trucks, kerb_trucks=True)
    detailed = detailed_towns(towns) if args.detailed else []
    specs = [validation_town()] + towns + detailed + (greenery_towns(detailed) if args.greenery else []) \
        + jam_towns(args.jams)
    print(f"rendering {len(specs)} towns ({sum(s.frames for s in specs)} frames) into {root}", file=sys.stderr)
    out = render_trainset(root, specs, workers=args.workers, log=lambda m: print(m, file=sys.stderr, flush=True))
    print(f"done: {out['frames_rendered']} frames in {out['seconds'] / 60:.1f} min", file=sys.stderr)
    return 0
