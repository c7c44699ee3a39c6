"""The compiled updates of :class:`mono_map.mapping.mirror.LogOddsMirror` (``csrc/raycast.c``): block slots for
new cells, OctoMap's clamped ``updateNode`` on distinct cells (float32 log-odds)."""

from __future__ import annotations

import numpy as np

from mono_map.mapping.kernel_threads import helper_pool, use_two_threads


def mirror_alloc_c(fn, keys: np.ndarray, table: np.ndarray, table_lo: np.ndarray, n_blocks: int) -> np.ndarray:
    """``mm_mirror_alloc``: flat table indices of the blocks of ``keys`` that had no slot (now slots
    n_blocks, n_blocks + 1, ... in that order)."""
    assert table.dtype == np.int32 and table.flags.c_contiguous
    shape = np.array(table.shape, dtype=np.int64)
    out = np.empty(min(len(keys), table.size), dtype=np.int64)
    m = fn.mirror_alloc(keys.ctypes.data, len(keys), table.ctypes.data,
                        np.ascontiguousarray(table_lo, dtype=np.int64).ctypes.data, shape.ctypes.data, int(n_blocks),
                        out.ctypes.data)
    if m < 0:
        raise AssertionError("key outside the mirror's block table")   # the caller grows the table first
    return out[:m]


def mirror_apply_c(fn, keys: np.ndarray, update, table: np.ndarray, table_lo: np.ndarray, pool: np.ndarray,
                   dirty: np.ndarray, cmin, cmax, thres) -> tuple[int, np.ndarray]:
    """``mm_mirror_apply``: OctoMap's clamped update of distinct cells ``keys`` by ``update`` (float32 scalar or
    (N,) array); returns (#cells changed, rows of ``keys`` whose occupied state flipped). Large frames run
    on two threads, each on half of the keys (distinct cells: no two threads write one cell)."""
    assert pool.dtype == np.float32 and dirty.dtype == np.bool_ and table.dtype == np.int32
    keys = np.ascontiguousarray(keys, dtype=np.int64)
    upd = None if np.ndim(update) == 0 else np.ascontiguousarray(update, dtype=np.float32)
    shape = np.array(table.shape, dtype=np.int64)
    tlo = np.ascontiguousarray(table_lo, dtype=np.int64)

    def run(a: int, b: int) -> tuple[int, np.ndarray]:
        flips = np.empty(b - a, dtype=np.int64)
        n_flip = np.zeros(1, dtype=np.int64)
        n = fn.mirror_apply(keys[a:b].ctypes.data, b - a, None if upd is None else upd[a:b].ctypes.data,
                            float(update) if upd is None else 0.0, table.ctypes.data, tlo.ctypes.data,
                            shape.ctypes.data, pool.ctypes.data, dirty.ctypes.data, float(cmin), float(cmax),
                            float(thres), flips.ctypes.data, n_flip.ctypes.data)
        if n < 0:
            raise AssertionError("mirror block missing")   # mirror_alloc_c runs first
        return int(n), flips[:int(n_flip[0])] + a

    if not use_two_threads(len(keys)):
        return run(0, len(keys))
    cut = len(keys) // 2
    future = helper_pool().submit(run, cut, len(keys))
    n_a, f_a = run(0, cut)
    n_b, f_b = future.result()
    return n_a + n_b, np.concatenate([f_a, f_b])
