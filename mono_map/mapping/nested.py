"""Keep maps of one frame that share one ray cast (the demo's keep 0.8 and 1.0, ``eval --table``'s keep sweep).

A keep map keeps the ``round(keep · n_valid)`` lowest-score valid pixels of a frame (ties in raster order,
:func:`mono_map.mapping.select.select_pixels`), so the kept pixels of the keeps of one prediction nest:
keep 0.8's are among keep 1.0's. :func:`nested_frame` selects them for every keep, back-projects the
largest keep's pixels once and casts each distinct end cell's ray once
(:func:`compute_nested_updates`); each map's key sets are exactly those of its own
scan, so the maps are the ones built one by one.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mono_map.errors import MonoMapError
from mono_map.mapping.octree import TREE_MAX_VAL, coord_to_key, key_in_range
from mono_map.mapping.points import camera_origin, pixels_to_world
from mono_map.mapping.raycast import KeySets, compute_update, frame_keys
from mono_map.mapping.select import select_pixels


@dataclass(frozen=True)
class KeepGroup:
    """The keeps (ascending, distinct) of the keep maps that share a frame's ray cast, and what they share:
    ``key`` names the prediction, ranking, stride, depth range and cell size (equal keys, equal pixels)."""

    keeps: tuple[float, ...]
    key: tuple

    def level(self, keep: float) -> int:
        """Index of ``keep`` in :attr:`keeps`."""
        return self.keeps.index(keep)


@dataclass
class NestedFrame:
    """One frame of a :class:`KeepGroup`: per keep its kept-pixel mask and key sets; the largest keep's
    world points (metres, raster order) with the level from which each is kept."""

    masks: list[np.ndarray]          # H×W bool per keep, ascending keeps
    valid: np.ndarray                # H×W bool, valid pixels
    points: np.ndarray               # (N, 3) float64, the largest keep's kept pixels back-projected
    levels: np.ndarray               # (N,) uint8: index of the smallest keep that keeps the point
    key_sets: list[KeySets]          # per keep, as compute_update of that keep's points

    def points_of(self, level: int) -> np.ndarray:
        """(M, 3) world points of the keep at ``level`` (raster order, as ``pixels_to_world`` of its mask)."""
        return np.compress(self.levels <= level, self.points, axis=0)


def nested_frame(depth: np.ndarray, score: np.ndarray, keeps: tuple[float, ...], depth_range: tuple[float, float],
                 stride: int, p_beyond: np.ndarray | None, K: np.ndarray, T_world_cam2: np.ndarray,
                 resolution: float) -> NestedFrame:
    """Masks, points and key sets of the keeps ``keeps`` (ascending) of one predicted frame: depth (H×W
    metres, z), score (H×W, lower = more confident), p_beyond (H×W or None) as for ``select_pixels``;
    K (3×3) and ``T_world_cam2`` (4×4, camera → world) back-project; ``resolution`` is the cell size (m)."""
    if list(keeps) != sorted(set(keeps)) or not keeps:
        raise MonoMapError(f"keeps: must be distinct and ascending, got {keeps}")
    masks, valid = [], None
    for k in keeps:
        mask, valid = select_pixels(depth, score, k, *depth_range, stride=stride, return_valid=True,
                                    p_beyond=p_beyond)
        masks.append(mask)
    level_img = np.full(masks[-1].shape, 255, dtype=np.uint8)
    for j in range(len(keeps) - 1, -1, -1):
        level_img[masks[j]] = j
    points = pixels_to_world(depth, masks[-1], K, T_world_cam2)
    levels = level_img[masks[-1]]
    key_sets = compute_nested_updates(points, levels, len(keeps), camera_origin(T_world_cam2), resolution)
    return NestedFrame(masks, valid, points, levels, key_sets)


def compute_nested_updates(points: np.ndarray, levels: np.ndarray, n_levels: int, origin: np.ndarray,
                           resolution: float) -> list[KeySets]:
    """The key sets of nested scans in one ray cast: entry j is ``compute_update(points[levels <= j], origin,
    resolution)`` (the same free and occupied sets; unlimited range, discretised end points), for j = 0 …
    ``n_levels`` − 1.

    points: (N, 3) world end points, metres; levels: (N,) ints in [0, n_levels) — a point belongs to every
    scan from its level on (e.g. the keep 0.8 pixels at level 0, the rest of keep 1.0 at level 1). Each
    distinct end cell's ray is cast once, at the lowest level that has it; a cell's first ray gives the level
    from which it is free, and end cells of later levels leave the free sets from their level on. Without
    the compiled kernel (or for a huge frame box) every scan is computed on its own.
    """
    n_levels = int(n_levels)
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    levels = np.asarray(levels).reshape(-1)
    if not 1 <= n_levels < 255:
        raise MonoMapError(f"n_levels: must be 1…254, got {n_levels}")
    if len(levels) != len(pts):
        raise MonoMapError(f"levels: {len(levels)} levels for {len(pts)} points")
    if len(pts) and (levels.min() < 0 or levels.max() >= n_levels):
        raise MonoMapError(f"levels: must lie in [0, {n_levels}), got {levels.min()}…{levels.max()}")
    if not np.isfinite(pts).all():
        raise MonoMapError("points: non-finite coordinates (NaN or inf) in the scan")
    from mono_map.mapping.raycast_c import load_kernel

    kernel = load_kernel()
    res = float(resolution)
    origin32 = np.asarray(origin, dtype=np.float64).reshape(3).astype(np.float32)
    key_origin = coord_to_key(origin32[None, :], res)[0]
    out = None
    if kernel is not None and len(pts) and key_in_range(key_origin[None, :])[0]:
        out = _nested_updates_c(kernel, pts, levels, n_levels, origin32, key_origin, res)
    if out is None:
        out = [compute_update(pts[levels <= j], origin, res) for j in range(n_levels)]
    return out


def _nested_updates_c(kernel, pts: np.ndarray, levels: np.ndarray, n_levels: int, origin32: np.ndarray,
                      key_origin: np.ndarray, res: float) -> list[KeySets] | None:
    """:func:`compute_nested_updates` with the compiled kernel (None: box too large for a bitmap).

    The bitmap over the frame's box (reused across frames) holds 2 for the end cells of the levels cast so
    far and 1 for cells already emitted as free; level by level, that level's new end cells are marked 2
    and its rays emit only cells still 0 (the kernel of :func:`mono_map.mapping.raycast.compute_update`,
    unchanged)."""
    from mono_map.mapping.raycast_c import ray_cells_c, unique_cells_c

    framed = frame_keys(kernel, pts, key_origin, res)
    if framed is None:
        return None
    _, keys, box, mark = framed
    try:
        # each level's distinct end cells not at a lower level (unique_cells skips cells already marked 2)
        ends, end_keys, n_ends = [], [], []
        for j in range(n_levels):
            kj = np.compress(levels == j, keys, axis=0)
            rows, cen = unique_cells_c(kernel, kj, box.lo, box.strides, mark, res, TREE_MAX_VAL)
            ends.append(cen)
            end_keys.append(kj[rows])
            n_ends.append(len(rows))
        end_keys = np.concatenate(end_keys)
        end_lin = box.linear(end_keys)
        starts = np.r_[0, np.cumsum(n_ends)]
        mark[end_lin] = 0
        parts = []
        for j in range(n_levels):
            a, b = starts[j], starts[j + 1]
            mark[end_lin[a:b]] = 2                # occupied from this level on
            parts.append(ray_cells_c(kernel, origin32, key_origin, ends[j], end_keys[a:b], res, box.lo,
                                     box.strides, TREE_MAX_VAL, mark) if b > a else np.zeros(0, np.int64))
        free_all = np.concatenate(parts)
        mark[free_all] = 0
        for j in range(n_levels):                 # 1 + the level from which a cell is an end cell
            mark[end_lin[starts[j]:starts[j + 1]]] = j + 1
        end_level = mark[free_all]                # 0: never an end cell
    except BaseException:
        mark[:] = 0                      # marks of unknown extent: zero all before the next frame
        raise
    mark[end_lin] = 0                    # leave the reused bitmap zeroed (free cells were zeroed above)
    cuts = np.cumsum([len(p) for p in parts])   # by level: level j's free cells are a prefix less some end cells
    out = []
    for j in range(n_levels):
        n_end, cut = int(starts[j + 1]), int(cuts[j])
        sub = end_level[:cut]
        ok = (sub == 0) | (sub > j + 1)  # not an end cell of a level <= j
        lin = free_all[:cut] if ok.all() else np.compress(ok, free_all[:cut])
        out.append(KeySets(free=box.keys(lin), occupied=end_keys[:n_end], n_rays=n_end, n_endpoints=n_end,
                           lo=box.lo, hi=box.lo + box.dims - 1))
    return out
