"""A stand-in depth predictor built from ground-truth depth (synthetic sequences carry ``depth_2/``).

For developing and testing the mapping pipeline without a trained model, and as a controlled
experiment: each pixel's log-depth gets Gaussian noise whose scale σ grows at depth
discontinuities (where monocular models smear depth into "streaks"), and the reported entropy is
the differential entropy of that log-normal error, ``0.5·log(2πe σ²)`` nats — an uncertainty that
is informative by construction. With ``with_probs`` it also gives the distribution it claims:
the log-normal error around its noisy depth discretised into the depth bins (mass below the first
edge in the first bin, mass beyond the last edge as ``p_beyond``, the bin probabilities
conditional on a surface within range as every DepthPrediction's), so both ``--integrate keep``
and ``--integrate distribution`` run on it. It is NOT the learned model; results with it say
nothing about the model's quality.

``shared_sigma`` adds an error the views *share*, as a network's bias is shared: a smooth random field fixed
in the world (a sum of random plane waves of wavelength ~``shared_wavelength`` metres, unit variance), scaled
by ``shared_sigma`` and added to the log-depth of every pixel whose true surface point lies there — the same
surface point gets the same error in every frame, so averaging views cannot remove it. The claimed σ is then
√(σ² + shared_sigma²) (each view's error, honestly reported).
"""

from __future__ import annotations

import numpy as np

from mono_map.depth.bins import DepthBins
from mono_map.depth.inference import DepthPrediction, check_probs_step
from mono_map.errors import MonoMapError
from mono_map.mapping.points import pixels_to_world


def lognormal_bin_probs(depth: np.ndarray, sigma: np.ndarray, bins: DepthBins,
                        beyond_only: bool = False) -> tuple[np.ndarray | None, np.ndarray]:
    """N(log depth, σ²) over log-depth, discretised into ``bins``: (K×H×W float32 probabilities, H×W
    float32 mass beyond the last edge). Mass below the first edge goes to the first bin; pixels with
    depth ≤ 0 get all mass beyond. ``beyond_only``: (None, the mass beyond) — the same values."""
    import torch

    d = torch.as_tensor(np.array(depth, dtype=np.float32))
    s = torch.as_tensor(np.array(sigma, dtype=np.float32)).clamp_min(1e-6)
    mu = torch.log(d.clamp_min(1e-6))
    e = torch.as_tensor(bins.log_edges, dtype=torch.float32).view(-1, 1, 1)
    if beyond_only:
        beyond = 1.0 - torch.special.ndtr((e[-1] - mu) / s)
        beyond[d <= 0] = 1.0
        return None, beyond.clamp(0, 1).numpy()
    c = torch.special.ndtr((e - mu) / s)                  # P(log depth < edge), (K+1)×H×W
    c[0] = 0.0
    probs = c[1:] - c[:-1]
    beyond = 1.0 - c[-1]
    none = d <= 0
    probs[:, none] = 0.0
    beyond[none] = 1.0
    return probs.clamp_min(0).numpy(), beyond.clamp(0, 1).numpy()


