"""Pixel selection by uncertainty: keep the lowest-entropy fraction of each frame's valid pixels."""

from __future__ import annotations

import numpy as np

from mono_map.errors import MonoMapError

DEFAULT_KEEP = 0.8   # the paper's uncertainty-aware map: the 80 % lowest-entropy valid pixels of a frame


def check_keep(keep: float) -> float:
    keep = float(keep)
    if not (0.0 < keep <= 1.0) or not np.isfinite(keep):
        raise MonoMapError(f"--keep: must be in (0, 1], got {keep}")
    return keep


def valid_pixels(depth: np.ndarray, min_depth: float, max_depth: float, stride: int = 1) -> np.ndarray:
    """H×W bool: finite depth within [min_depth, max_depth] metres, on the stride grid (every
    ``stride``-th row and column, starting at 0)."""
    if stride < 1:
        raise MonoMapError(f"--stride: must be a positive integer, got {stride}")
    d = np.asarray(depth)
    ok = np.isfinite(d) & (d >= min_depth) & (d <= max_depth)
    if stride > 1:
        grid = np.zeros(d.shape, dtype=bool)
        grid[::stride, ::stride] = True
        ok &= grid
    return ok


RANKS = ("entropy", "metric")   # what "most confident" means when a keep map ranks its pixels


def check_rank(rank: str, option: str = "rank") -> str:
    """``rank`` if it is one of RANKS, else MonoMapError naming ``option`` (the argument or a tool's flag)."""
    if rank not in RANKS:
        raise MonoMapError(f"{option}: unknown ranking {rank!r} (choose from {', '.join(RANKS)})")
    return rank


def confidence_score(depth: np.ndarray, entropy: np.ndarray, rank: str = "entropy") -> np.ndarray:
    """H×W float32 score, lower = more confident. "entropy": the prediction's entropy (nats), the paper's —
    over log-spaced bins it measures spread in log-depth, i.e. relative to the depth. "metric": entropy +
    log(depth), the differential entropy of the metric depth for a distribution over log-depth
    (h(d) = h(log d) + E[log d], E[log d] taken as log of the expected depth), up to a constant: spread in
    metres, as map cells are; it ranks near pixels above far ones of the same relative spread."""
    e = np.asarray(entropy, dtype=np.float32)
    if check_rank(rank) == "entropy":
        return e
    with np.errstate(divide="ignore", invalid="ignore"):
        return e + np.log(np.asarray(depth, dtype=np.float32))


BEYOND_THRESHOLD = 0.5   # a pixel more likely to see no surface within range (sky) than one is never an end point


def select_pixels(depth: np.ndarray, entropy: np.ndarray, keep: float, min_depth: float = 1.0,
                  max_depth: float = 80.0, stride: int = 1, return_valid: bool = False,
                  p_beyond: np.ndarray | None = None):
    """H×W bool mask of the kept pixels.

    Exactly ``round(keep · n_valid)`` of the n_valid valid pixels are kept: those with the lowest
    entropy (ties broken by raster order, so the result is deterministic). Pixels whose entropy is
    not finite count as invalid, and so do pixels whose probability of no surface within range
    (``p_beyond``, H×W) is at least ``BEYOND_THRESHOLD``: sky is never inserted as an occupied end
    point. With return_valid, returns (kept, valid) masks.
    """
    keep = check_keep(keep)
    depth = np.asarray(depth)
    entropy = np.asarray(entropy)
    if depth.shape != entropy.shape or depth.ndim != 2:
        raise MonoMapError(f"entropy: shape {entropy.shape} does not match depth {depth.shape} (H×W expected)")
    valid = valid_pixels(depth, min_depth, max_depth, stride) & np.isfinite(entropy)
    if p_beyond is not None:
        p_beyond = np.asarray(p_beyond)
        if p_beyond.shape != depth.shape:
            raise MonoMapError(f"p_beyond: shape {p_beyond.shape} does not match depth {depth.shape}")
        valid &= ~(p_beyond >= BEYOND_THRESHOLD)
    idx = np.flatnonzero(valid)
    n_keep = int(round(keep * len(idx)))
    mask = np.zeros(depth.size, dtype=bool)
    if n_keep == len(idx):
        mask[idx] = True
    elif n_keep > 0:
        e = entropy.reshape(-1)[idx]
        t = np.partition(e, n_keep - 1)[n_keep - 1]        # the n_keep-th lowest entropy
        below = e < t
        ties = np.flatnonzero(e == t)[: n_keep - int(below.sum())]   # ties: raster order
        mask[idx[below]] = True
        mask[idx[ties]] = True
    mask = mask.reshape(depth.shape)
    return (mask, valid) if return_valid else mask
