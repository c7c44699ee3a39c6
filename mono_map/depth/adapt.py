"""Self-supervised adaptation of a depth checkpoint to the sequence being mapped (``mono-map adapt``).

No labels: neighbouring frames of the sequence, warped into frame t through the predicted depth and the
sequence's own metric poses, must reproduce frame t (monodepth2's loss: SSIM + L1, per-pixel minimum over
the sources, auto-masking, edge-aware smoothness; :mod:`mono_map.depth.photometric`). The poses fix the
scale. Sources are chosen by baseline, not frame offset (a stopped car gives no depth signal). Pixels the
base model calls sky are left out and its probability of "no surface within range" is held to the base
model's; BatchNorm statistics stay frozen; optionally supervised batches of a synthetic training sequence
are mixed in (replay, normalised to the photometric term's size), or Depth Hints (:mod:`mono_map.depth.hints`:
the plane sweep's best depth supervises the pixels where it explains the image better). Frames held out from
the targets score the weights every ``eval_every`` steps (their photometric error): the best are written.

The result is an ordinary checkpoint named ``<base>-adapted-<seq>-<digest>.pt``; the digest covers the base
checkpoint's sha256, the sequence (data root, name, frames) and every setting. Runs resume from
``~/.cache/mono-map/adapt/<run>/state.pt`` (the run key leaves out ``steps``: a longer run continues a
shorter one); batches are drawn from a generator seeded with (seed, step), so a resumed run equals an
uninterrupted one.
"""

from __future__ import annotations

import hashlib
import json
import os
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from mono_map.depth.sources import choose_sources
from mono_map.errors import MonoMapError

HINT_LOSSES = ("log", "head")   # Depth Hints' term: on the expected depth (log L1) or the head's own loss on the bins
STEREO_MODES = ("auto", "on", "off")   # the right colour camera (image_3): if every frame has it / required / never

ADAPT_VERSION = 1
DEFAULT_FRAMES = 500   # frames adapted on unless told (build's default too); a synthetic sequence is rendered that far


