"""The machinery of one adaptation step (:mod:`mono_map.depth.adapt` runs it): the network's expected depth at
stride 4, monodepth2's photometric loss through the known poses (:mod:`mono_map.depth.photometric`), the holds of
p(no surface) and of each pixel's entropy to the base model's, the normalised supervised replay."""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from mono_map.depth import photometric
from mono_map.depth.photometric import to_tensor
from mono_map.geometry import scaled_intrinsics


# ------------------------------------------------------------------ the adapter
class Adapter:
    """Fine-tunes ``model`` on ``frames`` with photometric reprojection; ``step`` is the algorithm."""

    def __init__(self, model, base_beyond: torch.Tensor | None, frames: SequenceFrames,
                 sources: dict[int, list[int]], cfg: AdaptConfig, replay: tuple | None = None):
        self.model, self.cfg, self.frames, self.sources = model, cfg, frames, sources
        self.bins = model.cfg.bins
        self.head = model.head
        self.beyond = model.cfg.beyond
        self.base_beyond = base_beyond        # (N,1,h4,w4) base p(no surface) at stride 4, or None
        self.replay = replay                  # (images (R,H,W,3) uint8, LiDAR depth (R,H,W) m) or None
        self.replay_scale = None              # photometric / supervised loss of the base model (step 0)
        # the photometric loss is computed at 1/loss_scale of the network input (the depth is stride 4 anyway)
        sc = cfg.loss_scale
        self.small = downsample_images(frames.images, sc)
        H, W = self.small.shape[1:3]
        self.content = torch.zeros(1, 1, H, W, dtype=torch.bool)
        self.content[..., :frames.content[0] // sc, :frames.content[1] // sc] = True
        self.K = torch.as_tensor(scaled_intrinsics(frames.K, 1 / sc, 1 / sc), dtype=torch.float32)
        self.train_targets = sorted(sources)  # the run sets them without its held-out frames
        self.hints = None                     # DepthHints at the loss resolution (set by the run when cfg.hints > 0)
        self.base_entropy = None              # (N,1,h4,w4) the base model's entropy, nats (set by the run when cfg.entropy_hold > 0)
        h4, w4 = -(-frames.images.shape[1] // 4), -(-frames.images.shape[2] // 4)
        self.content4 = torch.zeros(1, 1, h4, w4, dtype=torch.bool)   # content at the network's output stride 4
        self.content4[..., :-(-frames.content[0] // 4), :-(-frames.content[1] // 4)] = True
        self.optimizer = torch.optim.Adam([p for p in model.parameters() if p.requires_grad], lr=cfg.lr)
        freeze_batchnorm(model)

    # --- pieces
    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Raw head outputs at the decoder's stride 4 (B,C,H/4,W/4), float32."""
        x = x.contiguous(memory_format=torch.channels_last)
        if self.cfg.precision == "bf16":
            with torch.autocast("cpu", dtype=torch.bfloat16):
                return self.model(x, upsample=False).float()
        return self.model(x, upsample=False)

    def depth_and_beyond(self, low: torch.Tensor, size: tuple[int, int]) -> tuple[torch.Tensor, torch.Tensor | None]:
        """(expected depth (B,1,H,W) m at ``size``, log-space expectation; beyond logit at stride 4 or None)."""
        from mono_map.depth.distribution import expected_depth
        from mono_map.depth.heads import split_beyond

        x, beyond_logit = split_beyond(self.head, low, self.bins, self.beyond)
        depth = expected_depth(torch.softmax(x[:, :self.bins.num_bins], 1), self.bins, "log").unsqueeze(1)
        depth = F.interpolate(depth, size=size, mode="bilinear", align_corners=False)
        return depth.clamp(self.bins.min_depth, self.bins.max_depth), beyond_logit

    def source_lists(self, targets: list[int]) -> list[list[int]]:
        """Each target's neighbouring frames, padded to 2·per_side by repeating its own (the loss is a minimum over
        them); with the right camera, its right image last (a target without neighbours: the right image alone)."""
        n = max(2, 2 * self.cfg.per_side)
        if not self.frames.stereo:
            return [[self.sources[t][k % len(self.sources[t])] for k in range(n)] for t in targets]
        out = []
        for t in targets:
            near = self.sources[t][:-1] or self.sources[t][-1:]
            out.append([near[k % len(near)] for k in range(n)] + [self.sources[t][-1]])
        return out

    def batch(self, targets: list[int], mirrored: torch.Tensor | None = None):
        """Network inputs (B,3,H,W); at the loss resolution the targets, 2·per_side sources each (repeated if
        fewer exist), their poses T_src_tgt (B,4,4), the pixels that count (content, not sky) and the
        intrinsics (B,3,3). Samples where ``mirrored`` (B,) bool is true are all of these seen in a mirror."""
        f = self.frames
        x = to_tensor(f.images[targets])
        tgt = to_tensor(self.small[targets])
        srcs = self.source_lists(targets)
        sources = [to_tensor(self.small[[s[k] for s in srcs]]) for k in range(len(srcs[0]))]
        poses = [torch.as_tensor(np.stack([np.linalg.inv(f.poses[s[k]]) @ f.poses[t] for s, t in zip(srcs, targets)]),
                                 dtype=torch.float32) for k in range(len(srcs[0]))]
        mask = self.content.expand(len(targets), 1, *tgt.shape[-2:])
        if self.base_beyond is not None:
            sky = F.interpolate(self.base_beyond[targets], size=tgt.shape[-2:], mode="nearest") > self.cfg.sky_threshold
            mask = mask & ~sky
        K = self.K.expand(len(targets), 3, 3)
        if mirrored is not None:
            x, tgt, mask = mirror_images(x, mirrored), mirror_images(tgt, mirrored), mirror_images(mask, mirrored)
            sources = [mirror_images(s, mirrored) for s in sources]
            poses = [mirror_poses(T, mirrored) for T in poses]
            K = mirror_intrinsics(K, tgt.shape[-1], mirrored)
        return x, tgt, sources, poses, mask, K

    def photometric_loss(self, targets: list[int], mirrored: torch.Tensor | None = None
                         ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None, dict]:
        """(photometric loss, smoothness, beyond logit or None, info) of ``targets`` (those ``mirrored`` seen in
        a mirror); with hints on, the hint term is in ``info["hint_loss"]`` (a tensor) and the share of hinted
        pixels in ``info["hinted"]``."""
        x, tgt, sources, poses, mask, K = self.batch(targets, mirrored)
        low = self.forward(x)
        depth, beyond_logit = self.depth_and_beyond(low, tgt.shape[-2:])
        if self.frames.stereo:   # the neighbours and the right image are auto-masked apart
            reproj, seen = photometric.grouped_reprojection(
                tgt, [(sources[:-1], poses[:-1]), (sources[-1:], poses[-1:])], depth, K)
            photo, used = photometric.reduce_reprojection(reproj, seen, tgt, sources, mask=mask, automask=False,
                                                          trim=self.cfg.trim)
        else:
            reproj, seen = photometric.min_reprojection_error(tgt, sources, depth, K, poses)
            photo, used = photometric.reduce_reprojection(reproj, seen, tgt, sources, mask=mask, trim=self.cfg.trim)
        smooth = photometric.smoothness_loss(depth, tgt)
        info = {"used": float(used.float().mean())}
        if self.hints is not None:
            info["hint_loss"], info["hinted"] = self.hint_loss(low, depth, reproj.detach(), mask, targets)
        if self.base_entropy is not None and self.cfg.entropy_hold > 0:
            info["entropy_loss"] = self.entropy_hold_loss(low, targets, mirrored)
        return photo, smooth, beyond_logit, info

    def hint_loss(self, low: torch.Tensor, depth: torch.Tensor, pred_error: torch.Tensor, mask: torch.Tensor,
                  targets: list[int]) -> tuple[torch.Tensor, float]:
        """Depth Hints' supervised term, summed over the pixels where the hint's photometric error beats the
        prediction's and divided by the counted (content, not sky) pixels; and the share of those hinted."""
        from mono_map.depth.hints import hint_mask

        hd, he = self.hints.depth[targets], self.hints.error[targets]
        use = hint_mask(hd, he, pred_error) & mask
        n_use, n_all = use.sum(), mask.sum().clamp_min(1)
        if self.cfg.hint_loss == "log":
            r = (depth.clamp_min(1e-3).log() - hd.clamp_min(1e-3).log()).abs()
            loss = (r * use).sum() / n_all
        else:   # the head's own training loss towards the hint (the bins' soft target), at the hinted pixels
            from mono_map.depth.losses import head_loss
            from mono_map.depth.train import outputs_at_targets

            out, dep = outputs_at_targets(low, torch.where(use, hd, torch.zeros_like(hd))[:, 0])
            loss = head_loss(self.head, out, dep, self.bins, beyond=self.beyond) * (n_use / n_all)
        return loss, float(n_use) / float(n_all)

    def entropy_hold_loss(self, low: torch.Tensor, targets: list[int], mirrored: torch.Tensor | None = None
                          ) -> torch.Tensor:
        """Mean of (H − H_base)² (nats²) over the pixels at stride 4 that show content and no sky: each pixel's
        entropy held to the base model's. The photometric loss moves the expected depth and says nothing about
        its uncertainty; this keeps the base's (supervised) ranking of the pixels by confidence."""
        from mono_map.depth.distribution import entropy_of_logits
        from mono_map.depth.heads import split_beyond

        x, _ = split_beyond(self.head, low, self.bins, self.beyond)
        ent = entropy_of_logits(x[:, :self.bins.num_bins]).unsqueeze(1)
        base = self.base_entropy[targets]
        keep = self.content4.expand_as(base)
        if self.base_beyond is not None:
            keep = keep & (self.base_beyond[targets] <= self.cfg.sky_threshold)
        if mirrored is not None:
            base, keep = mirror_images(base, mirrored), mirror_images(keep, mirrored)
        return ((ent - base) ** 2 * keep).sum() / keep.sum().clamp_min(1)

    def beyond_loss(self, beyond_logit: torch.Tensor | None, targets: list[int],
                    mirrored: torch.Tensor | None = None) -> torch.Tensor:
        """KL(base ‖ current) of the Bernoulli "no surface within range", mean over pixels: 0 at the base."""
        if beyond_logit is None or self.base_beyond is None or not self.cfg.beyond_weight:
            return torch.zeros(())
        p = self.base_beyond[targets]
        if mirrored is not None:
            p = mirror_images(p, mirrored)
        p = p[:, 0].clamp(1e-4, 1 - 1e-4)
        bce = F.binary_cross_entropy_with_logits(beyond_logit, p, reduction="none")
        ent = -(p * p.log() + (1 - p) * (1 - p).log())
        return (bce - ent).mean()

    def replay_loss(self, rng: np.random.Generator) -> torch.Tensor:
        """The supervised loss of the model's head on ``batch_size`` replay frames (LiDAR targets)."""
        from mono_map.depth.losses import head_loss
        from mono_map.depth.train import outputs_at_targets

        images, depths = self.replay
        pick = rng.integers(len(images), size=self.cfg.batch_size)
        low = self.forward(to_tensor(images[pick]))
        out, dep = outputs_at_targets(low, torch.as_tensor(depths[pick]))
        return head_loss(self.head, out, dep, self.bins, beyond=self.beyond)

    # --- the algorithm
    def step(self, step: int) -> dict:
        """One step: draw targets, warp their sources through the predicted depth with the known poses,
        minimise photometric error + smoothness + the beyond-range hold (+ the entropy hold, Depth Hints,
        normalised replay)."""
        rng = np.random.default_rng([self.cfg.seed, step])
        train = self.train_targets
        targets = [train[k] for k in rng.choice(len(train), size=min(self.cfg.batch_size, len(train)), replace=False)]
        # the targets seen in a mirror (B,) bool, drawn only when mirroring is on (a run without it draws as before)
        mirrored = torch.as_tensor(rng.random(len(targets)) < self.cfg.mirror) if self.cfg.mirror else None
        self.model.train()
        freeze_batchnorm(self.model)
        photo, smooth, beyond_logit, info = self.photometric_loss(targets, mirrored)
        loss = (photo + self.cfg.smoothness * smooth
                + self.cfg.beyond_weight * self.beyond_loss(beyond_logit, targets, mirrored))
        hint = info.pop("hint_loss", None)
        if hint is not None:
            loss = loss + self.cfg.hints * hint
            info["hint"] = float(hint.detach())
        held = info.pop("entropy_loss", None)
        if held is not None:
            loss = loss + self.cfg.entropy_hold * held
            info["entropy_hold"] = float(held.detach())
        rep = torch.zeros(())
        if self.replay is not None and self.cfg.replay > 0:
            rep = self.replay_loss(rng)
            if self.replay_scale is None:   # the replay term starts at ``replay`` × the photometric term
                self.replay_scale = float(photo.detach()) / max(float(rep.detach()), 1e-9)
            loss = loss + self.cfg.replay * self.replay_scale * rep
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        self.optimizer.step()
        return {"loss": float(loss.detach()), "photometric": float(photo.detach()), "smoothness": float(smooth.detach()),
                "replay": float(rep.detach()), **info}

    @torch.no_grad()
    def heldout_error(self, targets: list[int]) -> float:
        """Mean photometric loss over held-out targets (the stopping rule; no ground truth)."""
        self.model.eval()
        errs = [float(self.photometric_loss([t])[0]) for t in targets]
        return float(np.mean(errs)) if errs else float("nan")


# ------------------------------------------------------------------ mirrored samples
def mirror_images(a: torch.Tensor, which: torch.Tensor) -> torch.Tensor:
    """(B,C,H,W) with the samples ``which`` (B,) bool flipped left-right (the whole width)."""
    return torch.where(which.view(-1, 1, 1, 1), a.flip(-1), a)


def mirror_intrinsics(K: torch.Tensor, width: int, which: torch.Tensor) -> torch.Tensor:
    """Intrinsics (B,3,3) of images ``width`` pixels wide flipped left-right where ``which``: pixel u -> width-1-u
    (pixel centres at integers), so cx -> width-1-cx and the skew changes sign."""
    M = K.clone()
    M[:, 0, 2] = width - 1 - K[:, 0, 2]
    M[:, 0, 1] = -K[:, 0, 1]
    return torch.where(which.view(-1, 1, 1), M, K)


def mirror_poses(T: torch.Tensor, which: torch.Tensor) -> torch.Tensor:
    """Relative poses (B,4,4) in the mirrored cameras (x -> -x in both): S·T·S, S = diag(-1, 1, 1, 1)."""
    S = torch.diag(torch.tensor([-1.0, 1.0, 1.0, 1.0], dtype=T.dtype))
    return torch.where(which.view(-1, 1, 1), S @ T @ S, T)


def downsample_images(images: np.ndarray, factor: int) -> np.ndarray:
    """(N,H,W,3) uint8 -> (N,H/factor,W/factor,3) uint8 by area averaging (factor 1: unchanged)."""
    if factor == 1:
        return images
    import cv2

    N, H, W = images.shape[:3]
    return np.stack([cv2.resize(im, (W // factor, H // factor), interpolation=cv2.INTER_AREA) for im in images])


def freeze_batchnorm(model) -> None:
    """BatchNorm layers use and keep the base model's running statistics (eval mode), still trainable."""
    for m in model.modules():
        if isinstance(m, torch.nn.BatchNorm2d):
            m.eval()


def copy_state(model) -> dict:
    return {k: v.detach().clone() for k, v in model.state_dict().items()}


def save_state(path: Path, state: dict) -> None:
    from mono_map.io import atomic_path

    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        torch.save(state, tmp)


@torch.no_grad()
def base_statistics(model, images: np.ndarray, precision: str, chunk: int = 8
                    ) -> tuple[torch.Tensor | None, torch.Tensor]:
    """The base model's p(no surface within range) (None for a model without it) and the entropy of its bin
    distribution (nats) at stride 4, each (N,1,H/4,W/4)."""
    from mono_map.depth.distribution import entropy_of_logits
    from mono_map.depth.heads import split_beyond

    model.eval()
    beyond, entropy = [], []
    for k in range(0, len(images), chunk):
        x = to_tensor(images[k:k + chunk]).contiguous(memory_format=torch.channels_last)
        if precision == "bf16":
            with torch.autocast("cpu", dtype=torch.bfloat16):
                low = model(x, upsample=False).float()
        else:
            low = model(x, upsample=False)
        bins, logit = split_beyond(model.head, low, model.cfg.bins, model.cfg.beyond)
        entropy.append(entropy_of_logits(bins[:, :model.cfg.bins.num_bins]).unsqueeze(1))
        if logit is not None:
            beyond.append(torch.sigmoid(logit).unsqueeze(1))
    return (torch.cat(beyond) if beyond else None), torch.cat(entropy)
