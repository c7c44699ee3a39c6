"""The rerun viewer process: the bundled binary, a spawned (or reused) viewer and the sink streaming to it."""

from __future__ import annotations

from pathlib import Path

from mono_map.errors import MonoMapError

APP_ID = "mono-map"


def rerun_binary() -> str:
    """Path of the rerun viewer/CLI binary bundled with rerun-sdk (the venv's bin may not be on PATH)."""
    import shutil

    try:
        import rerun_cli

        exe = Path(rerun_cli.__file__).parent / "rerun"
        if exe.exists():
            return str(exe)
    except ImportError:  # pragma: no cover
        pass
    exe = shutil.which("rerun")
    if exe is None:  # pragma: no cover
        raise MonoMapError("--viewer: the rerun viewer binary was not found (pip install rerun-sdk)")
    return exe


def spawn_viewer(rec, port: int = 9876):
    """Start a detached rerun viewer (or reuse one already listening on ``port``) for recording
    ``rec``; return the sink that streams to it."""
    import rerun as rr

    try:
        rr.spawn(port=port, connect=False, hide_welcome_screen=True, executable_path=rerun_binary(), recording=rec)
    except RuntimeError as exc:
        raise MonoMapError(f"--viewer: could not start the rerun viewer ({str(exc).splitlines()[0]})") from None
    return rr.GrpcSink(f"rerun+http://127.0.0.1:{port}/proxy")

