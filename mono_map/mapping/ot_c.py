"""OctoMap's ``.ot`` stream, compiled (``csrc/raycast.c``): written from a log-odds mirror's blocks
(:class:`mono_map.mapping.mirror.LogOddsMirror`), its nodes and leaves counted, its leaves read back."""

from __future__ import annotations

import numpy as np


def _blocks_in_code_order(block_codes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(block slots sorted by their depth-13 code, the sorted codes), as ``mm_ot_nodes`` walks them."""
    codes = np.asarray(block_codes, dtype=np.int64)
    slot = np.argsort(codes, kind="stable").astype(np.int64)
    return slot, np.ascontiguousarray(codes[slot])


def ot_nodes_c(fn, pool: np.ndarray, block_codes: np.ndarray, header: bytes = b"") -> tuple[np.ndarray, int]:
    """``mm_ot_nodes``: (``header`` + the node bytes of OctoMap's .ot stream as a uint8 array, node count) of the
    known (non-NaN) cells of a log-odds mirror: float32 ``pool`` of blocks of 8×8×8 cells (see
    integrate.LogOddsMirror), ``block_codes`` (B,) each block's depth-13 code
    (``octree.child_order_codes(block_key >> 3)``). The nodes are the same bytes as ``octree.ot_stream`` of
    those cells. The buffer is sized for the worst case but only the written pages take memory."""
    assert pool.dtype == np.float32 and pool.flags.c_contiguous
    slot, codes = _blocks_in_code_order(block_codes)
    cap = (512 + 64 + 8 + 1 + 13) * len(slot) + 1     # a full block's subtree and its path to the root
    h = len(header)
    out = np.empty(h + 5 * cap, dtype=np.uint8)
    out[:h] = np.frombuffer(header, dtype=np.uint8)
    leaves = np.zeros(1, dtype=np.int64)
    n = fn.ot_nodes(pool.ctypes.data, slot.ctypes.data, codes.ctypes.data, len(slot), out[h:].ctypes.data, cap,
                    leaves.ctypes.data, None, None, None, None, None)
    if n < 0:
        raise AssertionError("node bound exceeded")   # cannot happen: cap bounds every block's nodes
    return out[:h + 5 * n], int(n)


def ot_counts_c(fn, pool: np.ndarray, block_codes: np.ndarray, cache: dict | None = None) -> tuple[int, int]:
    """``mm_ot_nodes`` counting only: (nodes, leaves) of the octree the mirror's known cells make (OctoMap's
    ``size()`` and ``getNumLeafNodes()``). ``cache``: per block slot arrays ``dirty`` (bool), ``kind`` (int8),
    ``value`` (float32), ``nodes`` and ``leaves`` (int64): only dirty blocks are walked; they are cached and
    marked clean."""
    slot, codes = _blocks_in_code_order(block_codes)
    leaves = np.zeros(1, dtype=np.int64)
    if cache is None:
        ptrs = (None,) * 5
    else:
        arrays = (cache["dirty"], cache["kind"], cache["value"], cache["nodes"], cache["leaves"])
        for a, dt in zip(arrays, (np.bool_, np.int8, np.float32, np.int64, np.int64)):
            assert a.dtype == dt and a.flags.c_contiguous and len(a) >= len(slot)
        ptrs = tuple(a.ctypes.data for a in arrays)
    n = fn.ot_nodes(pool.ctypes.data, slot.ctypes.data, codes.ctypes.data, len(slot), None, 0, leaves.ctypes.data,
                    *ptrs)
    return int(n), int(leaves[0])


def ot_leaves_c(fn, data: np.ndarray, n_leaves: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``mm_ot_leaves``: (min-corner keys (N, 3) int64, depths (N,) int64, float32 log-odds (N,)) of the
    leaves of a .ot node stream (uint8, header stripped) holding ``n_leaves`` leaves."""
    d = np.ascontiguousarray(data, dtype=np.uint8)
    keys = np.empty((n_leaves, 3), dtype=np.int64)
    depth = np.empty(n_leaves, dtype=np.int8)
    val = np.empty(n_leaves, dtype=np.float32)
    m = fn.ot_leaves(d.ctypes.data, len(d), n_leaves, keys.ctypes.data, depth.ctypes.data, val.ctypes.data)
    if m < 0 or m != n_leaves:
        raise AssertionError(f"mm_ot_leaves: {m} (tree of {n_leaves} leaves)")   # OctoMap wrote the stream
    return keys, depth.astype(np.int64), val
