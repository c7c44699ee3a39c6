"""The compiled plane sweep (``csrc/sweep.c``): :func:`mono_map.depth.multiview.sweep_cost` one plane at a time in
C — each source warped through every plane (torch's bilinear, border-padded sampling at pixel centres), its
SSIM + L1 error against the target over 3×3 reflection-padded windows, the minimum over the sources — without
torch's (planes × pixels) temporaries (``benchmarks/bench_fused_build.py``); also the sweep's windowed cost and
its reading at the prior's pixels (:func:`~mono_map.depth.multiview.windowed_cost`,
:func:`~mono_map.depth.multiview.resample`). Images grey float32 in [0, 1]; poses 4×4 metres, target camera →
source camera; K of the images' grid.
"""

from __future__ import annotations

import ctypes

import numpy as np

from mono_map import ckernel

_P, _I64 = ctypes.c_void_p, ctypes.c_int64
library = ckernel.loader("sweep", {
    "mm_sweep_cost": ([_I64, _I64, _P, _I64, _P, _P, _P, _I64, _P, _P, _P], ctypes.c_int),
    "mm_windowed_cost": ([_I64, _I64, _I64, _P, _P, _I64, _P, _P, _P], ctypes.c_int),
    "mm_resample": ([_I64, _I64, _I64, _P, _I64, _I64, _I64, _I64, _I64, _P], None),
}, "The compiled plane sweep")


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


def windowed_cost(lib, cost: np.ndarray, ident: np.ndarray, window: int) -> tuple[np.ndarray, np.ndarray]:
    """:func:`mono_map.depth.multiview.windowed_cost` of ``cost`` (D, h, w) float32 (inf: unseen) and ``ident``
    (h, w): (windowed cost (D, h, w), informative (h, w) bool)."""
    D, h, w = cost.shape
    cost = np.ascontiguousarray(cost, dtype=np.float32)
    ident = np.ascontiguousarray(ident, dtype=np.float32)
    c_out = np.empty_like(cost)
    i_out = np.empty_like(ident)
    info = np.empty((h, w), np.uint8)
    if lib.mm_windowed_cost(D, h, w, cost.ctypes.data, ident.ctypes.data, int(window), c_out.ctypes.data,
                            i_out.ctypes.data, info.ctypes.data) != 0:
        raise MemoryError("plane sweep: out of memory")
    return c_out, info.astype(bool)


def resample(lib, x: np.ndarray, size: tuple[int, int], full: tuple[int, int], step: int) -> np.ndarray:
    """:func:`mono_map.depth.multiview.resample` of ``x`` (C, h, w) float32: ``size`` + (C,) float32."""
    C, h, w = x.shape
    xl = np.ascontiguousarray(np.asarray(x, dtype=np.float32).transpose(1, 2, 0))
    out = np.empty((size[0], size[1], C), np.float32)
    lib.mm_resample(h, w, C, xl.ctypes.data, size[0], size[1], full[0], full[1], int(step), out.ctypes.data)
    return out
