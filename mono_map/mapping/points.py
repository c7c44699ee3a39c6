"""Measurements → world points and sensor origins (metres; world = first cam0 frame).

Camera: pixels (u, v) with depth z along image_2's optical axis → cam2 with K2⁻¹ → world with
``T_world_cam2``; the sensor origin is image_2's optical centre. LiDAR: velodyne points → world
with ``T_world_velo = T_world_cam2 · T_cam2_velo``; the origin is the velodyne centre.
"""

from __future__ import annotations

import ctypes

import numpy as np

from mono_map import ckernel, geometry

# pixels_to_world and lidar_to_world in one pass over the image / scan (mono_map/csrc/points.c): the float64
# operations of the numpy forms in the same order (built without fused multiply-adds: numpy's bits), 6-12x faster
# than their temporaries (docs/history/results-log.md).
_P, _I64 = ctypes.c_void_p, ctypes.c_int64
FOV_MIN_DEPTH = 1e-3        # metres in front of image_2 for a LiDAR point to count as in view
library = ckernel.loader("points", {
    "mm_pixels_to_world": ([_P, _P, _I64, _I64, _P, _P, _P], _I64),
    "mm_lidar_to_world": ([_P, _I64, _I64, ctypes.c_int, _P, _P, _I64, _I64, ctypes.c_double, _P, _P], _I64),
}, "The compiled back-projection and LiDAR transform")


def pixels_to_world(depth: np.ndarray, mask: np.ndarray, K: np.ndarray, T_world_cam2: np.ndarray) -> np.ndarray:
    """(N, 3) float64 world points of the masked pixels of an H×W depth image (metres, z-depth), in raster
    order. A float32 depth image goes through the compiled kernel (the same bits as the numpy form)."""
    lib = library() if np.asarray(depth).dtype == np.float32 else None
    if lib is None:
        return pixels_to_world_numpy(depth, mask, K, T_world_cam2)
    depth = np.ascontiguousarray(depth)
    mask = np.ascontiguousarray(mask, dtype=np.bool_)
    if depth.ndim != 2 or mask.shape != depth.shape:
        raise ValueError(f"pixels_to_world: depth {depth.shape} and mask {mask.shape} must be one H×W shape")
    k = np.ascontiguousarray(K, dtype=np.float64)
    t = np.ascontiguousarray(np.asarray(T_world_cam2, dtype=np.float64)[:3, :4])
    out = np.empty((int(np.count_nonzero(mask)), 3), dtype=np.float64)
    n = lib.mm_pixels_to_world(depth.ctypes.data, mask.ctypes.data, depth.shape[0], depth.shape[1], k.ctypes.data,
                               t.ctypes.data, out.ctypes.data)
    assert n == len(out)
    return out


def pixels_to_world_numpy(depth: np.ndarray, mask: np.ndarray, K: np.ndarray, T_world_cam2: np.ndarray) -> np.ndarray:
    """:func:`pixels_to_world` in numpy (the reference of the compiled path; any depth dtype)."""
    v, u = np.nonzero(mask)
    return pixel_points_to_world(u, v, np.asarray(depth, dtype=np.float64)[v, u], K, T_world_cam2)


def pixel_points_to_world(u: np.ndarray, v: np.ndarray, z: np.ndarray, K: np.ndarray,
                          T_world_cam2: np.ndarray) -> np.ndarray:
    """(N, 3) float64 world points of pixels (u, v) (columns, rows) at z-depths z (metres)."""
    return rigid_columns(T_world_cam2, *geometry.backproject_columns(K, u, v, np.asarray(z, dtype=np.float64)))


def rigid_columns(T: np.ndarray, x: np.ndarray, y: np.ndarray, z: np.ndarray) -> np.ndarray:
    """(N, 3) points T · (x, y, z) from contiguous coordinate columns, written out (no BLAS call: cheaper
    and thread-free for 3×3; contiguous columns: ~1.6x faster than the same sums over an (N, 3) array)."""
    T = np.asarray(T, dtype=np.float64)
    out = np.empty((len(x), 3), dtype=np.float64)
    acc, tmp = np.empty(len(x)), np.empty(len(x))
    for r in range(3):   # T[r,0]·x + T[r,1]·y + T[r,2]·z + T[r,3] in this order: the bits of the (N, 3) form
        np.multiply(x, T[r, 0], out=acc)
        np.multiply(y, T[r, 1], out=tmp)
        acc += tmp
        np.multiply(z, T[r, 2], out=tmp)
        acc += tmp
        acc += T[r, 3]
        out[:, r] = acc
    return out


