"""Atomic file output: results appear whole or not at all, alone or as a set; output paths checked before any work.

Each output is written to a temporary file beside it (:mod:`mono_map.temps`: the names, the sweeping of
what killed runs left) and renamed onto it when complete. A set of outputs is published together, the
previous files put back if a rename fails (:func:`publish_renames`); many files at once go through a
staging folder (:func:`staged_dir`).
"""

from __future__ import annotations

import contextlib
import json
import os
import tempfile
from pathlib import Path
from typing import Any, Iterator

from mono_map.temps import clean_stale_temps, is_temp_name, register_temp_dir, sweep_once, temp_path


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, suffix: str | None = None) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; on success rename it onto ``path``.

    Writers write the temporary file (keeping ``path``'s extension unless ``suffix``
    is given, since some libraries pick the format from it); if the body raises,
    the temporary file is removed and ``path`` is left untouched.
    """
    with atomic_outputs(path, suffixes=None if suffix is None else [suffix]) as (tmp_path,):
        yield tmp_path


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
        files = sorted(p for p in stage.rglob("*") if p.is_file() and not is_temp_name(p.name))
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
