"""Temporary files of mono-map's atomic outputs (:mod:`mono_map.io`): their names, the folders they went to,
and the removal of those a killed run left behind.

Temporary files are ``.<stem>.<pid>.<random>.tmp<suffix>`` beside their target (``mkstemp``: unique
per process and call, so concurrent writers never share one); backups of replaced files
``.<stem>.<pid>.<random>.tmpbak<suffix>``, staging folders ``.<folder>.<pid>.<random>.tmpstage``.
A process killed before it could remove its temporaries leaves them behind; :func:`clean_stale_temps`
removes those whose process is gone, in the folders written to (listed in :func:`temp_registry`, swept
by :func:`sweep_registered_temps` before each command). :func:`user_path` turns any of these names in
a message back into the output it stands for.
"""

from __future__ import annotations

import os
import re
import tempfile
from pathlib import Path

# a file name holds at most 255 bytes: the temporary's stem is cut so that any legal target name fits
_NAME_MAX = 255
_TEMP_OVERHEAD = 1 + 1 + 10 + 1 + 8 + 4 + 3  # "." stem "." pid "." random ".tmp" kind, bytes


def temp_path(path: str | os.PathLike, suffix: str | None = None, kind: str = "") -> Path:
    """A new empty temporary file beside ``path``, unique to this process and call (mkstemp): named
    ``.<stem>.<pid>.<random>.tmp<kind><suffix>`` (the stem shortened where a long name would not fit)."""
    path = Path(path)
    suffix = path.suffix if suffix is None else suffix
    room = _NAME_MAX - _TEMP_OVERHEAD - len(kind.encode()) - len(suffix.encode())
    stem = path.stem.encode()[:max(8, room)].decode("utf-8", "ignore")
    register_temp_dir(path.parent)
    fd, tmp = tempfile.mkstemp(prefix=f".{stem}.{os.getpid()}.", suffix=f".tmp{kind}{suffix}", dir=path.parent)
    os.close(fd)
    return Path(tmp)


# Folders temporary files were written to, so that the next run sweeps what a killed one left wherever
# it was (beside --rrd, --json, ... too): one absolute path a line, appended once per folder and process.
_REGISTERED: set[str] = set()
_REGISTRY_COMPACT = 200  # lines: rewritten (deduplicated, swept folders dropped) beyond this


def temp_registry() -> Path:
    """The list of folders temporary files went to: ``$XDG_CACHE_HOME/mono-map/temp-dirs.txt``
    (``~/.cache`` by default)."""
    return Path(os.environ.get("XDG_CACHE_HOME") or "~/.cache").expanduser() / "mono-map" / "temp-dirs.txt"


def register_temp_dir(folder: Path) -> None:
    """Note ``folder`` in :func:`temp_registry` (once per process); a registry that cannot be written
    only means a killed run's temporaries there wait for the next write into that folder."""
    key = str(Path(folder).resolve())
    if key in _REGISTERED:
        return
    _REGISTERED.add(key)
    try:
        reg = temp_registry()
        reg.parent.mkdir(parents=True, exist_ok=True)
        with open(reg, "a") as fh:  # O_APPEND: concurrent short lines do not interleave
            fh.write(key + "\n")
    except OSError:
        pass


def sweep_registered_temps() -> list[Path]:
    """Remove the temporaries of dead runs in every folder of :func:`temp_registry` (run by the CLI
    before a command); returns what was removed."""
    reg = temp_registry()
    try:
        lines = reg.read_text().splitlines()
    except (OSError, UnicodeDecodeError):
        return []
    folders = list(dict.fromkeys(ln for ln in lines if ln.startswith("/")))
    removed = []
    for d in folders:
        removed += clean_stale_temps(d)
    _REGISTERED.update(folders)
    if len(lines) > _REGISTRY_COMPACT:  # keep the folders that still hold (live runs') temporaries
        keep = [d for d in folders if Path(d).is_dir() and any(Path(d).glob(".*.tmp*"))]
        try:
            fd, tmp = tempfile.mkstemp(prefix=".temp-dirs.", dir=reg.parent)
            with os.fdopen(fd, "w") as fh:
                fh.write("".join(d + "\n" for d in keep))
            os.replace(tmp, reg)
        except OSError:
            pass
    return removed


_SWEPT: set[str] = set()


def sweep_once(folder: Path) -> None:
    """:func:`clean_stale_temps` of ``folder`` the first time this process writes there (a folder of
    thousands of frames is listed once, not once per file)."""
    key = str(Path(folder).resolve())
    if key not in _SWEPT:
        _SWEPT.add(key)
        clean_stale_temps(folder)


_TEMP_NAME = re.compile(r"\.(\d+)\.[A-Za-z0-9_]{8}\.tmp[^/]*$")  # .<stem>.<pid>.<mkstemp's 8>.tmp<suffix>


def is_temp_name(name: str) -> bool:
    """Whether a file or folder name is one of mono-map's temporaries (see the module doc)."""
    return _TEMP_NAME.search(name) is not None


def clean_stale_temps(directory: str | os.PathLike) -> list[Path]:
    """Remove the temporary files and staging folders (see the module doc) in ``directory`` whose
    writing process is gone."""
    removed = []
    directory = Path(directory)
    if not directory.is_dir():
        return removed
    for p in directory.glob(".*.tmp*"):
        m = _TEMP_NAME.search(p.name)
        if m is None or pid_alive(int(m.group(1))):
            continue
        try:
            if p.is_dir():  # a staging folder (staged_dir)
                import shutil

                shutil.rmtree(p)
            else:
                p.unlink()
            removed.append(p)
        except OSError:
            pass
    return removed


def pid_alive(pid: int) -> bool:
    """Whether process ``pid`` exists (on this machine)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    except (OverflowError, ValueError):
        return False
    return True


_STAGE_PART = re.compile(r"/\.[^/]*\.\d+\.[A-Za-z0-9_]{8}\.tmpstage(?=/)")
_TEMP_PART = re.compile(r"(?<![^/\s'\"])\.([^/\s]*?)\.\d+\.[A-Za-z0-9_]{8}\.tmp(?:bak)?([^/\s]*)")


def user_path(text: str) -> str:
    """``text`` with every staging folder and temporary file name (see the module doc) replaced by the
    output it stands for: what users see names their files, never mono-map's hidden ones."""
    text = _STAGE_PART.sub("", text)
    return _TEMP_PART.sub(lambda m: m.group(1) + m.group(2), text)
