"""Photometric reprojection between frames with known poses (monodepth2, Godard et al. 2019), in torch.

A target image's predicted depth and the relative pose of a source camera warp the source into the
target's view; SSIM + L1 compares the two. Conventions: images (B,3,H,W) in [0,1]; depth (B,1,H,W)
metres along the target camera's z; K (B,3,3) pixels of these images; ``T_src_tgt`` (B,4,4) maps points
of the target camera frame into the source camera frame (metres).
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

SSIM_WEIGHT = 0.85          # monodepth2: 0.85·(1 − SSIM)/2 + 0.15·L1
AUTOMASK_MARGIN = 1e-3      # a pixel counts only if warping lowers its error by more than this


def to_tensor(images: np.ndarray) -> torch.Tensor:
    """(N,h,w,3) uint8 images → (N,3,h,w) float tensor in [0,1]."""
    return torch.from_numpy(np.ascontiguousarray(images)).permute(0, 3, 1, 2).float().div_(255.0)


def pixel_grid(h: int, w: int, dtype=torch.float32) -> torch.Tensor:
    """(3, h·w) homogeneous pixel centres (u, v, 1), u along columns."""
    v, u = torch.meshgrid(torch.arange(h, dtype=dtype), torch.arange(w, dtype=dtype), indexing="ij")
    return torch.stack([u.reshape(-1), v.reshape(-1), torch.ones(h * w, dtype=dtype)])


def warp(source: torch.Tensor, depth: torch.Tensor, K: torch.Tensor, T_src_tgt: torch.Tensor
         ) -> tuple[torch.Tensor, torch.Tensor]:
    """The source image seen from the target camera: (warped (B,3,H,W), valid (B,1,H,W) bool).

    Every target pixel is back-projected with its depth, moved into the source camera and projected;
    the source is sampled there bilinearly. Pixels landing behind the source camera or outside its
    image are invalid."""
    B, _, H, W = source.shape
    pix = pixel_grid(H, W, depth.dtype).to(depth.device)                           # (3, HW)
    rays = torch.linalg.inv(K.to(depth.dtype)) @ pix                               # (B, 3, HW)
    pts = rays * depth.reshape(B, 1, -1)
    T = T_src_tgt.to(depth.dtype)
    pts = T[:, :3, :3] @ pts + T[:, :3, 3:]
    proj = K.to(depth.dtype) @ pts
    z = proj[:, 2:3]
    uv = proj[:, :2] / z.clamp_min(1e-3)
    gx = (2 * uv[:, 0] + 1) / W - 1                                               # align_corners=False
    gy = (2 * uv[:, 1] + 1) / H - 1
    grid = torch.stack([gx, gy], -1).view(B, H, W, 2)
    warped = F.grid_sample(source, grid.to(source.dtype), mode="bilinear", padding_mode="border",
                           align_corners=False)
    valid = (z.view(B, 1, H, W) > 1e-3) & (grid.abs().amax(-1, keepdim=True) <= 1).permute(0, 3, 1, 2)
    return warped, valid


def box3(x: torch.Tensor) -> torch.Tensor:
    """Mean over 3×3 windows of a padded (…, H+2, W+2) tensor -> (…, H, W): ``F.avg_pool2d(x, 3, 1)`` as
    separable sums of shifted slices (about 10× faster here on the CPU, same values to float rounding)."""
    r = x[..., :-2, :] + x[..., 1:-1, :] + x[..., 2:, :]
    return (r[..., :-2] + r[..., 1:-1] + r[..., 2:]) / 9.0


def ssim_error(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """(1 − SSIM)/2 per pixel and channel over 3×3 windows (reflection-padded), in [0, 1]."""
    C1, C2 = 0.01 ** 2, 0.03 ** 2
    x, y = F.pad(x, (1, 1, 1, 1), mode="reflect"), F.pad(y, (1, 1, 1, 1), mode="reflect")
    mu_x, mu_y = box3(x), box3(y)
    sxx = box3(x * x) - mu_x ** 2
    syy = box3(y * y) - mu_y ** 2
    sxy = box3(x * y) - mu_x * mu_y
    n = (2 * mu_x * mu_y + C1) * (2 * sxy + C2)
    d = (mu_x ** 2 + mu_y ** 2 + C1) * (sxx + syy + C2)
    return torch.clamp((1 - n / d) / 2, 0, 1)


def photometric_error(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """(B,1,H,W) monodepth2's per-pixel error: 0.85·(1 − SSIM)/2 + 0.15·|pred − target|, channel mean."""
    l1 = (pred - target).abs().mean(1, keepdim=True)
    return SSIM_WEIGHT * ssim_error(pred, target).mean(1, keepdim=True) + (1 - SSIM_WEIGHT) * l1


