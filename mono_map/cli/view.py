"""``mono-map view``: open a recording (.rrd) or a finished map (.bt) in the rerun viewer.

Heavy imports (rerun, octomap) happen inside the command so ``mono-map --help`` stays fast.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

from mono_map.errors import MonoMapError
from mono_map.viz.screenshot import check_display, rerun_binary, screenshot


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "view", help="open a recording (.rrd) or a finished OctoMap (.bt) in the rerun viewer",
        description="Open FILE in the rerun viewer. A .rrd (e.g. from `mono-map build --rrd`) is opened as "
                    "is; a .bt map is logged as occupied cells coloured by height. With --save the "
                    "recording is written to a file instead of opening a viewer; with --screenshot the "
                    "real viewer renders the default layout headless (no display needed) into a PNG.")
    p.add_argument("file", help="a .rrd recording or a .bt OctoMap")
    p.add_argument("--save", metavar="OUT.rrd", help="write the recording here instead of opening a viewer")
    p.add_argument("--screenshot", metavar="OUT.png",
                   help="render the recording in a headless viewer (default layout, 1920x1080) to this PNG")
    p.add_argument("--frame", type=int, default=None, help="frame shown by --screenshot (default: the last)")
    p.add_argument("--cells", default="voxels", choices=("voxels", "points", "boxes"),
                   help="how a .bt map's cells are drawn (default voxels)")
    p.set_defaults(func=run_view)


def _check_rrd(path: Path) -> None:
    """Refuse a file rerun cannot decode: the header (RrdReader), then every chunk (``rerun rrd verify``)."""
    import warnings

    from rerun.chunk import RrdReader

    try:
        with warnings.catch_warnings():  # "no footer/manifest" warnings: verify below decides
            warnings.simplefilter("ignore")
            recordings = RrdReader(path).recordings()
    except Exception as exc:  # rerun raises RuntimeError/ValueError for non-RRD data
        raise MonoMapError(f"{path}: not a readable rerun recording ({exc})") from None
    if not recordings:
        raise MonoMapError(f"{path}: rerun file holds no recording")
    proc = subprocess.run([rerun_binary(), "rrd", "verify", str(path)], stdout=subprocess.PIPE,
                          stderr=subprocess.STDOUT, text=True, errors="replace", timeout=600)
    if proc.returncode != 0:
        lines = [ln.strip() for ln in proc.stdout.splitlines() if ln.strip()]
        why = next((ln for ln in lines if "rror" in ln), lines[-1] if lines else f"exit {proc.returncode}")
        raise MonoMapError(f"{path}: rerun cannot decode this recording (rerun rrd verify: {why[:200]})")


def run_view(args) -> int:
    path = Path(args.file)
    if not path.is_file():
        raise MonoMapError(f"{path}: no such file")
    suffix = path.suffix.lower()
    if suffix not in (".rrd", ".bt"):
        raise MonoMapError(f"{path}: expected a .rrd recording or a .bt OctoMap (got '{suffix or 'no suffix'}')")
    if args.frame is not None and args.frame < 0:
        raise MonoMapError(f"--frame: must be a frame number >= 0, got {args.frame}")
    if args.screenshot is not None:
        from mono_map.io import check_output_file

        check_output_file(args.screenshot, "--screenshot", ".png")
    if args.save is not None:
        from mono_map.io import check_output_file
        from mono_map.mapping.publish import RRD_MIN_FREE

        check_output_file(args.save, "--save", ".rrd", min_free=RRD_MIN_FREE if suffix == ".bt" else 0)

    if suffix == ".rrd":
        _check_rrd(path)
        rrd = path
        if args.save is not None:
            from mono_map.io import atomic_path

            with atomic_path(args.save) as tmp:
                shutil.copyfile(path, tmp)
            rrd = Path(args.save)
            print(f"wrote {rrd}", file=sys.stderr)
    else:
        from mono_map.viz.rerun_cells import log_bt_map

        if args.save is None and args.screenshot is None:
            check_display()
            info = log_bt_map(path, spawn=True, cells=args.cells)
            print(f"{path}: {info['cells']} occupied cells at {info['resolution']} m sent to the viewer",
                  file=sys.stderr)
            return 0
        rrd = Path(args.save) if args.save is not None else path.with_suffix(".view.rrd")
        try:
            info = log_bt_map(path, rrd=rrd, cells=args.cells)
        except RuntimeError as exc:  # rerun's file sink could not flush (a full disk)
            raise MonoMapError(f"{rrd}: rerun could not write the recording ({' '.join(str(exc).split())}); "
                               "nothing was published") from None
        lo, hi = info["height_range"]
        print(f"wrote {rrd}: {info['cells']} occupied cells at {info['resolution']} m in {info['blocks']} blocks, "
              f"height colour range {lo:.2f}..{hi:.2f} m", file=sys.stderr)

    if args.screenshot is not None:
        screenshot(rrd, Path(args.screenshot), args.frame)
        print(f"wrote {args.screenshot}", file=sys.stderr)
    elif args.save is None:
        check_display()
        # Open in a detached viewer process (returns immediately).
        subprocess.Popen([rerun_binary(), str(rrd)], start_new_session=True,
                         stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return 0
