"""Typed entry points: one declared schema per kind of input, checked where the value enters.

A schema is a dataclass whose fields carry their type (the annotation) and their range
(``field(metadata=bounded(...))``). :func:`check_fields` checks a mapping read from a file
(TOML/JSON config, checkpoint metadata) against it and names the file, section and key of the
first bad value in one line; :func:`check_env` does the same for the ``MONO_MAP_*`` environment
variables (:data:`ENVIRONMENT`), before any command runs.

To declare a checked field::

    from dataclasses import dataclass, field
    from mono_map.schema import bounded

    @dataclass(frozen=True)
    class MyConfig:
        steps: int = field(default=100, metadata=bounded(lo=1))
        rate: float = field(default=0.5, metadata=bounded(lo=0, hi=1, lo_open=True))
        mode: str = field(default="a", metadata=bounded(choices=("a", "b")))
        size: tuple = field(default=(4, 4), metadata=bounded(item=int, length=2, lo=1))

    values = check_fields(MyConfig, raw_dict, "train.toml [train]")   # MonoMapError naming the key
    cfg = MyConfig(**values)

Types understood: ``int`` (not bool; an integral float such as 3.0 is not accepted), ``float``
(int accepted, finite unless ``finite=False``), ``str``, ``bool``, ``tuple``/``list`` (a list or
tuple; ``item`` types and bounds its elements) and ``X | None``. Bounds apply to numbers and to
the elements of sequences.
"""

from __future__ import annotations

import math
import os
from dataclasses import MISSING, dataclass, fields
from typing import Any

from mono_map.errors import MonoMapError


def bounded(lo: float | None = None, hi: float | None = None, *, lo_open: bool = False, hi_open: bool = False,
            choices: tuple | None = None, item: type | None = None, length: int | None = None,
            multiple_of: int | None = None, finite: bool = True, nonempty: bool = False) -> dict:
    """Field metadata declaring a value's range: ``lo``/``hi`` (closed unless ``lo_open``/``hi_open``),
    ``choices``, ``multiple_of``, sequences' ``item`` type and ``length``, ``finite`` floats,
    ``nonempty`` strings/sequences."""
    return {"schema": dict(lo=lo, hi=hi, lo_open=lo_open, hi_open=hi_open, choices=choices, item=item,
                           length=length, multiple_of=multiple_of, finite=finite, nonempty=nonempty)}


_TYPE_NAMES = {"int": int, "float": float, "str": str, "bool": bool, "tuple": tuple, "list": list, "dict": dict}


def _types(annotation: Any) -> tuple[set, bool]:
    """(allowed base types, None allowed) of a field annotation (a string under postponed evaluation)."""
    text = annotation if isinstance(annotation, str) else getattr(annotation, "__name__", str(annotation))
    allowed, optional = set(), False
    for part in text.split("|"):
        part = part.strip()
        base = part.split("[", 1)[0].strip()
        if base in ("None", "NoneType"):
            optional = True
        elif base in _TYPE_NAMES:
            allowed.add(_TYPE_NAMES[base])
        elif base.startswith("tuple") or base.startswith("Tuple"):
            allowed.add(tuple)
    return allowed, optional


def _describe(t: type) -> str:
    return {int: "an integer", float: "a number", str: "a string", bool: "true or false", tuple: "a list",
            list: "a list", dict: "a table"}[t]


def check_value(value: Any, types: set, optional: bool, spec: dict | None, where: str) -> Any:
    """``value`` checked against allowed ``types`` and the :func:`bounded` ``spec``; the value (lists
    as tuples, ints as floats where a float is declared) or MonoMapError naming ``where``."""
    spec = spec or {}
    if value is None:
        if optional or not types:
            return None
        raise MonoMapError(f"{where}: expected {' or '.join(sorted(_describe(t) for t in types))}, got nothing")
    if not types:
        return value
    got = None
    if bool in types and isinstance(value, bool):
        got = value
    elif int in types and isinstance(value, int) and not isinstance(value, bool):
        got = value
    elif float in types and isinstance(value, (int, float)) and not isinstance(value, bool):
        got = float(value)
    elif str in types and isinstance(value, str):
        got = value
    elif (tuple in types or list in types) and isinstance(value, (list, tuple)):
        got = tuple(value)
    elif dict in types and isinstance(value, dict):
        got = value
    if got is None:
        want = " or ".join(sorted({_describe(t) for t in types}))
        raise MonoMapError(f"{where}: expected {want}, got {value!r}")
    if isinstance(got, tuple):
        if spec.get("length") is not None and len(got) != spec["length"]:
            raise MonoMapError(f"{where}: expected {spec['length']} values, got {len(got)}")
        if spec.get("nonempty") and not got:
            raise MonoMapError(f"{where}: must not be empty")
        item = spec.get("item")
        if item is not None:
            got = tuple(check_value(v, {item}, False, {**spec, "length": None, "nonempty": False, "item": None},
                                    f"{where}[{i}]") for i, v in enumerate(got))
        return got
    if isinstance(got, str):
        if spec.get("nonempty") and not got:
            raise MonoMapError(f"{where}: must not be empty")
    if spec.get("choices") is not None and got not in spec["choices"]:
        raise MonoMapError(f"{where}: must be one of {', '.join(map(repr, spec['choices']))}, got {got!r}")
    if isinstance(got, (int, float)) and not isinstance(got, bool):
        if isinstance(got, float) and spec.get("finite", True) and not math.isfinite(got):
            raise MonoMapError(f"{where}: must be a finite number, got {got!r}")
        lo, hi = spec.get("lo"), spec.get("hi")
        if lo is not None and (got < lo or (spec.get("lo_open") and got == lo)):
            raise MonoMapError(f"{where}: must be {'>' if spec.get('lo_open') else '>='} {lo:g}, got {got!r}")
        if hi is not None and (got > hi or (spec.get("hi_open") and got == hi)):
            raise MonoMapError(f"{where}: must be {'<' if spec.get('hi_open') else '<='} {hi:g}, got {got!r}")
        if spec.get("multiple_of") and got % spec["multiple_of"]:
            raise MonoMapError(f"{where}: must be a multiple of {spec['multiple_of']}, got {got!r}")
    return got


