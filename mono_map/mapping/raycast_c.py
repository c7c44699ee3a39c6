"""Optional compiled kernel for the DDA of :mod:`mono_map.mapping.raycast` (same cells, ~20× faster).

The C source, ``mono_map/csrc/raycast.c``, is OctoMap 1.10's ``computeRayKeys`` transcribed with the same
types (``float`` points and direction, ``double`` tMax/tDelta), emitting linear box indices, with the
distribution weights, the log-odds mirror and the .ot I/O beside it. It is built at install (or on
first use into a cache, :mod:`mono_map.ckernel`) and loaded with ctypes. Without a compiler (or with
``MONO_MAP_NO_C=1``) the numpy implementation is used; the tests check both give the same cells.
Compiled with ``-ffp-contract=off`` and no ``-ffast-math`` so the float arithmetic is IEEE, as in
OctoMap's own build.
"""

from __future__ import annotations

import ctypes
import os
import threading

import numpy as np

from mono_map import ckernel

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


_PARALLEL_MIN_RAYS = 4096
_WEIGHT_CHUNKS = 16      # distribution rays: chunks of groups shared out between the two threads
_POOL = None


def _threads() -> int:
    """Threads for the kernel: ``$MONO_MAP_RAY_THREADS`` (1 or 2), else 2 when the process may use 2 CPUs."""
    env = os.environ.get("MONO_MAP_RAY_THREADS")
    if env:
        return max(1, min(2, int(env)))
    try:
        return min(2, len(os.sched_getaffinity(0)))
    except AttributeError:  # not Linux
        return min(2, os.cpu_count() or 1)


_POOL_LOCK = threading.Lock()


def _pool():
    global _POOL
    with _POOL_LOCK:   # builds in several threads share the one helper thread (each waits for its own half)
        if _POOL is None:
            from concurrent.futures import ThreadPoolExecutor

            _POOL = ThreadPoolExecutor(max_workers=1, thread_name_prefix="mm-dda")
    return _POOL


def _capacity(ke: np.ndarray, ko: np.ndarray) -> int:
    """Cells the rays to key_ends ``ke`` can emit at most: their DDA steps plus slack."""
    return int(np.abs(ke - ko[None, :]).sum()) + 8 * len(ke) + 16


def _run(fn, o, ko, resolution, lo, st, tree_max_val, e, ke, out, mark=None) -> int:
    """One kernel call; returns the number of indices written to ``out`` (< 0: see the C source)."""
    return int(fn(o.ctypes.data, ko.ctypes.data, e.ctypes.data, ke.ctypes.data, len(e), float(resolution),
                  lo.ctypes.data, st.ctypes.data, int(tree_max_val), out.ctypes.data, len(out),
                  None if mark is None else mark.ctypes.data, 0 if mark is None else len(mark)))


