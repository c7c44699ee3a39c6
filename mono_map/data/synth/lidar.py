"""Velodyne HDL-64E simulation: 64 beams (+2.0° … −24.8°), one 360° sweep per frame.

Rays start at the velodyne origin (T_world_velo = T_world_cam0 · Tr, Tr = T_cam0_velo);
points are returned in the velodyne frame (x forward, y left, z up) as float32
x y z reflectance.  Range noise ~2 cm; returns drop out on dark surfaces (black paint
returns ~1 ray in 6), at grazing incidence and beyond 120 m; glass lets most rays
through (they return from whatever is behind) or drops them.
"""

from __future__ import annotations

import numpy as np

from mono_map.data.synth import kernels
from mono_map.data.synth import materials as M
from mono_map.data.synth.camera import cast_rays

N_AZIMUTH = 2083             # 0.173° steps, ~120 k returns per scan in a street
MAX_RANGE = 120.0
RANGE_NOISE = 0.02           # metres (1 sigma)
GLASS_PASS = 0.65            # probability a ray goes through glass
GLASS_DROP = 0.25            # probability it is lost at the glass (the rest returns from the glass)


def beam_elevations() -> np.ndarray:
    """HDL-64E: upper block 32 lasers +2.0° … −8.33° (1/3°), lower block 32 lasers −8.83° … −24.8°."""
    upper = np.linspace(2.0, -8.33, 32)
    lower = np.linspace(-8.83, -24.8, 32)
    return np.radians(np.concatenate([upper, lower]))


def ray_directions() -> np.ndarray:
    """(64 · N_AZIMUTH, 3) unit directions in the velodyne frame, beam-major."""
    el = beam_elevations()[:, None]
    az = np.linspace(np.pi, -np.pi, N_AZIMUTH, endpoint=False)[None, :]
    az = az + np.radians(0.04) * (np.arange(64)[:, None] % 4)     # small per-laser azimuth offsets
    d = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el) * np.ones_like(az)], -1)
    return d.reshape(-1, 3)


def glass_pass(scene, town, p: np.ndarray, d: np.ndarray, t: np.ndarray, n: np.ndarray, refl: np.ndarray,
               glass: np.ndarray, u: np.ndarray, nthreads: int, surface) -> np.ndarray:
    """Glass hits: the ray passes through (re-cast from just behind the pane: ``t``, ``n``, ``refl`` updated in
    place), is lost, or returns from the pane (low reflectance), by the uniform draw ``u`` of each hit.

    ``p``, ``d``: hit points and ray directions (K, 3); ``surface``: materials.surface or its compiled twin.
    Returns the (K,) bool mask of lost rays.
    """
    through = glass & (u < GLASS_PASS)
    lost = glass & (u >= GLASS_PASS) & (u < GLASS_PASS + GLASS_DROP)
    ti = np.nonzero(through)[0]
    if len(ti):
        o2 = p[ti] + 0.05 * d[ti]
        a2 = cast_rays(scene, o2, d[ti], nthreads)
        t2 = a2["t_hit"]
        ok = np.isfinite(t2) & (t[ti] + t2 < MAX_RANGE)
        lost[ti[~ok]] = True
        tj = ti[ok]
        t[tj] = t[tj] + 0.05 + t2[ok]
        p2 = o2[ok] + t2[ok, None] * d[tj]
        n[tj] = a2["primitive_normals"][ok]
        s2 = surface(town, p2, n[tj], a2["primitive_ids"][ok].astype(np.int64), a2["primitive_uvs"][ok], lidar=True)
        refl[tj] = np.where(s2.glass, 0.05, s2.lidar_refl)
    return lost


def sweep_rays(T_world_velo: np.ndarray, dirs_velo: np.ndarray, rng: np.random.Generator):
    """A sweep's rays: (float32 velodyne-frame directions (N, 3), world directions (N, 3), world origins (N, 3,
    a broadcast view), the glass draw (N,) uniform — the sweep's first draw from ``rng``)."""
    R = T_world_velo[:3, :3].astype(np.float32)
    o = T_world_velo[:3, 3].astype(np.float32)
    dirs_velo = dirs_velo.astype(np.float32)
    dw = dirs_velo @ R.T
    return dirs_velo, dw, np.broadcast_to(o, dw.shape), rng.random(len(dw))


