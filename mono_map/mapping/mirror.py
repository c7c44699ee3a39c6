"""The map while it is built: a sparse float32 mirror of OctoMap's leaf log-odds, indexed by key.

Cells live in blocks of 8×8×8 (keys: OctoMap's 16-bit cell addresses, :mod:`mono_map.mapping.octree`);
updates follow OctoMap's ``updateNode`` arithmetic and clamping to the bit (compiled:
:mod:`mono_map.mapping.mirror_c`, or numpy), and the mirror writes its cells as one ``.ot`` stream
(:mod:`mono_map.mapping.ot_c`) from which the ``octomap.OcTree`` is made
(:class:`mono_map.mapping.integrate.MapIntegrator`).
"""

from __future__ import annotations

import numpy as np

from mono_map.mapping.octree import child_order_codes, key_bounds, ot_header, sorted_unique


class LogOddsMirror:
    """Sparse float32 copy of the leaf log-odds, indexed by OctoMap key (NaN = unknown).

    Storage: blocks of 8×8×8 cells in one growing pool (4 bytes a cell), found through a dense table
    of block slots over the bounding box of blocks seen so far (which grows when needed). Per block:
    a changed-since-counted flag and the cached node / leaf counts of its subtree
    (:meth:`tree_counts`).
    """

    SHIFT = 3
    BLOCK = 1 << SHIFT
    CELLS = BLOCK ** 3

    def __init__(self) -> None:
        self.table: np.ndarray | None = None     # int32 block slot, -1 = none
        self.table_lo = np.zeros(3, dtype=np.int64)
        self.pool = np.full(0, np.nan, dtype=np.float32)     # current log-odds
        self.block_keys = np.zeros((0, 3), dtype=np.int64)   # key of each block's first cell
        # per block: changed since counted, and its subtree's cached kind / value / nodes / leaves
        self.blocks = {"dirty": np.zeros(0, dtype=bool), "kind": np.zeros(0, dtype=np.int8),
                       "value": np.zeros(0, dtype=np.float32), "nodes": np.zeros(0, dtype=np.int64),
                       "leaves": np.zeros(0, dtype=np.int64)}
        self.n_blocks = 0

    def _grow_table(self, blo: np.ndarray, bhi: np.ndarray) -> None:
        if self.table is None:
            lo, hi = blo - 4, bhi + 4
        else:
            old_lo = self.table_lo
            old_hi = old_lo + np.array(self.table.shape) - 1
            if np.all(blo >= old_lo) and np.all(bhi <= old_hi):
                return
            span = old_hi - old_lo + 1
            lo = np.where(blo < old_lo, np.minimum(blo, old_lo - span // 2), old_lo)
            hi = np.where(bhi > old_hi, np.maximum(bhi, old_hi + span // 2), old_hi)
        lo = np.maximum(lo, 0)
        hi = np.minimum(hi, (1 << (16 - self.SHIFT)) - 1)
        table = np.full(tuple((hi - lo + 1).tolist()), -1, dtype=np.int32)
        if self.table is not None:
            o = self.table_lo - lo
            s = self.table.shape
            table[o[0]:o[0] + s[0], o[1]:o[1] + s[1], o[2]:o[2] + s[2]] = self.table
        self.table, self.table_lo = table, lo

    def _block_index(self, keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        b = (keys >> self.SHIFT) - self.table_lo
        flat = np.ravel_multi_index((b[:, 0], b[:, 1], b[:, 2]), self.table.shape)
        local = ((keys[:, 0] & 7) << 6) | ((keys[:, 1] & 7) << 3) | (keys[:, 2] & 7)
        return flat, local

    def _grow_for(self, keys: np.ndarray, bounds: tuple | None) -> None:
        """Grow the block table to cover (N ≥ 1, 3) ``keys``, whose (lo, hi) key bounds may be given."""
        if bounds is not None and bounds[0] is not None:
            blo, bhi = np.maximum(bounds[0], 0) >> self.SHIFT, np.minimum(bounds[1], 65535) >> self.SHIFT
        else:
            blo, bhi = (b >> self.SHIFT for b in key_bounds(keys))
        self._grow_table(blo, bhi)

    def index(self, keys: np.ndarray, create: bool, bounds: tuple | None = None) -> np.ndarray:
        """Pool indices of keys ((N, 3) int64); with create=False, -1 where the block is absent.
        bounds: optional (lo, hi) key bounds of ``keys`` (saves a pass)."""
        if len(keys) == 0:
            return np.zeros(0, dtype=np.int64)
        if create:
            self._grow_for(keys, bounds)
        else:
            blocks = keys >> self.SHIFT
            if self.table is None:
                return np.full(len(keys), -1, dtype=np.int64)
            hi = self.table_lo + np.array(self.table.shape)
            inside = np.all((blocks >= self.table_lo) & (blocks < hi), axis=1)
            if not inside.all():
                out = np.full(len(keys), -1, dtype=np.int64)
                out[inside] = self.index(keys[inside], create=False)
                return out
        flat, local = self._block_index(keys)
        tbl = self.table.reshape(-1)
        slots = tbl[flat]
        if create:
            missing = slots < 0
            if missing.any():
                new_blocks = sorted_unique(flat[missing])
                tbl[new_blocks] = np.arange(self.n_blocks, self.n_blocks + len(new_blocks), dtype=np.int32)
                self._add_blocks(new_blocks)
                slots = tbl[flat]
            return slots.astype(np.int64) * self.CELLS + local
        out = slots.astype(np.int64) * self.CELLS + local
        out[slots < 0] = -1
        return out

    def _add_blocks(self, new_blocks: np.ndarray) -> None:
        """Storage for blocks at flat table indices ``new_blocks``, whose table slots are already set to
        n_blocks, n_blocks + 1, ... in that order."""
        start = self.n_blocks
        self.n_blocks += len(new_blocks)
        bk = (np.stack(np.unravel_index(new_blocks, self.table.shape), axis=1) + self.table_lo) << self.SHIFT
        need = self.n_blocks * self.CELLS
        if need > len(self.pool):
            self.pool = _grow(self.pool, max(need, int(len(self.pool) * 1.5)), np.nan)
        if self.n_blocks > len(self.block_keys):
            cap = max(self.n_blocks, int(len(self.block_keys) * 1.5))
            self.block_keys = _grow(self.block_keys, cap, 0)
            self.blocks = {k: _grow(a, cap, 0) for k, a in self.blocks.items()}
        self.block_keys[start:self.n_blocks] = bk
        self.blocks["dirty"][start:self.n_blocks] = True

    def update(self, kernel, keys: np.ndarray, update, cmin, cmax, thres,
               bounds: tuple | None = None) -> tuple[int, np.ndarray]:
        """OctoMap's ``updateNode`` on distinct cells ``keys`` ((N, 3) int64) by ``update`` (float32 scalar
        or (N,)) with clamping to [cmin, cmax], creating blocks as needed: the compiled ``kernel``, or numpy
        (the same arithmetic) when it is None. Returns (#cells changed, rows of ``keys`` whose occupied state
        (log-odds ≥ thres) flipped); cells already clamped in the update's direction are left alone, as
        ``updateNode`` does. bounds: optional (lo, hi) key bounds of ``keys``."""
        if kernel is None:
            return self._update_numpy(keys, update, cmin, cmax, thres, bounds)
        from mono_map.mapping.mirror_c import mirror_alloc_c, mirror_apply_c

        keys = np.ascontiguousarray(keys, dtype=np.int64)
        self._grow_for(keys, bounds)
        new_blocks = mirror_alloc_c(kernel, keys, self.table, self.table_lo, self.n_blocks)
        if len(new_blocks):
            self._add_blocks(new_blocks)
        return mirror_apply_c(kernel, keys, update, self.table, self.table_lo, self.pool, self.blocks["dirty"], cmin,
                              cmax, thres)

    def _update_numpy(self, keys: np.ndarray, update, cmin, cmax, thres,
                      bounds: tuple | None) -> tuple[int, np.ndarray]:
        """:meth:`update` in numpy."""
        if np.ndim(update) == 0:
            upd = np.full(len(keys), update, dtype=np.float32)
        else:
            upd = np.asarray(update, dtype=np.float32)
        idx = self.index(keys, create=True, bounds=bounds)
        old = self.pool[idx]
        known = ~np.isnan(old)
        change = ~(known & (((upd >= 0) & (old >= cmax)) | ((upd <= 0) & (old <= cmin))))
        idx, old, known, upd = idx[change], old[change], known[change], upd[change]
        new = np.where(known, old, np.float32(0.0)).astype(np.float32) + upd
        new = np.where(new < cmin, cmin, new)
        new = np.where(new > cmax, cmax, new).astype(np.float32)
        self.pool[idx] = new
        self.blocks["dirty"][idx // self.CELLS] = True
        was_occ = known & (old >= thres)
        is_occ = new >= thres
        flipped = (is_occ & ~was_occ) | (was_occ & ~is_occ)
        return len(idx), np.flatnonzero(change)[flipped]

    def keys_of(self, idx: np.ndarray) -> np.ndarray:
        """Keys ((N, 3) int64) of pool indices."""
        slot, local = np.divmod(np.asarray(idx, dtype=np.int64), self.CELLS)
        off = np.stack([(local >> 6) & 7, (local >> 3) & 7, local & 7], axis=1)
        return self.block_keys[slot] + off

    def get(self, keys: np.ndarray) -> np.ndarray:
        """Log-odds of keys (float32, NaN = unknown)."""
        idx = self.index(np.asarray(keys, dtype=np.int64), create=False)
        out = np.full(len(idx), np.nan, dtype=np.float32)
        ok = idx >= 0
        out[ok] = self.pool[idx[ok]]
        return out

    def known_cells(self) -> int:
        return int(np.count_nonzero(~np.isnan(self.pool[: self.n_blocks * self.CELLS])))

    def block_codes(self) -> np.ndarray:
        """Each block's depth-13 code in OctoMap's child order (the order the octree holds them)."""
        return child_order_codes(self.block_keys[:self.n_blocks] >> self.SHIFT)

    def tree_counts(self, kernel, codes: np.ndarray | None = None) -> tuple[int, int]:
        """(nodes, leaves) of the pruned octree of the known cells — OctoMap's ``size()`` and
        ``getNumLeafNodes()`` — walking only the blocks changed since the last count (compiled kernel).
        codes: :meth:`block_codes`, if the caller has them."""
        from mono_map.mapping.ot_c import ot_counts_c

        return ot_counts_c(kernel, self.pool, self.block_codes() if codes is None else codes, self.blocks)

    def node_stream(self, kernel, resolution: float) -> np.ndarray:
        """The whole ``.ot`` stream (header + nodes, uint8) of the known cells (compiled kernel)."""
        from mono_map.mapping.ot_c import ot_nodes_c

        codes = self.block_codes()
        n, _ = self.tree_counts(kernel, codes)
        data, n_written = ot_nodes_c(kernel, self.pool, codes, ot_header(n, resolution))
        assert n_written == n
        return data

    @property
    def nbytes(self) -> int:
        return int(self.pool.nbytes + self.block_keys.nbytes + sum(a.nbytes for a in self.blocks.values())
                   + (self.table.nbytes if self.table is not None else 0))


def _grow(a: np.ndarray, n: int, fill) -> np.ndarray:
    """``a`` with room for ``n`` rows, the new ones ``fill``. Resized in place (realloc: a large array is
    remapped, not copied, so growing does not hold two copies); ``a`` must own its data and have no views."""
    old = len(a)
    a.resize((n,) + a.shape[1:], refcheck=False)
    a[old:] = fill
    return a