@dataclass(frozen=True)
class AdaptConfig:
    """Settings of an adaptation run (all in the checkpoint's digest)."""

    steps: int = 300
    lr: float = 1e-4                 # Adam (chosen on real01: 1e-4 / 300 steps beat 5e-5 / 300 and 1e-4 / 600)
    batch_size: int = 4              # target frames per step
    min_baseline: float = 0.3        # m: a source must be at least this far from the target camera
    max_baseline: float = 4.0        # m: ... and at most this far
    max_offset: int = 10             # frames: sources searched up to this many frames before and after
    per_side: int = 1                # sources per side, each at >= 2x the previous one's baseline
    smoothness: float = 1e-3         # edge-aware smoothness weight
    beyond_weight: float = 1.0       # KL of p(no surface) to the base model's
    sky_threshold: float = 0.5       # base p(no surface) above this: no photometric loss
    replay: float = 0.0              # weight of supervised replay, relative to the photometric term at step 0
    replay_seq: str = ""             # synthetic training sequence of the replay ("" = none)
    replay_frames: int = 40          # replay frames (evenly spread over the replay sequence)
    eval_every: int = 25             # steps between held-out evaluations (and saved states)
    trim: float = 0.0                # leave out this fraction of the highest-error pixels of a batch
    loss_scale: int = 2              # photometric loss at 1/loss_scale of the network input (1 or 2)
    # False (the default since the twelfth stop): the encoder stays the base model's, only the decoder and head adapt.
    # From the 6000-step model the whole network adapted made real01 worse (0.268 -> 0.293 / 0.284, adapt seeds 0 / 1),
    # the decoder alone better (0.252 / 0.253); 06 improves either way (0.088 -> 0.068 whole, 0.075 decoder only)
    train_encoder: bool = False
    seed: int = 0
    precision: str = "fp32"          # "bf16": bfloat16 autocast of the network's forward pass
    # Depth Hints: the plane sweep's best depth where it beats the prediction (weight; 0 = off). Off: 0.1 with contrast
    # 0.1 lowered real01's AbsRel for seeds 0 and 1 but left 06's unchanged (docs/real_kitti.md), and the protocol
    # makes a lever the default only where it helps on both
    hints: float = 0.0
    hint_loss: str = "log"           # "log": |log d − log hint| on the expected depth; "head": the head's training loss
    hint_contrast: float = 0.1       # a hint only where the sweep's mean cost exceeds its best by more than this
    # the same frame's right colour camera (image_3) as one more source of every target (monodepth2's "MS"): a
    # 0.53 m baseline at the same instant, so it also sees a stopped car's frames and things moving with the car.
    # Off by default: no gain measured on the synthetic towns (06, 00, 07's stop); real01 has no image_3
    stereo: str = "off"
    # probability that a drawn target is mirrored left-right with its sources (images, intrinsics, poses and the
    # base model's p(no surface) mirrored together: the same geometry seen in a mirror; monodepth2 flips half its
    # training samples). 0 = off
    mirror: float = 0.0
    # weight of the hold of each pixel's entropy to the base model's (mean of (H − H_base)², nats²; 0 = off): the
    # photometric loss moves the depth and teaches nothing about its uncertainty, which without the hold drifts
    # and ranks the pixels worse (00: AUC RMSE 1.38 -> 1.62 m; the adapted depths ranked by the base's entropy 1.26 m)
    entropy_hold: float = 0.0

    def validate(self) -> None:
        checks = [(self.steps >= 1, "--steps", f"must be >= 1, got {self.steps}"),
                  (self.lr > 0 and np.isfinite(self.lr), "--lr", f"must be a positive number, got {self.lr}"),
                  (self.batch_size >= 1, "--batch-size", f"must be >= 1, got {self.batch_size}"),
                  (self.min_baseline >= 0, "--min-baseline", f"must be >= 0 m, got {self.min_baseline}"),
                  (self.max_baseline > self.min_baseline, "--max-baseline",
                   f"must exceed --min-baseline ({self.min_baseline} m), got {self.max_baseline}"),
                  (self.max_offset >= 1, "max_offset", f"must be >= 1, got {self.max_offset}"),
                  (self.per_side >= 1, "--per-side", f"must be >= 1, got {self.per_side}"),
                  (np.isfinite(self.smoothness) and self.smoothness >= 0, "--smoothness",
                   f"must be a number >= 0, got {self.smoothness}"),
                  (self.replay >= 0, "--replay", f"must be >= 0, got {self.replay}"),
                  (not self.replay or bool(self.replay_seq), "--replay", "needs --replay-seq (a synthetic training sequence)"),
                  (self.replay_seq != "00", "--replay-seq", "00 is the held-out evaluation sequence, never trained on"),
                  (0 <= self.trim < 1, "--trim", f"must be in [0, 1), got {self.trim}"),
                  (self.loss_scale in (1, 2, 4), "loss_scale", f"must be 1, 2 or 4, got {self.loss_scale}"),
                  (self.eval_every >= 1, "eval_every", f"must be >= 1, got {self.eval_every}"),
                  (self.precision in ("fp32", "bf16"), "--precision", f"must be fp32 or bf16, got {self.precision}"),
                  (isinstance(self.hints, (int, float)) and np.isfinite(self.hints) and self.hints >= 0, "--hints",
                   f"must be a number >= 0 (0 = off), got {self.hints}"),
                  (np.isfinite(self.hint_contrast) and self.hint_contrast >= 0, "--hint-contrast",
                   f"must be a number >= 0, got {self.hint_contrast}"),
                  (self.hint_loss in HINT_LOSSES, "--hint-loss", f"must be one of {', '.join(HINT_LOSSES)}, got {self.hint_loss}"),
                  (isinstance(self.mirror, (int, float)) and 0 <= self.mirror <= 1, "--mirror",
                   f"must be a probability in [0, 1], got {self.mirror}"),
                  (not (self.mirror and self.hints), "--mirror", "cannot be combined with --hints (not mirrored)"),
                  (isinstance(self.entropy_hold, (int, float)) and np.isfinite(self.entropy_hold)
                   and self.entropy_hold >= 0, "--entropy-hold", f"must be a number >= 0 (0 = off), got {self.entropy_hold}"),
                  (self.stereo in STEREO_MODES, "--stereo", f"must be one of {', '.join(STEREO_MODES)}, got {self.stereo}")]
        for ok, option, why in checks:
            if not ok:
                raise MonoMapError(f"{option}: {why}")

    def run_settings(self) -> dict:
        """Everything but ``steps``: what a longer run shares with a shorter one."""
        d = asdict(self)
        d.pop("steps")
        d.pop("stereo")      # the run records whether it used image_3 (``run_key``), not the mode asked for
        if not self.hints:   # off: the key of a run from before hints existed (its checkpoint name stays valid)
            for k in ("hints", "hint_loss", "hint_contrast"):
                d.pop(k)
        if not self.mirror:  # off: the key of a run from before mirroring existed
            d.pop("mirror")
        if not self.entropy_hold:   # off: the key of a run from before the entropy hold existed
            d.pop("entropy_hold")
        return d


