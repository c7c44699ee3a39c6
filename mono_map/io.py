"""Atomic file output: results appear whole or not at all, alone or as a set.

Temporary files are ``.<stem>.<pid>.<random>.tmp<suffix>`` beside their target (``mkstemp``: unique
per process and call, so concurrent writers never share one); backups of replaced files
``.<stem>.<pid>.<random>.tmpbak<suffix>``, staging folders ``.<folder>.<pid>.<random>.tmpstage``. A set of
outputs is published together, the previous files put back if a rename fails (:func:`publish_renames`).
A process killed before it could remove its temporaries leaves them behind; :func:`clean_stale_temps`
removes those whose process is gone, in the folders written to (listed in :func:`temp_registry`, swept
by :func:`sweep_registered_temps` before each command). :func:`user_path` turns any of these names in
a message back into the output it stands for.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import tempfile
from pathlib import Path
from typing import Any, Iterator


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, suffix: str | None = None) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success rename it onto ``path``.

    Writers write the temporary file (keeping ``path``'s extension unless ``suffix``
    is given, since some libraries pick the format from it); if the body raises,
    the temporary file is removed and ``path`` is left untouched.
    """
    with atomic_outputs(path, suffixes=None if suffix is None else [suffix]) as (tmp_path,):
        yield tmp_path


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


def check_output_targets(targets: list[Path]) -> None:
    """MonoMapError naming the first target that is a folder (it could never be replaced by a file):
    checked before any work, so the earlier files of a set are never touched."""
    from mono_map.errors import MonoMapError

    for t in targets:
        if t.is_dir():
            raise MonoMapError(f"{t}: a folder is in the way of this output (remove or rename it)")
        parent = t.parent
        while not parent.exists() and parent != parent.parent:
            parent = parent.parent
        if parent.exists() and not parent.is_dir():
            raise MonoMapError(f"{t}: cannot create it ({parent} is a file, not a folder)")


@contextlib.contextmanager
def atomic_outputs(*paths: str | os.PathLike, suffixes: list[str] | None = None) -> Iterator[list[Path]]:
    """Yield one temporary path per target; on success publish them all, on failure none.

    The targets are renamed in the order given, so a reader that checks the last one (e.g. a
    map's ``.json`` beside its ``.bt``) sees either the whole set or an incomplete one it
    ignores; if a rename fails, the targets already renamed are removed again.
    """
    targets = [Path(p) for p in paths]
    check_output_targets(targets)
    for d in sorted({t.parent for t in targets}):
        sweep_once(d)  # what killed runs left here, wherever they wrote
    temps: list[Path] = []
    created: list[Path] = []  # folders made here, removed again (if empty) when nothing is published
    published = False
    try:
        for i, target in enumerate(targets):
            created += _make_dirs(target.parent)
            temps.append(temp_path(target, None if suffixes is None else suffixes[i]))
        yield temps
        with _dir_locks(sorted({t.parent for t in targets})):  # another writer's set never interleaves
            publish_renames(list(zip(temps, targets)))
        published = True
    finally:
        for tmp in temps:
            tmp.unlink(missing_ok=True)
        if not published:
            _remove_empty_dirs(created)


_SWEPT: set[str] = set()


def sweep_once(folder: Path) -> None:
    """:func:`clean_stale_temps` of ``folder`` the first time this process writes there (a folder of
    thousands of frames is listed once, not once per file)."""
    key = str(Path(folder).resolve())
    if key not in _SWEPT:
        _SWEPT.add(key)
        clean_stale_temps(folder)


