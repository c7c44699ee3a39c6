"""Atomic output: whole file or nothing, with the permissions a plain open() would give."""

import os
import stat
import subprocess
import sys
from pathlib import Path

import pytest

from mono_map.io import atomic_path, write_json_atomic


def test_failed_write_leaves_no_file_and_no_temporary(tmp_path):
    target = tmp_path / "map.bt"
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            tmp.write_bytes(b"half")
            raise RuntimeError("writer died")
    assert list(tmp_path.iterdir()) == []


def test_failed_write_keeps_the_previous_file(tmp_path):
    target = tmp_path / "stats.json"
    write_json_atomic(target, {"a": 1})
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            tmp.write_text("{broken")
            raise RuntimeError("writer died")
    assert target.read_text().strip().startswith("{") and '"a": 1' in target.read_text()
    assert [p.name for p in tmp_path.iterdir()] == ["stats.json"]


def test_written_file_mode_is_what_a_plain_open_gives(tmp_path):
    write_json_atomic(tmp_path / "a.json", {"x": 1})
    (tmp_path / "plain.json").write_text("{}")
    assert stat.S_IMODE((tmp_path / "a.json").stat().st_mode) == stat.S_IMODE((tmp_path / "plain.json").stat().st_mode)


def test_written_file_mode_follows_the_umask_of_the_process(tmp_path):
    """io reads the umask once, at import: a process started with umask 002 writes 0664 files
    (neither mkstemp's 0600 nor the usual 0644)."""
    target = tmp_path / "a.json"
    code = ("import os, sys; os.umask(0o002); from mono_map.io import write_json_atomic; "
            "write_json_atomic(sys.argv[1], {'x': 1})")
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[1]))
    subprocess.run([sys.executable, "-c", code, str(target)], check=True, env=env)
    assert stat.S_IMODE(target.stat().st_mode) == 0o664
