"""How much of a depth error the views share (docs/fused.md, "How good the depth must be").

Two frames of a synthetic sequence see some surface points in both; at those points a predictor's log-depth
errors (log predicted − log true, each in its own frame) can be compared. Their correlation is the share of the
error's variance the two views have in common — an error fixed to the surface (a network's bias for what it sees)
gives ~1, noise drawn per frame ~0. Fusion across views averages the unshared part away and keeps the shared part.
"""

from __future__ import annotations

import numpy as np

from mono_map.geometry import pose_inverse, project_points, transform_points
from mono_map.mapping.points import pixels_to_world


def common_surface_pixels(seq, i: int, j: int, max_px: float = 0.1,
                          max_depth_m: float = 0.01) -> tuple[np.ndarray, np.ndarray]:
    """Pixels of frames ``i`` and ``j`` that see one surface point (by the ground-truth depth ``depth_2``): frame
    i's pixel whose point projects into frame j within ``max_px`` of a pixel centre, with j's true depth there
    within ``max_depth_m`` metres of the point's (visible, not occluded). Returns ((N, 2), (N, 2)) int (row, column)
    in i and in j."""
    gi, gj = seq.depth(i), seq.depth(j)
    if gi is None or gj is None:
        raise ValueError(f"frames {i}, {j}: no ground-truth depth (synthetic sequences only)")
    mask = gi > 0
    rows_i, cols_i = np.nonzero(mask)
    pts = pixels_to_world(np.asarray(gi, np.float32), mask, seq.calib.K2, seq.T_world_cam2(i))
    uv, z = project_points(seq.calib.K2, transform_points(pose_inverse(seq.T_world_cam2(j)), pts))
    ok = np.isfinite(uv).all(axis=1)
    r = np.zeros(uv.shape, dtype=np.int64)
    r[ok] = np.rint(uv[ok]).astype(np.int64)
    h, w = gj.shape
    ok &= (np.abs(uv - r) <= max_px).all(axis=1) & (r[:, 0] >= 0) & (r[:, 0] < w) & (r[:, 1] >= 0) & (r[:, 1] < h)
    ok[ok] &= np.abs(gj[r[ok, 1], r[ok, 0]] - z[ok]) <= max_depth_m
    return np.stack([rows_i[ok], cols_i[ok]], axis=1), np.stack([r[ok, 1], r[ok, 0]], axis=1)


def log_errors(pred_depth: np.ndarray, true_depth: np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """log(predicted / true depth) at (row, column) ``pixels`` (N,) float64; both depths > 0 there."""
    p = np.asarray(pred_depth, np.float64)[pixels[:, 0], pixels[:, 1]]
    t = np.asarray(true_depth, np.float64)[pixels[:, 0], pixels[:, 1]]
    return np.log(p / t)


def shared_share(err_i: np.ndarray, err_j: np.ndarray) -> dict:
    """Statistics of paired log errors of one surface point in two views: ``n``, ``rms`` (of both views'
    errors), ``correlation`` (the shared share of the variance), ``rms_difference``."""
    a, b = np.asarray(err_i, np.float64), np.asarray(err_j, np.float64)
    if len(a) < 2 or a.std() == 0 or b.std() == 0:
        corr = float("nan")
    else:
        corr = float(np.corrcoef(a, b)[0, 1])
    return {"n": int(len(a)), "rms": float(np.sqrt(np.mean(np.concatenate([a, b]) ** 2))) if len(a) else float("nan"),
            "correlation": corr, "rms_difference": float(np.sqrt(np.mean((a - b) ** 2))) if len(a) else float("nan")}
