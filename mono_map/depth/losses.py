"""Training targets and losses of the heads (:mod:`mono_map.depth.heads`), paper Sec. III.

  binary    BCE of K sigmoids vs the unnormalised soft target q̃_k = exp(-(k-y*)²/2σ²)  (the paper's method)
  softmax   cross-entropy vs the normalised discretised Gaussian q_k = q̃_k / Z
  ordinal   BCE of the threshold classifiers P(y > k)
  gaussian  Gaussian NLL of log-depth
  l2, berhu regression of log-depth
  mhl       relaxed winner-takes-all L2 of M log-depth hypotheses: (1−ε)·min_m r_m² + ε/(M−1)·Σ_{others} r_m²
Targets are depth in metres per pixel: 0 (or <= 0) = no value; +inf or anything beyond ``max_depth`` =
**no surface within range** (sky). With ``beyond=True`` such pixels train towards "beyond": binary
towards all K labels 0, softmax towards its extra class, ordinal towards every threshold exceeded,
Gaussian / regression heads through their beyond logit (BCE over all valid pixels; the depth term
only where a surface is in range). With ``beyond=False`` (the paper's practice) they are clipped
into the last bin. Losses average over valid pixels.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from mono_map.depth.bins import DepthBins
from mono_map.depth.heads import (HeadSpec, gaussian_params, get_head, hypotheses_log_depth, regression_log_depth,
                                  split_beyond)
from mono_map.errors import MonoMapError


def soft_target(depth: torch.Tensor, bins: DepthBins, sigma: float | None = None) -> torch.Tensor:
    """(B,H,W) metres -> (B,K,H,W) unnormalised soft target q̃_k = exp(-(k - y*)² / 2σ²).

    σ defaults to bins.soft_target_sigma(): every bin within 25 % of the true depth gets q̃ > 0.5.
    """
    sigma = bins.soft_target_sigma() if sigma is None else sigma
    y = bins.continuous_index(depth).unsqueeze(1)
    k = torch.arange(bins.num_bins, dtype=depth.dtype, device=depth.device).view(1, -1, 1, 1)
    return torch.exp(-((k - y) ** 2) / (2.0 * sigma * sigma))


def valid_mask(depth: torch.Tensor, bins: DepthBins) -> torch.Tensor:
    """Pixels with a target: a depth (> 0) or "no surface" (+inf)."""
    return depth > 0


def beyond_mask(depth: torch.Tensor, bins: DepthBins) -> torch.Tensor:
    """Pixels whose target says no surface within the bin range (+inf, or deeper than max_depth)."""
    return depth > bins.max_depth


def masked_mean(per_pixel: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    n = mask.sum()
    if n == 0:
        return per_pixel.sum() * 0.0
    return (per_pixel * mask).sum() / n


def relaxed_wta(sq: torch.Tensor, epsilon: float) -> torch.Tensor:
    """(B,M,H,W) squared errors of M hypotheses -> (B,H,W) relaxed winner-takes-all loss (Rupprecht et al.):
    weight 1−ε on the best hypothesis, ε/(M−1) on each other; ε = 0 trains only the winner."""
    m = sq.shape[1]
    if m == 1:
        return sq[:, 0]
    best = sq.min(1).values
    return (1 - epsilon) * best + epsilon / (m - 1) * (sq.sum(1) - best)


def head_loss(head: HeadSpec | str, output: torch.Tensor, depth: torch.Tensor, bins: DepthBins,
              beyond: bool = False, wta_epsilon: float = 0.05) -> torch.Tensor:
    """Scalar training loss of a head's raw network output (B,C,H,W) against target depth (B,H,W) metres."""
    head = get_head(head) if isinstance(head, str) else head
    mask = valid_mask(depth, bins)
    far = beyond_mask(depth, bins) & mask if beyond else torch.zeros_like(mask)
    near = mask & ~far
    safe = torch.where(near, depth, torch.full_like(depth, bins.min_depth))
    safe = safe.clamp(bins.min_depth, bins.max_depth)
    base = head.base
    if base == "binary":
        q = soft_target(safe, bins) * near.unsqueeze(1)          # beyond: all K labels 0
        bce = F.binary_cross_entropy_with_logits(output, q, reduction="none").sum(1)
        return masked_mean(bce, mask)
    x, beyond_logit = split_beyond(head, output, bins, beyond)
    extra = 0.0
    if beyond_logit is not None and base not in ("softmax", "ordinal"):
        extra = masked_mean(F.binary_cross_entropy_with_logits(beyond_logit, far.to(output.dtype),
                                                               reduction="none"), mask)
    if base == "softmax":
        q = soft_target(safe, bins) * near.unsqueeze(1)
        q = q / q.sum(1, keepdim=True).clamp_min(1e-12)
        if beyond:
            q = torch.cat([q, far.unsqueeze(1).to(q.dtype)], 1)
        ce = -(q * F.log_softmax(output, 1)).sum(1)
        return masked_mean(ce, mask)
    if base == "ordinal":
        y = bins.continuous_index(safe).unsqueeze(1)
        k = torch.arange(bins.num_bins - 1, dtype=depth.dtype, device=depth.device).view(1, -1, 1, 1)
        t = (y > k + 0.5).to(output.dtype)
        if beyond:   # beyond: every threshold exceeded, including the one at max_depth
            t = torch.where(far.unsqueeze(1), torch.ones_like(t), t)
            t = torch.cat([t, far.unsqueeze(1).to(t.dtype)], 1)
        bce = F.binary_cross_entropy_with_logits(output, t, reduction="none").sum(1)
        return masked_mean(bce, mask)
    if base == "gaussian":
        mean, log_var = gaussian_params(x, bins)
        nll = 0.5 * (torch.exp(-log_var) * (safe.log() - mean) ** 2 + log_var)
        return masked_mean(nll, near) + extra
    if base in ("l2", "berhu"):
        r = (regression_log_depth(x, bins) - safe.log()).abs()
        if base == "l2":
            return masked_mean(r * r, near) + extra
        c = (0.2 * (r * near).max()).detach().clamp_min(1e-6)
        b = torch.where(r <= c, r, (r * r + c * c) / (2 * c))
        return masked_mean(b, near) + extra
    if base == "mhl":
        sq = (hypotheses_log_depth(x, bins) - safe.log().unsqueeze(1)) ** 2
        return masked_mean(relaxed_wta(sq, wta_epsilon), near) + extra
    raise MonoMapError(f"head: no loss for {head.name!r}")
