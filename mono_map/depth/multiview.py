"""Multi-view fusion of a frame's depth distribution: a plane-sweep photometric likelihood over the model's own
depth bins from neighbouring frames of the sequence, combined with the network's bin probabilities.

A frame's per-pixel bin probabilities p_k (the prior) share their errors with the next frame's (the model
places a surface wrong in every view alike); the images and the sequence's metric poses do not. For each
bin centre d_k, every neighbour (chosen by baseline, :func:`mono_map.depth.sources.choose_sources`) is warped
into the frame through the fronto-parallel plane at depth d_k (:func:`mono_map.depth.photometric.warp`) and
compared (monodepth2's SSIM + L1, :func:`mono_map.depth.photometric.photometric_error`); per pixel and bin the
cost c_k is the minimum over the neighbours (a surface occluded in one is seen in the other). The posterior is

    q_k ∝ p_k^a · exp(−c_k / τ)            (a = ``prior_power``, τ = ``temperature``; normalised per pixel)

Pixels keep the prior where the sweep says nothing: no neighbour in range, fewer than half the bins seen by
a neighbour (bins seen by none get the pixel's mean cost), or the unwarped neighbours already match at least
as well as the best plane (auto-masking: a static camera, things moving with it, textureless sky).
Conventions: images H×W×3 uint8 RGB; poses ``T_world_cam`` 4×4 metres (image_2's, world = first cam0 frame);
the cost is computed at 1/``scale`` of the image (the decoder's stride) and read at the prior's pixels.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np

from mono_map.errors import MonoMapError
from mono_map.depth import sweep_c
from mono_map.depth.sources import choose_sources
from mono_map.geometry import scaled_intrinsics


@dataclass(frozen=True)
class MultiviewConfig:
    """Settings of the multi-view posterior.

    sources: neighbours used per frame (the nearest before and after within the baseline range: 1 or 2);
    min_baseline, max_baseline: metres between the cameras' centres; max_offset: frames searched each way;
    temperature: τ of the likelihood exp(−cost/τ) (cost: SSIM+L1 error, 0–1); prior_power: a of p^a;
    scale: the cost is computed at 1/scale of the image resolution; window: the cost is averaged over
    window×window pixels of that grid (odd; 1 = per pixel); stereo: the frame's own right colour camera
    (image_3, same instant, 0.53 m right of image_2) is one more source."""

    sources: int = 2
    min_baseline: float = 0.3
    max_baseline: float = 4.0
    max_offset: int = 10
    # chosen on training town 06 (AbsRel of the expected depth, docs/fused.md), never on 00
    temperature: float = 0.02
    prior_power: float = 1.0
    scale: int = 4
    window: int = 3
    stereo: bool = False


def check_multiview_config(cfg: MultiviewConfig) -> MultiviewConfig:
    """``cfg`` if every setting is usable, else MonoMapError naming the option (one line)."""
    if int(cfg.sources) != cfg.sources or cfg.sources not in (1, 2):
        raise MonoMapError(f"--fused-multiview: neighbours per frame must be 0 (off), 1 or 2, got {cfg.sources}")
    for name, v in (("multiview-temperature", cfg.temperature), ("multiview-max-baseline", cfg.max_baseline)):
        if not (math.isfinite(v) and v > 0):
            raise MonoMapError(f"--fused-{name}: must be a positive number, got {v}")
    if not (math.isfinite(cfg.min_baseline) and 0 <= cfg.min_baseline < cfg.max_baseline):
        raise MonoMapError(f"--fused-multiview-min-baseline: must be in [0, max baseline {cfg.max_baseline:g}) m, "
                           f"got {cfg.min_baseline}")
    if not (math.isfinite(cfg.prior_power) and cfg.prior_power >= 0):
        raise MonoMapError(f"--fused-multiview-prior-power: must be a number >= 0, got {cfg.prior_power}")
    if int(cfg.max_offset) != cfg.max_offset or cfg.max_offset < 1:
        raise MonoMapError(f"multiview max_offset: must be a positive integer (frames), got {cfg.max_offset}")
    if int(cfg.window) != cfg.window or cfg.window < 1 or cfg.window % 2 == 0:
        raise MonoMapError(f"multiview window: must be an odd positive integer (pixels), got {cfg.window}")
    if int(cfg.scale) != cfg.scale or cfg.scale < 1:
        raise MonoMapError(f"multiview scale: must be a positive integer, got {cfg.scale}")
    return cfg


def ssim_l1_against(target, C1: float = 0.01 ** 2, C2: float = 0.03 ** 2):
    """A function x (D,1,h,w) → (D,h,w) monodepth2 error 0.85·(1 − SSIM)/2 + 0.15·|x − target| against the
    one-channel ``target`` (1,h,w) (reflection-padded 3×3 windows, as
    :func:`mono_map.depth.photometric.photometric_error`; the target's window statistics computed once)."""
    import torch
    import torch.nn.functional as F

    from mono_map.depth.photometric import SSIM_WEIGHT, box3

    y = F.pad(target.unsqueeze(0), (1, 1, 1, 1), mode="reflect")
    mu_y = box3(y)
    syy = box3(y * y) - mu_y ** 2

    def error(x):
        xp = F.pad(x, (1, 1, 1, 1), mode="reflect")
        mu_x = box3(xp)
        sxx = box3(xp * xp) - mu_x ** 2
        sxy = box3(xp * y) - mu_x * mu_y
        n = (2 * mu_x * mu_y + C1) * (2 * sxy + C2)
        d = (mu_x ** 2 + mu_y ** 2 + C1) * (sxx + syy + C2)
        ssim = torch.clamp((1 - n / d) / 2, 0, 1)
        return (SSIM_WEIGHT * ssim + (1 - SSIM_WEIGHT) * (x - target).abs())[:, 0]

    return error


def plane_warp(source, K: np.ndarray, T_src_tgt: np.ndarray, depths: np.ndarray):
    """``source`` (C,h,w) seen from the target camera through fronto-parallel planes at ``depths`` (D,) metres:
    (warped (D,C,h,w), valid (D,h,w) bool) — :func:`mono_map.depth.photometric.warp` with a constant depth per
    plane, as one homography per plane (p_src ~ K·R·K⁻¹·p + K·t / d): the same sampling (bilinear, border,
    pixel centres) and validity (in front of the source camera, inside its image)."""
    import torch
    import torch.nn.functional as F

    from mono_map.depth.photometric import pixel_grid

    C, h, w = source.shape
    D = len(depths)
    K = np.asarray(K, dtype=np.float64)
    T = np.asarray(T_src_tgt, dtype=np.float64)
    A = torch.as_tensor((K @ T[:3, :3] @ np.linalg.inv(K)).astype(np.float32)) @ pixel_grid(h, w)   # (3, hw)
    b = torch.as_tensor((K @ T[:3, 3]).astype(np.float32)).view(1, 3, 1)
    inv_d = torch.as_tensor(1.0 / np.asarray(depths, dtype=np.float64), dtype=torch.float32).view(D, 1, 1)
    proj = A.unsqueeze(0) + b * inv_d                                                   # (D, 3, hw) / depth
    z = proj[:, 2]
    zc = z.clamp_min(1e-6)
    gx = (2 * proj[:, 0] / zc + 1) / w - 1
    gy = (2 * proj[:, 1] / zc + 1) / h - 1
    grid = torch.stack([gx, gy], -1).view(D, h, w, 2)
    warped = F.grid_sample(source.unsqueeze(0).expand(D, C, h, w), grid, mode="bilinear", padding_mode="border",
                           align_corners=False)
    valid = (z > 0) & (gx.abs() <= 1) & (gy.abs() <= 1)
    return warped, valid.view(D, h, w)


def sweep_cost(target, sources: list, K: np.ndarray, T_src_tgt: list[np.ndarray], depths: np.ndarray):
    """Plane-sweep cost of ``target`` (1,h,w) grey float tensor in [0,1] against ``sources`` (each (1,h,w))
    with relative poses ``T_src_tgt`` (4×4, target camera → source camera, metres) and intrinsics ``K`` (3×3
    of this grid), over fronto-parallel planes at ``depths`` (D,) metres. Returns (cost (D,h,w): per plane the
    minimum over the sources of the SSIM+L1 error, inf where no source sees the plane; identity (h,w): the
    minimum error of the unwarped sources). Compiled (:mod:`mono_map.depth.sweep_c`) where it is available,
    else in torch."""
    import torch

    lib = sweep_c.library() if target.shape[1] > 1 and target.shape[2] > 1 else None
    if lib is not None:                         # the same one plane at a time in C
        cost, ident = sweep_c.sweep_cost(lib, target[0].numpy(), [s[0].numpy() for s in sources], K, T_src_tgt,
                                         depths)
        return torch.from_numpy(cost), torch.from_numpy(ident)
    D = len(depths)
    _, h, w = target.shape
    error = ssim_l1_against(target)
    cost = torch.full((D, h, w), float("inf"))
    ident = torch.full((h, w), float("inf"))
    for src, T in zip(sources, T_src_tgt):
        warped, valid = plane_warp(src, K, T, depths)
        cost = torch.minimum(cost, error(warped).masked_fill_(~valid, float("inf")))
        ident = torch.minimum(ident, error(src.unsqueeze(0))[0])
    return cost, ident


def likelihood(cost, ident, temperature: float, window: int = 1):
    """(log-likelihood (D,h,w) = −(c − min c)/τ, informative (h,w) bool) of a sweep's ``cost`` (D,h,w) and
    ``identity`` (h,w): planes no source sees get the pixel's mean cost, then costs and identity are averaged
    over ``window``×``window`` pixels; a pixel is informative where at least half the planes are seen and the
    best plane beats the unwarped sources."""
    return likelihood_of_groups([(cost, ident)], temperature, window)


def windowed_cost(cost, ident, window: int = 1):
    """(cost (D,h,w), informative (h,w) bool) of one sweep, as :func:`likelihood` reads it."""
    import torch
    import torch.nn.functional as F

    lib = sweep_c.library()
    if lib is not None:                         # the same in one compiled pass
        c, info = sweep_c.windowed_cost(lib, cost.numpy(), ident.numpy(), window)
        return torch.from_numpy(c), torch.from_numpy(info)
    seen = torch.isfinite(cost)
    n_seen = seen.float().sum(0)
    c = torch.where(seen, cost, torch.zeros_like(cost))
    mean = c.sum(0) / n_seen.clamp_min(1)
    c = torch.where(seen, c, mean.unsqueeze(0))
    if window > 1:
        r = window // 2
        c = F.avg_pool2d(F.pad(c.unsqueeze(0), (r, r, r, r), mode="replicate"), window, 1)[0]
        ident = F.avg_pool2d(F.pad(ident[None, None], (r, r, r, r), mode="replicate"), window, 1)[0, 0]
    return c, (n_seen * 2 >= cost.shape[0]) & (ident > c.min(0).values)


def likelihood_of_groups(groups: list, temperature: float, window: int = 1):
    """:func:`likelihood` of several sweeps ``groups`` [(cost, identity), ...], each auto-masked on its own (the
    neighbouring frames as one group, the same instant's right image as another: a scene moving with the car
    matches the unwarped neighbours, not the unwarped right image); per pixel the minimum cost over the groups
    informative there."""
    import torch

    c, informative = None, None
    for cost, ident in groups:
        cg, ig = windowed_cost(cost, ident, window)
        cg = torch.where(ig.unsqueeze(0), cg, torch.full_like(cg, float("inf")))
        c, informative = (cg, ig) if c is None else (torch.minimum(c, cg), informative | ig)
    c = torch.where(informative.unsqueeze(0), c, torch.zeros_like(c))
    best = c.min(0).values
    return (best.unsqueeze(0) - c) / float(temperature), informative


def parabola_peak(values, log_centres: np.ndarray, dim: int = 0):
    """The log-depth of the peak per pixel (h,w) tensor of ``values`` (D,h,w) tensor (the D values along
    ``dim``) over the evenly spaced ``log_centres`` (D,) (log metres; a sweep's planes or the depth bins): the
    highest one's centre refined by a parabola through it and its two neighbours (at most half a spacing; none
    at the first and last centre or where the peak is flat). A sweep's best plane from its log-likelihood; a
    distribution's mode from its bin probabilities."""
    import torch

    lc = torch.as_tensor(np.asarray(log_centres, dtype=np.float32))
    D = lc.numel()
    k = values.argmax(dim)
    km, kp = (k - 1).clamp_min(0), (k + 1).clamp_max(D - 1)
    l0, lm, lp = (values.gather(dim, i.unsqueeze(dim)).squeeze(dim) for i in (k, km, kp))
    curv = lm - 2 * l0 + lp
    inner = (k > 0) & (k < D - 1) & (curv < 0)
    offset = torch.where(inner, 0.5 * (lm - lp) / torch.where(inner, curv, torch.ones_like(curv)),
                         torch.zeros_like(curv)).clamp(-0.5, 0.5)
    step = float(lc[1] - lc[0]) if D > 1 else 0.0
    return lc[k] + offset * step


def posterior_change(prior, loglik, informative, log_centres: np.ndarray, prior_power: float = 1.0):
    """The posterior p^a·exp(``loglik``), normalised, where ``informative`` and the product has mass, the
    prior elsewhere; the bins last: ``prior`` and ``loglik`` (h,w,K) float32 tensors, ``informative`` (h,w)
    bool. Returns (posterior (h,w,K), its change of the expected log-depth (h,w), of the entropy (h,w)
    nats against the prior; 0 where the prior is kept). The entropy from the logarithms the posterior is made
    of: log q = a·log p + ℓ − log Σ, so −Σ q log q = log Σ − Σ q (a·log p + ℓ) (one logarithm per bin for both
    entropies instead of two x·log x passes)."""
    import torch

    a = float(prior_power)
    lc = torch.as_tensor(np.asarray(log_centres, dtype=np.float32))
    logp = torch.log(prior.clamp_min(1e-30))                 # p = 0 contributes p·log p = 0 below
    q = (prior if a == 1 else torch.exp(logp * a)) * torch.exp(loglik)
    mass = q.sum(-1)
    use = informative & (mass > 0)
    q = torch.where(use.unsqueeze(-1), q / mass.clamp_min(1e-30).unsqueeze(-1), prior)
    e0 = -(prior * logp).sum(-1)
    e1 = mass.clamp_min(1e-30).log() - (q * (logp if a == 1 else logp * a).add_(loglik)).sum(-1)
    dm = torch.where(use, (q - prior) @ lc, torch.zeros_like(mass))
    de = torch.where(use, e1 - e0, torch.zeros_like(mass))
    return q, dm, de


def resample(x, size: tuple[int, int], full: tuple[int, int], step: int):
    """``x`` (C,h,w) torch (a grid covering a ``full`` (H, W) image) read bilinearly at the pixels
    [::step, ::step] of the full image, channels last: ``size`` + (C,) (contiguous)."""
    import torch
    import torch.nn.functional as F

    lib = sweep_c.library()
    if lib is not None and x.shape[1] > 1 and x.shape[2] > 1:
        return torch.from_numpy(sweep_c.resample(lib, x.numpy(), size, full, step))
    H, W = full
    v = torch.arange(size[0], dtype=torch.float32) * step
    u = torch.arange(size[1], dtype=torch.float32) * step
    gy, gx = torch.meshgrid(2 * (v + 0.5) / H - 1, 2 * (u + 0.5) / W - 1, indexing="ij")
    grid = torch.stack([gx, gy], -1).unsqueeze(0)
    out = F.grid_sample(x.unsqueeze(0).contiguous(memory_format=torch.channels_last), grid, mode="bilinear",
                        padding_mode="border", align_corners=False)[0]
    return out.permute(1, 2, 0).contiguous()


class MultiviewPosterior:
    """Turns a frame's DepthPrediction into the multi-view posterior's (:meth:`refine`); holds a few
    neighbours' reduced images."""

    def __init__(self, cfg: MultiviewConfig, bins, cache: int = 24):
        self.cfg, self.bins = check_multiview_config(cfg), bins
        self.images: OrderedDict[int, object] = OrderedDict()
        self.cache = int(cache)
        self.last_informative = float("nan")     # fraction of the last frame's pixels the sweep changed

    def small_image(self, seq, i: int, right: bool = False):
        """Frame ``i``'s image_2 (``right``: image_3) in grey (channel mean), area-averaged to 1/scale: (1,h,w)
        float tensor in [0,1] (cached)."""
        import torch
        import torch.nn.functional as F

        key = (i, right)
        if key not in self.images:
            rgb = seq.image_right(i) if right else seq.image(i)
            img = torch.as_tensor(np.ascontiguousarray(rgb)).float().mean(-1, keepdim=True).permute(2, 0, 1).div(255.0)
            H, W = img.shape[1:]
            s = int(self.cfg.scale)
            self.images[key] = F.interpolate(img.unsqueeze(0), size=(math.ceil(H / s), math.ceil(W / s)),
                                             mode="area")[0] if s > 1 else img
            while len(self.images) > self.cache:
                self.images.popitem(last=False)
        return self.images[key]

    def neighbours(self, seq, i: int) -> list[int]:
        """Frames of ``seq`` that serve ``i`` as sources (by baseline; at most ``sources``)."""
        c = self.cfg
        lo, hi = max(0, i - c.max_offset), min(len(seq) - 1, i + c.max_offset)
        idx = list(range(lo, hi + 1))
        pos = np.stack([seq.T_world_cam2(j)[:3, 3] for j in idx])
        found = choose_sources(pos, c.min_baseline, c.max_baseline, c.max_offset).get(i - lo, [])
        srcs = [idx[k] for k in found]
        if len(srcs) > c.sources:        # one source: the one after (the scene ahead is seen from closer)
            srcs = srcs[-c.sources:]
        return srcs

    def refine(self, seq, i: int, pred):
        """The DepthPrediction ``pred`` of frame ``i`` of ``seq`` with its bin probabilities replaced by the
        posterior, its expected depth and entropy moved by the posterior's change at each prior pixel (read
        at full resolution from the nearest prior pixel; unchanged where the sweep says nothing); ``pred``
        itself if no neighbour qualifies. ``pred.probs`` is needed (K×H'×W' every ``probs_step`` pixels)."""
        import dataclasses

        import torch

        if pred.probs is None:
            raise MonoMapError("multiview: the prediction has no bin probabilities")
        # the neighbours and the right image are auto-masked apart (likelihood_of_groups): groups of (frame, right?)
        groups = [g for g in ([(j, False) for j in self.neighbours(seq, i)], [(i, True)] if self.cfg.stereo else [])
                  if g]
        if not groups:
            self.last_informative = 0.0
            return pred
        if self.cfg.stereo:
            seq.require_right([i], "multiview stereo")
        tgt = self.small_image(seq, i)
        h, w = tgt.shape[1:]
        H, W = pred.depth.shape
        Ks = scaled_intrinsics(seq.calib.K2, w / W, h / H)
        T_t = seq.T_world_cam2(i)
        with torch.no_grad():
            sweeps = [sweep_cost(tgt, [self.small_image(seq, j, right) for j, right in g], Ks,
                                 [np.linalg.inv(seq.T_world_cam3(j) if right else seq.T_world_cam2(j)) @ T_t
                                  for j, right in g], self.bins.centres) for g in groups]
            ll, info = likelihood_of_groups(sweeps, self.cfg.temperature, int(self.cfg.window))
            step = int(pred.probs_step)
            # bins last: each pixel's K probabilities side by side (the predictor's sampled probabilities are
            # stored so; a (K,h,w) view of them is channels-last)
            prior = torch.from_numpy(np.ascontiguousarray(np.asarray(pred.probs, dtype=np.float32).transpose(1, 2, 0)))
            size = tuple(prior.shape[:2])
            informative = resample(info.float().unsqueeze(0), size, (H, W), step)[..., 0] > 0.5
            q, dm, de = posterior_change(prior, resample(ll, size, (H, W), step), informative,
                                         self.bins.log_centres, self.cfg.prior_power)
            dm, de, q = dm.numpy(), de.numpy(), q.numpy().transpose(2, 0, 1)
        self.last_informative = float(informative.float().mean())
        rows = np.minimum(np.arange(H) // step, size[0] - 1)
        cols = np.minimum(np.arange(W) // step, size[1] - 1)
        ratio = np.exp(dm)[rows][:, cols]
        dent = de[rows][:, cols]
        depth = np.where(pred.depth > 0, pred.depth * ratio, pred.depth).astype(np.float32)
        entropy = (np.asarray(pred.entropy, dtype=np.float32) + dent).astype(np.float32)
        return dataclasses.replace(pred, depth=depth, entropy=entropy, probs=q)