def min_reprojection_error(target: torch.Tensor, sources: list[torch.Tensor], depth: torch.Tensor, K: torch.Tensor,
                           poses: list[torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
    """Per pixel the minimum over the sources of the warped error (B,1,H,W) (1e3 where no source sees the
    pixel) and the pixels some source sees (B,1,H,W) bool."""
    errs, valids = [], []
    for src, T in zip(sources, poses):
        warped, valid = warp(src, depth, K, T)
        e = photometric_error(warped, target)
        errs.append(torch.where(valid, e, torch.full_like(e, 1e3)))   # outside the source: never the minimum
        valids.append(valid)
    return torch.cat(errs, 1).min(1, keepdim=True).values, torch.stack(valids).any(0)


def reprojection_loss(target: torch.Tensor, sources: list[torch.Tensor], depth: torch.Tensor, K: torch.Tensor,
                      poses: list[torch.Tensor], mask: torch.Tensor | None = None, automask: bool = True,
                      trim: float = 0.0) -> tuple[torch.Tensor, torch.Tensor]:
    """monodepth2's loss: per pixel the minimum over the sources of the warped error; with ``automask``,
    pixels whose unwarped sources already match at least as well (minus :data:`AUTOMASK_MARGIN`: a static
    camera, things moving with it) are left out. ``mask`` (B,1,H,W) bool restricts the pixels further
    (e.g. no sky, no padding). ``trim`` > 0 also leaves out that fraction of the counted pixels with the
    highest error (a robust mean against what no static scene explains: traffic, reflections).
    Returns (mean over the counted pixels, counted-pixel mask)."""
    reproj, used = min_reprojection_error(target, sources, depth, K, poses)
    return reduce_reprojection(reproj, used, target, sources, mask, automask, trim)


def auto_mask(reproj: torch.Tensor, used: torch.Tensor, target: torch.Tensor, sources: list[torch.Tensor]
              ) -> torch.Tensor:
    """``used`` (B,1,H,W) bool where the warped error ``reproj`` beats the unwarped sources' by
    :data:`AUTOMASK_MARGIN` (monodepth2's auto-mask: a static camera, things moving with it are left out)."""
    with torch.no_grad():   # the unwarped sources' error does not depend on the depth: no gradient
        ident = torch.cat([photometric_error(s, target) for s in sources], 1).min(1, keepdim=True).values
    return used & (reproj < ident - AUTOMASK_MARGIN)


def grouped_reprojection(target: torch.Tensor, groups: list[tuple[list[torch.Tensor], list[torch.Tensor]]],
                         depth: torch.Tensor, K: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(per-pixel error, counted pixels) of several source groups [(sources, poses), ...], each auto-masked on
    its own: a pixel counts for a group where its warped error beats the group's unwarped sources (minus
    :data:`AUTOMASK_MARGIN`), and its error is the minimum over the groups it counts for. The neighbouring
    frames are one group, the same instant's right image another: a car moving with the camera matches the
    unwarped neighbours (masked there) but not the unwarped right image. Reduce with ``automask=False``."""
    best, counted = None, None
    for sources, poses in groups:
        reproj, used = min_reprojection_error(target, sources, depth, K, poses)
        used = auto_mask(reproj, used, target, sources)
        reproj = torch.where(used, reproj, torch.full_like(reproj, 1e3))
        best, counted = (reproj, used) if best is None else (torch.minimum(best, reproj), counted | used)
    return best, counted


def reduce_reprojection(reproj: torch.Tensor, used: torch.Tensor, target: torch.Tensor, sources: list[torch.Tensor],
                        mask: torch.Tensor | None = None, automask: bool = True, trim: float = 0.0
                        ) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`reprojection_loss` from its per-pixel error ``reproj`` and seen pixels ``used`` (the output of
    :func:`min_reprojection_error`)."""
    if automask:
        used = auto_mask(reproj, used, target, sources)
    if mask is not None:
        used = used & mask
    if trim > 0 and used.any():
        with torch.no_grad():
            worst = torch.quantile(reproj[used].float()[:1_000_000], 1.0 - trim)
        used = used & (reproj <= worst)
    n = used.sum()
    loss = (reproj * used).sum() / n.clamp_min(1)
    return loss, used


def smoothness_loss(depth: torch.Tensor, image: torch.Tensor) -> torch.Tensor:
    """Edge-aware smoothness of the mean-normalised disparity 1/depth (monodepth2), a scalar."""
    disp = 1.0 / depth.clamp_min(1e-3)
    disp = disp / disp.mean((2, 3), keepdim=True).clamp_min(1e-6)
    dx = (disp[..., :, :-1] - disp[..., :, 1:]).abs()
    dy = (disp[..., :-1, :] - disp[..., 1:, :]).abs()
    ix = (image[..., :, :-1] - image[..., :, 1:]).abs().mean(1, keepdim=True)
    iy = (image[..., :-1, :] - image[..., 1:, :]).abs().mean(1, keepdim=True)
    return (dx * torch.exp(-ix)).mean() + (dy * torch.exp(-iy)).mean()