def _distinct_cells(fn, o, ko, resolution, lo, st, tree_max_val, e, ke, mark) -> np.ndarray:
    """The kernel with a bitmap: distinct linear indices of the rays o -> e, marked 1 in ``mark``."""
    out = np.empty(min(_capacity(ke, ko), len(mark)), dtype=np.int64)
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
    (the kernel marks atomically, so each cell comes from one thread): same set of cells, see ``_threads``."""
    o = np.ascontiguousarray(origin32, dtype=np.float32)
    ko = np.ascontiguousarray(key_origin, dtype=np.int64)
    e = np.ascontiguousarray(ends32, dtype=np.float32)
    ke = np.ascontiguousarray(key_ends, dtype=np.int64)
    lo = np.ascontiguousarray(lo, dtype=np.int64)
    st = np.ascontiguousarray(strides, dtype=np.int64)
    if mark is not None:
        assert mark.dtype == np.uint8 and mark.flags.c_contiguous
        args = (o, ko, resolution, lo, st, tree_max_val)
        if len(e) < _PARALLEL_MIN_RAYS or _threads() < 2:
            return _distinct_cells(fn, *args, e, ke, mark)
        # two halves of equal DDA work on two threads (ctypes releases the GIL), deduplicating into
        # the one shared bitmap (consecutive rays, mostly neighbours, stay on one thread)
        steps = np.cumsum(np.abs(ke - ko[None, :]).sum(axis=1))
        cut = int(np.searchsorted(steps, steps[-1] / 2))
        future = _pool().submit(_distinct_cells, fn, *args, e[cut:], ke[cut:], mark)
        try:
            first = _distinct_cells(fn, *args, e[:cut], ke[:cut], mark)
            return np.concatenate([first, future.result()])
        except BaseException:            # e.g. Ctrl-C: the caller clears the bitmap once the other thread is done
            _settle(future)
            raise
    cap = _capacity(ke, ko)
    while True:
        out = np.empty(cap, dtype=np.int64)
        n = _run(fn, o, ko, resolution, lo, st, tree_max_val, e, ke, out)
        if n >= 0:
            return out[:n]
        cap *= 2


def ray_weights_c(fn, origin32: np.ndarray, key_origin: np.ndarray, ends32: np.ndarray, key_ends: np.ndarray,
                  has_end: np.ndarray, scale: np.ndarray, probs: np.ndarray, p_beyond: np.ndarray,
                  edges: np.ndarray, hit: float, miss: float, resolution: float, lo: np.ndarray,
                  strides: np.ndarray, tree_max_val: int, box_size: int, min_update: float = 0.0,
                  dense: bool = True, free_threshold: float | None = None, *,
                  ray_ids: np.ndarray, mass: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Run ``mm_ray_weights``: (linear box indices, float32 log-odds updates) of the distribution-weighted
    rays, one entry per distinct cell (rays combined: largest positive update, else most negative).
    Rays with the same ``ray_ids`` (int64 (N,)) share one walk, so they must
    have the same end point and ``has_end`` (in :func:`distribution_update`: the same far cell, whose centre
    and its cut at the range limit are the ray's end).
    dense=True accumulates in a float32 buffer over the whole box (reused across frames; on two threads
    for large frames, each half of the groups in its own buffer, merged by the same rule); dense=False writes
    (index, update) pairs with repeats and combines them here (for boxes too large to allocate).
    edges: (K+1,) for all rays or (N, K+1) per ray, float64 metres. ``free_threshold`` (a float32 update ≤
    −min_update; None: off): a cell where some ray's update is ≤ it and no ray's is positive may come out as
    exactly ``miss`` instead of the most negative update — for callers that snap such cells to a whole miss
    anyway (:func:`mono_map.mapping.distribution.snap_threshold`); the kernel then skips evaluating rays in
    the cells where their update is surely ≤ it (most of a ray's length). ``mass``: each ray's sum of its
    probs in bin order, float64 (N,), as :func:`check_rows_c` gives it (None: summed in the kernel)."""
    c = dict(o=np.ascontiguousarray(origin32, dtype=np.float32), ko=np.ascontiguousarray(key_origin, dtype=np.int64),
             lo=np.ascontiguousarray(lo, dtype=np.int64), st=np.ascontiguousarray(strides, dtype=np.int64),
             hit=float(hit), miss=float(miss), min_update=float(min_update), res=float(resolution),
             tmv=int(tree_max_val), box_size=int(box_size), snap=int(free_threshold is not None),
             thr=float(free_threshold) if free_threshold is not None else 0.0)
    rays = dict(e=np.ascontiguousarray(ends32, dtype=np.float32), ke=np.ascontiguousarray(key_ends, dtype=np.int64),
                he=np.ascontiguousarray(has_end, dtype=np.uint8), sc=np.ascontiguousarray(scale, dtype=np.float64),
                pr=np.ascontiguousarray(probs, dtype=np.float32), pb=np.ascontiguousarray(p_beyond, dtype=np.float64),
                ed=np.ascontiguousarray(edges, dtype=np.float64),
                ms=None if mass is None else np.ascontiguousarray(mass, dtype=np.float64))
    n = len(rays["e"])
    ids = np.asarray(ray_ids, dtype=np.int64)
    order = np.argsort(ids, kind="stable")
    srt = ids[order]
    groups = np.flatnonzero(np.r_[True, srt[1:] != srt[:-1]]) if n else np.zeros(0, np.int64)
    if not dense:
        lin, dl = _weights_run(fn, c, rays, order, groups, n, None)
        return combine_updates(lin, dl)
    if n < _PARALLEL_MIN_RAYS or _threads() < 2 or len(groups) < 2:
        acc = _zeroed_accumulator(0, box_size)
        try:
            lin, _ = _weights_run(fn, c, rays, order, groups, n, acc)
            return lin, _acc_take(fn, lin, acc)
        except BaseException:            # e.g. Ctrl-C: cells of unknown extent written; zero all for the next frame
            acc[:] = 0.0
            raise
    # the groups in chunks of about equal work (one DDA walk per group, each ray's set-up ~ 20 steps), taken by
    # two threads as they come free (each thread accumulates into its own buffer; merged below)
    sizes = np.diff(np.r_[groups, n])
    work = np.cumsum(np.abs(rays["ke"][order[groups]] - c["ko"][None, :]).sum(axis=1) + 20 * sizes)
    cuts = np.unique(np.r_[0, np.searchsorted(work, work[-1] * np.arange(1, _WEIGHT_CHUNKS) / _WEIGHT_CHUNKS),
                           len(groups)])
    chunks = iter(zip(cuts[:-1], cuts[1:]))
    lock, cancel = threading.Lock(), threading.Event()

    def worker(acc: np.ndarray) -> np.ndarray:
        lins = []
        while True:
            with lock:
                chunk = None if cancel.is_set() else next(chunks, None)
            if chunk is None:
                return np.concatenate(lins) if lins else np.zeros(0, np.int64)
            a, b = int(chunk[0]), int(chunk[1])
            lins.append(_weights_run(fn, c, rays, order, groups[a:b], int(groups[b]) if b < len(groups) else n,
                                     acc)[0])

    acc_a, acc_b = _zeroed_accumulator(0, box_size), _zeroed_accumulator(1, box_size)
    future = _pool().submit(worker, acc_b)
    try:
        lin_a = worker(acc_a)
        lin_b = future.result()
        fresh = np.empty(len(lin_b), dtype=np.int64)
        m = fn.acc_merge(lin_b.ctypes.data, len(lin_b), acc_a.ctypes.data, acc_b.ctypes.data, fresh.ctypes.data)
        lin = np.concatenate([lin_a, fresh[:m]])
        return lin, _acc_take(fn, lin, acc_a)
    except BaseException:                # e.g. Ctrl-C: stop the other thread, then zero both buffers for the next frame
        cancel.set()
        _settle(future)
        acc_a[:] = 0.0
        acc_b[:] = 0.0
        raise


