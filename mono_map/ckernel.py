"""Load the C kernels (``mono_map/csrc/<name>.c``) as shared libraries with ctypes (optional speed-ups with a numpy fallback).

``pip install`` builds each source into ``mono_map/_lib/<name>_<digest>.so`` (setup.py calls
:func:`compile_library`), the digest covering the flags, the source and the headers it includes. At
run time :func:`load` takes that library when its digest matches the source beside it; a missing or
stale one (an edited source, an install without a compiler) is compiled once with the system C
compiler (``$CC``, else ``cc``) into a cache directory (``$MONO_MAP_CACHE`` or ``~/.cache/mono_map``)
and reused by every later process. Either way the code is IEEE float code (``-O3 -ffp-contract=off
-fno-fast-math``: no fused multiply-adds, no reassociation, so float32 arithmetic in the same order
gives numpy's bits). ``MONO_MAP_NO_C=1``, a missing compiler or a failed build give None: callers
keep their numpy path. This module uses the standard library only (setup.py loads it by path).
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import re
import subprocess
import sys
import tempfile
from pathlib import Path

CFLAGS = ("-O3", "-fPIC", "-shared", "-ffp-contract=off", "-fno-fast-math", "-Wall",
          "-Werror=implicit-function-declaration")
SOURCE_DIR = Path(__file__).resolve().parent / "csrc"      # the kernels' .c and .h files
BUILT_DIR = Path(__file__).resolve().parent / "_lib"       # libraries built at install
LIBRARIES = ("raycast", "points", "synth", "fused", "sweep")                  # csrc/<name>.c, one library each

_INCLUDE = re.compile(r'^\s*#\s*include\s+"([^"]+)"', re.MULTILINE)


def cache_dir() -> Path:
    """Where libraries compiled at run time are kept: ``$MONO_MAP_CACHE`` or ``~/.cache/mono_map``."""
    env = os.environ.get("MONO_MAP_CACHE")
    return Path(env).expanduser() if env else Path("~/.cache/mono_map").expanduser()


def disabled() -> bool:
    """True when ``MONO_MAP_NO_C=1`` asks for the numpy paths only."""
    return os.environ.get("MONO_MAP_NO_C", "0") == "1"


def source_files(name: str, source_dir: Path = SOURCE_DIR) -> list[Path]:
    """``<name>.c`` and the local headers it includes (``#include "x.h"``, one level), in that order."""
    src = Path(source_dir) / f"{name}.c"
    return [src, *(src.parent / h for h in _INCLUDE.findall(src.read_text()))]


def digest(name: str, source_dir: Path = SOURCE_DIR) -> str:
    """12 hex digits of the flags and the bytes of :func:`source_files`: a library's name carries it."""
    h = hashlib.sha1(" ".join(CFLAGS).encode())
    for f in source_files(name, source_dir):
        h.update(f.name.encode() + b"\0" + f.read_bytes())
    return h.hexdigest()[:12]


def built_name(name: str, source_dir: Path = SOURCE_DIR) -> str:
    """File name of the library built at install: ``<name>_<digest>.so``."""
    return f"{name}_{digest(name, source_dir)}.so"


def compile_library(src: Path, out: Path, quiet: bool = True) -> None:
    """Compile the C file ``src`` into the shared library ``out`` with :data:`CFLAGS` (atomically: a
    temporary file in ``out``'s directory, then renamed). Raises OSError / SubprocessError on failure;
    ``quiet=False`` lets the compiler's warnings through (install)."""
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=out.parent) as tmp:   # same file system: atomic rename
        so = Path(tmp) / out.name
        subprocess.run([os.environ.get("CC", "cc"), *CFLAGS, "-o", str(so), str(src), "-lm"],
                       check=True, capture_output=quiet, timeout=300)
        os.replace(so, out)


def library_path(name: str, source_dir: Path = SOURCE_DIR, built_dir: Path = BUILT_DIR) -> Path:
    """The library to load for ``csrc/<name>.c``: the one built at install if its digest is current,
    else the cache's ``<name>_<digest>_<python tag>.so`` (compiled on first use)."""
    d = digest(name, source_dir)
    built = Path(built_dir) / f"{name}_{d}.so"
    if built.is_file():
        return built
    cached = cache_dir() / f"{name}_{d}_{sys.implementation.cache_tag}.so"
    if not cached.is_file():   # concurrent first uses from several processes are safe: atomic rename
        compile_library(Path(source_dir) / f"{name}.c", cached)
    return cached


def loader(name: str, signatures: dict, doc: str):
    """A module's ``library()``: the library of ``csrc/<name>.c`` with ``signatures`` set, loaded on the first call
    and kept (None with ``MONO_MAP_NO_C=1``, checked at every call, or when it cannot be loaded). ``doc``: what the
    library computes, for the function's docstring."""
    kept: list = []

    def library() -> ctypes.CDLL | None:
        if disabled():
            return None
        if not kept:
            kept.append(load(name, signatures))
        return kept[0]
    library.__doc__ = f"{doc} (ctypes library), or None (no compiler, or ``MONO_MAP_NO_C=1``)."
    return library


def load(name: str, signatures: dict, source_dir: Path = SOURCE_DIR, built_dir: Path = BUILT_DIR) -> ctypes.CDLL | None:
    """The library of ``<source_dir>/<name>.c`` with ``signatures`` ({function: (argtypes, restype)}) set, or None."""
    if disabled():
        return None
    try:
        lib = ctypes.CDLL(str(library_path(name, source_dir, built_dir)))
        for fname, (argtypes, restype) in signatures.items():
            fn = getattr(lib, fname)
            fn.argtypes, fn.restype = argtypes, restype
        return lib
    except (OSError, subprocess.SubprocessError, AttributeError) as exc:
        print(f"mono-map: note: compiled {name} kernel unavailable ({type(exc).__name__}); using numpy",
              file=sys.stderr)
        return None
