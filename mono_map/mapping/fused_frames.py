"""A frame's prediction into the fused surface, and its pixels' hits out of it (``--integrate fused``).

:func:`fuse_prediction` fuses one frame's expected depth (moved to its mode), weights and truncation bands from
its bin probabilities into a :class:`~mono_map.mapping.fused.SurfaceFusion` and queues the frame;
:func:`due_surface_points` snaps the queued frames' pixels ``lag`` frames later and returns their hits.
"""

from __future__ import annotations

import numpy as np

from mono_map.errors import MonoMapError
from mono_map.geometry import backproject_pixels, depth_normals, transform_points
from mono_map.mapping.fused import SurfaceFusion, log_spread, mode_shift, pixel_weights


def fuse_prediction(fusion: SurfaceFusion, pred, valid: np.ndarray, K: np.ndarray, T_world_cam2: np.ndarray,
                    edges: np.ndarray, ray_step: int) -> int:
    """Fuse one frame's prediction (``pred.depth`` H×W expected depth, ``pred.probs`` K×H'×W' bin probabilities
    every ``pred.probs_step`` pixels, optional ``pred.p_beyond`` H×W) at every ``ray_step``-th pixel row and
    column of the ``valid`` (H×W bool) pixels into ``fusion``; ``K``: image_2's 3×3 intrinsics. Pixels more
    likely beyond range than not, farther than ``max_depth`` or spread wider than ``max_spread`` are left out
    of the TSDF. The frame's expected depths (every ``snap_step``-th pixel of the grid, all of them: whether a
    pixel finds a surface decides) wait in ``fusion.pending`` to be snapped (:func:`due_surface_points`).
    Returns the number of pixels fused."""
    cfg = fusion.cfg
    s, ps = int(ray_step), int(getattr(pred, "probs_step", 1))
    if s % ps:
        raise MonoMapError(f"--integrate fused: bin probabilities every {ps} pixels cannot serve rays every {s}")
    probs = np.asarray(pred.probs)[:, ::s // ps, ::s // ps]
    depth = np.asarray(pred.depth, dtype=np.float32)[::s, ::s]
    ok = np.asarray(valid, dtype=bool)[::s, ::s]
    if probs.shape[1:] != depth.shape:
        raise MonoMapError(f"--integrate fused: bin probabilities {probs.shape} do not match the ray grid {depth.shape}")
    pb = getattr(pred, "p_beyond", None)
    if pb is not None:
        ok &= ~(np.asarray(pb)[::s, ::s] > 0.5)
    spread = log_spread(probs, edges)
    if cfg.mode:                                   # onto the dominant mode instead of the expectation
        depth = np.where(depth > 0, depth * np.exp(mode_shift(probs, edges)), np.float32(0.0)).astype(np.float32)
    ok &= (depth > 0) & (depth <= cfg.max_depth) & (spread <= cfg.max_spread)
    d = np.where(ok, depth, np.float32(0.0)).astype(np.float32)
    trunc = np.clip(cfg.trunc_sigma * d * spread, cfg.trunc_min * fusion.res, cfg.trunc_max).astype(np.float32)
    Ks = np.asarray(K, dtype=np.float64).copy()
    Ks[:2] /= s                                                      # pixel (s·j, s·i) is grid pixel (j, i)
    fine = None
    if cfg.subpixel:                                                 # the voxels read the full-resolution depth
        full = np.asarray(pred.depth, dtype=np.float32)
        okf = np.repeat(np.repeat(ok, s, axis=0), s, axis=1)[:full.shape[0], :full.shape[1]]
        fine = (np.where(okf & (full > 0), full, np.float32(0.0)), np.asarray(K, dtype=np.float64), s)
    # the surface's normals (euclid): of every pixel with a depth, the fused ones and those only snapped
    normals = depth_normals(np.where(depth > 0, depth, np.float32(0.0)), Ks)[0] if cfg.euclid else None
    fusion.integrate(d, pixel_weights(spread, cfg), trunc, Ks, T_world_cam2, fine, normals)
    q = int(cfg.snap_step)                                            # the pixels snapped later
    Kq = Ks.copy()
    Kq[:2] /= q
    fusion.pending.append((np.ascontiguousarray(np.where(depth > 0, depth, np.float32(0))[::q, ::q], np.float32),
                           Kq, np.asarray(T_world_cam2, dtype=np.float64),
                           None if normals is None else np.ascontiguousarray(normals[::q, ::q])))
    return int(ok.sum())


def due_surface_points(fusion: SurfaceFusion, flush: bool = False) -> list[np.ndarray]:
    """World points (N, 3) metres, one array per frame fused ``lag`` frames ago (``flush``: every frame still
    pending), of its pixels' depths snapped to the fused surface (:meth:`SurfaceFusion.snap_depths`); pixels
    with no surface within ``snap_window`` give none. Those frames leave the queue."""
    out = []
    while fusion.pending and (flush or len(fusion.pending) > fusion.cfg.lag):
        depth, Ks, T, normals = fusion.pending.pop(0)
        z = fusion.snap_depths(depth, Ks, T, fusion.cfg.snap_window, normals=normals)
        if fusion.cfg.gate > 0:     # the fused surface confirms the pixel's own depth instead of replacing it
            z = np.where((z > 0) & (np.abs(z - depth) <= fusion.cfg.gate * fusion.res), depth, np.float32(0.0))
        v, u = np.nonzero(z > 0)
        out.append(transform_points(T, backproject_pixels(Ks, u, v, z[v, u])))
    return out