def scan(scene, town, T_world_velo: np.ndarray, dirs_velo: np.ndarray, rng: np.random.Generator,
         nthreads: int = 0) -> np.ndarray:
    """One sweep: (M, 4) float32 x y z reflectance in the velodyne frame.

    Runs the compiled kernels when available (:mod:`kernels`; the same bits), else :func:`scan_numpy`.
    """
    if not kernels.fits(town):
        return scan_numpy(scene, town, T_world_velo, dirs_velo, rng, nthreads)
    dirs_velo, dw, origins, rng_u = sweep_rays(T_world_velo, dirs_velo, rng)
    h = kernels.Hits(town, cast_rays(scene, origins, dw, nthreads), dw, origins, MAX_RANGE, face_ray=False)
    idx, t, d, p, n = h.idx, h.th, h.d, h.p, h.n
    surf = kernels.surface(town, p, n, h.prim, h.uvs, lidar=True)
    refl = surf.lidar_refl
    lost = glass_pass(scene, town, p, d, t, n, refl, surf.glass, rng_u[idx], nthreads, kernels.surface)
    idx, t, refl, cosi, p_ret = kernels.lidar_returns(h, lost, refl, MAX_RANGE)
    keep = rng.random(len(idx)) < p_ret
    n_keep = int(np.count_nonzero(keep))
    noise_r = rng.normal(0, RANGE_NOISE, n_keep).astype(np.float32)
    noise_i = rng.normal(0, 0.02, n_keep).astype(np.float32)
    return kernels.lidar_points(keep, idx, t, refl, cosi, noise_r, noise_i, dirs_velo)


def scan_numpy(scene, town, T_world_velo: np.ndarray, dirs_velo: np.ndarray, rng: np.random.Generator,
               nthreads: int = 0) -> np.ndarray:
    """:func:`scan` in numpy (the reference of the compiled path)."""
    dirs_velo, dw, origins, rng_u = sweep_rays(T_world_velo, dirs_velo, rng)
    ans = cast_rays(scene, origins, dw, nthreads)
    t = ans["t_hit"]
    idx = np.nonzero(np.isfinite(t) & (t < MAX_RANGE))[0]
    t = t[idx]
    d = dw[idx]
    p = origins[idx] + t[:, None] * d
    n = ans["primitive_normals"][idx]
    prim = ans["primitive_ids"][idx].astype(np.int64)
    surf = M.surface(town, p, n, prim, ans["primitive_uvs"][idx], lidar=True)
    refl = surf.lidar_refl
    lost = glass_pass(scene, town, p, d, t, n, refl, surf.glass, rng_u[idx], nthreads, M.surface)
    keep = ~lost
    idx, t, d, n, refl = idx[keep], t[keep], d[keep], n[keep], refl[keep]
    cosi = np.abs(np.einsum("ij,ij->i", n, d))
    p_ret = np.clip(refl * 12.0, 0, 1) * np.clip(cosi * 8.0, 0, 1) * 0.995
    p_ret *= np.clip(1.3 - (t / MAX_RANGE) ** 2 * (0.15 / np.maximum(refl, 0.01)), 0, 1)
    keep = rng.random(len(idx)) < p_ret
    idx, t, refl, cosi = idx[keep], t[keep], refl[keep], cosi[keep]
    r = t + rng.normal(0, RANGE_NOISE, len(idx)).astype(np.float32)
    inten = np.clip(refl * (0.55 + 0.45 * cosi) + rng.normal(0, 0.02, len(idx)).astype(np.float32), 0, 0.99)
    pts = dirs_velo[idx] * r[:, None]
    return np.concatenate([pts, inten[:, None]], axis=1).astype(np.float32)
