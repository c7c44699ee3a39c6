"""Compile a small C source at run time and load it with ctypes (optional speed-ups with a numpy fallback).

The library is built once with the system C compiler (``$CC``, else ``cc``) as IEEE float code
(``-O3 -ffp-contract=off -fno-fast-math``: no fused multiply-adds, no reassociation, so float32
arithmetic in the same order gives numpy's bits) into a cache directory (``$MONO_MAP_CACHE`` or
``~/.cache/mono_map``), named by the source's hash, and reused by every later process.
``MONO_MAP_NO_C=1``, a missing compiler or a failed build give None: callers keep their numpy path.
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import subprocess
import sys
import tempfile
from pathlib import Path

CFLAGS = ("-O3", "-fPIC", "-shared", "-ffp-contract=off", "-fno-fast-math", "-Werror=implicit-function-declaration")


def cache_dir() -> Path:
    """Where compiled libraries are kept: ``$MONO_MAP_CACHE`` or ``~/.cache/mono_map``."""
    env = os.environ.get("MONO_MAP_CACHE")
    return Path(env).expanduser() if env else Path("~/.cache/mono_map").expanduser()


def disabled() -> bool:
    """True when ``MONO_MAP_NO_C=1`` asks for the numpy paths only."""
    return os.environ.get("MONO_MAP_NO_C", "0") == "1"


def load(name: str, source: str, signatures: dict) -> ctypes.CDLL | None:
    """The library compiled from ``source`` with ``signatures`` ({function: (argtypes, restype)}) set, or None.

    ``name`` prefixes the cached file (``<name>_<source hash>_<python tag>.so``). Concurrent first
    uses from several processes are safe: each compiles into a temporary directory and renames.
    """
    if disabled():
        return None
    digest = hashlib.sha1(" ".join(CFLAGS).encode() + source.encode()).hexdigest()[:12]
    lib_path = cache_dir() / f"{name}_{digest}_{sys.implementation.cache_tag}.so"
    try:
        if not lib_path.is_file():
            lib_path.parent.mkdir(parents=True, exist_ok=True)
            with tempfile.TemporaryDirectory(dir=lib_path.parent) as tmp:   # same file system: atomic rename
                src = Path(tmp) / f"{name}.c"
                src.write_text(source)
                so = Path(tmp) / f"{name}.so"
                subprocess.run([os.environ.get("CC", "cc"), *CFLAGS, "-o", str(so), str(src), "-lm"],
                               check=True, capture_output=True, timeout=120)
                os.replace(so, lib_path)
        lib = ctypes.CDLL(str(lib_path))
        for fname, (argtypes, restype) in signatures.items():
            fn = getattr(lib, fname)
            fn.argtypes, fn.restype = argtypes, restype
        return lib
    except (OSError, subprocess.SubprocessError, AttributeError) as exc:
        print(f"mono-map: note: compiled {name} kernel unavailable ({type(exc).__name__}); using numpy",
              file=sys.stderr)
        return None
