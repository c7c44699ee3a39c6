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

import numpy as np

from mono_map.errors import MonoMapError
from mono_map.mapping.octree import Leaves, occupied_keys, sorted_unique, tree_leaves


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


def _pack(keys: np.ndarray) -> np.ndarray:
    return (keys[:, 0] << 34) | (keys[:, 1] << 17) | keys[:, 2]


def surface_precision(map_leaves: Leaves, surface_leaves: Leaves) -> dict:
    """Share of the map's occupied finest cells within one cell (26-neighbourhood) of an occupied cell of
    ``surface_leaves`` (the camera ground-truth ``depth-gt`` map): how much of what the map calls a
    surface lies on a true one. Volume-weighted like the other metrics."""
    if not np.isclose(map_leaves.resolution, surface_leaves.resolution):
        raise MonoMapError(f"map resolution {map_leaves.resolution} m differs from the surface map's "
                           f"{surface_leaves.resolution} m")
    mk, surface = occupied_keys(map_leaves), occupied_keys(surface_leaves)
    near = near_surface(mk, surface)
    return {"surface_precision": float(near.mean()) if len(mk) else 0.0, "occupied_cells": int(len(mk)),
            "surface_cells": int(len(surface)), "on_surface_cells": int(near.sum())}


def near_surface(keys: np.ndarray, surface_keys: np.ndarray) -> np.ndarray:
    """(N,) bool: whether each cell of ``keys`` (N, 3 OctoMap keys) lies within one cell (26-neighbourhood) of
    a cell of ``surface_keys`` (M, 3; e.g. a depth-gt map's ``occupied_keys``)."""
    truth = np.sort(_pack(surface_keys + 1))                        # +1: neighbours of key 0 stay >= 0
    near = np.zeros(len(keys), dtype=bool)
    if len(truth):
        for off in np.stack(np.meshgrid([0, 1, 2], [0, 1, 2], [0, 1, 2], indexing="ij"), -1).reshape(-1, 3):
            q = _pack(keys + off)
            i = np.clip(np.searchsorted(truth, q), 0, len(truth) - 1)
            near |= truth[i] == q
    return near


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
