"""Fast exact OctoMap integration: batched ray casting + compiled updates of a log-odds mirror.

Per frame: :func:`mono_map.mapping.raycast.compute_update` gives the deduplicated free and occupied
key sets that ``insertPointCloud(..., discretize=True)`` would compute. They update a mirror of the
leaf log-odds (:class:`mono_map.mapping.mirror.LogOddsMirror`, float32, exactly OctoMap's ``updateNode``
arithmetic and clamping), which is the map while it is being built: the ``octomap.OcTree`` is made from it in one
``.ot`` stream when it is asked for (at the end of a build), node for node the tree that
frame-by-frame ``insertPointCloud`` builds — same cell values, same pruning, same ``memoryUsage``.
Leaf count, node count and ``memoryUsage`` during the build are counted from the mirror (only the
blocks changed since the last count are walked), and the mirror yields the cells whose occupied
state changed each frame, for viewers.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from mono_map.config import OctoMapConfig
from mono_map.errors import MonoMapError
from mono_map.mapping.mirror import LogOddsMirror
from mono_map.mapping.octree import key_to_coord, make_octree, octree_from_cells, tree_from_stream
from mono_map.mapping.raycast import KeySets, compute_update


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

    method="batched" (default): exact batched ray casting; the updates go to the float32 mirror, which
    holds the map while it is built. ``tree`` (or ``sync()``, or every ``sync_every`` frames) makes the
    ``octomap.OcTree`` from the mirror in one ``.ot`` stream — node for node the tree that frame-by-frame
    ``insertPointCloud`` builds (cells are independent and OctoMap prunes whenever eight children are
    equal). ``stats()`` counts leaves, nodes and ``memoryUsage`` from the mirror without a tree.
    ``finish()`` hands over the tree and frees the mirror (the end of a build: the tree and the mirror
    are never both alive at their full size, so a build's peak memory stays near the map's).
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
        self._pending = False              # the mirror changed since the tree was made
        # OctoMap stores these as float (logodds() returns float)
        self.hit = np.float32(self._tree.getProbHitLog())
        self.miss = np.float32(self._tree.getProbMissLog())
        self.cmin = np.float32(self._tree.getClampingThresMinLog())
        self.cmax = np.float32(self._tree.getClampingThresMaxLog())
        self.occ_thres = np.float32(self._tree.getOccupancyThresLog())
        self.frames = 0
        self.sync_seconds = 0.0
        self.finished = False

    @property
    def tree(self):
        """The ``octomap.OcTree``, made from the mirror first if the mirror changed since."""
        self.sync()
        return self._tree

    def insert(self, points: np.ndarray, origin: np.ndarray) -> FrameIntegration:
        """Integrate one scan: (N, 3) world end points (metres) seen from world ``origin`` (3,)."""
        self._check_open()
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
        return self._integrate(ks, {"raycast_s": time.perf_counter() - t0})

    def insert_key_sets(self, ks: KeySets) -> FrameIntegration:
        """Integrate one scan already ray-cast: the free and occupied keys of ``compute_update`` (for the same
        cell size and ``max_range``), e.g. one of :func:`mono_map.mapping.nested.compute_nested_updates`."""
        if self.method != "batched":
            raise MonoMapError("precomputed key sets need the batched integration method")
        self._check_open()
        self.frames += 1
        return self._integrate(ks, {})

    def _integrate(self, ks: KeySets, timings: dict) -> FrameIntegration:
        t1 = time.perf_counter()
        free_sent, freed = self._apply(ks.free, False, bounds=(ks.lo, ks.hi))
        occ_sent, became = self._apply(ks.occupied, True, bounds=(ks.lo, ks.hi))
        timings["mirror_s"] = time.perf_counter() - t1
        if self.sync_every and self.frames % self.sync_every == 0:
            timings["sync_s"] = self.sync()
        return FrameIntegration(ks, free_sent, occ_sent, became, freed, timings)

    def insert_updates(self, upd) -> FrameIntegration:
        """Integrate one frame of per-cell log-odds updates (:class:`mono_map.mapping.distribution.CellUpdates`:
        distinct keys, float32 updates), with OctoMap's ``updateNode`` arithmetic and clamping."""
        if self.method != "batched":
            raise MonoMapError("per-cell updates need the batched integration method")
        self._check_open()
        self.frames += 1
        t0 = time.perf_counter()
        bounds = (upd.lo, upd.hi)
        if upd.n_free is not None:           # already split by sign (distribution_update): views, no copies
            m = upd.n_free
            (free_keys, free_dl), (occ_keys, occ_dl) = (upd.keys[:m], upd.dl[:m]), (upd.keys[m:], upd.dl[m:])
        else:
            neg, pos = upd.dl < 0, upd.dl > 0
            # np.compress: 4× faster than boolean indexing of (N, 3) rows (~440 k cells a frame, nearly all free)
            free_keys, occ_keys = np.compress(neg, upd.keys, axis=0), np.compress(pos, upd.keys, axis=0)
            free_dl, occ_dl = np.compress(neg, upd.dl), np.compress(pos, upd.dl)
        n_free, freed = self._apply(free_keys, free_dl, bounds=bounds)
        n_occ, became = self._apply(occ_keys, occ_dl, bounds=bounds)
        timings = {"mirror_s": time.perf_counter() - t0}
        if self.sync_every and self.frames % self.sync_every == 0:
            timings["sync_s"] = self.sync()
        ks = KeySets(free_keys, occ_keys, n_rays=upd.n_rays, n_endpoints=len(occ_keys), lo=upd.lo, hi=upd.hi)
        return FrameIntegration(ks, n_free, n_occ, became, freed, timings)

    def _apply(self, keys: np.ndarray, update, bounds: tuple | None = None) -> tuple[int, np.ndarray]:
        """Log-odds updates into the mirror: ``update`` is a bool (True: hit, False: miss, for every key)
        or a float32 array (one update per key). Returns (#cells changed, centres whose occupied state flipped).

        Cells already clamped in the update's direction are left alone, as OctoMap's ``updateNode`` does.
        """
        if len(keys) == 0:
            return 0, np.zeros((0, 3))
        from mono_map.mapping.raycast_c import load_kernel

        if isinstance(update, (bool, np.bool_)):
            update = self.hit if update else self.miss
        n, flipped = self.mirror.update(load_kernel(), keys, update, self.cmin, self.cmax, self.occ_thres, bounds)
        self._pending = True
        return n, key_to_coord(keys[flipped], self.cfg.resolution)

    def _check_open(self) -> None:
        if self.finished:
            raise MonoMapError("integrator: finish() was called; no more frames can be integrated")

    def sync(self, release: bool = False) -> float:
        """Make the octree from the mirror if the mirror changed since it was last made; returns seconds.
        ``release``: the mirror is dropped once the stream is written (see :meth:`finish`)."""
        if self.mirror is None or not self._pending:
            return 0.0
        t0 = time.perf_counter()
        self._tree = None                      # the old tree is not needed: free it first (lower peak RSS)
        self._tree = self._tree_from_mirror(release)
        self._pending = False
        dt = time.perf_counter() - t0
        self.sync_seconds += dt
        return dt

    def finish(self):
        """The finished ``octomap.OcTree``; the per-frame buffers and the mirror are freed before the tree is
        allocated (no more frames)."""
        from mono_map.mapping.kernel_threads import release_buffers

        release_buffers()
        self.sync(release=True)
        self.mirror = None
        self.finished = True
        return self._tree

    def _tree_from_mirror(self, release: bool = False):
        """A new octree holding exactly the mirror's known cells (one .ot stream read by OctoMap); with
        ``release``, the mirror is dropped once the stream is written, before OctoMap reads it."""
        from mono_map.mapping.raycast_c import load_kernel

        m = self.mirror
        kernel = load_kernel()
        if kernel is None or m.n_blocks == 0:
            known = np.flatnonzero(~np.isnan(m.pool[:m.n_blocks * m.CELLS]))
            keys, values = m.keys_of(known), m.pool[known]
            if release:
                self.mirror = m = None
            return octree_from_cells(keys, values, self.cfg)

        def stream():
            data = self.mirror.node_stream(kernel, self.cfg.resolution)
            if release:
                self.mirror = None
            return data

        del m
        return tree_from_stream(stream, self.cfg)

    def stats(self) -> dict:
        """Leaf count, node count and memory (OctoMap's ``memoryUsage``, MB = 2**20 bytes) of the map's octree,
        counted from the mirror (no tree is made) or read from the tree."""
        from mono_map.mapping.raycast_c import load_kernel

        kernel = load_kernel()
        if self.mirror is not None and kernel is not None:
            nodes, leaves = self.mirror.tree_counts(kernel)
            mem = octree_memory_usage(nodes, leaves)
        else:
            tree = self.tree
            nodes, leaves, mem = int(tree.size()), int(tree.getNumLeafNodes()), int(tree.memoryUsage())
        return {"leaf_count": leaves, "memory_bytes": mem, "memory_mb": mem / 2**20, "tree_nodes": nodes}


_MEMORY_MODEL: list[tuple[int, int, int]] = []


def octree_memory_usage(nodes: int, leaves: int) -> int:
    """OctoMap's ``memoryUsage()`` (bytes) of an ``OcTree`` with ``nodes`` nodes of which ``leaves`` are leaves:
    the tree object + a node per node + an array of 8 child pointers per inner node. The three sizes are
    read from octomap-python itself (an empty tree, ``memoryUsageNode()``, a one-leaf tree of 17 nodes)."""
    if not _MEMORY_MODEL:
        import octomap

        t = octomap.OcTree(0.1)
        base, node = int(t.memoryUsage()), int(t.memoryUsageNode())
        t.updateNode(np.array([0.05, 0.05, 0.05]), True)
        assert t.size() == 17 and t.getNumLeafNodes() == 1
        children = (int(t.memoryUsage()) - base - 17 * node) // 16
        _MEMORY_MODEL.append((base, node, children))
    base, node, children = _MEMORY_MODEL[0]
    return base + node * nodes + children * (nodes - leaves) if nodes else base
