"""Prediction heads, their training targets and losses, selectable by name.

A head says how many output maps the network produces and how to turn them into
(a) a training loss against a metric depth target and (b) depth + uncertainty at test time.

Heads (paper Sec. III and its ablation):
  binary            K independent sigmoids, BCE vs unnormalised soft target q̃_k = exp(-(k-y*)²/2σ²)  (the paper's method)
  softmax           K-way softmax, cross-entropy vs the normalised discretised Gaussian q_k = q̃_k / Z
  ordinal           DORN-style: K-1 threshold classifiers P(y > k), BCE
  gaussian          mean and log-variance of log-depth, Gaussian NLL (Kendall & Gal)
  binary-dropout, gaussian-dropout   the same with dropout p=0.5 in the decoder, MC sampling at test
  l2, berhu         regression of log-depth (no uncertainty: their entropy is constant 0)
At test time every bin head is read through a softmax over its K logits (as the paper does).
Targets: depth in metres, 0 (or <= 0) = no value; losses average over valid pixels.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from mono_map.depth import distribution as dist
from mono_map.depth.bins import DepthBins
from mono_map.errors import MonoMapError


@dataclass(frozen=True)
class HeadSpec:
    name: str
    kind: str          # "bins" (K logits), "ordinal" (K-1 logits), "gaussian" (2 maps), "regression" (1 map)
    dropout: bool = False

    def out_channels(self, bins: DepthBins) -> int:
        return {"bins": bins.num_bins, "ordinal": bins.num_bins - 1, "gaussian": 2, "regression": 1}[self.kind]


HEADS: dict[str, HeadSpec] = {
    "binary": HeadSpec("binary", "bins"),
    "softmax": HeadSpec("softmax", "bins"),
    "ordinal": HeadSpec("ordinal", "ordinal"),
    "gaussian": HeadSpec("gaussian", "gaussian"),
    "binary-dropout": HeadSpec("binary-dropout", "bins", dropout=True),
    "gaussian-dropout": HeadSpec("gaussian-dropout", "gaussian", dropout=True),
    "l2": HeadSpec("l2", "regression"),
    "berhu": HeadSpec("berhu", "regression"),
}


def get_head(name: str) -> HeadSpec:
    if name not in HEADS:
        raise MonoMapError(f"head: unknown head {name!r} (choose from {', '.join(HEADS)})")
    return HEADS[name]


# ---------------------------------------------------------------- targets
def soft_target(depth: torch.Tensor, bins: DepthBins, sigma: float | None = None) -> torch.Tensor:
    """(B,H,W) metres -> (B,K,H,W) unnormalised soft target q̃_k = exp(-(k - y*)² / 2σ²).

    σ defaults to bins.soft_target_sigma(): every bin within 25 % of the true depth gets q̃ > 0.5.
    """
    sigma = bins.soft_target_sigma() if sigma is None else sigma
    y = bins.continuous_index(depth).unsqueeze(1)
    k = torch.arange(bins.num_bins, dtype=depth.dtype, device=depth.device).view(1, -1, 1, 1)
    return torch.exp(-((k - y) ** 2) / (2.0 * sigma * sigma))


def valid_mask(depth: torch.Tensor, bins: DepthBins) -> torch.Tensor:
    """Pixels with a depth value (> 0); depths beyond the bin range are clipped, not dropped."""
    return depth > 0


def _masked_mean(per_pixel: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    n = mask.sum()
    if n == 0:
        return per_pixel.sum() * 0.0
    return (per_pixel * mask).sum() / n


def _log_mid(bins: DepthBins) -> float:
    return 0.5 * (math.log(bins.min_depth) + math.log(bins.max_depth))


# ---------------------------------------------------------------- losses
def head_loss(head: HeadSpec | str, output: torch.Tensor, depth: torch.Tensor, bins: DepthBins) -> torch.Tensor:
    """Scalar training loss of a head's raw network output (B,C,H,W) against target depth (B,H,W) metres."""
    head = get_head(head) if isinstance(head, str) else head
    mask = valid_mask(depth, bins)
    safe = torch.where(mask, depth, torch.full_like(depth, bins.min_depth))
    base = head.name.replace("-dropout", "")
    if base == "binary":
        q = soft_target(safe, bins)
        bce = F.binary_cross_entropy_with_logits(output, q, reduction="none").sum(1)
        return _masked_mean(bce, mask)
    if base == "softmax":
        q = soft_target(safe, bins)
        q = q / q.sum(1, keepdim=True)
        ce = -(q * F.log_softmax(output, 1)).sum(1)
        return _masked_mean(ce, mask)
    if base == "ordinal":
        y = bins.continuous_index(safe).unsqueeze(1)
        k = torch.arange(bins.num_bins - 1, dtype=depth.dtype, device=depth.device).view(1, -1, 1, 1)
        t = (y > k + 0.5).to(output.dtype)
        bce = F.binary_cross_entropy_with_logits(output, t, reduction="none").sum(1)
        return _masked_mean(bce, mask)
    if base == "gaussian":
        mean, log_var = gaussian_params(output, bins)
        nll = 0.5 * (torch.exp(-log_var) * (safe.log() - mean) ** 2 + log_var)
        return _masked_mean(nll, mask)
    if base in ("l2", "berhu"):
        r = (regression_log_depth(output, bins) - safe.log()).abs()
        if base == "l2":
            return _masked_mean(r * r, mask)
        c = (0.2 * (r * mask).max()).detach().clamp_min(1e-6)
        b = torch.where(r <= c, r, (r * r + c * c) / (2 * c))
        return _masked_mean(b, mask)
    raise MonoMapError(f"head: no loss for {head.name!r}")


