"""``mono-map view``: open a recording (.rrd) or a finished map (.bt) in the rerun viewer.

Heavy imports (rerun, octomap) happen inside the command so ``mono-map --help`` stays fast.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

from mono_map.errors import MonoMapError
from mono_map.viz.rerun_stream import rerun_binary


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "view", help="open a recording (.rrd) or a finished OctoMap (.bt) in the rerun viewer",
        description="Open FILE in the rerun viewer. A .rrd (e.g. from `mono-map build --rrd`) is opened as "
                    "is; a .bt map is logged as occupied cells coloured by height. With --save the "
                    "recording is written to a file instead of opening a viewer; with --screenshot a "
                    "PNG of the viewer's default layout is rendered (offscreen via xvfb-run if there is "
                    "no display).")
    p.add_argument("file", help="a .rrd recording or a .bt OctoMap")
    p.add_argument("--save", metavar="OUT.rrd", help="write the recording here instead of opening a viewer")
    p.add_argument("--screenshot", metavar="OUT.png", help="render the viewer to this PNG and quit")
    p.add_argument("--size", default="1600x1000", help="viewer window size for --screenshot (default 1600x1000)")
    p.add_argument("--cells", default="voxels", choices=("voxels", "points", "boxes"),
                   help="how a .bt map's cells are drawn (default voxels)")
    p.set_defaults(func=run_view)


def _check_rrd(path: Path) -> None:
    from rerun.chunk import RrdReader

    try:
        recordings = RrdReader(path).recordings()
    except Exception as exc:  # rerun raises RuntimeError/ValueError for non-RRD data
        raise MonoMapError(f"{path}: not a readable rerun recording ({exc})") from None
    if not recordings:
        raise MonoMapError(f"{path}: rerun file holds no recording")


def screenshot(rrd: Path, png: Path, size: str = "1600x1000", timeout: float = 300.0) -> None:
    """Render ``rrd`` with the real viewer (default blueprint) into ``png``.

    Without a display this runs under ``xvfb-run`` (Debian ``xvfb``); the viewer renders with
    Vulkan on Mesa's llvmpipe CPU driver, slow but faithful.
    """
    from mono_map.io import atomic_path

    cmd = [rerun_binary(), "--port", "0", "--window-size", size]
    env = dict(os.environ, XDG_RUNTIME_DIR=os.environ.get("XDG_RUNTIME_DIR", "/tmp"))
    prefix = []
    if not env.get("DISPLAY"):
        if shutil.which("xvfb-run") is None:
            raise MonoMapError("--screenshot: no display and no xvfb-run (apt-get install xvfb)")
        w, h = (int(v) for v in size.lower().split("x"))
        prefix = ["xvfb-run", "-a", "-s", f"-screen 0 {w}x{h}x24"]
    with atomic_path(png) as tmp:
        proc = subprocess.run(prefix + cmd + ["--screenshot-to", str(tmp), str(rrd)], env=env,
                              stdout=subprocess.PIPE, stderr=subprocess.STDOUT, timeout=timeout, text=True)
        if proc.returncode != 0 or not tmp.exists() or tmp.stat().st_size == 0:
            tail = proc.stdout.strip().splitlines()[-1:] if proc.stdout else []
            raise MonoMapError(f"{png}: the viewer could not render a screenshot ({'; '.join(tail)})")


def run_view(args) -> int:
    path = Path(args.file)
    if not path.is_file():
        raise MonoMapError(f"{path}: no such file")
    suffix = path.suffix.lower()
    if suffix not in (".rrd", ".bt"):
        raise MonoMapError(f"{path}: expected a .rrd recording or a .bt OctoMap (got '{suffix or 'no suffix'}')")
    if args.save is not None and Path(args.save).suffix.lower() != ".rrd":
        raise MonoMapError(f"--save: {args.save}: the output must end in .rrd")

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
        from mono_map.viz.rerun_stream import log_bt_map

        if args.save is None and args.screenshot is None:
            info = log_bt_map(path, spawn=True, cells=args.cells)
            print(f"{path}: {info['cells']} occupied cells at {info['resolution']} m sent to the viewer",
                  file=sys.stderr)
            return 0
        rrd = Path(args.save) if args.save is not None else path.with_suffix(".view.rrd")
        info = log_bt_map(path, rrd=rrd, cells=args.cells)
        lo, hi = info["height_range"]
        print(f"wrote {rrd}: {info['cells']} occupied cells at {info['resolution']} m in {info['blocks']} blocks, "
              f"height colour range {lo:.2f}..{hi:.2f} m", file=sys.stderr)

    if args.screenshot is not None:
        screenshot(rrd, Path(args.screenshot), args.size)
        print(f"wrote {args.screenshot}", file=sys.stderr)
    elif args.save is None:
        # Open in a detached viewer process (returns immediately).
        subprocess.Popen([rerun_binary(), str(rrd)], start_new_session=True,
                         stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return 0
