"""Rigid transforms and pinhole projection (metres, pixels).

Conventions (see docs/data.md): poses are 4×4 float64 ``T_a_b`` mapping points
from frame b to frame a; camera frames are x right, y down, z forward.
"""

from __future__ import annotations

import numpy as np


def make_pose(R: np.ndarray | None = None, t: np.ndarray | None = None) -> np.ndarray:
    """4×4 float64 pose from a 3×3 rotation and a translation (metres)."""
    T = np.eye(4)
    if R is not None:
        T[:3, :3] = R
    if t is not None:
        T[:3, 3] = np.asarray(t, dtype=np.float64).reshape(3)
    return T


def pose_inverse(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid 4×4 transform (exact: R^T, -R^T t)."""
    R = T[:3, :3]
    t = T[:3, 3]
    out = np.eye(4)
    out[:3, :3] = R.T
    out[:3, 3] = -R.T @ t
    return out


def transform_points(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply 4×4 ``T`` to (N, 3) points; returns float64 (N, 3)."""
    p = np.asarray(points, dtype=np.float64)[:, :3]
    return p @ T[:3, :3].T + T[:3, 3]


def intrinsics_from_projection(P: np.ndarray) -> np.ndarray:
    """The 3×3 intrinsics K of a rectified 3×4 projection P = K·[I | t]."""
    return np.array(P, dtype=np.float64)[:3, :3].copy()


def scaled_intrinsics(K: np.ndarray, sx: float, sy: float) -> np.ndarray:
    """3×3 intrinsics after resizing an image by (sx, sy) (new size / old size), pixel centres kept:
    u' + ½ = (u + ½)·sx, v' + ½ = (v + ½)·sy."""
    K2 = np.array(K, np.float64).copy()
    K2[0, 0] *= sx
    K2[0, 1] *= sx
    K2[0, 2] = (K2[0, 2] + 0.5) * sx - 0.5
    K2[1, 1] *= sy
    K2[1, 2] = (K2[1, 2] + 0.5) * sy - 0.5
    return K2


def T_cam_cam0_from_projection(P: np.ndarray) -> np.ndarray:
    """Pose ``T_camX_cam0`` of a rectified camera whose projection is P = K·[I | t].

    KITTI's rectified cameras share cam0's orientation; ``t = K⁻¹ P[:, 3]`` is the
    translation from cam0 to camX (for image_2 about +0.06 m along x, i.e. the camera
    centre sits 6 cm to the left of cam0's).
    """
    P = np.asarray(P, dtype=np.float64)
    K = P[:3, :3]
    t = np.linalg.solve(K, P[:3, 3])
    return make_pose(np.eye(3), t)


def project_points(K: np.ndarray, points_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Project (N, 3) camera-frame points: returns pixel coordinates (N, 2) and depth z (N,).

    Pixel (u, v) = (0, 0) is the centre of the top-left pixel (OpenCV / KITTI).
    Points with z <= 0 get NaN pixel coordinates.
    """
    p = np.asarray(points_cam, dtype=np.float64)
    z = p[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uvw = p @ np.asarray(K, dtype=np.float64).T
        uv = uvw[:, :2] / uvw[:, 2:3]
    uv[z <= 0] = np.nan
    return uv, z


def backproject_pixels(K: np.ndarray, u: np.ndarray, v: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """Camera-frame points (N, 3) of pixels (u, v) at depth z (metres along the optical axis)."""
    return np.stack(backproject_columns(K, u, v, depth), axis=-1)


def backproject_columns(K: np.ndarray, u: np.ndarray, v: np.ndarray,
                        depth: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`backproject_pixels` as three contiguous (N,) float64 arrays x, y, z (camera frame, metres)."""
    K = np.asarray(K, dtype=np.float64)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    skew = K[0, 1]
    z = np.asarray(depth, dtype=np.float64)
    y = (np.asarray(v, dtype=np.float64) - cy) / fy * z
    x = ((np.asarray(u, dtype=np.float64) - cx) * z - skew * y) / fx
    return x, y, z


def lidar_depth_image(points_cam: np.ndarray, K: np.ndarray, height: int, width: int,
                      min_depth: float = 1e-3) -> np.ndarray:
    """Sparse depth image (H, W) float32 from camera-frame points; 0 = no value.

    Points are rounded to the nearest pixel; where several land on one pixel the
    nearest wins (the usual KITTI practice for LiDAR depth targets).
    """
    uv, z = project_points(K, points_cam)
    ok = z > min_depth
    uv, z = uv[ok], z[ok]
    u = np.round(uv[:, 0]).astype(np.int64)
    v = np.round(uv[:, 1]).astype(np.int64)
    inside = (u >= 0) & (u < width) & (v >= 0) & (v < height)
    u, v, z = u[inside], v[inside], z[inside]
    depth = np.full(height * width, np.inf, dtype=np.float64)
    np.minimum.at(depth, v * width + u, z)
    depth[~np.isfinite(depth)] = 0.0
    return depth.reshape(height, width).astype(np.float32)


def depth_normals(depth: np.ndarray, K: np.ndarray, min_cos: float = 0.05) -> tuple[np.ndarray, np.ndarray]:
    """Surface normals of a z-depth image ``depth`` (H, W) metres (0 = none) with pinhole ``K`` (3×3).

    Each pixel's two tangents are the differences of its back-projected point to a row and a column
    neighbour, on the side whose depth differs less (so a pixel beside a depth edge takes the surface it is
    on). Returns (normals (H, W, 3) float32 unit vectors in the camera frame, facing the camera, and
    cos (H, W) float32 = −n·(x/z, y/z, 1) ≥ ``min_cos``: a point at depth z on the pixel's ray lies
    cos·(d − z) metres in front of the plane through the pixel's surface point). Pixels without a
    usable neighbour on either axis get the reversed ray as normal (cos = |ray|)."""
    d = np.asarray(depth, dtype=np.float32)
    h, w = d.shape
    v, u = np.mgrid[0:h, 0:w].astype(np.float32)
    ray = np.stack([(u - np.float32(K[0, 2])) / np.float32(K[0, 0]),
                    (v - np.float32(K[1, 2])) / np.float32(K[1, 1]), np.ones_like(u)], axis=-1)
    P = ray * d[..., None]

    def tangent(axis: int) -> tuple[np.ndarray, np.ndarray]:
        fwd = np.zeros_like(P)
        bwd = np.zeros_like(P)
        ok_f = np.zeros(d.shape, bool)
        ok_b = np.zeros(d.shape, bool)
        if axis == 0:
            fwd[:-1], ok_f[:-1] = P[1:] - P[:-1], (d[1:] > 0) & (d[:-1] > 0)
            bwd[1:], ok_b[1:] = P[1:] - P[:-1], ok_f[:-1]
        else:
            fwd[:, :-1], ok_f[:, :-1] = P[:, 1:] - P[:, :-1], (d[:, 1:] > 0) & (d[:, :-1] > 0)
            bwd[:, 1:], ok_b[:, 1:] = P[:, 1:] - P[:, :-1], ok_f[:, :-1]
        use_f = ok_f & (~ok_b | (np.abs(fwd[..., 2]) <= np.abs(bwd[..., 2])))
        return np.where(use_f[..., None], fwd, bwd), ok_f | ok_b

    tv, ok_v = tangent(0)
    tu, ok_u = tangent(1)
    n = np.cross(tu, tv)
    norm = np.linalg.norm(n, axis=-1)
    good = ok_u & ok_v & (norm > 0)
    n = np.where(good[..., None], n / np.where(good, norm, 1.0)[..., None], -ray / np.linalg.norm(ray, axis=-1,
                                                                                                   keepdims=True))
    cos = -(n * ray).sum(axis=-1)
    n = np.where((cos < 0)[..., None], -n, n)                    # facing the camera
    cos = np.maximum(np.abs(cos), np.float32(min_cos))
    return n.astype(np.float32), cos.astype(np.float32)
