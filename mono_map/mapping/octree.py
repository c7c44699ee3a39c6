"""OctoMap primitives in one place: keys, Morton codes, the tree depth, trees from settings, .bt/.ot I/O
and a tree's leaves as Morton intervals (pruned leaves expanded into their finest cells).

Keys are OctoMap 1.10's 16-bit cell addresses, ``key = floor(coord / res) + 32768`` per axis, as
``int64`` arrays of shape (N, 3); coordinates are metres in the world frame. A Morton (Z-order) code
interleaves a key's bits (x highest): every octree node is one contiguous interval of codes, which
makes tree comparisons and bulk updates sort-and-search problems. Used by ray casting
(:mod:`~mono_map.mapping.raycast`), integration (:mod:`~mono_map.mapping.integrate`), the map metrics
(:mod:`mono_map.eval.map_metrics`) and the viewer (:mod:`mono_map.viz.codec`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mono_map.config import OctoMapConfig
from mono_map.errors import MonoMapError

TREE_DEPTH = 16                      # OctoMap 1.10
TREE_MAX_VAL = 1 << (TREE_DEPTH - 1)  # 32768: the key of coordinate 0


# --------------------------------------------------------------------------- keys


def resolution_factor(resolution: float) -> float:
    return 1.0 / float(resolution)


def coord_to_key(coords: np.ndarray, resolution: float) -> np.ndarray:
    """OctoMap ``coordToKey``: float32 coordinates (metres) → int64 keys (unchecked)."""
    c = np.asarray(coords, dtype=np.float32).astype(np.float64)
    return np.floor(resolution_factor(resolution) * c).astype(np.int64) + TREE_MAX_VAL


def key_in_range(keys: np.ndarray) -> np.ndarray:
    """Rows whose three keys are addressable (``coordToKeyChecked``)."""
    k = np.asarray(keys)
    if k.dtype == np.int64:   # one unsigned compare per column (a negative key wraps above the range): 8× faster
        u = k.view(np.uint64)
        return (u[..., 0] < 2 * TREE_MAX_VAL) & (u[..., 1] < 2 * TREE_MAX_VAL) & (u[..., 2] < 2 * TREE_MAX_VAL)
    return np.all((k >= 0) & (k < 2 * TREE_MAX_VAL), axis=-1)


def key_bounds(keys: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-axis (min, max) int64 (3,) of (N ≥ 1, 3) keys; column by column (numpy's ``min(axis=0)`` on an
    (N, 3) array is ~10× slower)."""
    k = np.asarray(keys)
    return (np.array([k[:, c].min() for c in range(3)], dtype=np.int64),
            np.array([k[:, c].max() for c in range(3)], dtype=np.int64))


def key_to_coord(keys: np.ndarray, resolution: float) -> np.ndarray:
    """Cell centres (float64 metres) of int keys: ``(key - 32768 + 0.5) * res``."""
    return (np.asarray(keys, dtype=np.float64) - TREE_MAX_VAL + 0.5) * float(resolution)


def sorted_unique(a: np.ndarray) -> np.ndarray:
    """``np.unique(a)`` by sorting: numpy 2.4's hash-based ``np.unique`` is ~100x slower on structured
    int64 codes such as packed keys or Morton codes (measured: 3 M codes 7.7 s vs 0.1 s)."""
    s = np.sort(np.asarray(a).ravel())
    return s[np.r_[True, s[1:] != s[:-1]]] if len(s) else s


def pack_keys(keys: np.ndarray) -> np.ndarray:
    """(N, 3) keys → one int64 each (for sets and joins; sorts like x, then y, then z)."""
    k = np.asarray(keys, dtype=np.int64)
    return (k[:, 0] << 32) | (k[:, 1] << 16) | k[:, 2]


def unpack_keys(packed: np.ndarray) -> np.ndarray:
    """Inverse of :func:`pack_keys`."""
    p = np.asarray(packed, dtype=np.int64)
    return np.stack([(p >> 32) & 0xFFFF, (p >> 16) & 0xFFFF, p & 0xFFFF], axis=1)


# --------------------------------------------------------------------------- Morton codes


def spread_bits(v: np.ndarray) -> np.ndarray:
    """Insert two zero bits between each of the low 21 bits (uint64; for 3-D Morton codes)."""
    x = v.astype(np.uint64) & np.uint64(0x1FFFFF)
    for shift, mask in ((32, 0x1F00000000FFFF), (16, 0x1F0000FF0000FF), (8, 0x100F00F00F00F00F),
                        (4, 0x10C30C30C30C30C3), (2, 0x1249249249249249)):
        x = (x | (x << np.uint64(shift))) & np.uint64(mask)
    return x


