"""Placing objects beside the road path: the table of objects (colour, flags, facade parameters), a coarse
raster of the footprints already used, footprints kept clear of the road, the path's frame at an arc length.
World frame: the first cam0 frame (x right, y down, z forward); metres.
"""

from __future__ import annotations

import numpy as np

from mono_map.data.synth.trajectory import PathIndex, RoadPath

# object flags
BLACK = 1
BRICK = 2
STOREFRONT = 4
VAN = 8
LARGE = 16          # a large vehicle: box truck, bus, tanker, semi-trailer (mono_map.data.synth.traffic)


class ObjectTable:
    """The objects placed so far: per object its base colour, flags, facade texture origin and parameters
    (the arrays of :class:`mono_map.data.synth.town.Town`)."""

    def __init__(self):
        self.color, self.flags, self.origin, self.params = [], [], [], []

    def add(self, color, flags=0, origin=(0, 0, 0), params=(0, 0, 0, 0)) -> int:
        self.color.append(color)
        self.flags.append(flags)
        self.origin.append(origin)
        self.params.append(params)
        return len(self.color) - 1


class Occupancy:
    """Coarse raster (0.5 m) of footprints already used, so revisited streets are not built twice."""

    def __init__(self, index: PathIndex, res: float = 0.5):
        self.origin = index.origin
        self.res = res
        rows = int(index.shape[0] * index.res / res) + 2
        cols = int(index.shape[1] * index.res / res) + 2
        self.grid = np.zeros((rows, cols), bool)

    def _ij(self, xz):
        ij = np.floor((xz - self.origin) / self.res).astype(np.int64)
        return np.clip(ij, 0, [self.grid.shape[1] - 1, self.grid.shape[0] - 1])

    def free(self, xz) -> bool:
        ij = self._ij(xz)
        return not self.grid[ij[:, 1], ij[:, 0]].any()

    def mark(self, xz) -> None:
        ij = self._ij(xz)
        self.grid[ij[:, 1], ij[:, 0]] = True


def footprint_samples(center, f, r, half_len, half_wid, step=0.5):
    """x-z points (N, 2) every ``step`` metres over a rectangle about ``center`` spanned by ``f`` and ``r``."""
    a = np.arange(-half_len, half_len + 1e-9, step)
    b = np.arange(-half_wid, half_wid + 1e-9, step)
    a = np.unique(np.concatenate([a, [half_len]]))
    b = np.unique(np.concatenate([b, [half_wid]]))
    A, B = np.meshgrid(a, b)
    pts = center[None, :] + A.reshape(-1, 1) * f[None, :] + B.reshape(-1, 1) * r[None, :]
    return pts[:, [0, 2]]


def clear_of_road(index: PathIndex, xz: np.ndarray, clearance: float) -> bool:
    """Whether every (N, 2) x-z point is at least ``clearance`` metres from the road path."""
    return index.min_distance(xz) >= clearance


def frame_at(path: RoadPath, s: float):
    """(path sample index, point, forward, right) of the road path at arc length ``s`` (metres)."""
    k = int(np.clip(np.searchsorted(path.s, s), 0, len(path.s) - 1))
    return k, path.points[k], path.forward[k], path.right[k]


def box_axes(f, r):
    """3×3 box axes: the columns forward ``f``, +y (down), right ``r``."""
    return np.stack([f, np.array([0.0, 1.0, 0.0]), r], 1)
