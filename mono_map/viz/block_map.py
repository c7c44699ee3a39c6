"""The occupied cells a viewer shows, kept per spatial block: a frame's changes applied to their blocks, the
blocks they touched returned for re-logging (:class:`~mono_map.viz.rerun_stream.RerunMapLogger`). Cells are
packed integer cell indices (:func:`mono_map.viz.codec.pack`); no rerun here.
"""

from __future__ import annotations

import numpy as np

from mono_map.viz.codec import group_by_block, sorted_difference, sorted_union, unpack


class BlockMap:
    """For every spatial block of ``block_cells`` cells per side, the sorted set of its occupied cells (and,
    ``by_prob``, one float32 occupancy probability per cell, NaN until an update gives it)."""

    def __init__(self, block_cells: int, by_prob: bool = False) -> None:
        self.block_cells = int(block_cells)
        self.by_prob = by_prob
        self.blocks: dict[int, np.ndarray] = {}   # packed block index → sorted packed cell indices
        self.probs: dict[int, np.ndarray] = {}    # by_prob: float32 per cell of blocks
        self.map_cells = 0

    def apply(self, add: np.ndarray, rem: np.ndarray, prob: tuple[np.ndarray, np.ndarray] | None) -> set[int]:
        """One frame's changes: packed cells that became occupied (``add``) and stopped being occupied
        (``rem``), then (packed cells, probabilities) of the cells whose probability changed (or None).
        Returns the packed indices of the blocks whose drawing changed."""
        touched: set[int] = set()
        for keys, adding in ((add, True), (rem, False)):
            for bk, pos in group_by_block(unpack(keys), self.block_cells):
                kb = keys[pos]
                old = self.blocks.get(bk)
                old = old if old is not None else np.zeros(0, np.int64)
                new = sorted_union(old, kb) if adding else sorted_difference(old, kb)
                self.map_cells += len(new) - len(old)
                if self.by_prob:
                    self.probs[bk] = carry_values(old, self.probs.get(bk), new)
                if len(new):
                    self.blocks[bk] = new
                else:
                    self.blocks.pop(bk, None)
                    self.probs.pop(bk, None)
                touched.add(bk)
        if prob is not None:
            keys, values = prob
            for bk, pos in group_by_block(unpack(keys), self.block_cells):
                cur = self.blocks.get(bk)
                if cur is None:
                    continue  # no occupied cell in this block: nothing drawn changes colour
                i = np.minimum(np.searchsorted(cur, keys[pos]), len(cur) - 1)
                hit = cur[i] == keys[pos]
                if hit.any():
                    self.probs[bk][i[hit]] = values[pos][hit]
                    touched.add(bk)
        return touched

    def occupied_cells(self, resolution: float) -> np.ndarray:
        """Current occupied cell centres (N,3) metres."""
        if not self.blocks:
            return np.zeros((0, 3))
        keys = np.concatenate(list(self.blocks.values()))
        return (unpack(keys).astype(np.float64) + 0.5) * resolution


def carry_values(old_keys: np.ndarray, old_values: np.ndarray | None, new_keys: np.ndarray) -> np.ndarray:
    """Per-cell float32 values of sorted ``old_keys`` carried over to sorted ``new_keys`` (NaN where new)."""
    out = np.full(len(new_keys), np.nan, dtype=np.float32)
    if len(old_keys) and len(new_keys) and old_values is not None:
        i = np.minimum(np.searchsorted(old_keys, new_keys), len(old_keys) - 1)
        hit = old_keys[i] == new_keys
        out[hit] = old_values[i[hit]]
    return out

