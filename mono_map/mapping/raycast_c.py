"""Optional compiled kernel for the DDA of :mod:`mono_map.mapping.raycast` (same cells, ~20× faster).

The C source, ``mono_map/csrc/raycast.c``, is OctoMap 1.10's ``computeRayKeys`` transcribed with the same
types (``float`` points and direction, ``double`` tMax/tDelta), emitting linear box indices, with the
distribution weights, the log-odds mirror and the .ot I/O beside it (their bindings:
:mod:`~mono_map.mapping.distribution_c`, :mod:`~mono_map.mapping.mirror_c`, :mod:`~mono_map.mapping.ot_c`;
this module loads the library for all of them). It is built at install (or on first use into a cache,
:mod:`mono_map.ckernel`) and loaded with ctypes. Without a compiler (or with
``MONO_MAP_NO_C=1``) the numpy implementation is used; the tests check both give the same cells.
Compiled with ``-ffp-contract=off`` and no ``-ffast-math`` so the float arithmetic is IEEE, as in
OctoMap's own build.
"""

from __future__ import annotations

import ctypes

import numpy as np

from mono_map import ckernel
from mono_map.mapping.kernel_threads import helper_pool, settle, use_two_threads

_LIB = None
_TRIED = False

_P, _I64, _F32, _F64, _INT = ctypes.c_void_p, ctypes.c_int64, ctypes.c_float, ctypes.c_double, ctypes.c_int
# every exported function: (argtypes, restype)
_SIGNATURES = {
    "mm_ray_cells": ([_P, _P, _P, _P, _I64, _F64, _P, _P, _I64, _P, _I64, _P, _I64], _I64),
    "mm_ray_weights": ([_P, _P, _P, _P, _P, _P, _P, _P, _I64, _P, _P, _P, _I64, _I64, _F32, _F32, _F32, _F64, _P, _P,
                        _I64, _P, _I64, _P, _P, _I64, _INT, _F32, _P], _I64),
    "mm_far_depth": ([_P, _P, _P, _I64, _I64, _I64, _F64, _P], None),
    "mm_point_keys": ([_P, _I64, _F64, _I64, _P, _P, _P, _P], _I64),
    "mm_unique_cells": ([_P, _I64, _P, _P, _P, _I64, _F64, _I64, _P, _P], _I64),
    "mm_box_keys": ([_P, _I64, _P, _P, _P], None),
    "mm_mirror_alloc": ([_P, _I64, _P, _P, _P, _I64, _P], _I64),
    "mm_mirror_apply": ([_P, _I64, _P, _F32, _P, _P, _P, _P, _P, _F32, _F32, _F32, _P, _P], _I64),
    "mm_ot_nodes": ([_P, _P, _P, _I64, _P, _I64, _P, _P, _P, _P, _P, _P], _I64),
    "mm_ot_leaves": ([_P, _I64, _I64, _P, _P, _P], _I64),
    "mm_ray_mass": ([_P, _P, _I64, _I64, _F64, _P, _I64, _F64, _P, _P, _P], None),
    "mm_acc_merge": ([_P, _I64, _P, _P, _P], _I64),
    "mm_acc_take": ([_P, _I64, _P, _P], None),
    "mm_quantise_split": ([_P, _P, _I64, _F32, _F32, _F64, _INT, _P, _P, _P], _I64),
    "mm_check_rows": ([_P, _P, _I64, _I64, _F64, _P, _P, _P], None),
}


def load_kernel():
    """The compiled ``mm_ray_cells`` (ctypes function; the other kernels are its attributes without the
    ``mm_`` prefix, ``.weights`` is ``mm_ray_weights``) or None if unavailable/disabled (:mod:`mono_map.ckernel`)."""
    global _LIB, _TRIED
    if ckernel.disabled():
        return None
    if _TRIED:
        return _LIB
    _TRIED = True
    lib = ckernel.load("raycast", _SIGNATURES)
    if lib is None:
        return None
    fn = lib.mm_ray_cells
    fn.weights = lib.mm_ray_weights
    for name in _SIGNATURES:
        if name not in ("mm_ray_cells", "mm_ray_weights"):
            setattr(fn, name[3:], getattr(lib, name))
    _LIB = fn
    return _LIB


def dda_capacity(ke: np.ndarray, ko: np.ndarray) -> int:
    """Cells the rays to key_ends ``ke`` can emit at most: their DDA steps plus slack."""
    return int(np.abs(ke - ko[None, :]).sum()) + 8 * len(ke) + 16


def _run(fn, o, ko, resolution, lo, st, tree_max_val, e, ke, out, mark=None) -> int:
    """One kernel call; returns the number of indices written to ``out`` (< 0: see the C source)."""
    return int(fn(o.ctypes.data, ko.ctypes.data, e.ctypes.data, ke.ctypes.data, len(e), float(resolution),
                  lo.ctypes.data, st.ctypes.data, int(tree_max_val), out.ctypes.data, len(out),
                  None if mark is None else mark.ctypes.data, 0 if mark is None else len(mark)))


