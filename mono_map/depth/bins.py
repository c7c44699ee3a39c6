"""Log-spaced depth bins (paper Eq. 1) and the continuous bin index of a depth.

Bin k (0-based here, 1-based in the paper) covers [e_k, e_{k+1}) metres with
log e_k = log a + k/K (log b - log a), k = 0..K.  Its centre is the log-space
midpoint exp((log e_k + log e_{k+1}) / 2), as in the authors' released code.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from mono_map.errors import MonoMapError


@dataclass(frozen=True)
class DepthBins:
    """K log-spaced intervals over [min_depth, max_depth) metres."""

    num_bins: int = 64
    min_depth: float = 1.0
    max_depth: float = 80.0

    def __post_init__(self) -> None:
        if self.num_bins < 2:
            raise MonoMapError(f"bins: num_bins must be >= 2, got {self.num_bins}")
        if not (0 < self.min_depth < self.max_depth):
            raise MonoMapError(f"bins: need 0 < min_depth < max_depth, got {self.min_depth}, {self.max_depth}")

    @property
    def log_width(self) -> float:
        """Width of one bin in natural-log depth units."""
        return (math.log(self.max_depth) - math.log(self.min_depth)) / self.num_bins

    @property
    def log_edges(self) -> np.ndarray:
        """(K+1,) log-depth edges; paper Eq. 1 gives the first K (d_k, k = 1..K)."""
        return math.log(self.min_depth) + np.arange(self.num_bins + 1, dtype=np.float64) * self.log_width

    @property
    def edges(self) -> np.ndarray:
        """(K+1,) metres."""
        return np.exp(self.log_edges)

    @property
    def log_centres(self) -> np.ndarray:
        """(K,) log-depth bin centres (log-space midpoints)."""
        e = self.log_edges
        return 0.5 * (e[:-1] + e[1:])

    @property
    def centres(self) -> np.ndarray:
        """(K,) metres."""
        return np.exp(self.log_centres)

    def continuous_index(self, depth):
        """Continuous bin index y* of depth (metres): y* = k exactly at the centre of bin k.

        Works on numpy arrays and torch tensors; depths are clipped to [min_depth, max_depth]
        so y* lies in [-0.5, K - 0.5].
        """
        lo, hi = self.min_depth, self.max_depth
        if _is_torch(depth):
            d = depth.clamp(lo, hi)
            return (d.log() - math.log(lo)) / self.log_width - 0.5
        d = np.clip(np.asarray(depth, dtype=np.float64), lo, hi)
        return (np.log(d) - math.log(lo)) / self.log_width - 0.5

    def index_to_depth(self, index):
        """Inverse of continuous_index: metres at (fractional) bin index."""
        if _is_torch(index):
            return (math.log(self.min_depth) + (index + 0.5) * self.log_width).exp()
        return np.exp(math.log(self.min_depth) + (np.asarray(index, dtype=np.float64) + 0.5) * self.log_width)

    def soft_target_sigma(self, ratio: float = 1.25) -> float:
        """σ (in bins) of the soft target exp(-(k-y*)²/2σ²) that is exactly 0.5 at depth ratio ``ratio``.

        Bins whose centre depth d satisfies max(d/d*, d*/d) < ratio (within 25 % for 1.25) are
        less than log(ratio)/log_width bins away, so their label exceeds 0.5:
        exp(-x²/2σ²) = 0.5  <=>  x = σ·sqrt(2 ln 2).
        """
        return math.log(ratio) / self.log_width / math.sqrt(2.0 * math.log(2.0))

    def to_dict(self) -> dict:
        return {"num_bins": self.num_bins, "min_depth": self.min_depth, "max_depth": self.max_depth}


def _is_torch(x) -> bool:
    return type(x).__module__.startswith("torch")
