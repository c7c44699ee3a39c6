"""Depth Hints (Watson et al., ICCV 2019) for self-supervised adaptation: the plane sweep's best depth per pixel
as a supervised target, used only where it explains the target image better than the current prediction.

A hint is computed once per target frame from the project's one plane sweep (:mod:`mono_map.depth.multiview`:
every source warped through fronto-parallel planes at the K bin centres, SSIM+L1 in grey, the minimum over the
sources, averaged over ``window``×``window`` pixels) with the sequence's known metric poses, so it is metric:
the plane of lowest cost, refined between planes by a parabola (:func:`~mono_map.depth.multiview.parabola_peak`).
Pixels where the sweep says nothing (fewer than half the planes seen, or the unwarped sources already match:
a static camera, things moving with it, sky) get no hint, and with a contrast floor neither do pixels whose
cost curve has no distinct minimum (the planes' mean cost within the floor of the best). The hint's own
photometric error (the adaptation's SSIM+L1 in colour, minimum over the same sources:
:func:`~mono_map.depth.photometric.min_reprojection_error`) is stored with it; at every step a pixel is
supervised only where that error is below the prediction's.
Conventions: images (N,h,w,3) uint8 at the loss resolution; K (3,3) of those images; poses ``T_world_cam``
(N,4,4) metres.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from mono_map.depth.multiview import likelihood, parabola_peak, sweep_cost
from mono_map.depth.photometric import min_reprojection_error, to_tensor


@dataclass(frozen=True)
class DepthHints:
    """Per frame: ``depth`` (N,1,h,w) float32 metres (0 = no hint) and ``error`` (N,1,h,w) the hint's photometric
    error (inf where there is no hint)."""

    depth: torch.Tensor
    error: torch.Tensor


def sweep_hint(target: torch.Tensor, sources: list[torch.Tensor], K: np.ndarray, T_src_tgt: list[np.ndarray],
               depths: np.ndarray, log_depths: np.ndarray, window: int = 3, min_contrast: float = 0.0
               ) -> tuple[torch.Tensor, torch.Tensor]:
    """(hint depth (h,w) metres, informative (h,w) bool) of ``target`` (3,h,w) in [0,1] against ``sources`` (each
    (3,h,w)) with poses ``T_src_tgt`` (4×4 target camera → source camera, metres), over planes at ``depths`` (D,)
    metres (``log_depths`` their logs, evenly spaced). With ``min_contrast`` > 0 a pixel is informative only
    where its planes' mean cost exceeds the best by more than that (a distinct minimum: texture and parallax)."""
    grey = [x.mean(0, keepdim=True) for x in [target, *sources]]
    cost, ident = sweep_cost(grey[0], grey[1:], K, T_src_tgt, depths)
    loglik, informative = likelihood(cost, ident, 1.0, window)
    if min_contrast > 0:
        informative = informative & (-loglik.mean(0) > min_contrast)
    return torch.exp(parabola_peak(loglik, log_depths)), informative


@torch.no_grad()
def compute_hints(images: np.ndarray, K: np.ndarray, poses: np.ndarray, sources: dict[int, list[int]], bins,
                  content: torch.Tensor | None = None, window: int = 3, min_contrast: float = 0.0,
                  progress_desc: str = "adapt: hints"
                  ) -> DepthHints:
    """The hints of every target in ``sources`` (frame → its source frames, indices into ``images``) at the
    images' resolution; frames that are not targets, and pixels outside ``content`` ((h,w) bool), get none."""
    from mono_map.progress import progress

    N, h, w = images.shape[:3]
    depth = torch.zeros(N, 1, h, w)
    error = torch.full((N, 1, h, w), float("inf"))
    Kt = torch.as_tensor(K, dtype=torch.float32)[None]
    for t in progress(sorted(sources), total=len(sources), desc=progress_desc, unit="frame"):
        srcs = sources[t]
        tgt = to_tensor(images[[t]])
        src = [to_tensor(images[[s]]) for s in srcs]
        rel = [np.linalg.inv(poses[s]) @ poses[t] for s in srcs]
        d, informative = sweep_hint(tgt[0], [x[0] for x in src], K, rel, bins.centres, bins.log_centres, window,
                                    min_contrast)
        if content is not None:
            informative = informative & content
        err, seen = min_reprojection_error(tgt, src, d[None, None], Kt,
                                           [torch.as_tensor(T, dtype=torch.float32)[None] for T in rel])
        keep = informative[None, None] & seen
        depth[t] = torch.where(keep, d[None, None], torch.zeros(())).squeeze(0)
        error[t] = torch.where(keep, err, torch.full_like(err, float("inf"))).squeeze(0)
    return DepthHints(depth, error)


def hint_mask(hint_depth: torch.Tensor, hint_error: torch.Tensor, pred_error: torch.Tensor) -> torch.Tensor:
    """Pixels (B,1,h,w) bool where a hint exists and its photometric error is lower than the prediction's."""
    return (hint_depth > 0) & (hint_error < pred_error)
