"""The compiled distribution kernels of :mod:`mono_map.mapping.distribution` (``csrc/raycast.c``, loaded by
:func:`mono_map.mapping.raycast_c.load_kernel`): each ray's expected OctoMap update from its bin
probabilities (``mm_ray_weights``), the unconditional bin mass and far depth, the checks of the
distributions, the updates' quantisation. Depths in metres, updates float32 log-odds.
"""

from __future__ import annotations

import threading

import numpy as np

from mono_map.mapping.kernel_threads import helper_pool, on_two_threads, settle, use_two_threads, zeroed_accumulator
from mono_map.mapping.raycast_c import dda_capacity

_WEIGHT_CHUNKS = 16      # distribution rays: chunks of groups shared out between the two threads


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
    if not use_two_threads(n) or len(groups) < 2:
        acc = zeroed_accumulator(0, box_size)
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

    acc_a, acc_b = zeroed_accumulator(0, box_size), zeroed_accumulator(1, box_size)
    future = helper_pool().submit(worker, acc_b)
    try:
        lin_a = worker(acc_a)
        lin_b = future.result()
        fresh = np.empty(len(lin_b), dtype=np.int64)
        m = fn.acc_merge(lin_b.ctypes.data, len(lin_b), acc_a.ctypes.data, acc_b.ctypes.data, fresh.ctypes.data)
        lin = np.concatenate([lin_a, fresh[:m]])
        return lin, _acc_take(fn, lin, acc_a)
    except BaseException:                # e.g. Ctrl-C: stop the other thread, then zero both buffers for the next frame
        cancel.set()
        settle(future)
        acc_a[:] = 0.0
        acc_b[:] = 0.0
        raise


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
    cap = dda_capacity(r["ke"][order[starts]], c["ko"]) + 2 * len(starts)     # one walk (+ end cell) per group
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

    on_two_threads(part, n)
    return out, far


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

    on_two_threads(rows, len(pr))
    keys = ("bad_p", "neg_p", "min_p", "bad_b", "neg_b", "min_b", "max_total")
    tot, low, high = stats.sum(axis=0), stats.min(axis=0), stats.max(axis=0)    # counts, minima, the max total
    vals = [tot[0], tot[1], low[2], tot[3], tot[4], low[5], high[6]]
    return dict(zip(keys, (float(v) for v in vals)), n_over=int(over.sum()))
