"""Prediction heads: how many output maps each produces and how to decode them (paper Sec. III).

Heads (by name):
  binary            K independent sigmoids trained on soft targets (the paper's method)
  softmax           K-way softmax (cross-entropy against the normalised soft target)
  ordinal           DORN-style threshold classifiers P(y > k)
  gaussian          mean and log-variance of log-depth (Kendall & Gal)
  binary-dropout, gaussian-dropout   the same with dropout in the decoder, MC-sampled at test time
  l2, berhu         regression of log-depth (no uncertainty: their entropy is constant 0)
  mhl               M regressed log-depth hypotheses, relaxed winner-takes-all L2 (Rupprecht et al. 2017;
                    the paper's Table III baseline); depth = their log-mean, "entropy" = their log-depth spread

With ``beyond=True`` (model v2) every head also says how likely a pixel has **no surface within
the bin range** (sky, or farther than ``max_depth``): binary through "none of the K bins fires"
(no extra channel: p_beyond = Π_k (1 − σ(l_k))), softmax through an extra (K+1)-th class, ordinal
through an extra threshold at ``max_depth``, Gaussian and regression heads through an extra logit.
Bin probabilities are then conditional on a surface within range (they sum to 1); the unconditional
ones are ``(1 − p_beyond) · probs``. At test time every bin head is read through a softmax over its
K bin logits, as the paper does. Statistics go through :mod:`mono_map.depth.distribution`.
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
    kind: str          # "bins" (K logits), "ordinal" (K-1), "gaussian" (2 maps), "regression" (1), "hypotheses" (M)
    dropout: bool = False

    @property
    def base(self) -> str:
        return self.name.replace("-dropout", "")

    def out_channels(self, bins: DepthBins, beyond: bool = False, hypotheses: int = 1) -> int:
        k = bins.num_bins
        n = {"bins": k, "ordinal": k - 1, "gaussian": 2, "regression": 1, "hypotheses": hypotheses}[self.kind]
        if beyond and self.base != "binary":   # binary says "beyond" with all K sigmoids off
            n += 1
        return n


HEADS: dict[str, HeadSpec] = {
    "binary": HeadSpec("binary", "bins"),
    "softmax": HeadSpec("softmax", "bins"),
    "ordinal": HeadSpec("ordinal", "ordinal"),
    "gaussian": HeadSpec("gaussian", "gaussian"),
    "binary-dropout": HeadSpec("binary-dropout", "bins", dropout=True),
    "gaussian-dropout": HeadSpec("gaussian-dropout", "gaussian", dropout=True),
    "l2": HeadSpec("l2", "regression"),
    "berhu": HeadSpec("berhu", "regression"),
    "mhl": HeadSpec("mhl", "hypotheses"),
}


def get_head(name: str) -> HeadSpec:
    if name not in HEADS:
        raise MonoMapError(f"head: unknown head {name!r} (choose from {', '.join(HEADS)})")
    return HEADS[name]


def log_mid(bins: DepthBins) -> float:
    """Log-depth at the middle of the bin range: the zero of the Gaussian / regression outputs."""
    return 0.5 * (math.log(bins.min_depth) + math.log(bins.max_depth))


def gaussian_params(output: torch.Tensor, bins: DepthBins) -> tuple[torch.Tensor, torch.Tensor]:
    """(B,C,H,W) raw output -> (mean log-depth, log-variance), each (B,H,W)."""
    return output[:, 0] + log_mid(bins), output[:, 1].clamp(-12.0, 8.0)


def regression_log_depth(output: torch.Tensor, bins: DepthBins) -> torch.Tensor:
    return output[:, 0] + log_mid(bins)


def hypotheses_log_depth(output: torch.Tensor, bins: DepthBins) -> torch.Tensor:
    """(B,M,H,W) raw MHL output -> (B,M,H,W) log-depth hypotheses."""
    return output + log_mid(bins)


def split_beyond(head: HeadSpec, output: torch.Tensor, bins: DepthBins, beyond: bool):
    """(in-range outputs, beyond-range logit (B,H,W) or None) of a raw (B,C,H,W) output.

    For binary the beyond logit is log p_beyond − log(1 − p_beyond) with p_beyond = Π(1 − σ(l_k)).
    """
    if not beyond:
        return output, None
    if head.base == "binary":
        log_none = F.logsigmoid(-output).sum(1)                       # log Π(1 − σ)
        return output, log_none - torch.log(-torch.expm1(log_none.clamp_max(-1e-6)))
    if head.kind == "bins":                                           # softmax: class K is "beyond"
        return output[:, :-1], output[:, -1]
    if head.kind == "ordinal":                                        # threshold K-1 is at max_depth
        return output, output[:, -1]
    return output[:, :-1], output[:, -1]


# ---------------------------------------------------------------- decoding
def decode(head: HeadSpec | str, outputs: torch.Tensor, bins: DepthBins, space: str = "log",
           with_probs: bool = False, beyond: bool = False) -> dict[str, torch.Tensor]:
    """Raw outputs -> depth (B,H,W) m, entropy (B,H,W) nats, argmax (B,H,W) m, p_beyond (B,H,W),
    probs (B,K,H,W) or None, and for MHL its hypotheses ``modes`` (B,M,H,W) m in output order.

    ``outputs`` is (B,C,H,W), or (S,B,C,H,W) for S Monte-Carlo dropout samples, which are combined:
    bin heads average their probabilities; Gaussian heads use the mixture's mean and total variance.
    Depth, entropy and probs describe the distribution given a surface within range; p_beyond is
    0 for a model trained without beyond-range targets.
    """
    head = get_head(head) if isinstance(head, str) else head
    mc = outputs.dim() == 5
    flat = outputs.flatten(0, 1) if mc else outputs
    x, beyond_logit = split_beyond(head, flat, bins, beyond)
    p_beyond = torch.sigmoid(beyond_logit) if beyond_logit is not None else torch.zeros_like(flat[:, 0])

    def mc_mean(t):
        return t.view(outputs.shape[0], outputs.shape[1], *t.shape[1:]).mean(0) if mc else t

    p_beyond = mc_mean(p_beyond)
    if head.kind == "bins":
        logp = torch.log_softmax(x, 1)
        if mc:
            p = mc_mean(logp.exp())
            logp = torch.log(p.clamp_min(1e-12))
        else:
            p = logp.exp()
        return {"depth": dist.expected_depth(p, bins, space), "entropy": -(p * logp).sum(1),
                "argmax": dist.argmax_depth(p, bins), "p_beyond": p_beyond, "probs": p if with_probs else None}
    if head.kind == "ordinal":
        p = mc_mean(dist.ordinal_to_probs(x[:, :bins.num_bins - 1]))
        return {"depth": dist.expected_depth(p, bins, space), "entropy": dist.entropy(p),
                "argmax": dist.argmax_depth(p, bins), "p_beyond": p_beyond, "probs": p if with_probs else None}
    if head.kind == "gaussian":
        means, log_vars = gaussian_params(x, bins)
        if mc:
            means = means.view(outputs.shape[0], -1, *means.shape[1:])
            var = torch.exp(log_vars).view_as(means).mean(0) + means.var(0, unbiased=False)
            mean, log_var = means.mean(0), torch.log(var.clamp_min(1e-12))
        else:
            mean, log_var = means, log_vars
        depth = torch.exp(mean + 0.5 * torch.exp(log_var)) if space == "linear" else torch.exp(mean)
        probs = dist.gaussian_to_probs(mean, log_var, bins) if with_probs else None
        return {"depth": depth.clamp(bins.min_depth, bins.max_depth), "entropy": dist.gaussian_entropy(log_var),
                "argmax": torch.exp(mean).clamp(bins.min_depth, bins.max_depth), "p_beyond": p_beyond,
                "probs": probs}
    if head.kind == "regression":
        depth = torch.exp(mc_mean(regression_log_depth(x, bins))).clamp(bins.min_depth, bins.max_depth)
        return {"depth": depth, "entropy": torch.zeros_like(depth), "argmax": depth, "p_beyond": p_beyond,
                "probs": None}
    if head.kind == "hypotheses":
        hyp = mc_mean(hypotheses_log_depth(x, bins))
        lo, hi = math.log(bins.min_depth), math.log(bins.max_depth)
        depth = torch.exp(hyp.mean(1)).clamp(bins.min_depth, bins.max_depth)
        spread = hyp.std(1, unbiased=False) if hyp.shape[1] > 1 else torch.zeros_like(depth)
        return {"depth": depth, "entropy": spread, "argmax": depth, "p_beyond": p_beyond, "probs": None,
                "modes": torch.exp(hyp.clamp(lo, hi))}
    raise MonoMapError(f"head: cannot decode {head.name!r}")
