"""Exact batched ray casting: OctoMap's per-scan free/occupied key sets, for a whole frame at once.

Reproduces ``OccupancyOcTreeBase::insertPointCloud(scan, origin, maxrange, lazy, discretize=True)``
of OctoMap 1.10 up to (but not including) the tree update:

* ``computeDiscreteUpdate``: end points are snapped to their cell centres and deduplicated;
* ``computeUpdate``: per end point the free cells of ``computeRayKeys(origin, end)`` (a 3-D DDA,
  Amanatides & Woo) and the end point's cell as occupied; rays longer than ``max_range`` are cut at
  ``max_range`` and mark free cells only;
* occupied wins over free; every cell appears once.

The arithmetic follows OctoMap's own types step by step — points are ``float32`` (``point3d``),
``tMax``/``tDelta`` are ``float64`` accumulated by repeated addition — so the key sets are identical,
not merely close. All rays of a frame advance together (numpy, one DDA step per loop iteration),
and cells are deduplicated with a bitmap over the frame's bounding box of keys.

Keys are OctoMap's 16-bit cell addresses (:mod:`mono_map.mapping.octree`); they are returned
as ``int64`` arrays of shape (N, 3). Coordinates are metres in the world frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mono_map.errors import MonoMapError
from mono_map.mapping.octree import (TREE_MAX_VAL, coord_to_key, key_bounds, key_in_range, key_to_coord, pack_keys,
                                     sorted_unique, unpack_keys)

_DBL_MAX = np.finfo(np.float64).max
_BITMAP_MAX_CELLS = 400_000_000  # bigger frame boxes fall back to sorting


@dataclass
class KeySets:
    """One frame's OctoMap update: disjoint sets of free and occupied cell keys (int64, (N, 3))."""

    free: np.ndarray
    occupied: np.ndarray
    n_rays: int = 0           # rays cast (after discretisation)
    n_endpoints: int = 0      # end points marked occupied (rays within max_range)
    lo: np.ndarray | None = None  # bounds of all keys (inclusive), when known
    hi: np.ndarray | None = None


def norm_f32(d: np.ndarray) -> np.ndarray:
    """``Vector3::norm()``: float32 sum of squares, sqrt in double."""
    sq = (d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1]) + d[:, 2] * d[:, 2]
    return np.sqrt(sq.astype(np.float64))


def discretize(points: np.ndarray, resolution: float) -> tuple[np.ndarray, np.ndarray]:
    """``computeDiscreteUpdate``'s first half: unique end-point keys and their float32 centres."""
    keys = coord_to_key(points, resolution)
    ok = key_in_range(keys)
    if not ok.all():
        raise MonoMapError(f"points: {int((~ok).sum())} end points lie outside OctoMap's addressable "
                           f"range (±{TREE_MAX_VAL * resolution:.0f} m at {resolution} m)")
    packed = np.sort(pack_keys(keys))          # sort-based unique (order is irrelevant to the sets)
    keys = unpack_keys(packed[np.r_[True, packed[1:] != packed[:-1]]])
    centres = key_to_coord(keys, resolution).astype(np.float32)
    return keys, centres


class KeyBox:
    """Dense linear indexing of keys inside an axis-aligned box of cells."""

    def __init__(self, lo: np.ndarray, hi: np.ndarray, margin: int = 2):
        self.lo = np.asarray(lo, dtype=np.int64) - margin
        self.dims = np.asarray(hi, dtype=np.int64) + margin + 1 - self.lo
        self.strides = np.array([self.dims[1] * self.dims[2], self.dims[2], 1], dtype=np.int64)
        self.size = int(np.prod(self.dims))

    def linear(self, keys: np.ndarray) -> np.ndarray:
        k = np.asarray(keys, dtype=np.int64)   # column by column: 4× faster than (keys - lo) @ strides
        return ((k[..., 0] - self.lo[0]) * self.strides[0] + (k[..., 1] - self.lo[1]) * self.strides[1]
                + (k[..., 2] - self.lo[2]))

    def keys(self, lin: np.ndarray) -> np.ndarray:
        from mono_map.mapping.raycast_c import box_keys_c, load_kernel

        lin = np.asarray(lin, dtype=np.int64)
        kernel = load_kernel()
        if kernel is not None:
            return box_keys_c(kernel, lin, self.lo, self.strides)
        k0, rem = _divmod(lin, int(self.strides[0]))
        k1, k2 = _divmod(rem, int(self.strides[1]))
        out = np.empty((len(lin), 3), dtype=np.int64)
        out[:, 0] = k0 + self.lo[0]
        out[:, 1] = k1 + self.lo[1]
        out[:, 2] = k2 + self.lo[2]
        return out