class NoisyGroundTruthPredictor:
    """``predict_frame(seq, i, image)`` → DepthPrediction from ``seq.depth(i)`` plus structured noise.

    sigma: log-depth noise (fraction) on smooth surfaces; edge_sigma: extra noise at depth edges
    (relative depth jump to a neighbour above ``edge_jump``) and their ``edge_width``-pixel halo.
    """

    def __init__(self, sigma: float = 0.03, edge_sigma: float = 0.5, edge_jump: float = 0.1,
                 edge_width: int = 3, seed: int = 0, bins: DepthBins | None = None,
                 shared_sigma: float = 0.0, shared_wavelength: float = 10.0):
        if not (np.isfinite(sigma) and 0 < sigma < 1):
            raise MonoMapError(f"oracle sigma: a log-depth noise in (0, 1), got {sigma}")
        for name, v in (("edge_sigma", edge_sigma), ("shared_sigma", shared_sigma)):
            if not (np.isfinite(v) and 0 <= v < 1):
                raise MonoMapError(f"oracle {name}: a log-depth noise in [0, 1), got {v}")
        if not (np.isfinite(shared_wavelength) and shared_wavelength > 0):
            raise MonoMapError(f"oracle shared_wavelength: metres > 0, got {shared_wavelength}")
        self.shared_sigma = float(shared_sigma)
        self.shared_wavelength = float(shared_wavelength)
        self.sigma = float(sigma)
        self.edge_sigma = float(edge_sigma)
        self.edge_jump = float(edge_jump)
        self.edge_width = int(edge_width)
        self.seed = int(seed)
        self.bins = bins or DepthBins()

    def sigma_map(self, depth: np.ndarray) -> np.ndarray:
        """Per-pixel log-depth noise σ (H×W float32)."""
        d = np.where(depth > 0, depth, np.nan).astype(np.float64)
        logd = np.log(d)
        edge = np.zeros(d.shape, dtype=bool)
        dx = np.abs(np.diff(logd, axis=1)) > self.edge_jump
        dy = np.abs(np.diff(logd, axis=0)) > self.edge_jump
        edge[:, 1:] |= dx
        edge[:, :-1] |= dx
        edge[1:, :] |= dy
        edge[:-1, :] |= dy
        grow = edge.copy()
        for _ in range(self.edge_width):  # dilate the edge mask (4-neighbourhood)
            g = grow.copy()
            g[1:, :] |= grow[:-1, :]
            g[:-1, :] |= grow[1:, :]
            g[:, 1:] |= grow[:, :-1]
            g[:, :-1] |= grow[:, 1:]
            grow = g
        return np.where(grow, self.sigma + self.edge_sigma, self.sigma).astype(np.float32)

    def shared_field(self, points_world: np.ndarray) -> np.ndarray:
        """The shared log-depth error (N,) float64 at world points (N, 3) metres: ``shared_sigma`` × a unit-variance
        smooth field, √(2/M)·Σ cos(k_m·x + φ_m) over M = 64 plane waves with random directions, wavelengths
        ``shared_wavelength`` × [0.5, 1.5] and phases (fixed by ``seed``)."""
        m = 64
        rng = np.random.default_rng((self.seed, 4242))
        d = rng.standard_normal((m, 3))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        k = d * (2 * np.pi / (self.shared_wavelength * rng.uniform(0.5, 1.5, (m, 1))))
        phase = rng.uniform(0, 2 * np.pi, m)
        out = np.zeros(len(points_world))
        for a in range(0, len(points_world), 65536):      # blocks: (N × M) temporaries stay small
            x = np.asarray(points_world[a:a + 65536], dtype=np.float64)
            out[a:a + 65536] = np.cos(x @ k.T + phase).sum(axis=1)
        return self.shared_sigma * np.sqrt(2.0 / m) * out

    def shared_error(self, seq, i: int, gt: np.ndarray) -> np.ndarray:
        """H×W float32 shared log-depth error of frame ``i``'s true surface points (0 where gt ≤ 0)."""
        out = np.zeros(gt.shape, dtype=np.float32)
        mask = gt > 0
        out[mask] = self.shared_field(pixels_to_world(np.asarray(gt, np.float32), mask, seq.calib.K2,
                                                      seq.T_world_cam2(i)))
        return out

    def predict_frame(self, seq, i: int, image: np.ndarray | None = None, with_probs: bool = False,
                      probs_step: int = 1) -> DepthPrediction:
        """The noisy depth of frame ``i`` (+ with_probs: its bin probabilities at the pixels
        [::probs_step, ::probs_step], the same values as at step 1)."""
        gt = seq.depth(i)
        if gt is None:
            raise MonoMapError(f"{seq.depth_dir}: no ground-truth depth for frame {i}; the oracle "
                               f"predictor needs a synthetic sequence (use --model CKPT for real data)")
        sig = self.sigma_map(gt)
        rng = np.random.default_rng((self.seed, int(i)))
        noise = rng.standard_normal(gt.shape).astype(np.float32) * sig
        if self.shared_sigma > 0:
            noise += self.shared_error(seq, i, gt)
            sig = np.sqrt(sig ** 2 + np.float32(self.shared_sigma) ** 2).astype(np.float32)
        depth = np.where(gt > 0, gt * np.exp(noise), np.float32(0.0)).astype(np.float32)
        entropy = (0.5 * np.log(2 * np.pi * np.e * sig.astype(np.float64) ** 2)).astype(np.float32)
        entropy[gt <= 0] = np.inf
        probs = p_beyond = None
        step = check_probs_step(probs_step)
        if with_probs:
            # per pixel, so the sampled pixels alone give the same values as the whole image
            probs, p_beyond_s = lognormal_bin_probs(depth[::step, ::step], sig[::step, ::step], self.bins)
            p_beyond = p_beyond_s if step == 1 else lognormal_bin_probs(depth, sig, self.bins, beyond_only=True)[1]
            # DepthPrediction's convention: bin probabilities conditional on a surface within range
            within = 1.0 - p_beyond_s
            probs = np.where(within > 0, probs / np.where(within > 0, within, 1.0), 0.0).astype(np.float32)
            if step > 1:   # channels-last memory, as DepthPredictor's sampled probabilities
                probs = np.moveaxis(np.ascontiguousarray(np.moveaxis(probs, 0, -1)), -1, 0)
        return DepthPrediction(depth=depth, entropy=entropy, probs=probs, p_beyond=p_beyond, probs_step=step)