def _settle(future) -> None:
    """Wait until the other thread's kernel call is over (its result or error is not wanted any more)."""
    import concurrent.futures

    concurrent.futures.wait([future])


def _acc_take(fn, lin: np.ndarray, acc: np.ndarray) -> np.ndarray:
    """float32 acc[lin], zeroing those cells (the buffer stays zeroed for the next frame)."""
    lin = np.ascontiguousarray(lin, dtype=np.int64)
    dl = np.empty(len(lin), dtype=np.float32)
    fn.acc_take(lin.ctypes.data, len(lin), acc.ctypes.data, dl.ctypes.data)
    return dl


def _weights_run(fn, c: dict, r: dict, order: np.ndarray, starts: np.ndarray, stop: int,
                 acc: np.ndarray | None) -> tuple[np.ndarray, np.ndarray | None]:
    """One ``mm_ray_weights`` call over the groups beginning at ``starts`` (positions in ``order``; the last
    ends at ``stop``): (distinct indices, None) accumulating into ``acc``, or with acc None the (index,
    update) pairs with repeats."""
    k = r["pr"].shape[1]
    edge_stride = 0 if r["ed"].ndim == 1 else r["ed"].shape[1]
    bounds = np.ascontiguousarray(np.r_[starts, stop], dtype=np.int64)
    cap = _capacity(r["ke"][order[starts]], c["ko"]) + 2 * len(starts)     # one walk (+ end cell) per group
    if acc is not None:
        cap = min(cap, c["box_size"])
    order = np.ascontiguousarray(order, dtype=np.int64)
    while True:
        out = np.empty(cap, dtype=np.int64)
        out_dl = None if acc is not None else np.empty(cap, dtype=np.float32)
        n = int(fn.weights(c["o"].ctypes.data, c["ko"].ctypes.data, r["e"].ctypes.data, r["ke"].ctypes.data,
                           r["he"].ctypes.data, r["sc"].ctypes.data, order.ctypes.data, bounds.ctypes.data,
                           len(starts), r["pr"].ctypes.data,
                           r["pb"].ctypes.data, r["ed"].ctypes.data, edge_stride, k, c["hit"], c["miss"],
                           c["min_update"], c["res"], c["lo"].ctypes.data, c["st"].ctypes.data, c["tmv"],
                           None if acc is None else acc.ctypes.data, c["box_size"], out.ctypes.data,
                           None if out_dl is None else out_dl.ctypes.data, len(out), c["snap"], c["thr"],
                           None if r["ms"] is None else r["ms"].ctypes.data))
        if n == -2:
            raise AssertionError("ray left its bounding box")  # the margin covers DDA overshoot
        if n == -3:
            raise MemoryError("mm_ray_weights: no memory for the ray states")
        if n >= 0:
            return out[:n], None if out_dl is None else out_dl[:n]
        if acc is not None:     # cannot happen (distinct cells <= box); guard against a partial write
            raise AssertionError("accumulator capacity exceeded")
        cap *= 2


