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


def rerun_binary() -> str:
    from mono_map.viz.rerun_viewer import rerun_binary as find

    return find()


def _free_port() -> int:
    import socket

    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


class _PaintTimeout(Exception):
    pass


def screenshot(rrd: Path, png: Path, frame: int | None = None, timeout: float = 300.0) -> None:
    """Render ``rrd`` into ``png``: headless viewer first; if its paint deadline is missed (CPU
    rasterizer on a busy machine), the windowed viewer's ``--screenshot-to`` under ``xvfb-run``
    (last frame only; the picture may show a hover tooltip)."""
    try:
        _screenshot_headless(rrd, png, frame, timeout)
    except _PaintTimeout as exc:
        why = str(exc) or ("the headless viewer did not finish painting in time (software rendering on a busy "
                           "machine?)")
        if shutil.which("xvfb-run") is None:
            raise MonoMapError(f"--screenshot: {png}: {why} and xvfb-run is not installed") from None
        screenshot_xvfb(rrd, png, timeout)


def screenshot_xvfb(rrd: Path, png: Path, timeout: float) -> None:
    from mono_map.io import atomic_path

    env = dict(os.environ, XDG_RUNTIME_DIR=os.environ.get("XDG_RUNTIME_DIR", "/tmp"))
    with atomic_path(png) as tmp:
        cmd = ["xvfb-run", "-a", "-s", "-screen 0 1600x900x24", rerun_binary(), "--port", str(_free_port()),
               "--window-size", "1600x900", "--screenshot-to", str(tmp), str(rrd)]
        # own process group: on a timeout xvfb-run, Xvfb and the viewer all go (killing xvfb-run alone
        # leaves the other two running)
        proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                                start_new_session=True)
        try:
            proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            kill_group(proc)
            raise MonoMapError(f"--screenshot: {png}: the viewer did not finish within {timeout:.0f} s "
                               "(software rendering on a busy machine?)") from None
        except BaseException:
            kill_group(proc)
            raise
        if proc.returncode != 0 or not tmp.exists() or tmp.stat().st_size == 0:
            raise MonoMapError(f"--screenshot: {png}: the viewer could not render a picture")


def kill_group(proc: subprocess.Popen) -> None:
    """SIGKILL a child started with ``start_new_session=True`` and everything it started; reap it."""
    import signal

    try:
        os.killpg(proc.pid, signal.SIGKILL)
    except ProcessLookupError:
        pass
    proc.wait()


def _screenshot_headless(rrd: Path, png: Path, frame: int | None = None, timeout: float = 300.0) -> None:
    """Render ``rrd`` with the real viewer, headless (no display needed), into ``png`` (1920×1080).

    The viewer opens the recording with its default blueprint, jumps to ``frame`` on the ``frame``
    timeline (default: the last), and saves a screenshot. Needs a Vulkan driver; without a GPU,
    Mesa's lavapipe CPU rasterizer (Debian ``mesa-vulkan-drivers``) works, slowly.
    """
    from rerun.experimental import ViewerClient

    from mono_map.io import quiet_native_output

    png = Path(png)
    if png.suffix.lower() != ".png":
        raise MonoMapError(f"--screenshot: {png}: the output must end in .png")
    os.environ.setdefault("XDG_RUNTIME_DIR", "/tmp")

    try:
        with quiet_native_output():  # the viewer process inherits the sink: its logs and panics stay off the terminal
            viewer = ViewerClient.spawn(headless=True, port=_free_port(), executable_path=rerun_binary(),
                                        hide_welcome_screen=True)
    except Exception as exc:  # no graphics adapter, binary missing, ...
        raise MonoMapError(f"--screenshot: could not start a headless rerun viewer ({str(exc).splitlines()[0]})") \
            from None
    try:
        _drive_viewer(viewer, rrd, png, frame, timeout)
    except (MonoMapError, _PaintTimeout, KeyboardInterrupt):
        raise
    except Exception as exc:  # the headless viewer died (e.g. no render context on this machine): try xvfb
        raise _PaintTimeout(f"the headless rerun viewer stopped ({' '.join(str(exc).split())[:80] or type(exc).__name__}; "
                            "no graphics adapter it can render with?)") from None
    finally:
        try:
            viewer.quit()
        except Exception:  # noqa: BLE001 - already gone
            pass


def _drive_viewer(viewer, rrd: Path, png: Path, frame: int | None, timeout: float) -> None:
    """Open ``rrd`` in the running headless ``viewer``, go to ``frame`` and save ``png`` (atomically)."""
    import time

    from mono_map.io import atomic_path

    viewer.open(str(Path(rrd).resolve()))
    deadline = time.monotonic() + timeout
    while True:
        state = viewer.get_state()
        if not state.loading or time.monotonic() > deadline:
            break
        time.sleep(1.0)
    timelines = {t.name: t for r in state.recordings for t in r.timelines}
    if "frame" in timelines and timelines["frame"].end is not None:
        viewer.set_time("frame", sequence=int(timelines["frame"].end if frame is None else frame),
                        play_state="paused")
    time.sleep(2.0)  # let it paint the new time

    def shoot(path: Path) -> None:
        for attempt in range(4):  # a CPU rasterizer on a busy machine can miss the viewer's 15 s deadline
            try:
                viewer.save_screenshot(str(path.resolve()))
                return
            except TimeoutError:
                pass
        raise _PaintTimeout()

    with atomic_path(png) as tmp:
        # the first paint of a new time starts decoding its images (shown as loading dots):
        # shoot once, give the decoder time, shoot again
        shoot(tmp)
        time.sleep(5.0)
        shoot(tmp)
        if not tmp.exists() or tmp.stat().st_size == 0:
            raise MonoMapError(f"--screenshot: {png}: the viewer did not write a picture")


def check_display(what: str = "view", instead: str = "use --save OUT.rrd or --screenshot OUT.png") -> None:
    """MonoMapError, before any work, when there is no display to open a viewer on (Linux without
    $DISPLAY / $WAYLAND_DISPLAY): rerun's viewer would otherwise time out after a long wait."""
    if sys.platform.startswith("linux") and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        raise MonoMapError(f"{what}: no display to open a viewer on ({instead})")


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
        from mono_map.mapping.jobs import RRD_MIN_FREE

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
