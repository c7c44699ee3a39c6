"""Distribution-aware integration: each pixel's depth distribution sets the log-odds along its ray.

A pixel's prediction is a piecewise-uniform density over depth (metres along the optical axis):
K bins with probabilities ``probs`` between ``edges`` (mass spread uniformly over each bin's
length; a zero-width bin is a point mass), plus ``p_beyond``, the probability of no surface within
range. A cell the ray crosses between depths [z_in, z_out] gets the *expected* OctoMap update

    dl = P(z_in ≤ surface < z_out) · logit(prob_hit) + P(surface ≥ z_out or beyond range) · logit(prob_miss)

(mass before the cell says nothing about it). A confident pixel updates like a LiDAR return, an
uncertain one barely moves its cells, a two-mode pixel puts partial occupancy at both modes.

Rays stop at the *far depth*, where P(beyond) first falls below ``eps`` (or at the last bin edge):
the ray is cast, with OctoMap's own DDA (:mod:`raycast_c`), to the centre of the cell holding the
pixel's point at that depth, and the depth along it is z = t · far_depth / |centre − origin| (t =
metres from the origin). The far cell is the ray's end cell; rays beyond ``max_range`` are cut
there and update free cells only, as OctoMap does.

Per frame, several rays meeting one cell give it ONE update (OctoMap's per-scan rule, generalised):
the largest positive dl if any ray has one ("occupied wins"), else the most negative (the strongest
free evidence). With a point mass at each pixel's depth, dl is exactly logit(prob_hit) in the end
cell and logit(prob_miss) before it, the far depth is the pixel's depth and the ray goes to the
centre of its end cell — OctoMap's ``insertPointCloud(discretize=True)`` key sets with their
updates, so the map equals the ``--keep 1.0`` map bit for bit (tested).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from mono_map.errors import MonoMapError
from mono_map.mapping.octree import TREE_MAX_VAL, coord_to_key, key_bounds, key_in_range, key_to_coord
from mono_map.mapping.raycast import KeyBox, cut_at_range, norm_f32

_SUM_TOL = 1e-3       # probs + p_beyond may exceed 1 by float32 rounding, not more
_DENSE_MAX_CELLS = 300_000_000   # larger frame boxes combine (index, update) pairs by sorting instead


@dataclass(frozen=True)
class DistributionConfig:
    """Settings of ``--integrate distribution``.

    eps: rays stop where P(surface beyond) < eps; temperature: probabilities are sharpened (< 1)
    or flattened (> 1) as p^(1/T), renormalised to their mass, before use (1 = as predicted);
    ray_step: one ray every ray_step-th pixel row and column (on top of ``--stride``);
    min_update: updates weaker than this (log-odds magnitude) are dropped — a cell is created only
    when a ray says something about it (0 = keep all);
    bin_spread: each bin's mass spread over this central fraction of the bin (log-depth), the pattern
    shifted so the modal bin's mass sits at the pixel's local mean depth (1 = whole bins, unshifted;
    see :func:`narrow_bins`);
    quantum: per-cell updates rounded to multiples of this log-odds step (exact hits and misses kept), so
    cells take values from a lattice and free space prunes as in a hard map (0 = off; :func:`quantise_updates`);
    snap_free: negative (free-space) updates snapped to the sensor model's own lattice {miss, 0} — a cell
    gets a whole miss where the expected update is at least half a miss, else nothing — so cells only ever
    seen free hold exactly the values of a hard map's free cells and prune as those do (positive updates
    are rounded by ``quantum`` as before).
    """

    # all chosen on training town 06 (docs/results.md), never on 00
    eps: float = 0.5           # with snap_free (model v2): the map's memory below keep 0.8's; 0.2 with v1
    temperature: float = 0.5   # model v2
    ray_step: int = 2          # ~ the network's input resolution (192×640 for 376×1241 images)
    min_update: float = 0.05
    bin_spread: float = 1.0
    quantum: float = 0.2       # model v2: 18 % less memory, surface precision 84 -> 94 % on 06
    snap_free: bool = True     # model v2, eps 0.5: memory 119 -> 61 MB (keep 0.8: 67 MB) on frames 0-39 of 06


@dataclass
class CellUpdates:
    """One frame's distribution update: distinct cell keys (int64 (M, 3)) and float32 log-odds updates."""

    keys: np.ndarray
    dl: np.ndarray
    n_rays: int = 0
    lo: np.ndarray | None = None      # inclusive key bounds of the frame's box
    hi: np.ndarray | None = None
    n_free: int | None = None         # the first n_free updates are the negative ones, the rest positive (None: any order)