def compact_bits(x: np.ndarray) -> np.ndarray:
    """Inverse of :func:`spread_bits`: every third bit of x, packed (int64)."""
    x = x.astype(np.uint64) & np.uint64(0x1249249249249249)
    for shift, mask in ((2, 0x10C30C30C30C30C3), (4, 0x100F00F00F00F00F), (8, 0x1F0000FF0000FF),
                        (16, 0x1F00000000FFFF), (32, 0x1FFFFF)):
        x = (x | (x >> np.uint64(shift))) & np.uint64(mask)
    return x.astype(np.int64)


def morton_codes(keys: np.ndarray) -> np.ndarray:
    """Z-order codes (int64) of (N, 3) keys, x bits highest."""
    k = np.asarray(keys, dtype=np.int64)
    code = (spread_bits(k[:, 0]) << np.uint64(2)) | (spread_bits(k[:, 1]) << np.uint64(1)) | spread_bits(k[:, 2])
    return code.astype(np.int64)


def morton_to_keys(codes: np.ndarray) -> np.ndarray:
    """(N, 3) int64 keys of Morton codes (inverse of :func:`morton_codes`)."""
    c = np.asarray(codes, dtype=np.int64).astype(np.uint64)
    return np.stack([compact_bits(c >> np.uint64(2)), compact_bits(c >> np.uint64(1)), compact_bits(c)], axis=1)


def morton_order(keys: np.ndarray) -> np.ndarray:
    """Permutation sorting keys along the octree's Z-order (locality for bulk tree updates)."""
    return np.argsort(morton_codes(keys), kind="stable")


def child_order_codes(keys: np.ndarray) -> np.ndarray:
    """Codes whose sort order is OctoMap's child order at every level (z bits highest: child index is
    +1 for the x bit, +2 for y, +4 for z of the key at that level)."""
    k = np.asarray(keys, dtype=np.int64)
    return ((spread_bits(k[:, 2]) << np.uint64(2)) | (spread_bits(k[:, 1]) << np.uint64(1))
            | spread_bits(k[:, 0])).astype(np.int64)


# --------------------------------------------------------------------------- trees


def validate_octomap_config(cfg: OctoMapConfig) -> None:
    """MonoMapError naming the option if the OctoMap settings are not a valid sensor model."""
    if not (cfg.resolution > 0 and np.isfinite(cfg.resolution)):
        raise MonoMapError(f"--res: resolution must be a positive number of metres, got {cfg.resolution}")
    if cfg.resolution < 0.01:
        raise MonoMapError(f"--res: {cfg.resolution} m is finer than this tool supports (>= 0.01 m)")
    if not (0.0 < cfg.prob_miss < 0.5 < cfg.prob_hit < 1.0):
        raise MonoMapError(f"--prob-miss/--prob-hit: need 0 < miss < 0.5 < hit < 1, got miss={cfg.prob_miss}, "
                           f"hit={cfg.prob_hit}")
    if not (0.0 < cfg.clamp_min < cfg.occupancy_threshold < cfg.clamp_max < 1.0):
        raise MonoMapError(f"--clamp-min/--clamp-max: need 0 < min < {cfg.occupancy_threshold} < max < 1, "
                           f"got min={cfg.clamp_min}, max={cfg.clamp_max}")


def apply_sensor_model(tree, cfg: OctoMapConfig):
    """Set the config's hit/miss probabilities, clamping and occupancy threshold on ``tree``; returns it."""
    tree.setProbHit(float(cfg.prob_hit))
    tree.setProbMiss(float(cfg.prob_miss))
    tree.setClampingThresMin(float(cfg.clamp_min))
    tree.setClampingThresMax(float(cfg.clamp_max))
    tree.setOccupancyThres(float(cfg.occupancy_threshold))
    return tree


def make_octree(cfg: OctoMapConfig):
    """An empty ``octomap.OcTree`` with the config's resolution, sensor model and clamping."""
    import octomap

    validate_octomap_config(cfg)
    return apply_sensor_model(octomap.OcTree(float(cfg.resolution)), cfg)


_NODE = np.dtype([("v", "<f4"), ("c", "u1")])


