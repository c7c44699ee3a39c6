"""One frame of distribution integration: the valid pixels' bin probabilities of a prediction → the
rays' distributions → the cells' expected OctoMap updates (:mod:`mono_map.mapping.distribution`),
inserted into a :class:`~mono_map.mapping.integrate.MapIntegrator`.
"""

from __future__ import annotations

import numpy as np

from mono_map.errors import MonoMapError
from mono_map.mapping.distribution import (CellUpdates, DistributionConfig, distribution_update, far_depth,
                                           narrow_bins, ray_distributions, unconditional_mass)
from mono_map.mapping.integrate import MapIntegrator
from mono_map.mapping.points import camera_origin, pixel_points_to_world


def distribution_frame(integrator: MapIntegrator, pred, valid: np.ndarray, K: np.ndarray, T_world_cam2: np.ndarray,
                       edges: np.ndarray, dcfg: DistributionConfig, frame: int, free_only: bool = False):
    """Integrate the valid pixels' distributions of one prediction (``probs`` K×H×W, conditional on a
    surface within range as DepthPrediction's; optional ``p_beyond`` H×W, the probability of no surface
    within range). Each pixel's unconditional bin mass is (1 − p_beyond) · probs and p_beyond is mass
    beyond every cell; pixels with nothing within range (p_beyond > 1 − eps) are skipped. ``free_only``:
    only the free-space (negative) updates are applied (the free half of a fused map).
    Returns (FrameIntegration, number of rays)."""
    if pred.probs is None:
        raise MonoMapError(f"frame {frame}: the predictor gave no bin probabilities (--integrate distribution "
                           f"needs a distribution head: binary, softmax, ordinal, gaussian or a dropout variant)")
    probs = np.asarray(pred.probs)
    s, ps = dcfg.ray_step, getattr(pred, "probs_step", 1)
    if s % ps:
        raise MonoMapError(f"frame {frame}: bin probabilities every {ps} pixels cannot serve rays every {s}")
    h, w = -(-valid.shape[0] // ps), -(-valid.shape[1] // ps)
    if probs.ndim != 3 or probs.shape[1:] != (h, w) or probs.shape[0] != len(edges) - 1:
        raise MonoMapError(f"frame {frame}: bin probabilities are {probs.shape}, expected ({len(edges) - 1}, {h}, {w})")
    pb_img = getattr(pred, "p_beyond", None)
    if pb_img is not None:
        valid = valid & ~(np.asarray(pb_img) > 1.0 - dcfg.eps)
    sub = valid[::s, ::s]
    v, u = np.nonzero(sub)
    v, u = v * s, u * s
    pb = np.zeros(len(v)) if pb_img is None else np.clip(np.asarray(pb_img, dtype=np.float64)[v, u], 0.0, 1.0)
    grid = probs[:, ::s // ps, ::s // ps]          # the rays' pixels; a (H', W', K) array's view when ps == s
    cl = np.moveaxis(grid, 0, -1)                  # (H', W', K)
    if dcfg.bin_spread < 1.0:
        p, edges = narrow_bins(unconditional_mass(cl[sub], pb, dcfg.temperature), edges, dcfg.bin_spread)
        fd = far_depth(p, pb, edges, dcfg.eps)
    elif cl.flags.c_contiguous:                    # the rays' rows read in place (no gathered copy)
        p, fd = ray_distributions(cl.reshape(-1, cl.shape[-1]), pb, dcfg.temperature, edges, dcfg.eps,
                                  rows=np.flatnonzero(sub))
    else:
        p, fd = ray_distributions(cl[sub], pb, dcfg.temperature, edges, dcfg.eps, overwrite=True)
    upd = distribution_update(camera_origin(T_world_cam2), pixel_points_to_world(u, v, fd, K, T_world_cam2), fd,
                              p, pb, edges, integrator.cfg.resolution, integrator.hit, integrator.miss,
                              integrator.cfg.max_range, dcfg.min_update, dcfg.quantum, dcfg.snap_free)
    if free_only:
        upd = free_updates(upd)
    return integrator.insert_updates(upd), int(len(v))


def free_updates(upd: CellUpdates) -> CellUpdates:
    """The free-space (negative) updates of a frame's :class:`CellUpdates` (views when already split by sign)."""
    if upd.n_free is not None:
        m = upd.n_free
        return CellUpdates(upd.keys[:m], upd.dl[:m], upd.n_rays, upd.lo, upd.hi, m)
    neg = upd.dl < 0
    return CellUpdates(upd.keys[neg], upd.dl[neg], upd.n_rays, upd.lo, upd.hi, int(neg.sum()))

