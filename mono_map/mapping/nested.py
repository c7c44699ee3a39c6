"""Keep maps of one frame that share one ray cast (the demo's keep 0.8 and 1.0, ``eval --table``'s keep sweep).

A keep map keeps the ``round(keep · n_valid)`` lowest-score valid pixels of a frame (ties in raster order,
:func:`mono_map.mapping.select.select_pixels`), so the kept pixels of the keeps of one prediction nest:
keep 0.8's are among keep 1.0's. :func:`nested_frame` selects them for every keep, back-projects the
largest keep's pixels once and casts each distinct end cell's ray once
(:func:`mono_map.mapping.raycast.compute_nested_updates`); each map's key sets are exactly those of its own
scan, so the maps are the ones built one by one.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mono_map.errors import MonoMapError
from mono_map.mapping.points import camera_origin, pixels_to_world
from mono_map.mapping.raycast import KeySets, compute_nested_updates
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