def gaussian_params(output: torch.Tensor, bins: DepthBins) -> tuple[torch.Tensor, torch.Tensor]:
    """(B,2,H,W) raw output -> (mean log-depth, log-variance), each (B,H,W)."""
    return output[:, 0] + _log_mid(bins), output[:, 1].clamp(-12.0, 8.0)


def regression_log_depth(output: torch.Tensor, bins: DepthBins) -> torch.Tensor:
    return output[:, 0] + _log_mid(bins)


# ---------------------------------------------------------------- decoding
def decode(head: HeadSpec | str, outputs: torch.Tensor, bins: DepthBins, space: str = "log",
           with_probs: bool = False) -> dict[str, torch.Tensor]:
    """Raw outputs -> depth (B,H,W) m, entropy (B,H,W) nats, argmax (B,H,W) m, probs (B,K,H,W) or None.

    ``outputs`` is (B,C,H,W), or (S,B,C,H,W) for S Monte-Carlo dropout samples, which are combined:
    bin heads average their softmax probabilities; Gaussian heads use the mixture's mean and total
    variance (mean of variances + variance of means).
    """
    head = get_head(head) if isinstance(head, str) else head
    mc = outputs.dim() == 5
    if head.kind == "bins" and not mc:  # one log-softmax serves probabilities, entropy and expectation
        logp = torch.log_softmax(outputs, 1)
        p = logp.exp()
        c = dist._centres(bins, p, space == "log")
        e = (p * c).sum(1)
        centres = torch.as_tensor(bins.centres, dtype=p.dtype, device=p.device)
        return {"depth": e.exp() if space == "log" else e, "entropy": -(p * logp).sum(1),
                "argmax": centres[outputs.argmax(1)], "probs": p if with_probs else None}
    if head.kind in ("bins", "ordinal"):
        if head.kind == "bins":
            p = dist.probs_from_logits(outputs.flatten(0, 1) if mc else outputs)
        else:
            p = dist.ordinal_to_probs(outputs.flatten(0, 1) if mc else outputs)
        if mc:
            p = p.view(outputs.shape[0], outputs.shape[1], *p.shape[1:]).mean(0)
        return {"depth": dist.expected_depth(p, bins, space), "entropy": dist.entropy(p),
                "argmax": dist.argmax_depth(p, bins), "probs": p if with_probs else None}
    if head.kind == "gaussian":
        if mc:
            means, log_vars = gaussian_params(outputs.flatten(0, 1), bins)
            means = means.view(outputs.shape[0], -1, *means.shape[1:])
            var = torch.exp(log_vars).view_as(means).mean(0) + means.var(0, unbiased=False)
            mean, log_var = means.mean(0), torch.log(var.clamp_min(1e-12))
        else:
            mean, log_var = gaussian_params(outputs, bins)
        if space == "linear":  # mean of a log-normal
            depth = torch.exp(mean + 0.5 * torch.exp(log_var))
        else:
            depth = torch.exp(mean)
        depth = depth.clamp(bins.min_depth, bins.max_depth)
        probs = dist.gaussian_to_probs(mean, log_var, bins) if with_probs else None
        return {"depth": depth, "entropy": dist.gaussian_entropy(log_var), "argmax": torch.exp(mean).clamp(
            bins.min_depth, bins.max_depth), "probs": probs}
    if head.kind == "regression":
        o = outputs.mean(0) if mc else outputs
        depth = torch.exp(regression_log_depth(o, bins)).clamp(bins.min_depth, bins.max_depth)
        return {"depth": depth, "entropy": torch.zeros_like(depth), "argmax": depth, "probs": None}
    raise MonoMapError(f"head: cannot decode {head.name!r}")