def _divmod(a: np.ndarray, b: int) -> tuple[np.ndarray, np.ndarray]:
    """Exact floor divmod of non-negative int64 (< 2**50) by a positive int, via float64 (faster than
    numpy's integer division); the float quotient is off by at most one and corrected."""
    q = (a * (1.0 / b)).astype(np.int64)
    r = a - q * b
    low = r < 0
    q[low] -= 1
    r[low] += b
    high = r >= b
    q[high] += 1
    r[high] -= b
    return q, r


def _ray_cells(origin32: np.ndarray, ends32: np.ndarray, resolution: float, box: KeyBox,
               key_origin: np.ndarray, mark: np.ndarray | None = None) -> np.ndarray:
    """Linear box indices of ``computeRayKeys(origin, end)`` for every end (free cells, with repeats;
    with ``mark``, which needs the compiled kernel: the distinct cells, marked 1 in ``mark``).

    All rays advance one DDA step per loop iteration. A ray can only stop near its end: it meets
    ``key_end`` exactly at step N = |Δkey|₁ (steps are monotone per axis), and ``min(tMax) > length``
    needs a crossing within float error of the end point, which only the last three crossings
    (one per axis) can be. So OctoMap's two stop tests run only from step N - 5 on; rays are sorted
    by N (descending) so that the rays being tested form a contiguous tail of the active prefix.
    """
    res = float(resolution)
    key_end = coord_to_key(ends32, res)
    from mono_map.mapping.raycast_c import load_kernel, ray_cells_c

    kernel = load_kernel()
    if mark is not None and kernel is None:
        raise ValueError("mark needs the compiled kernel")
    if kernel is not None:
        return ray_cells_c(kernel, origin32, key_origin, ends32, key_end, res, box.lo, box.strides, TREE_MAX_VAL,
                           mark)
    lin_origin = int(box.linear(key_origin[None, :])[0])
    moving = np.any(key_end != key_origin[None, :], axis=1)   # same cell: empty ray
    ends32, key_end = ends32[moving], key_end[moving]
    n = len(ends32)
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    n_steps = np.abs(key_end - key_origin[None, :]).sum(axis=1)
    order = np.argsort(-n_steps, kind="stable")
    ends32, key_end, n_steps = ends32[order], key_end[order], n_steps[order]
    lin_end = box.linear(key_end)

    d = ends32 - origin32[None, :]                   # float32
    length = norm_f32(d).astype(np.float32)         # (float) direction.norm()
    d = d / length[:, None]                          # float32 division (direction /= length)
    step = np.sign(d).astype(np.int64)
    o64 = origin32.astype(np.float64)
    d64 = d.astype(np.float64)
    border = key_to_coord(key_origin, res)[None, :] + (step * res * 0.5).astype(np.float32).astype(np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        t_max = np.where(step != 0, (border - o64[None, :]) / d64, _DBL_MAX)
        t_delta = np.where(step != 0, res / np.abs(d64), _DBL_MAX)
    dlin = step * box.strides[None, :]               # linear-index change per step, per axis

    t0, t1, t2 = (np.ascontiguousarray(t_max[:, i]) for i in range(3))
    dt0, dt1, dt2 = (np.ascontiguousarray(t_delta[:, i]) for i in range(3))
    s0, s1, s2 = (np.ascontiguousarray(dlin[:, i]) for i in range(3))
    cur = np.full(n, lin_origin, dtype=np.int64)
    lens = length.astype(np.float64)
    done = np.zeros(n, dtype=bool)
    # the check zone of step k: rays with n_steps <= k + MARGIN (a tail, since sorted descending)
    margin = 5
    neg_steps = -n_steps                             # ascending, for searchsorted
    buf = np.empty(int(n_steps.sum()) + 8 * n + 1, dtype=np.int64)
    buf[0] = lin_origin                              # every non-empty ray starts with the origin cell
    off = 1
    n_act = n
    k = 0
    while n_act:
        k += 1
        j0 = int(np.searchsorted(neg_steps, -(k + margin), side="left"))  # rays [0, j0) unchecked
        j0 = min(j0, n_act)
        a0, a1, a2 = t0[:n_act], t1[:n_act], t2[:n_act]
        c01 = a0 < a1
        m0 = c01 & (a0 < a2)
        m1 = (a1 < a2) > c01                         # not c01 and t1 < t2
        m2 = ~(m0 | m1)
        cur[:n_act] += np.where(m0, s0[:n_act], np.where(m1, s1[:n_act], s2[:n_act]))
        np.add(a0, dt0[:n_act], out=a0, where=m0)
        np.add(a1, dt1[:n_act], out=a1, where=m1)
        np.add(a2, dt2[:n_act], out=a2, where=m2)
        if j0:
            buf[off:off + j0] = cur[:j0]
            off += j0
        if j0 < n_act:
            z = slice(j0, n_act)
            stop = cur[z] == lin_end[z]
            stop |= np.minimum(np.minimum(t0[z], t1[z]), t2[z]) > lens[z]
            dz = done[z]
            dz |= stop
            emit = cur[z][~dz]
            if len(emit):
                if off + len(emit) > len(buf):
                    buf = np.concatenate([buf, np.empty(len(buf), dtype=np.int64)])
                buf[off:off + len(emit)] = emit
                off += len(emit)
            # drop finished rays from the end of the active prefix
            live = np.flatnonzero(~dz)
            n_act = j0 + (int(live[-1]) + 1 if len(live) else 0)
    return buf[:off]


def _check_in_box(lin: np.ndarray, box: KeyBox) -> None:
    if len(lin) and (lin.min() < 0 or lin.max() >= box.size):
        raise AssertionError("ray left its bounding box")  # cannot happen: the margin covers DDA overshoot


def cut_at_range(ends32: np.ndarray, origin32: np.ndarray, max_range: float | None) -> tuple[np.ndarray, np.ndarray]:
    """OctoMap's max-range rule for float32 ray ends (N, 3): (ends with the too-long ones moved to
    ``origin + direction · max_range``, float32; bool (N,) rays within range). max_range < 0 or None: no limit."""
    if max_range is None or max_range < 0:
        return ends32, np.ones(len(ends32), dtype=bool)
    d = ends32 - origin32[None, :]
    inside = norm_f32(d) <= max_range
    out = ends32.copy()
    if not inside.all():
        dfar = d[~inside]
        nrm = norm_f32(dfar).astype(np.float32)
        out[~inside] = (origin32[None, :] + (dfar / nrm[:, None]) * np.float32(max_range)).astype(np.float32)
    return out, inside


def compute_update(points: np.ndarray, origin: np.ndarray, resolution: float,
                   max_range: float = -1.0, discretize_points: bool = True) -> KeySets:
    """Free and occupied key sets of one scan, exactly as OctoMap's ``insertPointCloud`` computes them.

    points: (N, 3) end points, world frame, metres; origin: (3,) sensor origin (world);
    max_range < 0 = unlimited. With ``discretize_points=False`` the rays go to the raw end points
    (OctoMap's ``computeUpdate`` without ``computeDiscreteUpdate``).
    """
    res = float(resolution)
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if not np.isfinite(pts).all():
        raise MonoMapError("points: non-finite coordinates (NaN or inf) in the scan")
    origin32 = np.asarray(origin, dtype=np.float64).reshape(3).astype(np.float32)
    key_origin = coord_to_key(origin32[None, :], res)[0]
    if not key_in_range(key_origin[None, :])[0]:
        raise MonoMapError(f"origin: {origin32.tolist()} is outside OctoMap's addressable range")
    empty = np.zeros((0, 3), dtype=np.int64)
    if len(pts) == 0:
        return KeySets(empty, empty.copy())
    from mono_map.mapping.raycast_c import load_kernel

    kernel = load_kernel()
    if kernel is not None:
        ks = _compute_update_c(kernel, pts, origin32, key_origin, res, max_range, discretize_points)
        if ks is not None:
            return ks
    if discretize_points:
        _, ends = discretize(pts, res)
    else:
        ends = pts.astype(np.float32)
        ok = key_in_range(coord_to_key(ends, res))
        if not ok.all():
            raise MonoMapError(f"points: {int((~ok).sum())} end points lie outside OctoMap's addressable range")
    n_rays = len(ends)

    # max range: long rays are cut (free cells only, no occupied end point)
    cut, inside = cut_at_range(ends, origin32, max_range)
    ray_ends = np.concatenate([ends[inside], cut[~inside]]) if not inside.all() else ends
    occ_ends = ends[inside]

    occ_keys = coord_to_key(occ_ends, res)
    ray_end_keys = coord_to_key(ray_ends, res)
    occ_keys = occ_keys[key_in_range(occ_keys)]
    ok = key_in_range(ray_end_keys)
    ray_ends, ray_end_keys = ray_ends[ok], ray_end_keys[ok]
    all_keys = np.concatenate([ray_end_keys, occ_keys, key_origin[None, :]])
    box = KeyBox(*key_bounds(all_keys))

    occ_lin = box.linear(occ_keys) if len(occ_keys) else np.zeros(0, np.int64)
    if box.size <= _BITMAP_MAX_CELLS:
        from mono_map.mapping.raycast_c import load_kernel

        mark = np.zeros(box.size, dtype=np.uint8)
        if load_kernel() is not None:              # distinct cells straight from the kernel
            free_lin = _ray_cells(origin32, ray_ends, res, box, key_origin, mark=mark)
        else:                                      # numpy: repeats; dedup through the bitmap
            free_lin = _ray_cells(origin32, ray_ends, res, box, key_origin)
            _check_in_box(free_lin, box)
            mark[free_lin] = 1
            free_lin = np.flatnonzero(mark)
        mark[occ_lin] = 2                          # occupied wins
        free_u = free_lin[mark[free_lin] == 1]
        occ_u = sorted_unique(occ_lin)
    else:
        free_lin = _ray_cells(origin32, ray_ends, res, box, key_origin)
        _check_in_box(free_lin, box)
        occ_u = sorted_unique(occ_lin)
        free_u = np.setdiff1d(sorted_unique(free_lin), occ_u, assume_unique=True)
    return KeySets(free=box.keys(free_u), occupied=box.keys(occ_u), n_rays=n_rays, n_endpoints=len(occ_u),
                   lo=box.lo, hi=box.lo + box.dims - 1)


def frame_keys(kernel, pts: np.ndarray, key_origin: np.ndarray, res: float):
    """A frame's end points for the compiled ray casts (here and in
    :func:`mono_map.mapping.nested.compute_nested_updates`): (float32 points, keys (N, 3), the frame's KeyBox
    with the origin, its zeroed reused bitmap), or None when the box is too large for a bitmap; MonoMapError
    for points outside OctoMap's addressable range."""
    from mono_map.mapping.kernel_threads import zeroed_bitmap
    from mono_map.mapping.raycast_c import point_keys_c

    pts32, keys, lo, hi, n_out = point_keys_c(kernel, pts, res, TREE_MAX_VAL)
    if n_out:
        raise MonoMapError(f"points: {n_out} end points lie outside OctoMap's addressable "
                           f"range (±{TREE_MAX_VAL * res:.0f} m at {res} m)")
    box = KeyBox(np.minimum(lo, key_origin), np.maximum(hi, key_origin))
    if box.size > _BITMAP_MAX_CELLS:
        return None
    return pts32, keys, box, zeroed_bitmap(box.size)


def _compute_update_c(kernel, pts: np.ndarray, origin32: np.ndarray, key_origin: np.ndarray, res: float,
                      max_range: float, discretize_points: bool) -> KeySets | None:
    """:func:`compute_update` with the compiled kernel throughout (None: box too large for a bitmap).

    One bitmap over the frame's box of keys (reused across frames): the end points' keys are
    deduplicated through it, marking the occupied cells 2 (``computeDiscreteUpdate``); the rays then
    mark and emit only cells still 0 — the free cells minus the occupied ones (occupied wins), each once.
    """
    from mono_map.mapping.raycast_c import ray_cells_c, unique_cells_c

    framed = frame_keys(kernel, pts, key_origin, res)
    if framed is None:
        return None
    pts32, keys, box, mark = framed
    try:
        if discretize_points:            # one ray per distinct end cell, to the cell's centre
            rows, ends = unique_cells_c(kernel, keys, box.lo, box.strides, mark, res, TREE_MAX_VAL)
            end_keys = keys[rows]
        else:
            ends, end_keys = pts32, keys
        n_rays = len(ends)
        inside = None
        if max_range is not None and max_range >= 0:
            ray_ends, inside = cut_at_range(ends, origin32, max_range)
            if inside.all():
                inside = None
            else:                        # cut rays: free cells only, cast to the cut point
                ray_keys = end_keys.copy()
                ray_keys[~inside] = coord_to_key(ray_ends[~inside], res)
        if inside is None:
            ray_ends, ray_keys, occ_keys = ends, end_keys, end_keys
        else:
            occ_keys = end_keys[inside]
        if discretize_points:
            occ_lin = box.linear(end_keys)
            if inside is not None:
                mark[occ_lin[~inside]] = 0   # not occupied after all
                occ_lin = occ_lin[inside]
        else:                            # raw ends: the occupied cells are their distinct keys
            rows, _ = unique_cells_c(kernel, occ_keys, box.lo, box.strides, mark, res, TREE_MAX_VAL, centres=False)
            occ_keys = occ_keys[rows]
            occ_lin = box.linear(occ_keys)
        free_lin = ray_cells_c(kernel, origin32, key_origin, ray_ends, ray_keys, res, box.lo, box.strides,
                               TREE_MAX_VAL, mark)
    except BaseException:
        mark[:] = 0                      # marks of unknown extent: zero all before the next frame
        raise
    mark[free_lin] = 0                   # leave the reused bitmap zeroed
    mark[occ_lin] = 0
    free = box.keys(free_lin)
    return KeySets(free=free, occupied=occ_keys, n_rays=n_rays, n_endpoints=len(occ_keys),
                   lo=box.lo, hi=box.lo + box.dims - 1)