def ot_stream(keys: np.ndarray, values: np.ndarray, resolution: float) -> tuple[bytes, int]:
    """(bytes of a .ot file, number of nodes) for finest cells ``keys`` (N ≥ 1, 3) with float32 log-odds ``values``.

    The tree OctoMap would hold after updating those cells one by one: OctoMap prunes eight sibling
    leaves with equal log-odds into their parent after every update and an inner node holds the
    maximum of its children, so the final tree depends only on the cell values. The stream is a
    pre-order walk: per node its float32 log-odds and one byte whose bit i says child i exists
    (:func:`child_order_codes`)."""
    codes = child_order_codes(keys)
    order = np.argsort(codes, kind="stable")
    codes = codes[order]
    vals = np.asarray(values, dtype=np.float32)[order]
    is_leaf = np.ones(len(codes), dtype=bool)
    masks = np.zeros(len(codes), dtype=np.uint8)
    rec_depth, rec_code, rec_val, rec_mask = [], [], [], []
    for depth in range(TREE_DEPTH, 0, -1):
        parent = codes >> 3
        starts = np.flatnonzero(np.r_[True, parent[1:] != parent[:-1]])
        counts = np.diff(np.r_[starts, len(codes)])
        vmin = np.minimum.reduceat(vals, starts)
        vmax = np.maximum.reduceat(vals, starts)
        all_leaf = np.logical_and.reduceat(is_leaf, starts)
        collapse = (counts == 8) & all_leaf & (vmin == vmax)     # OctoMap's isNodeCollapsible
        keep = ~np.repeat(collapse, counts)
        rec_depth.append(np.full(int(keep.sum()), depth, dtype=np.int64))
        rec_code.append(codes[keep] << (3 * (TREE_DEPTH - depth)))
        rec_val.append(vals[keep])
        rec_mask.append(masks[keep])
        child_bits = np.bitwise_or.reduceat((np.uint8(1) << (codes & 7).astype(np.uint8)).astype(np.uint8), starts)
        codes, vals, is_leaf = parent[starts], vmax.astype(np.float32), collapse
        masks = np.where(collapse, np.uint8(0), child_bits).astype(np.uint8)
    rec_depth.append(np.zeros(1, dtype=np.int64))
    rec_code.append(codes)
    rec_val.append(vals)
    rec_mask.append(masks)
    depth = np.concatenate(rec_depth)
    full = np.concatenate(rec_code)
    order = np.lexsort((depth, full))                             # pre-order: parent before its first child
    nodes = np.empty(len(order), dtype=_NODE)
    nodes["v"] = np.concatenate(rec_val)[order]
    nodes["c"] = np.concatenate(rec_mask)[order]
    return ot_header(len(nodes), resolution) + nodes.tobytes(), len(nodes)


def ot_header(n_nodes: int, resolution: float) -> bytes:
    """The text header of a .ot stream of ``n_nodes`` nodes at ``resolution`` metres."""
    return (f"# Octomap OcTree file\n# (feel free to add / change comments, but leave the first line as it is!)\n"
            f"#\nid OcTree\nsize {n_nodes}\nres {float(resolution)!r}\ndata\n").encode()


def tree_from_stream(make_stream, cfg: OctoMapConfig):
    """An ``octomap.OcTree`` read in one C++ call from the ``.ot`` stream ``make_stream()`` returns (bytes
    or a uint8 array), with ``cfg``'s sensor model. The stream goes through a temporary file and is
    dropped before OctoMap reads it (a bytes argument would be copied twice more in memory), so the
    stream and the tree are never both alive at full size — as long as the caller keeps no reference."""
    import os
    import tempfile

    import octomap

    with tempfile.TemporaryDirectory(prefix="mono-map-ot-") as tmp:
        path = os.path.join(tmp, "map.ot")
        data = make_stream()
        with open(path, "wb") as fh:
            fh.write(memoryview(data))
        del data
        tree = octomap.OcTree.read(path.encode())
    return apply_sensor_model(tree, cfg)


