"""The compiled plane sweep (``csrc/sweep.c``): :func:`mono_map.depth.multiview.sweep_cost` one plane at a time in
C — each source warped through every plane (torch's bilinear, border-padded sampling at pixel centres), its
SSIM + L1 error against the target over 3×3 reflection-padded windows, the minimum over the sources — without
torch's (planes × pixels) temporaries (``benchmarks/bench_fused_build.py``). Images grey float32 in [0, 1];
poses 4×4 metres, target camera → source camera; K of the images' grid.
"""

from __future__ import annotations

import ctypes

import numpy as np

from mono_map import ckernel

_P, _I64 = ctypes.c_void_p, ctypes.c_int64
_LIB: list = []


def library():
    """The compiled sweep (ctypes library), or None (no compiler, or ``MONO_MAP_NO_C=1``)."""
    if ckernel.disabled():
        return None
    if not _LIB:
        _LIB.append(ckernel.load("sweep", {
            "mm_sweep_cost": ([_I64, _I64, _P, _I64, _P, _P, _P, _I64, _P, _P, _P], ctypes.c_int)}))
    return _LIB[0]


def sweep_cost(lib, target: np.ndarray, sources: list[np.ndarray], K: np.ndarray, T_src_tgt: list[np.ndarray],
               depths: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(cost (D, h, w) float32: per plane at ``depths`` (D,) metres the minimum over ``sources`` (each (h, w)) of
    the warped source's SSIM+L1 error against ``target`` (h, w), inf where no source sees the plane; identity
    (h, w): the minimum error of the unwarped sources)."""
    h, w = target.shape
    tgt = np.ascontiguousarray(target, dtype=np.float32)
    src = np.ascontiguousarray(np.stack([np.asarray(s, dtype=np.float32).reshape(h, w) for s in sources]))
    K = np.asarray(K, dtype=np.float64)
    Kinv = np.linalg.inv(K)
    m = np.ascontiguousarray(np.stack([(K @ np.asarray(T, np.float64)[:3, :3] @ Kinv).astype(np.float32)
                                       for T in T_src_tgt]))
    bt = np.ascontiguousarray(np.stack([(K @ np.asarray(T, np.float64)[:3, 3]).astype(np.float32) for T in T_src_tgt]))
    inv_d = np.ascontiguousarray(1.0 / np.asarray(depths, dtype=np.float64), dtype=np.float32)
    cost = np.empty((len(inv_d), h, w), np.float32)
    ident = np.empty((h, w), np.float32)
    if lib.mm_sweep_cost(h, w, tgt.ctypes.data, len(src), src.ctypes.data, m.ctypes.data, bt.ctypes.data, len(inv_d),
                         inv_d.ctypes.data, cost.ctypes.data, ident.ctypes.data) != 0:
        raise MemoryError("plane sweep: out of memory")
    return cost, ident