def check_distribution_config(cfg: DistributionConfig) -> DistributionConfig:
    if not (0.0 < cfg.eps < 1.0):
        raise MonoMapError(f"--eps: must be in (0, 1), got {cfg.eps}")
    if not (cfg.temperature > 0 and np.isfinite(cfg.temperature)):
        raise MonoMapError(f"--temperature: must be a positive number, got {cfg.temperature}")
    if not (0.0 < cfg.bin_spread <= 1.0):
        raise MonoMapError(f"--bin-spread: must be in (0, 1], got {cfg.bin_spread}")
    if not (0.0 <= cfg.min_update < 0.4):
        raise MonoMapError(f"--min-update: must be in [0, 0.4) (log-odds), got {cfg.min_update}")
    if not (0.0 <= cfg.quantum <= 0.5):
        raise MonoMapError(f"--quantum: must be in [0, 0.5] (log-odds; 0 = off), got {cfg.quantum}")
    if int(cfg.ray_step) != cfg.ray_step or cfg.ray_step < 1:
        raise MonoMapError(f"--ray-step: must be a positive integer, got {cfg.ray_step}")
    return cfg


def check_distribution(probs: np.ndarray, p_beyond: np.ndarray | None, edges: np.ndarray,
                       what: str = "distribution", mass: np.ndarray | None = None
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Validate and normalise the types: (probs float32 (N, K), p_beyond float64 (N,), edges float64
    (K+1,) or (N, K+1)). MonoMapError (one line naming ``what``) for NaN/inf, negative values, a
    total above 1, or edges that are not finite, non-negative and non-decreasing. ``mass`` (float64 (N,)):
    filled with each row's sum of probs in bin order (a by-product of the check)."""
    probs = np.asarray(probs)
    if probs.ndim != 2:
        raise MonoMapError(f"{what}: probabilities must be (N pixels, K bins), got shape {probs.shape}")
    n, k = probs.shape
    pb = np.zeros(n) if p_beyond is None else np.asarray(p_beyond, dtype=np.float64).reshape(-1)
    if len(pb) != n:
        raise MonoMapError(f"{what}: p_beyond has {len(pb)} values for {n} pixels")
    edges = np.asarray(edges, dtype=np.float64)
    if edges.shape not in ((k + 1,), (n, k + 1)):
        raise MonoMapError(f"{what}: bin edges must be ({k + 1},) or ({n}, {k + 1}), got {edges.shape}")
    if not np.isfinite(edges).all() or (edges < 0).any() or (np.diff(edges, axis=-1) < 0).any():
        raise MonoMapError(f"{what}: bin edges must be finite, non-negative and non-decreasing (metres)")
    probs = np.ascontiguousarray(probs, dtype=np.float32)
    st = row_stats(probs, pb, mass)
    for name, bad, neg, low in (("probabilities", st["bad_p"], st["neg_p"], st["min_p"]),
                                ("p_beyond", st["bad_b"], st["neg_b"], st["min_b"])):
        if bad:
            raise MonoMapError(f"{what}: {int(bad)} {name} are NaN or infinite")
        if neg:
            raise MonoMapError(f"{what}: {int(neg)} {name} are negative (min {low:.3g})")
    if n and st["max_total"] > 1 + _SUM_TOL:
        raise MonoMapError(f"{what}: {st['n_over']} pixels have probabilities summing above 1 (max "
                           f"{st['max_total']:.4f}); expected bin probabilities + p_beyond <= 1")
    return probs, pb, edges


def row_stats(probs: np.ndarray, pb: np.ndarray, mass: np.ndarray | None = None) -> dict:
    """Counts of non-finite and negative values, minima, the largest row total and the rows above 1 + tol
    (compiled: one pass; numpy otherwise); ``mass`` (float64 (N,)): filled with the rows' sums of finite probs."""
    from mono_map.mapping.distribution_c import check_rows_c
    from mono_map.mapping.raycast_c import load_kernel

    kernel = load_kernel()
    if kernel is not None:
        return check_rows_c(kernel, probs, pb, 1 + _SUM_TOL, mass)
    fin_p, fin_b = np.isfinite(probs), np.isfinite(pb)
    sums = np.where(fin_p, probs, 0).sum(axis=1, dtype=np.float64)
    if mass is not None:
        mass[:] = sums
    total = sums + np.where(fin_b, pb, 0)
    return {"bad_p": int((~fin_p).sum()), "neg_p": int(((probs < 0) & fin_p).sum()),   # finite ones, as compiled
            "min_p": float(probs[fin_p].min()) if fin_p.any() else 0.0,
            "bad_b": int((~fin_b).sum()), "neg_b": int(((pb < 0) & fin_b).sum()),
            "min_b": float(pb[fin_b].min()) if fin_b.any() else 0.0,
            "max_total": float(total.max()) if len(total) else 0.0, "n_over": int((total > 1 + _SUM_TOL).sum())}


def apply_temperature(probs: np.ndarray, temperature: float, rows: int = 4096) -> np.ndarray:
    """p^(1/T) per pixel (row), rescaled to the pixel's original bin mass (T = 1: unchanged); float64 inside,
    float32 out. Done ``rows`` pixels at a time: every row's arithmetic is the same as on the whole array (the
    same result to the bit), with the float64 temporaries in cache (2.5× faster for a frame's 116 k rows)."""
    if temperature == 1.0:
        return probs
    probs = np.asarray(probs)
    out = np.empty(probs.shape, dtype=np.float32)
    for a in range(0, len(probs), rows):
        p = np.asarray(probs[a:a + rows], dtype=np.float64)
        q = p ** (1.0 / temperature)
        s = q.sum(axis=1, keepdims=True)
        out[a:a + rows] = q * (p.sum(axis=1, keepdims=True) / np.where(s > 0, s, 1.0))
    return out


def unconditional_mass(probs: np.ndarray, p_beyond: np.ndarray, temperature: float, rows: int = 4096) -> np.ndarray:
    """float32 (N, K) unconditional bin mass (1 − p_beyond) · p_T of conditional bin probabilities ``probs``
    (N, K) at ``temperature`` (:func:`apply_temperature`, rounded to float32 first), ``p_beyond`` (N,) float64;
    ``rows`` pixels at a time (the same bits as on the whole array, the temporaries in cache)."""
    probs = np.asarray(probs)
    pb = np.asarray(p_beyond, dtype=np.float64)
    out = np.empty(probs.shape, dtype=np.float32)
    for a in range(0, len(probs), rows):
        t = np.asarray(apply_temperature(probs[a:a + rows], temperature, rows), dtype=np.float64)
        out[a:a + rows] = t * (1.0 - pb[a:a + rows])[:, None]
    return out


def ray_distributions(probs: np.ndarray, p_beyond: np.ndarray, temperature: float, edges: np.ndarray,
                      eps: float, overwrite: bool = False, rows: np.ndarray | None = None
                      ) -> tuple[np.ndarray, np.ndarray]:
    """The rays' (float32 (N, K) unconditional bin mass, float64 (N,) far depths in metres) from conditional bin
    probabilities ``probs`` (N, K) and ``p_beyond`` (N,): :func:`unconditional_mass` at ``temperature``, then
    :func:`far_depth` at ``eps`` — compiled in one pass when the kernel is there (the same formulas; the row
    sums in another order, so the last float bit may differ). ``overwrite``: ``probs`` (the caller's scratch)
    may be overwritten with the result. ``rows`` (int (N,)): the rays are these rows of ``probs`` (M, K)
    (the compiled pass reads them in place instead of a gathered copy)."""
    from mono_map.mapping.distribution_c import ray_mass_c
    from mono_map.mapping.raycast_c import load_kernel

    kernel = load_kernel()
    if kernel is None:
        q = probs if rows is None else np.asarray(probs)[np.asarray(rows)]
        p = unconditional_mass(q, p_beyond, temperature)
        return p, far_depth(p, p_beyond, edges, eps)
    return ray_mass_c(kernel, probs, p_beyond, 1.0 / temperature, edges, eps, overwrite, rows)


def narrow_bins(probs: np.ndarray, edges: np.ndarray, spread: float) -> tuple[np.ndarray, np.ndarray]:
    """Sub-bin placement of the bins' mass: (probs (N, 2K-1), per-pixel edges (N, 2K)).

    A histogram says nothing about where in a bin the mass lies; the pixel's local mean (the
    log-depth mean over the modal bin and its two neighbours) is the best sub-bin estimate. Every
    bin's mass is spread over the central ``spread`` fraction of its log-width around its centre
    shifted by δ = local mean − modal centre (the same δ for all bins, so the order and the gaps
    stay), with empty gaps between. ``spread`` = 1 with δ = 0 would be the whole-bin reading.
    """
    p = np.asarray(probs, dtype=np.float32)
    n, k = p.shape
    le = np.log(np.asarray(edges, dtype=np.float64))
    lc = 0.5 * (le[:-1] + le[1:])
    w = le[1:] - le[:-1]
    a = p.argmax(axis=1)
    rows = np.arange(n)
    num = np.zeros(n)
    den = np.zeros(n)
    for off in (-1, 0, 1):
        j = np.clip(a + off, 0, k - 1)
        ok = (a + off >= 0) & (a + off < k)
        pj = np.where(ok, p[rows, j], 0.0)
        num += pj * lc[j]
        den += pj
    delta = np.where(den > 0, num / np.where(den > 0, den, 1.0) - lc[a], 0.0)
    lo = lc[None, :] + delta[:, None] - 0.5 * spread * w[None, :]
    hi = lc[None, :] + delta[:, None] + 0.5 * spread * w[None, :]
    out_edges = np.empty((n, 2 * k))
    out_edges[:, 0::2] = np.exp(lo)
    out_edges[:, 1::2] = np.exp(hi)
    out_probs = np.zeros((n, 2 * k - 1), dtype=np.float32)
    out_probs[:, 0::2] = p
    return out_probs, out_edges


def quantise_updates(dl: np.ndarray, hit: float, miss: float, quantum: float, snap_free: bool = False) -> np.ndarray:
    """float32 per-cell updates rounded to the nearest multiple of ``quantum`` (log-odds); values exactly
    equal to the float32 hit or miss update are kept, so point masses still give the hard map bit for bit.
    ``snap_free``: negative updates become exactly ``miss`` where dl ≤ miss / 2, else 0. Zeros mean
    "no update" (the caller drops them). ``quantum`` 0 and no ``snap_free``: unchanged."""
    dl = np.asarray(dl, dtype=np.float32)
    if quantum > 0:
        exact = (dl == np.float32(hit)) | (dl == np.float32(miss))
        q = (np.round(dl.astype(np.float64) / quantum) * quantum).astype(np.float32)
        dl = np.where(exact, dl, q)
    if snap_free:
        miss32 = np.float32(miss)
        dl = np.where(dl < 0, np.where(dl <= miss32 / 2, miss32, np.float32(0)), dl).astype(np.float32)
    return dl


@functools.lru_cache(maxsize=64)
def snap_threshold(hit: float, miss: float, quantum: float, min_update: float = 0.0) -> float:
    """The largest float32 update x ≤ −min_update that :func:`quantise_updates` with ``snap_free`` turns into a
    whole miss (every x at or below it does: rounding and snapping are monotone). A cell whose rays' most
    negative update is at or below it, and none positive, holds exactly ``miss`` after snapping."""
    def snaps(mag: np.uint32) -> bool:
        x = -np.array([mag], dtype=np.uint32).view(np.float32)
        return bool(quantise_updates(x, hit, miss, quantum, snap_free=True)[0] == np.float32(miss))

    bits = lambda v: np.array([v], dtype=np.float32).view(np.uint32)[0]   # noqa: E731 (magnitudes: monotone)
    a, b = bits(-np.float32(miss)), bits(np.float32(min_update))
    if not snaps(a):
        raise MonoMapError(f"sensor model: a whole miss ({miss}) does not survive snapping")
    if snaps(b):
        return float(-np.array([b], np.uint32).view(np.float32)[0])
    while a - b > 1:                    # snaps(a), not snaps(b): the smallest magnitude that snaps
        mid = np.uint32((int(a) + int(b)) // 2)
        a, b = (mid, b) if snaps(mid) else (a, mid)
    return float(-np.array([a], np.uint32).view(np.float32)[0])


def cdf(probs: np.ndarray, edges: np.ndarray, z: np.ndarray) -> np.ndarray:
    """P(surface < z) for every pixel (rows) and depth z ((N, M) or (M,) metres) — right-continuous at point masses."""
    p = np.asarray(probs, dtype=np.float64)
    n, k = p.shape
    e = np.broadcast_to(np.asarray(edges, dtype=np.float64), (n, k + 1))
    z = np.broadcast_to(np.asarray(z, dtype=np.float64), (n,) + np.shape(z)[-1:])
    lo, hi = e[:, None, :-1], e[:, None, 1:]
    w = hi - lo
    zz = z[:, :, None]
    frac = np.where(zz >= hi, 1.0, np.where((w > 0) & (zz > lo), (zz - lo) / np.where(w > 0, w, 1.0), 0.0))
    return (p[:, None, :] * frac).sum(axis=2)


def expected_updates(probs: np.ndarray, p_beyond: np.ndarray | None, edges: np.ndarray, z_in: np.ndarray,
                     z_out: np.ndarray, hit: float, miss: float) -> np.ndarray:
    """Expected OctoMap log-odds update of cells spanning depths [z_in, z_out) (metres, (N, M) or (M,))
    along N pixels' rays: P(in)·hit + P(beyond)·miss (hit, miss: log-odds of prob_hit, prob_miss).
    The reference formula; the frame path computes the same in the compiled kernel."""
    probs, pb, edges = check_distribution(probs, p_beyond, edges)
    mass = probs.sum(axis=1, dtype=np.float64)[:, None]
    c_in, c_out = cdf(probs, edges, z_in), cdf(probs, edges, z_out)
    return (c_out - c_in) * float(hit) + (mass - c_out + pb[:, None]) * float(miss)


def far_depth(probs: np.ndarray, p_beyond: np.ndarray, edges: np.ndarray, eps: float) -> np.ndarray:
    """(N,) depth (metres) where P(surface beyond) first falls below ``eps`` (linear within the bin); the
    last edge if it never does (e.g. p_beyond ≥ eps). A point mass's far depth is its depth."""
    from mono_map.mapping.distribution_c import far_depth_c
    from mono_map.mapping.raycast_c import load_kernel

    kernel = load_kernel()
    if kernel is not None:
        return far_depth_c(kernel, probs, p_beyond, edges, eps)
    p = np.asarray(probs, dtype=np.float64)
    n, k = p.shape
    e = np.broadcast_to(np.asarray(edges, dtype=np.float64), (n, k + 1))
    pb = np.asarray(p_beyond, dtype=np.float64)
    beyond_end = p.sum(axis=1)[:, None] - np.cumsum(p, axis=1) + pb[:, None]   # P(beyond) at each bin's upper edge
    below = beyond_end < eps
    found = below.any(axis=1)
    j = np.where(found, below.argmax(axis=1), k - 1)
    rows = np.arange(n)
    lo, hi, pj = e[rows, j], e[rows, j + 1], p[rows, j]
    at_lo = beyond_end[rows, j] + pj        # P(beyond) at the bin's lower edge
    with np.errstate(divide="ignore", invalid="ignore"):
        frac = np.where(pj > 0, (at_lo - eps) / pj, 0.0)
    z = lo + (hi - lo) * np.clip(frac, 0.0, 1.0)
    return np.where(found, z, e[:, -1])


def distribution_update(origin: np.ndarray, far_points: np.ndarray, far_depths: np.ndarray, probs: np.ndarray,
                        p_beyond: np.ndarray | None, edges: np.ndarray, resolution: float, hit: float, miss: float,
                        max_range: float = -1.0, min_update: float = 0.0, quantum: float = 0.0,
                        snap_free: bool = False) -> CellUpdates:
    """One frame's per-cell updates (see the module docstring).

    origin: (3,) camera centre (world, metres); far_points: (N, 3) each pixel's point at its far depth
    (world); far_depths: (N,) those depths (metres, as ``edges``); probs (N, K), p_beyond (N,) or None,
    edges (K+1,) or (N, K+1): the distributions; hit, miss: float32 log-odds of the sensor model;
    min_update: weaker updates are dropped; quantum, snap_free: updates rounded (:func:`quantise_updates`).
    """
    from mono_map.mapping.distribution_c import quantise_split_c, ray_weights_c
    from mono_map.mapping.raycast_c import load_kernel

    mass = np.empty(len(probs) if np.ndim(probs) == 2 else 0)   # the rays' sums of probs: the check's by-product
    probs, pb, edges = check_distribution(probs, p_beyond, edges, mass=mass)
    kernel = load_kernel()
    if kernel is None:
        raise MonoMapError("--integrate distribution: needs the compiled ray kernel (a C compiler 'cc'; "
                           "MONO_MAP_NO_C must not be 1)")
    res = float(resolution)
    origin32 = np.asarray(origin, dtype=np.float64).reshape(3).astype(np.float32)
    key_origin = coord_to_key(origin32[None, :], res)[0]
    if not key_in_range(key_origin[None, :])[0]:
        raise MonoMapError(f"origin: {origin32.tolist()} is outside OctoMap's addressable range")
    pts = np.asarray(far_points, dtype=np.float64).reshape(-1, 3)
    if not np.isfinite(pts).all():
        raise MonoMapError("points: non-finite coordinates (NaN or inf) in the frame's rays")
    empty = CellUpdates(np.zeros((0, 3), np.int64), np.zeros(0, np.float32))
    if len(pts) == 0:
        return empty
    far_keys = coord_to_key(pts, res)
    ok = key_in_range(far_keys)
    if not ok.all():
        raise MonoMapError(f"points: {int((~ok).sum())} ray ends lie outside OctoMap's addressable range "
                           f"(±{TREE_MAX_VAL * res:.0f} m at {res} m)")
    centres = key_to_coord(far_keys, res).astype(np.float32)          # the discretised far point
    length = norm_f32(centres - origin32[None, :])
    with np.errstate(divide="ignore", invalid="ignore"):
        scale = np.where(length > 0, np.asarray(far_depths, dtype=np.float64) / length, 0.0)
    ends, inside = cut_at_range(centres, origin32, max_range)
    end_keys = coord_to_key(ends, res)
    end_lo, end_hi = key_bounds(end_keys)
    box = KeyBox(np.minimum(end_lo, key_origin), np.maximum(end_hi, key_origin))
    # the kernel's bound on an update needs hit > 0 > miss (OctoMap's prob_hit > 0.5 > prob_miss)
    thr = snap_threshold(hit, miss, quantum, min_update) if snap_free and hit > 0 > miss else None
    far_box = KeyBox(*key_bounds(far_keys))                          # rays in one far cell share one walk
    lin, dl = ray_weights_c(kernel, origin32, key_origin, ends, end_keys, inside, scale, probs, pb, edges,
                            hit, miss, res, box.lo, box.strides, TREE_MAX_VAL, box.size, min_update=min_update,
                            dense=box.size <= _DENSE_MAX_CELLS, free_threshold=thr,
                            ray_ids=far_box.linear(far_keys), mass=mass)
    # quantise_updates, the zeros dropped, the free-space updates first (compiled, one pass)
    lin, dl, n_free = quantise_split_c(kernel, lin, dl, hit, miss, quantum, snap_free)
    return CellUpdates(keys=box.keys(lin), dl=dl, n_rays=len(pts), lo=box.lo, hi=box.lo + box.dims - 1,
                       n_free=n_free)