def octree_from_cells(keys: np.ndarray, values: np.ndarray, cfg: OctoMapConfig):
    """An ``octomap.OcTree`` holding exactly these finest cells (float32 log-odds), with ``cfg``'s sensor
    model, read in one C++ call from :func:`ot_stream`."""
    if len(keys) == 0:
        return make_octree(cfg)
    return tree_from_stream(lambda: ot_stream(keys, values, cfg.resolution)[0], cfg)


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
            tree = octomap.OcTree(0.1)   # placeholder resolution: readBinary sets the file's own
            if not tree.readBinary(str(path).encode()):
                tree = None
    if tree is None:
        first = next((ln.strip() for ln in said[0].splitlines() if ln.strip()), "")
        raise MonoMapError(f"{path}: OctoMap could not read this tree" + (f" ({first[:120]})" if first else ""))
    return tree


def write_tree_bt(tree, path) -> None:
    """Write the max-likelihood binary tree (.bt) atomically. Note: OctoMap's writeBinary converts
    the tree in memory to max-likelihood and prunes it."""
    from mono_map.io import atomic_path

    with atomic_path(path, suffix=".bt") as tmp:
        if not tree.writeBinary(str(tmp).encode()):
            raise MonoMapError(f"{path}: OctoMap could not write the tree")


def write_tree_ot(tree, path) -> None:
    """Write the probabilistic tree (.ot: every node's log-odds) atomically."""
    from mono_map.io import atomic_path

    with atomic_path(path, suffix=".ot") as tmp:
        if not tree.write(str(tmp).encode()):
            raise MonoMapError(f"{path}: OctoMap could not write the tree")


# --------------------------------------------------------------------------- leaves


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


def tree_leaves(tree) -> Leaves:
    """All leaves of an ``octomap.OcTree`` as Morton intervals; states are maximum-likelihood: occupied iff
    log-odds ≥ the tree's occupancy threshold. The tree's .ot stream is read by the compiled kernel
    (``mm_ot_leaves``; a 12 M-leaf tree in ~1 s instead of ~6 s with OctoMap's leaf iterator, which is the
    fallback without a C compiler)."""
    from mono_map.mapping.raycast_c import load_kernel

    res = float(tree.getResolution())
    thr = float(tree.getOccupancyThresLog())
    n = int(tree.getNumLeafNodes())
    kernel = load_kernel()
    if kernel is not None and n > 0:
        keys, depth, value = stream_leaves(kernel, tree, n)
        side = (1 << (TREE_DEPTH - depth)).astype(np.int64)
    else:
        keys, depth, value = iterator_leaves(tree, n, res)
        side = (1 << (TREE_DEPTH - depth)).astype(np.int64)
        keys -= keys % side[:, None]                                   # align (guards rounding)
    start = morton_codes(keys)
    order = np.argsort(start, kind="stable")
    return Leaves(start=start[order], length=(side ** 3)[order], occupied=(value >= thr)[order], resolution=res,
                  value=value[order])


def stream_leaves(kernel, tree, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(min-corner keys, depths, float64 log-odds) of the ``n`` leaves of ``tree``, parsed from its .ot stream
    (written to a temporary file: octomap-python writes files only)."""
    import os
    import tempfile

    from mono_map.mapping.ot_c import ot_leaves_c

    with tempfile.TemporaryDirectory(prefix="mono-map-leaves-") as tmp:
        path = os.path.join(tmp, "tree.ot")
        if not tree.write(path.encode()):
            raise MonoMapError("OctoMap could not write the tree's .ot stream to read its leaves")
        data = np.fromfile(path, dtype=np.uint8)
    at = bytes(data[:4096]).find(b"\ndata\n")
    if at < 0:
        raise MonoMapError("OctoMap wrote a .ot stream without its 'data' line")
    keys, depth, value = ot_leaves_c(kernel, data[at + 6:], n)
    return keys, depth, value.astype(np.float64)


def iterator_leaves(tree, n: int, res: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(min-corner keys, depths, log-odds) of the ``n`` leaves of ``tree`` from OctoMap's leaf iterator."""
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
    size = (1 << (TREE_DEPTH - depth)).astype(np.int64) * res
    corner = xyz - size[:, None] / 2 + res / 2                     # centre of the min-corner cell
    return np.round(corner / res - 0.5).astype(np.int64) + TREE_MAX_VAL, depth, value


def occupied_keys(leaves: Leaves) -> np.ndarray:
    """Keys ((N, 3) int64, Morton order) of every finest cell inside an occupied leaf (pruned leaves expanded)."""
    occ = Leaves(leaves.start[leaves.occupied], leaves.length[leaves.occupied], leaves.occupied[leaves.occupied],
                 leaves.resolution)
    codes, _ = occ.expand()
    return morton_to_keys(codes)