def check_fields(cls, values: Any, source: str, required: tuple = ()) -> dict:
    """``values`` (a mapping read from ``source``) checked against dataclass ``cls``'s declared fields:
    unknown keys, types and :func:`bounded` ranges; returns the checked values (lists as tuples).
    ``source`` names the file and section, e.g. ``"run.toml [train]"``; errors read ``source: key: ...``."""
    if not isinstance(values, dict):
        raise MonoMapError(f"{source}: expected a table of settings, got {type(values).__name__} {values!r}")
    declared = {f.name: f for f in fields(cls)}
    unknown = sorted(set(values) - set(declared))
    if unknown:
        raise MonoMapError(f"{source}: unknown key{'s' if len(unknown) > 1 else ''} {', '.join(map(str, unknown))} "
                           f"(known: {', '.join(declared)})")
    for name in required:
        if name not in values:
            raise MonoMapError(f"{source}: {name}: missing")
    out = {}
    for key, value in values.items():
        f = declared[key]
        types, optional = _types(f.type)
        out[key] = check_value(value, types, optional, f.metadata.get("schema"), f"{source}: {key}")
    return out


def check_instance(obj: Any, source: str) -> None:
    """Check a constructed dataclass's own field values (e.g. made in code or by ``replace``)."""
    check_fields(type(obj), {f.name: getattr(obj, f.name) for f in fields(obj)}, source)


# ------------------------------------------------------------------------------ environment variables


@dataclass(frozen=True)
class EnvVar:
    """A ``MONO_MAP_*`` variable: its parse (``kind``: "gb", "choice", "flag", "dir", "int", "path") and range."""

    name: str
    kind: str
    help: str
    choices: tuple = ()
    lo: float | None = None
    hi: float | None = None


ENVIRONMENT = (
    EnvVar("MONO_MAP_DATA", "dir", "data root (a folder; created when a sequence is rendered)"),
    EnvVar("MONO_MAP_RECIPES", "dir", "folder of synthetic sequence recipes"),
    EnvVar("MONO_MAP_TRAINSET", "dir", "training-town cache folder"),
    EnvVar("MONO_MAP_CACHE", "dir", "compiled kernels' cache folder"),
    EnvVar("MONO_MAP_PRECISION", "choice", "inference precision", choices=("fp32", "bf16")),
    EnvVar("MONO_MAP_MEMORY_GB", "number", "memory a build may use, GB", lo=0.001, hi=1e6),
    EnvVar("MONO_MAP_PROGRESS", "choice", "progress bars", choices=("0", "1")),
    EnvVar("MONO_MAP_NO_C", "choice", "numpy paths only", choices=("0", "1")),
    EnvVar("MONO_MAP_RAY_THREADS", "int", "ray-casting threads", lo=1, hi=2),
    EnvVar("MONO_MAP_RR_FLUSH_S", "number", "rerun flush tick, seconds", lo=0.001, hi=60),
)
_ENV = {v.name: v for v in ENVIRONMENT}


def env_value(name: str, environ: dict | None = None):
    """The checked value of ``MONO_MAP_*`` variable ``name`` (None if unset or empty); MonoMapError
    naming the variable if it is not in its declared range."""
    var = _ENV[name]
    raw = (os.environ if environ is None else environ).get(name)
    if raw is None or raw == "":
        return None
    where = f"${name}"
    if var.kind == "choice":
        if raw not in var.choices:
            raise MonoMapError(f"{where}: must be one of {', '.join(var.choices)} ({var.help}), got {raw!r}")
        return raw
    if var.kind in ("number", "int"):
        try:
            value = int(raw) if var.kind == "int" else float(raw)
        except ValueError:
            raise MonoMapError(f"{where}: expected {'an integer' if var.kind == 'int' else 'a number'} "
                               f"({var.help}), got {raw!r}") from None
        if not math.isfinite(value) or (var.lo is not None and value < var.lo) or \
                (var.hi is not None and value > var.hi):
            raise MonoMapError(f"{where}: must be a finite number in [{var.lo:g}, {var.hi:g}] ({var.help}), got {raw!r}")
        return value
    if var.kind == "dir":
        from pathlib import Path

        path = Path(raw).expanduser()
        if path.exists() and not path.is_dir():
            raise MonoMapError(f"{where}: {path} is a file, not a directory ({var.help})")
        return path
    return raw


def check_env(environ: dict | None = None) -> None:
    """Check every set ``MONO_MAP_*`` variable declared in :data:`ENVIRONMENT` once, before a command
    runs (variables not declared there are read, and checked, where they are used)."""
    for var in ENVIRONMENT:
        env_value(var.name, environ)