_BUFFERS = threading.local()   # per calling thread: maps built in different threads never share a buffer


def _buffers():
    """This thread's per-frame buffers: the visited bitmap ``mark`` and the two accumulators ``acc``."""
    b = _BUFFERS
    if not hasattr(b, "mark"):
        b.mark = np.zeros(0, dtype=np.uint8)
        b.acc = [np.zeros(0, dtype=np.float32), np.zeros(0, dtype=np.float32)]
    return b


def _zeroed_accumulator(slot: int, size: int) -> np.ndarray:
    """Zeroed float32 buffer ``slot`` (one per kernel thread) of at least ``size`` cells, reused across
    frames (allocating and faulting in hundreds of MB per frame would cost more than the rays); callers zero
    what they touched."""
    acc = _buffers().acc
    if len(acc[slot]) < size:
        acc[slot] = np.zeros(max(size, int(len(acc[slot]) * 1.25)), dtype=np.float32)
    return acc[slot]


def combine_updates(lin: np.ndarray, dl: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per distinct index: the largest positive update if any, else the most negative (the kernel's rule)."""
    if len(lin) == 0:
        return lin, dl
    order = np.argsort(lin, kind="stable")
    lin, dl = lin[order], dl[order]
    starts = np.flatnonzero(np.r_[True, lin[1:] != lin[:-1]])
    hi = np.maximum.reduceat(dl, starts)
    low = np.minimum.reduceat(dl, starts)
    return lin[starts], np.where(hi > 0, hi, low).astype(np.float32)


def quantise_split_c(fn, lin: np.ndarray, dl: np.ndarray, hit: float, miss: float, quantum: float,
                     snap_free: bool) -> tuple[np.ndarray, np.ndarray, int]:
    """``mm_quantise_split``: the updates ``dl`` (float32) at indices ``lin`` (int64) rounded as
    :func:`mono_map.mapping.distribution.quantise_updates`, the zeros dropped, the negatives first, then the
    positives (each in input order): (indices, updates, number of negatives)."""
    lin = np.ascontiguousarray(lin, dtype=np.int64)
    dl = np.ascontiguousarray(dl, dtype=np.float32)
    out_lin, out_dl = np.empty(len(lin), dtype=np.int64), np.empty(len(lin), dtype=np.float32)
    n_neg = np.zeros(1, dtype=np.int64)
    m = fn.quantise_split(lin.ctypes.data, dl.ctypes.data, len(lin), float(hit), float(miss), float(quantum),
                          int(bool(snap_free)), out_lin.ctypes.data, out_dl.ctypes.data, n_neg.ctypes.data)
    return out_lin[:m], out_dl[:m], int(n_neg[0])


def far_depth_c(fn, probs: np.ndarray, p_beyond: np.ndarray, edges: np.ndarray, eps: float) -> np.ndarray:
    """``mm_far_depth``: (N,) float64 depth where P(beyond) first falls below eps (see distribution.far_depth)."""
    pr = np.ascontiguousarray(probs, dtype=np.float32)
    pb = np.ascontiguousarray(p_beyond, dtype=np.float64)
    ed = np.ascontiguousarray(edges, dtype=np.float64)
    out = np.empty(len(pr), dtype=np.float64)
    fn.far_depth(pr.ctypes.data, pb.ctypes.data, ed.ctypes.data, 0 if ed.ndim == 1 else ed.shape[1], pr.shape[1],
                 len(pr), float(eps), out.ctypes.data)
    return out


def ray_mass_c(fn, probs: np.ndarray, p_beyond: np.ndarray, inv_temperature: float, edges: np.ndarray,
               eps: float, overwrite: bool = False, rows: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """``mm_ray_mass``: (float32 (N, K) unconditional bin mass, float64 (N,) far depths) of conditional bin
    probabilities (N, K) at temperature 1 / inv_temperature (see distribution.ray_distributions);
    ``overwrite``: the mass is written over ``probs`` when it is a C-contiguous float32 array; ``rows``
    (int64 (N,)): the rays are these rows of ``probs`` (M, K) (read in place, no gathered copy; not with
    overwrite); p_beyond and per-ray edges are then per ray."""
    pr = np.ascontiguousarray(probs, dtype=np.float32)
    pb = np.ascontiguousarray(p_beyond, dtype=np.float64)
    ed = np.ascontiguousarray(edges, dtype=np.float64)
    idx = None if rows is None else np.ascontiguousarray(rows, dtype=np.int64)
    k = pr.shape[1]
    n = len(pr) if idx is None else len(idx)
    if idx is not None and n and (idx.min() < 0 or idx.max() >= len(pr)):
        raise IndexError("ray_mass_c: row index out of range")
    if len(pb) != n or (ed.ndim == 2 and len(ed) != n):
        raise ValueError(f"ray_mass_c: {n} rays but {len(pb)} p_beyond values / edges of shape {ed.shape}")
    out = pr if overwrite and idx is None else np.empty((n, k), dtype=np.float32)   # element-wise: in place is safe
    far = np.empty(n, dtype=np.float64)
    es = 0 if ed.ndim == 1 else ed.shape[1]

    def part(a: int, b: int) -> None:      # rays a..b-1 (row by row: halves on two threads give the same bits)
        src, ix = (pr.ctypes.data + 4 * k * a, None) if idx is None else (pr.ctypes.data, idx.ctypes.data + 8 * a)
        fn.ray_mass(src, pb.ctypes.data + 8 * a, b - a, k, float(inv_temperature), ed.ctypes.data + 8 * es * a, es,
                    float(eps), out.ctypes.data + 4 * k * a, far.ctypes.data + 8 * a, ix)

    _on_two_threads(part, n)
    return out, far


def _on_two_threads(rows, n: int) -> None:
    """rows(a, b) over 0..n: in two halves on two threads for large n (ctypes releases the GIL), else at once."""
    if n < _PARALLEL_MIN_RAYS or _threads() < 2:
        rows(0, n)
        return
    half = n // 2
    future = _pool().submit(rows, half, n)
    rows(0, half)
    future.result()


def check_rows_c(fn, probs: np.ndarray, p_beyond: np.ndarray, tol: float, mass: np.ndarray | None = None) -> dict:
    """``mm_check_rows``: counts and extremes of N distributions' values (see distribution.check_distribution);
    ``mass`` (float64 (N,), C-contiguous): filled with each row's sum of finite probs in bin order."""
    assert mass is None or (mass.dtype == np.float64 and mass.flags.c_contiguous and mass.shape == (len(probs),))
    pr = np.ascontiguousarray(probs, dtype=np.float32)
    pb = np.ascontiguousarray(p_beyond, dtype=np.float64)
    k = pr.shape[1] if pr.ndim == 2 else 0
    # rows on two threads, each half its own stats; a half not run keeps the neutral ones
    stats = np.array([[0, 0, np.inf, 0, 0, np.inf, -np.inf]] * 2, dtype=np.float64)
    over = np.zeros(2, dtype=np.int64)

    def rows(a: int, b: int) -> None:
        h = int(a > 0)
        fn.check_rows(pr.ctypes.data + 4 * k * a, pb.ctypes.data + 8 * a, b - a, k, float(tol),
                      stats[h].ctypes.data, over[h:].ctypes.data, None if mass is None else mass.ctypes.data + 8 * a)

    _on_two_threads(rows, len(pr))
    keys = ("bad_p", "neg_p", "min_p", "bad_b", "neg_b", "min_b", "max_total")
    tot, low, high = stats.sum(axis=0), stats.min(axis=0), stats.max(axis=0)    # counts, minima, the max total
    vals = [tot[0], tot[1], low[2], tot[3], tot[4], low[5], high[6]]
    return dict(zip(keys, (float(v) for v in vals)), n_over=int(over.sum()))


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

    if len(keys) < _PARALLEL_MIN_RAYS or _threads() < 2:
        return run(0, len(keys))
    cut = len(keys) // 2
    future = _pool().submit(run, cut, len(keys))
    n_a, f_a = run(0, cut)
    n_b, f_b = future.result()
    return n_a + n_b, np.concatenate([f_a, f_b])


def release_buffers() -> None:
    """Free this thread's per-frame buffers kept between frames (visited bitmap, accumulators): at the end
    of a build."""
    vars(_BUFFERS).clear()   # the next _buffers() call starts this thread's buffers empty


def zeroed_bitmap(size: int) -> np.ndarray:
    """A zeroed uint8 bitmap of ``size`` cells, this thread's, reused across frames (as the accumulators);
    the caller zeroes the cells it marked before the next frame."""
    b = _buffers()
    if len(b.mark) < size:
        b.mark = np.zeros(max(size, int(len(b.mark) * 1.25)), dtype=np.uint8)
    return b.mark[:size]


def _blocks_in_code_order(block_codes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(block slots sorted by their depth-13 code, the sorted codes), as ``mm_ot_nodes`` walks them."""
    codes = np.asarray(block_codes, dtype=np.int64)
    slot = np.argsort(codes, kind="stable").astype(np.int64)
    return slot, np.ascontiguousarray(codes[slot])


def ot_nodes_c(fn, pool: np.ndarray, block_codes: np.ndarray, header: bytes = b"") -> tuple[np.ndarray, int]:
    """``mm_ot_nodes``: (``header`` + the node bytes of OctoMap's .ot stream as a uint8 array, node count) of the
    known (non-NaN) cells of a log-odds mirror: float32 ``pool`` of blocks of 8×8×8 cells (see
    integrate.LogOddsMirror), ``block_codes`` (B,) each block's depth-13 code
    (``octree.child_order_codes(block_key >> 3)``). The nodes are the same bytes as ``octree.ot_stream`` of
    those cells. The buffer is sized for the worst case but only the written pages take memory."""
    assert pool.dtype == np.float32 and pool.flags.c_contiguous
    slot, codes = _blocks_in_code_order(block_codes)
    cap = (512 + 64 + 8 + 1 + 13) * len(slot) + 1     # a full block's subtree and its path to the root
    h = len(header)
    out = np.empty(h + 5 * cap, dtype=np.uint8)
    out[:h] = np.frombuffer(header, dtype=np.uint8)
    leaves = np.zeros(1, dtype=np.int64)
    n = fn.ot_nodes(pool.ctypes.data, slot.ctypes.data, codes.ctypes.data, len(slot), out[h:].ctypes.data, cap,
                    leaves.ctypes.data, None, None, None, None, None)
    if n < 0:
        raise AssertionError("node bound exceeded")   # cannot happen: cap bounds every block's nodes
    return out[:h + 5 * n], int(n)


def ot_counts_c(fn, pool: np.ndarray, block_codes: np.ndarray, cache: dict | None = None) -> tuple[int, int]:
    """``mm_ot_nodes`` counting only: (nodes, leaves) of the octree the mirror's known cells make (OctoMap's
    ``size()`` and ``getNumLeafNodes()``). ``cache``: per block slot arrays ``dirty`` (bool), ``kind`` (int8),
    ``value`` (float32), ``nodes`` and ``leaves`` (int64): only dirty blocks are walked; they are cached and
    marked clean."""
    slot, codes = _blocks_in_code_order(block_codes)
    leaves = np.zeros(1, dtype=np.int64)
    if cache is None:
        ptrs = (None,) * 5
    else:
        arrays = (cache["dirty"], cache["kind"], cache["value"], cache["nodes"], cache["leaves"])
        for a, dt in zip(arrays, (np.bool_, np.int8, np.float32, np.int64, np.int64)):
            assert a.dtype == dt and a.flags.c_contiguous and len(a) >= len(slot)
        ptrs = tuple(a.ctypes.data for a in arrays)
    n = fn.ot_nodes(pool.ctypes.data, slot.ctypes.data, codes.ctypes.data, len(slot), None, 0, leaves.ctypes.data,
                    *ptrs)
    return int(n), int(leaves[0])


def ot_leaves_c(fn, data: np.ndarray, n_leaves: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``mm_ot_leaves``: (min-corner keys (N, 3) int64, depths (N,) int64, float32 log-odds (N,)) of the
    leaves of a .ot node stream (uint8, header stripped) holding ``n_leaves`` leaves."""
    d = np.ascontiguousarray(data, dtype=np.uint8)
    keys = np.empty((n_leaves, 3), dtype=np.int64)
    depth = np.empty(n_leaves, dtype=np.int8)
    val = np.empty(n_leaves, dtype=np.float32)
    m = fn.ot_leaves(d.ctypes.data, len(d), n_leaves, keys.ctypes.data, depth.ctypes.data, val.ctypes.data)
    if m < 0 or m != n_leaves:
        raise AssertionError(f"mm_ot_leaves: {m} (tree of {n_leaves} leaves)")   # OctoMap wrote the stream
    return keys, depth.astype(np.int64), val