# ------------------------------------------------------------------ sources
def held_out(targets: list[int]) -> list[int]:
    """Targets kept for the stopping rule: every 10th (from the 5th), or the middle one of 3–9, none of < 3."""
    if len(targets) >= 10:
        return targets[5::10]
    return [targets[len(targets) // 2]] if len(targets) >= 3 else []


# ------------------------------------------------------------------ data
@dataclass
class SequenceFrames:
    """The frames of an adaptation in the network's input size: images (N,H,W,3) uint8, K (3,3) of these
    images, poses T_world_cam2 (N,4,4), the content size (fh, fw) (the rest is padding), frame indices.
    With the right camera (``stereo``): images and poses (T_world_cam3) of frame j's image_3 at row N + j."""

    images: np.ndarray
    K: np.ndarray
    poses: np.ndarray
    content: tuple[int, int]
    indices: list[int]
    stereo: bool = False


def load_frames(seq, indices: list[int], H: int, W: int, desc: str = "adapt: read",
                stereo: bool = False) -> SequenceFrames:
    """Read image_2 and T_world_cam2 of ``indices`` of a sequence (any layout the reader opens); ``stereo``:
    then image_3 and T_world_cam3 of the same frames (image_3 shares image_2's K: ``seq.has_right``)."""
    from mono_map.depth.inference import resize_to_input
    from mono_map.progress import progress

    reads = [(i, seq.image) for i in indices] + ([(i, seq.image_right) for i in indices] if stereo else [])
    imgs, content = [], None
    for i, read in progress(reads, total=len(reads), desc=desc, unit="image"):
        im, content = resize_to_input(read(i), H, W)
        imgs.append(im)
    h, w = seq.image_size
    K = seq.calib.K2.copy()
    K[0] *= content[1] / w
    K[1] *= content[0] / h
    poses = [seq.T_world_cam2(i) for i in indices] + ([seq.T_world_cam3(i) for i in indices] if stereo else [])
    return SequenceFrames(np.stack(imgs), K, np.stack(poses), content, list(indices), stereo)


def use_stereo(seq, indices: list[int], mode: str) -> bool:
    """Whether an adaptation uses image_3: ``auto`` if every frame has it, ``on`` (required), ``off``."""
    if mode == "off":
        return False
    if mode == "on":
        seq.require_right(indices, "--stereo on")   # refused unless every frame has it
        return True
    return seq.has_right(indices)


def with_stereo_sources(sources: dict[int, list[int]], n: int) -> dict[int, list[int]]:
    """Every frame j of ``n`` gets its own right image (row n + j) as one more source, after its temporal ones."""
    return {j: sources.get(j, []) + [n + j] for j in range(n)}


# ------------------------------------------------------------------ the run
def sha256_file(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def run_key(base_sha: str, data_root: Path, seq: str, frames: list[int], cfg: AdaptConfig) -> dict:
    return {"version": ADAPT_VERSION, "base_sha256": base_sha, "data_root": str(Path(data_root).resolve()),
            "sequence": seq, "frames": frames, "settings": cfg.run_settings()}


def digest(obj) -> str:
    return hashlib.sha256(json.dumps(obj, sort_keys=True).encode()).hexdigest()[:12]


def default_state_dir() -> Path:
    return Path(os.environ.get("MONO_MAP_CACHE", Path.home() / ".cache" / "mono-map")).expanduser() / "adapt"


@dataclass(frozen=True)
class AdaptResult:
    checkpoint: Path
    metadata: dict


def adapt(base: str | None, data_root, seq_name: str, frames=None, cfg: AdaptConfig = AdaptConfig(),
          out_dir: str | os.PathLike = "outputs/adapt", state_dir: str | os.PathLike | None = None,
          resume: bool = True, replay_root=None, log=print) -> AdaptResult:
    """Adapt checkpoint ``base`` (path or shipped name; None = the shipped model) to sequence ``seq_name``
    under ``data_root`` on ``frames`` (a FrameSelection; None = the first :data:`DEFAULT_FRAMES`, as build) and write the best checkpoint to
    ``out_dir``. Every input is checked before any work; MonoMapError names the bad one."""
    import torch

    from mono_map.data.prepare import prepare_sequence
    from mono_map.depth.adapter import Adapter, base_statistics, copy_state, save_state
    from mono_map.depth.inference import load_checkpoint, resolve_checkpoint, save_checkpoint
    from mono_map.io import write_json_atomic
    from mono_map.progress import progress

    cfg.validate()
    path = resolve_checkpoint(base)
    model, payload = load_checkpoint(path)
    if model.head.kind != "bins" or model.head.dropout:
        raise MonoMapError(f"--model: {path}: a '{model.cfg.head}' head; adapt needs a bin distribution "
                           "(binary or softmax head) whose expected depth it can warp with")
    if frames is None:   # as build: never a whole synthetic recipe rendered by default
        from mono_map.frames import first_frames

        frames = first_frames(DEFAULT_FRAMES)
    seq = prepare_sequence(data_root, seq_name, frames, stereo=cfg.stereo == "on")   # on: a synthetic one renders image_3
    if seq.poses_cam0 is None:
        raise MonoMapError(f"{seq.pose_path}: no poses for sequence '{seq_name}'; adapt needs the sequence's "
                           "metric poses")
    indices = frames.resolve(len(seq))
    if len(indices) < 2:
        raise MonoMapError(f"--frames: adapt needs at least 2 frames of a moving camera, got {len(indices)}")
    centres = np.stack([seq.T_world_cam2(i)[:3, 3] for i in indices])
    sources = choose_sources(centres, cfg.min_baseline, cfg.max_baseline, cfg.max_offset, cfg.per_side)
    stereo = use_stereo(seq, indices, cfg.stereo)
    if stereo:
        sources = with_stereo_sources(sources, len(indices))
    if not sources:
        steps = np.linalg.norm(np.diff(centres, axis=0), axis=1)
        raise MonoMapError(f"{seq.path}: too little motion to adapt: no two frames within {cfg.max_offset} frames "
                           f"are {cfg.min_baseline:g}–{cfg.max_baseline:g} m apart (largest step between frames "
                           f"{steps.max():.3f} m; lower --min-baseline or choose other --frames)")
    replay_seq = None
    if cfg.replay > 0:
        replay_seq = prepare_sequence(replay_root or data_root, cfg.replay_seq, render=False)  # read only
        if not replay_seq.velodyne_files:
            raise MonoMapError(f"--replay-seq: {replay_seq.path}: no velodyne scans for supervised replay")
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise MonoMapError(f"--out: {out_dir} is a file, not a directory")

    base_sha = sha256_file(path)
    key = run_key(base_sha, seq.root, seq_name, indices, cfg)
    if stereo:
        key["stereo"] = True
    run_id = digest(key)
    name = f"{path.stem}-adapted-{seq_name}-{digest({**key, 'steps': cfg.steps})}"
    ckpt = out_dir / f"{name}.pt"
    if resume and ckpt.is_file() and (out_dir / f"{name}.json").is_file():
        log(f"adapt: {ckpt} is up to date (same base, sequence, frames and settings)")
        return AdaptResult(ckpt, json.loads((out_dir / f"{name}.json").read_text()))

    H, W = model.cfg.input_height, model.cfg.input_width
    data = load_frames(seq, indices, H, W, stereo=stereo)
    log(f"adapt: {len(indices)} frames, {len(sources)} targets; sources: neighbours by baseline"
        + (" and each frame's right camera (image_3)" if stereo else " (no image_3: --stereo off or not there)"))
    targets = sorted(sources)
    heldout = held_out(targets)
    base_beyond, base_entropy = None, None
    if model.cfg.beyond or cfg.entropy_hold > 0:   # one pass of the base model over the frames, only if it is used
        base_beyond, base_entropy = base_statistics(model, data.images[:len(indices)], cfg.precision)
    replay = load_replay(replay_seq, H, W, cfg.replay_frames) if replay_seq is not None else None
    if not cfg.train_encoder:
        for p in model.encoder.parameters():
            p.requires_grad_(False)
    adapter = Adapter(model, base_beyond, data, sources, cfg, replay)
    adapter.train_targets = [t for t in targets if t not in heldout] or targets
    if cfg.entropy_hold > 0:
        adapter.base_entropy = base_entropy
    if cfg.hints > 0:
        from mono_map.depth.hints import compute_hints

        adapter.hints = compute_hints(adapter.small, adapter.K.numpy(), data.poses, sources, model.cfg.bins,
                                      adapter.content[0, 0], min_contrast=cfg.hint_contrast)

    state_path = Path(state_dir or default_state_dir()) / run_id / "state.pt"
    start, curve, best = 0, [], {"error": float("inf"), "step": 0, "state": None}
    st = None
    if resume and state_path.is_file():
        try:
            st = torch.load(state_path, weights_only=False)
            st["step"], st["model"], st["optimizer"], st["curve"], st["best"]   # noqa: B018 - all there
        except Exception as exc:  # noqa: BLE001 - a truncated or foreign file: the run starts again
            log(f"adapt: {state_path}: unreadable saved state ({type(exc).__name__}); starting again")
            st = None
    if st is not None:
        if st["step"] <= cfg.steps:
            model.load_state_dict(st["model"])
            adapter.optimizer.load_state_dict(st["optimizer"])
            start, curve, best, adapter.replay_scale = st["step"], st["curve"], st["best"], st.get("replay_scale")
            log(f"adapt: resuming {run_id} at step {start}")
        else:
            log(f"adapt: the saved run {run_id} is at step {st['step']} > --steps {cfg.steps}; starting again")
    if start == 0:
        err = adapter.heldout_error(heldout)
        curve = [{"step": 0, "heldout_photometric": err}]
        best = {"error": err, "step": 0, "state": copy_state(model)}

    t0 = time.perf_counter()
    losses = []
    for step in progress(range(start, cfg.steps), total=cfg.steps - start, desc="adapt", unit="step"):
        losses.append(adapter.step(step))
        done = step + 1
        if done % cfg.eval_every == 0 or done == cfg.steps:
            err = adapter.heldout_error(heldout) if heldout else float("nan")
            recent = losses[-cfg.eval_every:]
            curve.append({"step": done, "heldout_photometric": err,
                          "train_photometric": float(np.mean([r["photometric"] for r in recent])),
                          "used_pixels": float(np.mean([r["used"] for r in recent])),
                          **({"hinted_pixels": float(np.mean([r["hinted"] for r in recent])),
                              "hint_loss": float(np.mean([r["hint"] for r in recent]))} if cfg.hints else {}),
                          **({"entropy_hold": float(np.mean([r["entropy_hold"] for r in recent]))}
                             if cfg.entropy_hold else {})})
            if not heldout or err < best["error"]:
                best = {"error": err, "step": done, "state": copy_state(model)}
            save_state(state_path, {"step": done, "model": model.state_dict(), "optimizer": adapter.optimizer.state_dict(),
                                    "curve": curve, "best": best, "replay_scale": adapter.replay_scale})
    wall = time.perf_counter() - t0

    model.load_state_dict(best["state"])
    meta = {"name": name, "adapted": {
        "base": str(path), "base_sha256": base_sha, "sequence": seq_name, "data_root": str(seq.root),
        "frames": indices, "targets": len(targets), "heldout": heldout, "settings": asdict(cfg), "stereo": stereo,
        "best_step": best["step"], "curve": curve, "wall_time_s_this_run": round(wall, 1), "run_id": run_id},
        "steps": cfg.steps, "base_training": payload.get("training", {})}
    out_dir.mkdir(parents=True, exist_ok=True)
    save_checkpoint(ckpt, model.eval(), training=meta)
    write_json_atomic(out_dir / f"{name}.json", {**meta, "checkpoint": ckpt.name, "sha256": sha256_file(ckpt)})
    return AdaptResult(ckpt, meta)


def load_replay(seq, H: int, W: int, n: int) -> tuple[np.ndarray, np.ndarray]:
    """``n`` frames spread over a synthetic training sequence: (images (n,H,W,3) uint8, LiDAR depth (n,H,W) m,
    0 = none) in the network's input size."""
    from mono_map.depth.inference import resize_to_input
    from mono_map.depth.train_data import downsample_depth
    from mono_map.progress import progress

    idx = np.unique(np.linspace(0, len(seq) - 1, min(n, len(seq))).round().astype(int))
    imgs, deps = [], []
    for i in progress(idx.tolist(), total=len(idx), desc="adapt: replay", unit="frame"):
        im, (fh, fw) = resize_to_input(seq.image(i), H, W)
        d = np.zeros((H, W), np.float32)
        d[:fh, :fw] = downsample_depth(seq.lidar_depth(i), fh, fw)
        imgs.append(im)
        deps.append(d)
    return np.stack(imgs), np.stack(deps)
