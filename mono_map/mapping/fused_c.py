"""The compiled kernels of the fused surface (``csrc/fused.c``), numpy's operations in its order without its
temporaries (``benchmarks/bench_fused_build.py``): :meth:`mono_map.mapping.fused.SurfaceFusion.snap_depths` in two
passes around open3d's hash-map lookup — the samples along each pixel's ray (their blocks, their voxels, how far
each cell's value moves to its sample), then the tsdf read and the zero crossing nearest each pixel's depth —,
and :meth:`~mono_map.mapping.fused.SurfaceFusion.integrate`'s update of the voxels near a frame's surface.
Metres; world = the sequence's first cam0 frame.
"""

from __future__ import annotations

import ctypes

import numpy as np

from mono_map import ckernel

_P, _I64, _D, _F = ctypes.c_void_p, ctypes.c_int64, ctypes.c_double, ctypes.c_float
library = ckernel.loader("fused", {
    "mm_snap_samples": ([_I64, _P, _P, _P, _I64, _P, _P, _P, _P, _D, _P, _P, _P, _P], None),
    "mm_snap_cross": ([_I64, _I64, _P, _P, _P, _P, _P, _P, _F, _F, _I64, _P], None),
    "mm_tsdf_update": ([_I64, _P, _P, _P, _P, _P, _P, _P, _P, _P, _P, _I64, _I64, _F, _D, _P, _P], _I64),
}, "The compiled fused surface's TSDF update and snap")


def ray_samples(lib, u: np.ndarray, v: np.ndarray, z0: np.ndarray, offs: np.ndarray, K: np.ndarray,
                T_world_cam: np.ndarray, res: float, normals_world: np.ndarray | None = None):
    """Pass 1 for pixels (``u``, ``v``) int64 with depths ``z0`` float64 (P,), samples at ``z0 + offs`` (S,)
    metres: (block coordinates (P·S, 3) int32, voxel index in its block (P·S,) int32, sample depths (P, S)
    float64, step (P, S) float64: the sample's signed distance minus its cell centre's — along the camera's axis,
    or along ``normals_world`` (P, 3) if given)."""
    n, s = len(u), len(offs)
    c = dict(u=np.ascontiguousarray(u, dtype=np.int64), v=np.ascontiguousarray(v, dtype=np.int64),
             z0=np.ascontiguousarray(z0, dtype=np.float64), offs=np.ascontiguousarray(offs, dtype=np.float64),
             k=np.ascontiguousarray(K, dtype=np.float64),
             t=np.ascontiguousarray(np.asarray(T_world_cam, dtype=np.float64)[:3, :4]))
    nw = None if normals_world is None else np.ascontiguousarray(normals_world, dtype=np.float64)
    blk = np.empty((n * s, 3), np.int32)
    loc = np.empty(n * s, np.int32)
    zs = np.empty((n, s), np.float64)
    step = np.empty((n, s), np.float64)
    lib.mm_snap_samples(n, c["u"].ctypes.data, c["v"].ctypes.data, c["z0"].ctypes.data, s, c["offs"].ctypes.data,
                        c["k"].ctypes.data, c["t"].ctypes.data, None if nw is None else nw.ctypes.data, float(res),
                        blk.ctypes.data, loc.ctypes.data, zs.ctypes.data, step.ctypes.data)
    return blk, loc, zs, step


def crossings(lib, slots: np.ndarray, loc: np.ndarray, zs: np.ndarray, step: np.ndarray, tsdf: np.ndarray,
              weight: np.ndarray, trunc_max: float, min_weight: float) -> np.ndarray:
    """Pass 2: per pixel (row of ``zs`` (P, S)) the depth (float32, 0 = none) of the zero crossing (from ≥ 0 to
    < 0, both samples with summed weight ≥ ``min_weight`` and depth > 0) nearest the middle sample, given each
    sample's block slot ``slots`` (P·S,) int64 (−1: no block), its voxel ``loc`` and ``step``; ``tsdf`` and
    ``weight``: open3d's attribute buffers (float32, 512 voxels a block), tsdf in units of ``trunc_max``."""
    n, s = zs.shape
    out = np.zeros(n, np.float32)
    slots = np.ascontiguousarray(slots, dtype=np.int64)
    tsdf = np.ascontiguousarray(tsdf, dtype=np.float32)
    weight = np.ascontiguousarray(weight, dtype=np.float32)
    lib.mm_snap_cross(n, s, slots.ctypes.data, loc.ctypes.data, zs.ctypes.data, step.ctypes.data, tsdf.ctypes.data,
                      weight.ctypes.data, float(trunc_max), float(min_weight), (s - 1) // 2, out.ctypes.data)
    return out


def tsdf_update(lib, vcoords: np.ndarray, vidx: np.ndarray, R: np.ndarray, t: np.ndarray, K: np.ndarray,
                depth: np.ndarray, trunc: np.ndarray, weight: np.ndarray, normals: np.ndarray | None,
                trunc_behind: float, trunc_max: float, tsdf: np.ndarray, wsum: np.ndarray) -> int:
    """One frame's TSDF update in place of open3d's buffers ``tsdf`` and ``wsum`` (float32, flattened): voxels at
    ``vcoords`` (N, 3) float32 with flattened indices ``vidx`` (N,) int64, camera ``R`` (3×3), ``t`` (3,) float32
    (world → camera, to the cells' centres), grid intrinsics ``K``; per pixel ``depth``, ``trunc``, ``weight``
    (H, W) float32 and ``normals`` (H, W, 3) or None (:meth:`SurfaceFusion.integrate`). Returns voxels updated."""
    h, w = depth.shape
    c = [np.ascontiguousarray(a, dtype=np.float32) for a in (vcoords, R, t, depth, trunc, weight)]
    idx = np.ascontiguousarray(vidx, dtype=np.int64)
    K = np.asarray(K, dtype=np.float64)
    kf = np.array([K[0, 0], K[0, 2], K[1, 1], K[1, 2]], dtype=np.float32)
    k64 = np.ascontiguousarray(K)
    nrm = None if normals is None else np.ascontiguousarray(normals, dtype=np.float32)
    if not (tsdf.flags.c_contiguous and wsum.flags.c_contiguous and tsdf.dtype == wsum.dtype == np.float32):
        raise ValueError("tsdf_update: the buffers must be contiguous float32 (views of open3d's)")
    return int(lib.mm_tsdf_update(len(idx), c[0].ctypes.data, idx.ctypes.data, c[1].ctypes.data, c[2].ctypes.data,
                                  kf.ctypes.data, k64.ctypes.data, c[3].ctypes.data, c[4].ctypes.data,
                                  c[5].ctypes.data, None if nrm is None else nrm.ctypes.data, h, w,
                                  float(np.float32(-trunc_behind)), float(trunc_max), tsdf.ctypes.data,
                                  wsum.ctypes.data))