def publish_renames(pairs: list[tuple[Path, Path]]) -> None:
    """Rename each (temporary, target) pair in order; if one rename fails, every target renamed so far
    gets its previous file back (kept as a hard-link backup until the set is complete) or is removed
    if it had none: a failed publication leaves what was there before."""
    backups: list[tuple[Path, Path | None]] = []
    try:
        for tmp, target in pairs:
            backup = None
            if target.is_file():
                backup = temp_path(target, kind="bak")
                backup.unlink()
                try:
                    os.link(target, backup)
                except OSError:  # a file system without hard links: a copy
                    import shutil

                    shutil.copy2(target, backup)
            backups.append((target, backup))
            if tmp.exists():  # mkstemp makes 0600; give results the mode a plain open() would
                os.chmod(tmp, 0o666 & ~_UMASK)
            os.replace(tmp, target)
    except BaseException:
        for target, backup in reversed(backups):
            if backup is not None:
                os.replace(backup, target)
            else:
                target.unlink(missing_ok=True)
        raise
    finally:
        for _, backup in backups:
            if backup is not None:
                backup.unlink(missing_ok=True)


def _remove_empty_dirs(created: list[Path]) -> None:
    """Remove the folders a failed publication made (innermost first), where they are still empty."""
    for d in reversed(created):
        try:
            d.rmdir()
        except OSError:
            pass


@contextlib.contextmanager
def staged_dir(out: str | os.PathLike) -> Iterator[Path]:
    """Yield a hidden staging folder inside ``out`` for many output files; on success publish them all
    at the same relative paths under ``out`` as one set (:func:`publish_renames`: a rename failing puts
    the earlier files back), on failure remove them all (``out`` too, if made here). Stale staging
    folders and temporary files of dead runs in ``out`` are removed first."""
    import shutil

    from mono_map.errors import MonoMapError

    out = Path(out)
    if out.exists() and not out.is_dir():
        raise MonoMapError(f"{out} is a file, not a folder")
    created = _make_dirs(out)
    sweep_once(out)
    register_temp_dir(out)
    stage = Path(tempfile.mkdtemp(prefix=f".{out.name[:64]}.{os.getpid()}.", suffix=".tmpstage", dir=out))
    published = False
    try:
        yield stage
        files = sorted(p for p in stage.rglob("*") if p.is_file() and not _TEMP_NAME.search(p.name))
        check_output_targets([out / f.relative_to(stage) for f in files])
        with _dir_locks([out]):
            for f in files:
                (out / f.relative_to(stage)).parent.mkdir(parents=True, exist_ok=True)
            publish_renames([(f, out / f.relative_to(stage)) for f in files])
        published = True
    finally:
        shutil.rmtree(stage, ignore_errors=True)
        if not published:
            _remove_empty_dirs(created)


_STAGE_PART = re.compile(r"/\.[^/]*\.\d+\.[A-Za-z0-9_]{8}\.tmpstage(?=/)")
_TEMP_PART = re.compile(r"(?<![^/\s'\"])\.([^/\s]*?)\.\d+\.[A-Za-z0-9_]{8}\.tmp(?:bak)?([^/\s]*)")


def user_path(text: str) -> str:
    """``text`` with every staging folder and temporary file name (see the module doc) replaced by the
    output it stands for: what users see names their files, never mono-map's hidden ones."""
    text = _STAGE_PART.sub("", text)
    return _TEMP_PART.sub(lambda m: m.group(1) + m.group(2), text)


@contextlib.contextmanager
def _dir_locks(dirs: list[Path]) -> Iterator[None]:
    """Exclusive advisory locks (flock) on folders, taken in sorted order: publishing a set of
    outputs is one step for every mono-map process writing into the same folders."""
    import fcntl

    fds = []
    try:
        for d in dirs:
            fd = os.open(d, os.O_RDONLY)
            fds.append(fd)
            fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        for fd in fds:
            os.close(fd)  # closing releases the lock


def _make_dirs(path: Path) -> list[Path]:
    """``mkdir -p path``; returns the folders it created, outermost first."""
    missing = []
    while not path.exists() and path != path.parent:
        missing.append(path)
        path = path.parent
    for d in reversed(missing):
        d.mkdir(exist_ok=True)
    return list(reversed(missing))


_TEMP_NAME = re.compile(r"\.(\d+)\.[A-Za-z0-9_]{8}\.tmp[^/]*$")  # .<stem>.<pid>.<mkstemp's 8>.tmp<suffix>


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


