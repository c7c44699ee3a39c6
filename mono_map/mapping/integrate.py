"""Fast exact OctoMap integration: batched ray casting + bulk updates through octomap-python.

Per frame: :func:`mono_map.mapping.raycast.compute_update` gives the deduplicated free and occupied
key sets that ``insertPointCloud(..., discretize=True)`` would compute. A mirror of the leaf
log-odds (:class:`LogOddsMirror`, float32, exactly OctoMap's arithmetic) then tells which of those
updates would change anything: OctoMap itself skips a cell already clamped in the update's
direction (``updateNode``'s early abort), so only the other cells are sent to the tree with
``updateNodes`` (misses first, then hits, as OctoMap does). The tree ends up node for node the same
as with ``insertPointCloud`` — same cell values, same pruning, same ``memoryUsage`` — and the mirror
also yields the cells whose occupied state changed this frame, for viewers.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from mono_map.config import OctoMapConfig
from mono_map.errors import MonoMapError
from mono_map.mapping.octree import (apply_sensor_model, child_order_codes, key_to_coord, make_octree, morton_order,
                                     octree_from_cells, ot_header, sorted_unique)
from mono_map.mapping.raycast import KeySets, compute_update


class LogOddsMirror:
    """Sparse float32 copy of the leaf log-odds, indexed by OctoMap key (NaN = unknown).

    Storage: blocks of 8×8×8 cells in one growing pool, found through a dense table of block
    slots over the bounding box of blocks seen so far (which grows when needed).
    """

    SHIFT = 3
    BLOCK = 1 << SHIFT
    CELLS = BLOCK ** 3

    def __init__(self) -> None:
        self.table: np.ndarray | None = None     # int32 block slot, -1 = none
        self.table_lo = np.zeros(3, dtype=np.int64)
        self.pool = np.full(0, np.nan, dtype=np.float32)     # current log-odds
        self.synced = np.full(0, np.nan, dtype=np.float32)   # value the octree holds
        self.dirty = np.zeros(0, dtype=bool)                  # changed since the last sync
        self.block_keys = np.zeros((0, 3), dtype=np.int64)   # key of each block's first cell
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

    def index(self, keys: np.ndarray, create: bool, bounds: tuple | None = None) -> np.ndarray:
        """Pool indices of keys ((N, 3) int64); with create=False, -1 where the block is absent.
        bounds: optional (lo, hi) key bounds of ``keys`` (saves a pass)."""
        if len(keys) == 0:
            return np.zeros(0, dtype=np.int64)
        if create:
            if bounds is not None and bounds[0] is not None:
                blo, bhi = np.maximum(bounds[0], 0) >> self.SHIFT, np.minimum(bounds[1], 65535) >> self.SHIFT
            else:
                blo, bhi = keys.min(axis=0) >> self.SHIFT, keys.max(axis=0) >> self.SHIFT
            self._grow_table(blo, bhi)
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
            cap = max(need, int(len(self.pool) * 1.5))
            self.pool = _grow(self.pool, cap, np.nan)
            self.synced = _grow(self.synced, cap, np.nan)
            self.dirty = _grow(self.dirty, cap, False)
        if self.n_blocks > len(self.block_keys):
            cap = max(self.n_blocks, int(len(self.block_keys) * 1.5))
            self.block_keys = _grow(self.block_keys, cap, 0)
        self.block_keys[start:self.n_blocks] = bk

    def update(self, kernel, keys: np.ndarray, update, cmin, cmax, thres,
               bounds: tuple | None = None) -> tuple[int, np.ndarray]:
        """The compiled ``updateNode`` on distinct cells ``keys`` ((N, 3) int64) by ``update`` (float32 scalar
        or (N,)), creating blocks as needed; (#cells changed, rows of ``keys`` whose occupied state flipped).
        bounds: optional (lo, hi) key bounds of ``keys``."""
        from mono_map.mapping.raycast_c import mirror_alloc_c, mirror_apply_c

        keys = np.ascontiguousarray(keys, dtype=np.int64)
        if bounds is not None and bounds[0] is not None:
            blo, bhi = np.maximum(bounds[0], 0) >> self.SHIFT, np.minimum(bounds[1], 65535) >> self.SHIFT
        else:
            blo, bhi = keys.min(axis=0) >> self.SHIFT, keys.max(axis=0) >> self.SHIFT
        self._grow_table(blo, bhi)
        new_blocks = mirror_alloc_c(kernel, keys, self.table, self.table_lo, self.n_blocks)
        if len(new_blocks):
            self._add_blocks(new_blocks)
        return mirror_apply_c(kernel, keys, update, self.table, self.table_lo, self.pool, self.dirty, cmin, cmax,
                              thres)

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

    @property
    def nbytes(self) -> int:
        return int(self.pool.nbytes + (self.table.nbytes if self.table is not None else 0))


def _grow(a: np.ndarray, n: int, fill) -> np.ndarray:
    out = np.full((n,) + a.shape[1:], fill, dtype=a.dtype)
    out[:len(a)] = a
    return out


_XYZ = np.dtype([("x", "f8"), ("y", "f8"), ("z", "f8")])


def _as_tuples(points: np.ndarray) -> list:
    """(N, 3) float64 → list of (x, y, z) tuples (the fastest input for octomap-python's updateNodes)."""
    return np.ascontiguousarray(points, dtype=np.float64).view(_XYZ).ravel().tolist()


def exact_increments(old: np.ndarray, new: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """float32 increments taking an octree value ``old`` exactly to ``new`` (old NaN = absent node, starting at 0).

    Returns (first, second): apply ``first`` then, where it is not NaN, ``second``. One step
    ``d = new - old`` works when ``float32(old + d) == new``; otherwise (``new`` much smaller than
    ``old``) go through zero: ``-old`` then ``new``, both exact.
    """
    base = np.where(np.isnan(old), np.float32(0.0), old).astype(np.float32)
    new = new.astype(np.float32)
    d = (new - base).astype(np.float32)
    bad = (base + d) != new
    first = np.where(bad, -base, d).astype(np.float32)
    second = np.where(bad, new, np.float32(np.nan)).astype(np.float32)
    return first, second


@dataclass
class FrameIntegration:
    """What one frame did to the map."""

    keys: KeySets
    n_free_sent: int                 # updates actually applied (others were no-ops at clamping)
    n_occupied_sent: int
    became_occupied: np.ndarray      # (M, 3) world cell centres, metres
    stopped_occupied: np.ndarray     # (F, 3) world cell centres, metres
    timings: dict = field(default_factory=dict)


class MapIntegrator:
    """An OctoMap built frame by frame with the fast exact path (or with ``insertPointCloud``).

    method="batched" (default): exact batched ray casting; the updates go to the float32 mirror at
    once and to the octree in bulk when it is needed (``tree``, ``stats()``, ``sync()``, or every
    ``sync_every`` frames): each cell whose value changed since the last sync gets one update with
    the exact float32 increment that takes the octree's value to the mirror's (cells grouped by
    increment, one ``updateNodes`` call per group). Cells are independent and OctoMap prunes
    whenever children become equal, so the synced tree equals, node for node, the tree that
    frame-by-frame ``insertPointCloud`` builds. When many cells changed, the tree is instead
    rebuilt from the mirror in one go (:func:`mono_map.mapping.octree.octree_from_cells`), which gives the same tree.
    method="insertPointCloud": octomap-python's own ``insertPointCloud(discretize=True)`` per frame
    (reference/benchmark; changed-cell lists are then empty).
    """

    def __init__(self, cfg: OctoMapConfig | None = None, method: str = "batched",
                 sync_every: int | None = None):
        if method not in ("batched", "insertPointCloud"):
            raise MonoMapError(f"method: unknown integration method {method!r} (batched | insertPointCloud)")
        self.cfg = cfg or OctoMapConfig()
        self.method = method
        self._tree = make_octree(self.cfg)
        self.mirror = LogOddsMirror() if method == "batched" else None
        self.sync_every = sync_every
        self._pending = False
        # OctoMap stores these as float (logodds() returns float)
        self.hit = np.float32(self._tree.getProbHitLog())
        self.miss = np.float32(self._tree.getProbMissLog())
        self.cmin = np.float32(self._tree.getClampingThresMinLog())
        self.cmax = np.float32(self._tree.getClampingThresMaxLog())
        self.occ_thres = np.float32(self._tree.getOccupancyThresLog())
        self.frames = 0
        self.sync_seconds = 0.0

    @property
    def tree(self):
        """The ``octomap.OcTree``, brought up to date first."""
        self.sync()
        return self._tree

    def insert(self, points: np.ndarray, origin: np.ndarray) -> FrameIntegration:
        """Integrate one scan: (N, 3) world end points (metres) seen from world ``origin`` (3,)."""
        import time

        pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        origin = np.asarray(origin, dtype=np.float64).reshape(3)
        if not np.isfinite(origin).all():
            raise MonoMapError("origin: sensor origin is not finite")
        if not np.isfinite(pts).all():
            raise MonoMapError("points: non-finite coordinates (NaN or inf) in the scan")
        empty = np.zeros((0, 3))
        self.frames += 1
        if self.method == "insertPointCloud":
            t0 = time.perf_counter()
            if len(pts):
                self._tree.insertPointCloud(np.ascontiguousarray(pts), origin,
                                            maxrange=float(self.cfg.max_range), discretize=True)
            ks = KeySets(np.zeros((0, 3), np.int64), np.zeros((0, 3), np.int64))
            return FrameIntegration(ks, 0, 0, empty, empty, {"update_s": time.perf_counter() - t0})

        t0 = time.perf_counter()
        ks = compute_update(pts, origin, self.cfg.resolution, max_range=self.cfg.max_range)
        t1 = time.perf_counter()
        free_sent, freed = self._apply(ks.free, False, bounds=(ks.lo, ks.hi))
        occ_sent, became = self._apply(ks.occupied, True, bounds=(ks.lo, ks.hi))
        t2 = time.perf_counter()
        timings = {"raycast_s": t1 - t0, "mirror_s": t2 - t1}
        if self.sync_every and self.frames % self.sync_every == 0:
            timings["sync_s"] = self.sync()
        return FrameIntegration(ks, free_sent, occ_sent, became, freed, timings)

    def insert_updates(self, upd) -> FrameIntegration:
        """Integrate one frame of per-cell log-odds updates (:class:`mono_map.mapping.distribution.CellUpdates`:
        distinct keys, float32 updates), with OctoMap's ``updateNode`` arithmetic and clamping."""
        import time

        if self.method != "batched":
            raise MonoMapError("per-cell updates need the batched integration method")
        self.frames += 1
        t0 = time.perf_counter()
        neg, pos = upd.dl < 0, upd.dl > 0
        bounds = (upd.lo, upd.hi)
        n_free, freed = self._apply(upd.keys[neg], upd.dl[neg], bounds=bounds)
        n_occ, became = self._apply(upd.keys[pos], upd.dl[pos], bounds=bounds)
        timings = {"mirror_s": time.perf_counter() - t0}
        if self.sync_every and self.frames % self.sync_every == 0:
            timings["sync_s"] = self.sync()
        ks = KeySets(upd.keys[neg], upd.keys[pos], n_rays=upd.n_rays, n_endpoints=int(pos.sum()),
                     lo=upd.lo, hi=upd.hi)
        return FrameIntegration(ks, n_free, n_occ, became, freed, timings)

    def _apply(self, keys: np.ndarray, update, bounds: tuple | None = None) -> tuple[int, np.ndarray]:
        """Log-odds updates into the mirror: ``update`` is a bool (True: hit, False: miss, for every key)
        or a float32 array (one update per key). Returns (#cells changed, centres whose occupied state flipped).

        Cells already clamped in the update's direction are left alone, as OctoMap's ``updateNode`` does.
        """
        if len(keys) == 0:
            return 0, np.zeros((0, 3))
        from mono_map.mapping.raycast_c import load_kernel

        kernel = load_kernel()
        if kernel is not None:                  # the same arithmetic, compiled
            if isinstance(update, (bool, np.bool_)):
                update = self.hit if update else self.miss
            n, flipped = self.mirror.update(kernel, keys, update, self.cmin, self.cmax, self.occ_thres, bounds)
            self._pending = True
            return n, key_to_coord(keys[flipped], self.cfg.resolution)
        if isinstance(update, (bool, np.bool_)):
            upd = np.full(len(keys), self.hit if update else self.miss, dtype=np.float32)
        else:
            upd = np.asarray(update, dtype=np.float32)
        idx = self.mirror.index(keys, create=True, bounds=bounds)
        old = self.mirror.pool[idx]
        known = ~np.isnan(old)
        change = ~(known & (((upd >= 0) & (old >= self.cmax)) | ((upd <= 0) & (old <= self.cmin))))
        idx, old, known, upd = idx[change], old[change], known[change], upd[change]
        new = np.where(known, old, np.float32(0.0)).astype(np.float32) + upd
        new = np.where(new < self.cmin, self.cmin, new)
        new = np.where(new > self.cmax, self.cmax, new).astype(np.float32)
        self.mirror.pool[idx] = new
        self.mirror.dirty[idx] = True
        self._pending = True
        was_occ = known & (old >= self.occ_thres)
        is_occ = new >= self.occ_thres
        flipped = (is_occ & ~was_occ) | (was_occ & ~is_occ)
        return len(idx), key_to_coord(keys[change][flipped], self.cfg.resolution)

    # measured here: a full rebuild costs ~0.4 µs per known cell, bulk updates ~2.5 µs per changed cell
    REBUILD_RATIO = 0.15

    def sync(self) -> float:
        """Bring the octree up to the mirror; returns seconds spent.

        Few changed cells: exact increments through ``updateNodes``. Many (relative to the map):
        rebuild the whole tree from the mirror in one ``.ot`` stream (:func:`~mono_map.mapping.octree.octree_from_cells`) — the same tree.
        """
        import time

        if self.mirror is None or not self._pending:
            return 0.0
        t0 = time.perf_counter()
        m = self.mirror
        used = m.n_blocks * m.CELLS
        idx = np.flatnonzero(m.dirty[:used])
        m.dirty[idx] = False
        self._pending = False
        new = m.pool[idx]
        old = m.synced[idx]
        moved = ~(new == old)                       # NaN old (absent) counts as moved
        idx, new, old = idx[moved], new[moved], old[moved]
        self.n_known = getattr(self, "n_known", 0) + int(np.isnan(old).sum())
        if len(idx) > self.REBUILD_RATIO * self.n_known or self._many_increments(new, old):
            del idx, new, old                      # a rebuild needs none of these, nor the old tree:
            self._tree = None                      # free them before it allocates (lower peak RSS)
            self._tree = self._rebuilt_tree()
            m.synced[:used] = m.pool[:used]
            self.rebuilds = getattr(self, "rebuilds", 0) + 1
        elif len(idx):
            keys = m.keys_of(idx)
            order = morton_order(keys)             # tree locality: several times faster updates
            keys, new, old, idx = keys[order], new[order], old[order], idx[order]
            first, second = exact_increments(old, new)
            centres = key_to_coord(keys, self.cfg.resolution)
            self._update_grouped(centres, first)
            two = ~np.isnan(second)
            if two.any():
                self._update_grouped(centres[two], second[two])
            m.synced[idx] = new
        dt = time.perf_counter() - t0
        self.sync_seconds += dt
        return dt

    def _rebuilt_tree(self):
        """A new octree holding exactly the mirror's known cells (one .ot stream read by OctoMap)."""
        from mono_map.mapping.raycast_c import load_kernel, ot_nodes_c

        m = self.mirror
        kernel = load_kernel()
        if kernel is None or m.n_blocks == 0:
            known = np.flatnonzero(~np.isnan(m.pool[:m.n_blocks * m.CELLS]))
            return octree_from_cells(m.keys_of(known), m.pool[known], self.cfg)
        import octomap

        nodes, n = ot_nodes_c(kernel, m.pool, child_order_codes(m.block_keys[:m.n_blocks] >> m.SHIFT))   # from the blocks
        if n == 0:
            return make_octree(self.cfg)
        return apply_sensor_model(octomap.OcTree.read(ot_header(n, self.cfg.resolution) + nodes), self.cfg)

    MAX_GROUPS = 2048   # distinct increments beyond which one updateNodes call per group costs more than a rebuild

    def _many_increments(self, new: np.ndarray, old: np.ndarray) -> bool:
        """True when the updates would need more than MAX_GROUPS ``updateNodes`` calls (per-cell distribution
        updates: nearly every cell its own increment)."""
        inc = (new - np.where(np.isnan(old), np.float32(0.0), old)).astype(np.float32)
        return len(sorted_unique(inc.view(np.uint32))) > self.MAX_GROUPS

    def _update_grouped(self, centres: np.ndarray, increments: np.ndarray) -> None:
        """``updateNodes`` once per distinct float32 increment."""
        bits = np.ascontiguousarray(increments, dtype=np.float32).view(np.uint32)
        order = np.argsort(bits, kind="stable")          # stable: Morton order kept within a group
        sb = bits[order]
        cuts = np.flatnonzero(np.diff(sb)) + 1
        for rows in np.split(order, cuts):
            value = float(increments[rows[0]])
            self._tree.updateNodes(_as_tuples(centres[rows]), value)

    def stats(self) -> dict:
        """Leaf count and memory (OctoMap's ``memoryUsage``, MB = 2**20 bytes); syncs and traverses the tree."""
        tree = self.tree
        mem = int(tree.memoryUsage())
        return {"leaf_count": int(tree.getNumLeafNodes()), "memory_bytes": mem,
                "memory_mb": mem / 2**20, "tree_nodes": int(tree.size())}