def _distinct_cells(fn, o, ko, resolution, lo, st, tree_max_val, e, ke, mark) -> np.ndarray:
    """The kernel with a bitmap: distinct linear indices of the rays o -> e, marked 1 in ``mark``."""
    out = np.empty(min(dda_capacity(ke, ko), len(mark)), dtype=np.int64)
    n = _run(fn, o, ko, resolution, lo, st, tree_max_val, e, ke, out, mark)
    if n < 0:   # -1 cannot happen (distinct cells <= min(steps, box)); -2: outside the box
        raise AssertionError("ray left its bounding box")  # the margin covers DDA overshoot
    return out[:n]


def ray_cells_c(fn, origin32: np.ndarray, key_origin: np.ndarray, ends32: np.ndarray, key_ends: np.ndarray,
                resolution: float, lo: np.ndarray, strides: np.ndarray, tree_max_val: int,
                mark: np.ndarray | None = None) -> np.ndarray | int:
    """Run the kernel; returns linear box indices (int64, with repeats), or with ``mark`` (uint8 bitmap
    over the box, 0 = unseen) the distinct indices of unmarked cells, marking them 1 in ``mark`` (cells
    already marked, e.g. 2 = occupied, are skipped). Large frames run on two threads sharing the bitmap
    (the kernel marks atomically, so each cell comes from one thread): same set of cells, see
    :func:`mono_map.mapping.kernel_threads.threads`."""
    o = np.ascontiguousarray(origin32, dtype=np.float32)
    ko = np.ascontiguousarray(key_origin, dtype=np.int64)
    e = np.ascontiguousarray(ends32, dtype=np.float32)
    ke = np.ascontiguousarray(key_ends, dtype=np.int64)
    lo = np.ascontiguousarray(lo, dtype=np.int64)
    st = np.ascontiguousarray(strides, dtype=np.int64)
    if mark is not None:
        assert mark.dtype == np.uint8 and mark.flags.c_contiguous
        args = (o, ko, resolution, lo, st, tree_max_val)
        if not use_two_threads(len(e)):
            return _distinct_cells(fn, *args, e, ke, mark)
        # two halves of equal DDA work on two threads (ctypes releases the GIL), deduplicating into
        # the one shared bitmap (consecutive rays, mostly neighbours, stay on one thread)
        steps = np.cumsum(np.abs(ke - ko[None, :]).sum(axis=1))
        cut = int(np.searchsorted(steps, steps[-1] / 2))
        future = helper_pool().submit(_distinct_cells, fn, *args, e[cut:], ke[cut:], mark)
        try:
            first = _distinct_cells(fn, *args, e[:cut], ke[:cut], mark)
            return np.concatenate([first, future.result()])
        except BaseException:            # e.g. Ctrl-C: the caller clears the bitmap once the other thread is done
            settle(future)
            raise
    cap = dda_capacity(ke, ko)
    while True:
        out = np.empty(cap, dtype=np.int64)
        n = _run(fn, o, ko, resolution, lo, st, tree_max_val, e, ke, out)
        if n >= 0:
            return out[:n]
        cap *= 2


def point_keys_c(fn, points: np.ndarray, resolution: float, tree_max_val: int):
    """``mm_point_keys``: (float32 points (N, 3), int64 keys (N, 3), key lo (3,), key hi (3,), #points out of range)."""
    pts = np.ascontiguousarray(points, dtype=np.float64)
    n = len(pts)
    pts32 = np.empty((n, 3), dtype=np.float32)
    keys = np.empty((n, 3), dtype=np.int64)
    lo, hi = np.empty(3, dtype=np.int64), np.empty(3, dtype=np.int64)
    bad = fn.point_keys(pts.ctypes.data, n, 1.0 / float(resolution), int(tree_max_val), pts32.ctypes.data,
                        keys.ctypes.data, lo.ctypes.data, hi.ctypes.data)
    return pts32, keys, lo, hi, int(bad)


def unique_cells_c(fn, keys: np.ndarray, lo: np.ndarray, strides: np.ndarray, mark: np.ndarray,
                   resolution: float, tree_max_val: int, centres: bool = True):
    """``mm_unique_cells``: (rows of the first key in each cell, float32 cell centres of those rows or None);
    marks those cells 2 in ``mark``."""
    k = np.ascontiguousarray(keys, dtype=np.int64)
    rows = np.empty(len(k), dtype=np.int64)
    cen = np.empty((len(k), 3), dtype=np.float32) if centres else None
    m = fn.unique_cells(k.ctypes.data, len(k), np.ascontiguousarray(lo, dtype=np.int64).ctypes.data,
                        np.ascontiguousarray(strides, dtype=np.int64).ctypes.data, mark.ctypes.data, len(mark),
                        float(resolution), int(tree_max_val), rows.ctypes.data, None if cen is None else cen.ctypes.data)
    if m < 0:
        raise AssertionError("key outside its bounding box")   # the box is built from these keys
    return rows[:m], None if cen is None else cen[:m]


def box_keys_c(fn, lin: np.ndarray, lo: np.ndarray, strides: np.ndarray) -> np.ndarray:
    """``mm_box_keys``: (N, 3) int64 keys of linear box indices."""
    lin = np.ascontiguousarray(lin, dtype=np.int64)
    out = np.empty((len(lin), 3), dtype=np.int64)
    fn.box_keys(lin.ctypes.data, len(lin), np.ascontiguousarray(lo, dtype=np.int64).ctypes.data,
                np.ascontiguousarray(strides, dtype=np.int64).ctypes.data, out.ctypes.data)
    return out
