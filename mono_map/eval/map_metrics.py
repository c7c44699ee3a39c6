"""Map-vs-reference metrics at the finest resolution, weighted by volume (every finest cell counts once).

The paper (Table IV): "a cell counts as correctly mapped if it has the same state (free or
occupied) as the LiDAR map". Here, exactly:

* the cells are the finest-resolution cells (``res``³) of the reference's known space; pruned
  leaves count with all the finest cells they cover (volume weighting, computed exactly);
* ``accuracy`` = cells whose state the map reproduces / reference known cells — a cell the map
  does not know counts as wrong;
* ``coverage`` = reference known cells the map knows; ``accuracy_covered`` = accuracy over those;
* occupied ``precision`` = reference-known cells occupied in both / reference-known cells the map
  has occupied; ``recall`` = occupied in both / occupied in the reference; ``f1`` their harmonic mean.

States are maximum-likelihood: occupied iff log-odds ≥ the tree's occupancy threshold. Both trees
must have the same resolution (the cell grids then coincide). The comparison walks both trees'
leaves once and intersects them as intervals of Morton (Z-order) codes, where every octree node
is one contiguous interval — exact and vectorised.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mono_map.errors import MonoMapError
from mono_map.mapping.raycast import TREE_MAX_VAL, _spread_bits
from mono_map.mapping.raycast import sorted_unique

TREE_DEPTH = 16


@dataclass
class Leaves:
    """A tree's leaves as Morton intervals: start code, length in finest cells, occupied flag."""

    start: np.ndarray     # int64, sorted
    length: np.ndarray    # int64
    occupied: np.ndarray  # bool
    resolution: float
    value: np.ndarray | None = None   # float log-odds per leaf

    @property
    def cells(self) -> int:
        return int(self.length.sum())

    def expand(self) -> tuple[np.ndarray, np.ndarray]:
        """Every finest cell: (Morton codes, leaf index), codes sorted."""
        total = int(self.length.sum())
        leaf = np.repeat(np.arange(len(self.start)), self.length)
        offset = np.arange(total) - np.repeat(np.cumsum(self.length) - self.length, self.length)
        return self.start[leaf] + offset, leaf



def load_tree(path: str | Path):
    """Read a .bt / .ot file into an ``octomap.OcTree``; MonoMapError if missing or not an OctoMap
    (OctoMap's own messages about a corrupt file are captured, not printed)."""
    import octomap

    from mono_map.io import quiet_native_output

    path = Path(path)
    if not path.is_file():
        raise MonoMapError(f"{path}: map file not found")
    with open(path, "rb") as fh:
        head = fh.read(4096)
    if not head.startswith(b"# Octomap OcTree"):
        raise MonoMapError(f"{path}: not an OctoMap file (.bt/.ot header missing)")
    header = head.split(b"\ndata\n", 1)
    if len(header) != 2 or not header[0].isascii():
        raise MonoMapError(f"{path}: corrupt OctoMap header (no 'data' line after the header's text lines)")
    with quiet_native_output() as said:
        if path.suffix == ".ot":
            tree = octomap.OcTree.read(str(path).encode())
        else:
            tree = octomap.OcTree(0.1)
            if not tree.readBinary(str(path).encode()):
                tree = None
    if tree is None:
        first = next((ln.strip() for ln in said[0].splitlines() if ln.strip()), "")
        raise MonoMapError(f"{path}: OctoMap could not read this tree" + (f" ({first[:120]})" if first else ""))
    return tree


def morton_codes(keys: np.ndarray) -> np.ndarray:
    k = np.asarray(keys, dtype=np.int64)
    code = (_spread_bits(k[:, 0]) << np.uint64(2)) | (_spread_bits(k[:, 1]) << np.uint64(1)) | _spread_bits(k[:, 2])
    return code.astype(np.int64)


def tree_leaves(tree) -> Leaves:
    """All leaves of an ``octomap.OcTree`` as Morton intervals (one pass of the leaf iterator)."""
    res = float(tree.getResolution())
    thr = float(tree.getOccupancyThresLog())
    n = int(tree.getNumLeafNodes())
    xyz = np.empty((n, 3), dtype=np.float64)
    depth = np.empty(n, dtype=np.int64)
    value = np.empty(n, dtype=np.float64)
    i = 0
    for it in tree.begin_leafs():
        if i >= n:
            break
        xyz[i, 0] = it.getX()
        xyz[i, 1] = it.getY()
        xyz[i, 2] = it.getZ()
        depth[i] = it.getDepth()
        value[i] = it.getValue()
        i += 1
    xyz, depth, value = xyz[:i], depth[:i], value[:i]
    side = (1 << (TREE_DEPTH - depth)).astype(np.int64)          # cells per side
    size = side * res
    corner = xyz - size[:, None] / 2 + res / 2                     # centre of the min-corner cell
    keys = np.round(corner / res - 0.5).astype(np.int64) + TREE_MAX_VAL
    keys -= keys % side[:, None]                                   # align (guards rounding)
    start = morton_codes(keys)
    order = np.argsort(start, kind="stable")
    return Leaves(start=start[order], length=(side ** 3)[order], occupied=(value >= thr)[order], resolution=res,
                  value=value[order])