def camera_origin(T_world_cam2: np.ndarray) -> np.ndarray:
    """Optical centre of image_2 in the world (3,)."""
    return np.asarray(T_world_cam2, dtype=np.float64)[:3, 3].copy()


def in_camera_fov(points_velo: np.ndarray, T_cam2_velo: np.ndarray, K: np.ndarray, height: int, width: int,
                  min_depth: float = FOV_MIN_DEPTH) -> np.ndarray:
    """Bool (N,): velodyne points that project inside image_2 (nearest pixel in range) with positive depth."""
    pts_cam = geometry.transform_points(T_cam2_velo, np.asarray(points_velo)[:, :3])
    uv, z = geometry.project_points(K, pts_cam)
    ok = z > min_depth
    with np.errstate(invalid="ignore"):
        u = np.round(uv[:, 0])
        v = np.round(uv[:, 1])
        ok &= (u >= 0) & (u < width) & (v >= 0) & (v < height)
    return ok


def lidar_to_world(scan: np.ndarray, T_world_cam2: np.ndarray, T_cam2_velo: np.ndarray,
                   fov_only: bool = False, K: np.ndarray | None = None,
                   image_size: tuple[int, int] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """World points (N, 3) of a velodyne scan ((M, ≥3), velodyne frame) and the velodyne centre (3,).

    fov_only: keep only points inside image_2's field of view (needs K and image_size (H, W)).
    Non-finite points are dropped. A float32 scan goes through the compiled kernel: the same points in the
    same order and bits as :func:`lidar_to_world_numpy` (the view test's arithmetic is written out where
    numpy multiplies matrices, so a point exactly on a pixel's rounding boundary could in principle fall the
    other way; tested equal on scans of 00).
    """
    if fov_only and (K is None or image_size is None):
        raise ValueError("fov_only needs K and image_size")
    scan = np.asarray(scan)
    lib = library() if scan.dtype == np.float32 and scan.ndim == 2 and scan.shape[1] >= 3 else None
    if lib is None:
        return lidar_to_world_numpy(scan, T_world_cam2, T_cam2_velo, fov_only, K, image_size)
    T_world_velo = np.asarray(T_world_cam2, dtype=np.float64) @ np.asarray(T_cam2_velo, dtype=np.float64)
    scan = np.ascontiguousarray(scan)
    out = np.empty((len(scan), 3), dtype=np.float64)
    tcv = np.ascontiguousarray(np.asarray(T_cam2_velo, dtype=np.float64)[:3, :4])
    k = np.ascontiguousarray(np.eye(3) if K is None else K, dtype=np.float64)
    h, w = image_size if fov_only else (0, 0)
    twv = np.ascontiguousarray(T_world_velo[:3, :4])
    m = lib.mm_lidar_to_world(scan.ctypes.data, len(scan), scan.shape[1], int(fov_only), tcv.ctypes.data,
                              k.ctypes.data, h, w, FOV_MIN_DEPTH, twv.ctypes.data, out.ctypes.data)
    return out[:m], T_world_velo[:3, 3].copy()


def lidar_to_world_numpy(scan: np.ndarray, T_world_cam2: np.ndarray, T_cam2_velo: np.ndarray,
                         fov_only: bool = False, K: np.ndarray | None = None,
                         image_size: tuple[int, int] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """:func:`lidar_to_world` in numpy (the reference of the compiled path; any dtype)."""
    T_world_velo = np.asarray(T_world_cam2, dtype=np.float64) @ np.asarray(T_cam2_velo, dtype=np.float64)
    pts = np.asarray(scan, dtype=np.float64)[:, :3]
    pts = pts[np.isfinite(pts).all(axis=1)]
    if fov_only:
        pts = pts[in_camera_fov(pts, T_cam2_velo, K, image_size[0], image_size[1])]
    return rigid_columns(T_world_velo, pts[:, 0], pts[:, 1], pts[:, 2]), T_world_velo[:3, 3].copy()
