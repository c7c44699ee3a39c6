"""The rerun viewer as a program: a recording rendered to a PNG (:func:`screenshot`: headless, or under
xvfb-run), and whether there is a display to open a viewer on (:func:`check_display`)."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

from mono_map.errors import MonoMapError


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