def prepare_output_dir(path: str | os.PathLike) -> Path:
    """Check ``path`` is usable as an output directory before any work is done.

    It is not created here (a command refused later leaves no empty folder behind): the nearest
    existing folder on the way must be a writable directory. Stale temporary files of dead
    processes in it are removed.
    """
    from mono_map.errors import MonoMapError

    path = Path(path)
    if path.exists() and not path.is_dir():
        raise MonoMapError(f"--out: {path} is a file, not a directory")
    existing = path
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if not existing.is_dir():
        raise MonoMapError(f"--out: {path}: cannot create the directory ({existing} is a file)")
    check_writable_dir(existing, "--out")
    clean_stale_temps(path)
    return path


def check_writable_dir(path: str | os.PathLike, option: str) -> None:
    """MonoMapError unless a file can be created in directory ``path`` (tried, then removed)."""
    from mono_map.errors import MonoMapError

    try:
        fd, tmp = tempfile.mkstemp(prefix=f".probe.{os.getpid()}.", suffix=".tmp", dir=path)
    except OSError as exc:
        raise MonoMapError(f"{option}: {path}: cannot write there ({exc.strerror})") from None
    os.close(fd)
    os.unlink(tmp)


def free_bytes(path: str | os.PathLike) -> int:
    """Bytes free for unprivileged writers on the file system holding ``path`` (or its nearest existing folder)."""
    path = Path(path)
    while not path.exists() and path != path.parent:
        path = path.parent
    st = os.statvfs(path)
    return st.f_bavail * st.f_frsize


def check_output_file(path: str | os.PathLike, option: str, suffix: str | None = None,
                      min_free: int = 0) -> Path:
    """Check an output file option before any work: not a directory, the right suffix, a writable folder."""
    from mono_map.errors import MonoMapError

    path = Path(path)
    if suffix is not None and path.suffix.lower() != suffix:
        raise MonoMapError(f"{option}: {path}: the file name must end in {suffix}")
    if path.is_dir():
        raise MonoMapError(f"{option}: {path} is a directory, not a file")
    parent = path.parent
    if parent.exists() and not parent.is_dir():
        raise MonoMapError(f"{option}: {parent} is a file, not a directory")
    if parent.exists():
        check_writable_dir(parent, option)
        clean_stale_temps(parent)
    if min_free and free_bytes(parent) < min_free:
        raise MonoMapError(f"{option}: {path}: only {free_bytes(parent) / 2**20:.1f} MB free there, "
                           f"need at least {min_free / 2**20:.0f} MB")
    return path


@contextlib.contextmanager
def quiet_native_output() -> Iterator[list[str]]:
    """Capture what native code (e.g. OctoMap's C++ reader) prints on file descriptors 1 and 2.

    Yields a list that holds the captured text (decoded, replacement characters for junk) once the
    block ends; the caller decides whether to show it, so a corrupt file cannot flood the terminal.
    """
    import sys

    captured: list[str] = []
    sys.stdout.flush()
    sys.stderr.flush()
    saved = [os.dup(1), os.dup(2)]
    with tempfile.TemporaryFile() as sink:
        os.dup2(sink.fileno(), 1)
        os.dup2(sink.fileno(), 2)
        try:
            yield captured
        finally:
            os.dup2(saved[0], 1)
            os.dup2(saved[1], 2)
            for fd in saved:
                os.close(fd)
            sink.seek(0)
            captured.append(sink.read(4096).decode("utf-8", "replace"))


def _read_umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


# read once at import: reading the umask means setting it, which per write would race with other
# threads creating files
_UMASK = _read_umask()


def write_bytes_atomic(path: str | os.PathLike, data: bytes) -> None:
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def write_text_atomic(path: str | os.PathLike, text: str) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(text)


def write_json_atomic(path: str | os.PathLike, obj: Any) -> None:
    write_text_atomic(path, json.dumps(obj, indent=2, sort_keys=False, default=_json_default) + "\n")


def _json_default(o: Any) -> Any:
    import numpy as np

    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")
