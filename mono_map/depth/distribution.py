"""Statistics of per-pixel categorical depth distributions, batched in torch.

Tensors are (B, K, H, W) (K depth bins along dim 1); depths are metres, entropy nats.
Everything is vectorised: no loops over pixels.
"""

from __future__ import annotations

import math

import torch

from mono_map.depth.bins import DepthBins


def probs_from_logits(logits: torch.Tensor) -> torch.Tensor:
    """Softmax over the K score maps (what the paper does at test time, for every head)."""
    return torch.softmax(logits, dim=1)


def _centres(bins: DepthBins, like: torch.Tensor, log: bool) -> torch.Tensor:
    c = bins.log_centres if log else bins.centres
    return torch.as_tensor(c, dtype=like.dtype, device=like.device).view(1, -1, 1, 1)


def expected_depth(probs: torch.Tensor, bins: DepthBins, space: str = "log") -> torch.Tensor:
    """(B,H,W) expected depth: ``log`` = exp(Σ p_k log d_k) (released code), ``linear`` = Σ p_k d_k (paper text)."""
    if space == "log":
        return torch.exp((probs * _centres(bins, probs, True)).sum(1))
    if space == "linear":
        return (probs * _centres(bins, probs, False)).sum(1)
    raise ValueError(f"space must be 'log' or 'linear', got {space!r}")


def std_log_depth(probs: torch.Tensor, bins: DepthBins) -> torch.Tensor:
    """(B,H,W) standard deviation of log-depth under the distribution (a second uncertainty measure)."""
    lc = _centres(bins, probs, True)
    mu = (probs * lc).sum(1, keepdim=True)
    return (probs * (lc - mu) ** 2).sum(1).clamp_min(0).sqrt()


def argmax_depth(probs: torch.Tensor, bins: DepthBins) -> torch.Tensor:
    """(B,H,W) centre depth of the most likely bin."""
    c = torch.as_tensor(bins.centres, dtype=probs.dtype, device=probs.device)
    return c[probs.argmax(1)]


def entropy(probs: torch.Tensor, eps: float = 1e-12) -> torch.Tensor:
    """(B,H,W) Shannon entropy in nats: 0 for one-hot, log K for uniform."""
    return -(probs * torch.log(probs.clamp_min(eps))).sum(1)


def entropy_of_logits(logits: torch.Tensor) -> torch.Tensor:
    """(B,H,W) entropy in nats of the softmax over the K score maps (B,K,H,W), from their log-softmax (no clamp:
    exact, and its gradient reaches every score)."""
    logp = torch.log_softmax(logits, 1)
    return -(logp.exp() * logp).sum(1)


def top_modes(probs: torch.Tensor, bins: DepthBins, m: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The ``m`` most probable local maxima along the bin axis, as depth hypotheses.

    A bin is a mode if p_k >= p_{k-1} and p_k > p_{k+1} (edges padded with -inf), so a plateau
    counts once. Returns (depths, probs), each (B, m, H, W), sorted by decreasing probability;
    pixels with fewer than m modes repeat their most probable mode.
    """
    k = probs.shape[1]
    neg = torch.full_like(probs[:, :1], -float("inf"))
    left = torch.cat([neg, probs[:, :-1]], 1)
    right = torch.cat([probs[:, 1:], neg], 1)
    is_mode = (probs >= left) & (probs > right)
    score = torch.where(is_mode, probs, torch.full_like(probs, -1.0))
    top_p, top_i = score.topk(min(m, k), dim=1)
    best_i = top_i[:, :1].expand_as(top_i)
    top_i = torch.where(top_p < 0, best_i, top_i)
    top_p = torch.gather(probs, 1, top_i)
    c = torch.as_tensor(bins.centres, dtype=probs.dtype, device=probs.device)
    return c[top_i], top_p


def top_bins(probs: torch.Tensor, bins: DepthBins, m: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The ``m`` most probable bins as depth hypotheses (the paper's Table III protocol: "we report back M
    depth hypotheses with the highest scores"; neighbouring bins of one peak count separately, unlike
    :func:`top_modes`). Returns (bin-centre depths, probs), each (B, m, H, W), by decreasing probability."""
    top_p, top_i = probs.topk(min(m, probs.shape[1]), dim=1)
    c = torch.as_tensor(bins.centres, dtype=probs.dtype, device=probs.device)
    return c[top_i], top_p


def gaussian_entropy(log_var: torch.Tensor) -> torch.Tensor:
    """Differential entropy (nats) of a Gaussian over log-depth with variance exp(log_var)."""
    return 0.5 * (log_var + math.log(2.0 * math.pi * math.e))


def gaussian_to_probs(mean_log: torch.Tensor, log_var: torch.Tensor, bins: DepthBins) -> torch.Tensor:
    """Discretise N(mean_log, exp(log_var)) over log-depth into the K bins (tails in the end bins) -> (B,K,H,W)."""
    e = bins.log_edges.copy()
    e[0], e[-1] = -float("inf"), float("inf")  # tails go to the end bins
    edges = torch.as_tensor(e, dtype=mean_log.dtype, device=mean_log.device).view(1, -1, 1, 1)
    std = torch.exp(0.5 * log_var).unsqueeze(1).clamp_min(1e-6)
    cdf = 0.5 * (1 + torch.erf((edges - mean_log.unsqueeze(1)) / (std * math.sqrt(2.0))))
    p = (cdf[:, 1:] - cdf[:, :-1]).clamp_min(0)
    return p / p.sum(1, keepdim=True).clamp_min(1e-12)


def ordinal_to_probs(logits: torch.Tensor) -> torch.Tensor:
    """DORN-style (B,K-1,H,W) threshold logits, P(y > k), -> (B,K,H,W) bin probabilities.

    p_k = P(y > k-1) - P(y > k) with P(y > -1) = 1 and P(y > K-1) = 0, clipped at 0 and renormalised.
    """
    s = torch.sigmoid(logits)
    one = torch.ones_like(s[:, :1])
    zero = torch.zeros_like(s[:, :1])
    above = torch.cat([one, s, zero], 1)
    p = (above[:, :-1] - above[:, 1:]).clamp_min(0)
    return p / p.sum(1, keepdim=True).clamp_min(1e-12)
