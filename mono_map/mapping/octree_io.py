"""Build OctoMap's full ``.ot`` stream for a set of finest cells in numpy, and load it as an OcTree.

Gives, in one C++ read, the tree OctoMap would hold after updating those cells one by one:
OctoMap prunes eight sibling leaves with equal log-odds into their parent after every update and
an inner node holds the maximum of its children, so the final tree depends only on the cell
values. The stream is a pre-order walk: per node its float32 log-odds and one byte whose bit i
says child i exists (child index: +1 for the x bit, +2 for y, +4 for z of the key at that level).
"""

from __future__ import annotations

import numpy as np

from mono_map.mapping.raycast import _spread_bits

TREE_DEPTH = 16
_NODE = np.dtype([("v", "<f4"), ("c", "u1")])


def dfs_codes(keys: np.ndarray) -> np.ndarray:
    """Codes whose sort order is OctoMap's child order at every level (z, y, x bits interleaved)."""
    k = np.asarray(keys, dtype=np.int64)
    return ((_spread_bits(k[:, 2]) << np.uint64(2)) | (_spread_bits(k[:, 1]) << np.uint64(1))
            | _spread_bits(k[:, 0])).astype(np.int64)


def ot_stream(keys: np.ndarray, values: np.ndarray, resolution: float) -> tuple[bytes, int]:
    """(bytes of a .ot file, number of nodes) for finest cells ``keys`` (N ≥ 1, 3) with float32 ``values``."""
    codes = dfs_codes(keys)
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
    """The text header of a .ot stream of ``n_nodes`` nodes."""
    return (f"# Octomap OcTree file\n# (feel free to add / change comments, but leave the first line as it is!)\n"
            f"#\nid OcTree\nsize {n_nodes}\nres {float(resolution)!r}\ndata\n").encode()


def octree_from_cells(keys: np.ndarray, values: np.ndarray, cfg):
    """An ``octomap.OcTree`` holding exactly these finest cells, with ``cfg``'s sensor model."""
    from mono_map.mapping.integrate import apply_sensor_model, make_octree

    if len(keys) == 0:
        return make_octree(cfg)
    import octomap

    data, _ = ot_stream(keys, values, cfg.resolution)
    return apply_sensor_model(octomap.OcTree.read(data), cfg)
