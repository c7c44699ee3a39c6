"""A screenshot that times out leaves no process behind and says so in one line."""

import os
import time

import pytest

from mono_map.errors import MonoMapError
from mono_map.viz.screenshot import screenshot_xvfb


def test_xvfb_screenshot_timeout_kills_the_whole_process_group(tmp_path, monkeypatch):
    bindir = tmp_path / "bin"
    bindir.mkdir()
    pidfile = tmp_path / "child.pid"
    fake = bindir / "xvfb-run"     # like xvfb-run: starts a server and the viewer, then waits for them
    fake.write_text(f"#!/bin/sh\nsleep 600 &\necho $! > {pidfile}\nwait\n")
    fake.chmod(0o755)
    monkeypatch.setenv("PATH", f"{bindir}{os.pathsep}{os.environ['PATH']}")
    png = tmp_path / "out.png"
    with pytest.raises(MonoMapError, match="did not finish within 2 s"):
        screenshot_xvfb(tmp_path / "x.rrd", png, timeout=2.0)
    child = int(pidfile.read_text())
    for _ in range(50):            # reaped by init: give it a moment
        try:
            os.kill(child, 0)
        except ProcessLookupError:
            break
        time.sleep(0.1)
    else:
        pytest.fail(f"the viewer's process {child} outlived the timeout")
    assert not png.exists() and not list(tmp_path.glob(".out*"))   # no half-written picture