def _state_at(leaves: Leaves, points: np.ndarray) -> np.ndarray:
    """-1 unknown / 0 free / 1 occupied at Morton codes ``points``."""
    idx = np.searchsorted(leaves.start, points, side="right") - 1
    ok = idx >= 0
    idx_c = np.clip(idx, 0, None)
    inside = ok & (points < leaves.start[idx_c] + leaves.length[idx_c]) if len(leaves.start) else np.zeros(len(points), bool)
    out = np.full(len(points), -1, dtype=np.int8)
    if len(leaves.start):
        out[inside] = leaves.occupied[idx_c[inside]].astype(np.int8)
    return out


def compare_leaves(map_leaves: Leaves, ref_leaves: Leaves) -> dict:
    """Volume-weighted cell-state comparison of a map against a reference (see module docstring)."""
    if not np.isclose(map_leaves.resolution, ref_leaves.resolution):
        raise MonoMapError(f"map resolution {map_leaves.resolution} m differs from the reference's "
                           f"{ref_leaves.resolution} m: cell grids do not coincide")
    bounds = sorted_unique(np.concatenate([map_leaves.start, map_leaves.start + map_leaves.length,
                                       ref_leaves.start, ref_leaves.start + ref_leaves.length]))
    seg_start, seg_len = bounds[:-1], np.diff(bounds)
    m = _state_at(map_leaves, seg_start)
    r = _state_at(ref_leaves, seg_start)
    w = seg_len.astype(np.float64)

    def total(mask):
        return float(w[mask].sum())

    ref_known = r >= 0
    both = ref_known & (m >= 0)
    same = both & (m == r)
    n_ref = total(ref_known)
    n_both = total(both)
    tp = total((m == 1) & (r == 1))
    map_occ = total((m == 1) & ref_known)
    ref_occ = total(r == 1)
    prec = tp / map_occ if map_occ else 0.0
    rec = tp / ref_occ if ref_occ else 0.0
    return {
        "ref_known_cells": int(n_ref), "ref_occupied_cells": int(ref_occ), "ref_free_cells": int(total(r == 0)),
        "map_known_cells": int(total(m >= 0)), "map_occupied_cells": int(total(m == 1)),
        "covered_cells": int(n_both), "correct_cells": int(total(same)),
        "accuracy": total(same) / n_ref if n_ref else 0.0,
        "coverage": n_both / n_ref if n_ref else 0.0,
        "accuracy_covered": total(same) / n_both if n_both else 0.0,
        "free_accuracy": total(same & (r == 0)) / total(r == 0) if total(r == 0) else 0.0,
        "precision": prec, "recall": rec,
        "f1": 2 * prec * rec / (prec + rec) if prec + rec else 0.0,
        "false_occupied_cells": int(total((m == 1) & (r == 0))),
        "missed_occupied_cells": int(total((m == 0) & (r == 1))),
    }


def tree_summary(tree) -> dict:
    mem = int(tree.memoryUsage())
    return {"leaf_count": int(tree.getNumLeafNodes()), "memory_bytes": mem, "memory_mb": mem / 2**20,
            "resolution": float(tree.getResolution())}


def evaluate_map(map_tree, ref_tree) -> dict:
    """Metrics of ``map_tree`` against ``ref_tree`` plus both trees' size (memoryUsage of the loaded trees)."""
    out = compare_leaves(tree_leaves(map_tree), tree_leaves(ref_tree))
    out["map"] = tree_summary(map_tree)
    out["reference"] = tree_summary(ref_tree)
    return out


def _compact_bits(x: np.ndarray) -> np.ndarray:
    """Inverse of ``_spread_bits``: every third bit of x, packed (for Morton decoding)."""
    x = x.astype(np.uint64) & np.uint64(0x1249249249249249)
    for shift, mask in ((2, 0x10C30C30C30C30C3), (4, 0x100F00F00F00F00F), (8, 0x1F0000FF0000FF),
                        (16, 0x1F00000000FFFF), (32, 0x1FFFFF)):
        x = (x | (x >> np.uint64(shift))) & np.uint64(mask)
    return x.astype(np.int64)


def morton_to_keys(codes: np.ndarray) -> np.ndarray:
    """(N, 3) int64 keys of Morton codes (inverse of :func:`morton_codes`)."""
    c = np.asarray(codes, dtype=np.int64).astype(np.uint64)
    return np.stack([_compact_bits(c >> np.uint64(2)), _compact_bits(c >> np.uint64(1)), _compact_bits(c)], axis=1)


def occupied_keys(leaves: Leaves) -> np.ndarray:
    """Keys ((N, 3) int64) of every finest cell inside an occupied leaf."""
    occ = Leaves(leaves.start[leaves.occupied], leaves.length[leaves.occupied], leaves.occupied[leaves.occupied],
                 leaves.resolution)
    codes, _ = occ.expand()
    return morton_to_keys(codes)


def _pack(keys: np.ndarray) -> np.ndarray:
    return (keys[:, 0] << 34) | (keys[:, 1] << 17) | keys[:, 2]


def surface_precision(map_leaves: Leaves, surface_leaves: Leaves) -> dict:
    """Share of the map's occupied finest cells within one cell (26-neighbourhood) of an occupied cell of
    ``surface_leaves`` (the camera ground-truth ``depth-gt`` map): how much of what the map calls a
    surface lies on a true one. Volume-weighted like the other metrics."""
    if not np.isclose(map_leaves.resolution, surface_leaves.resolution):
        raise MonoMapError(f"map resolution {map_leaves.resolution} m differs from the surface map's "
                           f"{surface_leaves.resolution} m")
    mk = occupied_keys(map_leaves)
    truth = np.sort(_pack(occupied_keys(surface_leaves) + 1))       # +1: neighbours of key 0 stay >= 0
    near = np.zeros(len(mk), dtype=bool)
    if len(truth):
        for off in np.stack(np.meshgrid([0, 1, 2], [0, 1, 2], [0, 1, 2], indexing="ij"), -1).reshape(-1, 3):
            q = _pack(mk + off)
            i = np.clip(np.searchsorted(truth, q), 0, len(truth) - 1)
            near |= truth[i] == q
    return {"surface_precision": float(near.mean()) if len(mk) else 0.0, "occupied_cells": int(len(mk)),
            "surface_cells": int(len(truth)), "on_surface_cells": int(near.sum())}


def _value_at(leaves: Leaves, points: np.ndarray) -> np.ndarray:
    """Log-odds at Morton codes ``points`` (NaN where unknown)."""
    out = np.full(len(points), np.nan)
    if not len(leaves.start):
        return out
    idx = np.searchsorted(leaves.start, points, side="right") - 1
    idx_c = np.clip(idx, 0, None)
    inside = (idx >= 0) & (points < leaves.start[idx_c] + leaves.length[idx_c])
    out[inside] = leaves.value[idx_c[inside]]
    return out


def calibration(map_leaves: Leaves, ref_leaves: Leaves, n_bins: int = 10) -> dict:
    """Reliability of a probabilistic map against a reference's states, over the cells both know
    (volume-weighted): the map's occupancy probabilities sigmoid(log-odds) in ``n_bins`` equal bins of
    [0, 1]; per bin the mean probability (confidence), the share of cells the reference has occupied
    (frequency) and the weight; ``ece`` = Σ weight·|frequency − confidence|. Needs the map's real
    log-odds (a ``.ot`` tree: ``.bt`` keeps only max-likelihood states)."""
    if not np.isclose(map_leaves.resolution, ref_leaves.resolution):
        raise MonoMapError(f"map resolution {map_leaves.resolution} m differs from the reference's "
                           f"{ref_leaves.resolution} m: cell grids do not coincide")
    bounds = sorted_unique(np.concatenate([map_leaves.start, map_leaves.start + map_leaves.length,
                                       ref_leaves.start, ref_leaves.start + ref_leaves.length]))
    seg, w = bounds[:-1], np.diff(bounds).astype(np.float64)
    value = _value_at(map_leaves, seg)
    ref = _state_at(ref_leaves, seg)
    both = ~np.isnan(value) & (ref >= 0)
    p = 1.0 / (1.0 + np.exp(-value[both]))
    occ = (ref[both] == 1).astype(np.float64)
    w = w[both]
    b = np.clip((p * n_bins).astype(np.int64), 0, n_bins - 1)
    weight = np.bincount(b, weights=w, minlength=n_bins)
    conf = np.bincount(b, weights=w * p, minlength=n_bins)
    freq = np.bincount(b, weights=w * occ, minlength=n_bins)
    with np.errstate(invalid="ignore", divide="ignore"):
        conf, freq = conf / weight, freq / weight
    total = weight.sum()
    share = weight / total if total else weight
    ece = float(np.nansum(share * np.abs(freq - conf)))
    return {"ece": ece, "bin_edges": np.linspace(0, 1, n_bins + 1).tolist(), "confidence": conf.tolist(),
            "frequency": freq.tolist(), "weight": share.tolist(), "cells": int(total)}
