"""Training of the depth network on the synthetic training towns (never sequence 00).

Pipeline: a one-off cache of training frames -> random crops with the paper's augmentations or a
camera's (:mod:`mono_map.depth.train_data`) -> Adam with step decay -> checkpoints (resumable) -> a
shipped checkpoint without optimizer state. The run's configuration: :mod:`mono_map.depth.train_config`.
Multi-process: launched by ``torchrun`` (env RANK/WORLD_SIZE) or ``torch.multiprocessing``; gloo on
CPU, nccl on GPU, DistributedDataParallel; rank 0 writes checkpoints.
"""

from __future__ import annotations

import json
import math
import os
import sys
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np

from mono_map.depth.train_config import RunConfig, TrainConfig
from mono_map.depth.train_data import TrainsetSampler, augmentation, build_cache, sample_batch
from mono_map.errors import MonoMapError


def outputs_at_targets(low, depth):
    """Bilinearly sample stride-4 score maps (B,C,h,w) at the pixels with a target in depth (B,H,W).

    Identical to up-sampling the score maps to H×W (bilinear, align_corners=False, as inference does)
    and reading the valid pixels, at a fraction of the cost for sparse LiDAR targets.
    Returns (1,C,1,N) outputs and (1,1,N) depths for ``head_loss``.
    """
    import torch
    import torch.nn.functional as F

    B, H, W = depth.shape
    outs, deps = [], []
    for b in range(B):
        v, u = torch.nonzero(depth[b] > 0, as_tuple=True)
        if v.numel() == 0:
            continue
        gx = (2 * u.to(low.dtype) + 1) / W - 1
        gy = (2 * v.to(low.dtype) + 1) / H - 1
        grid = torch.stack([gx, gy], -1).view(1, 1, -1, 2)
        outs.append(F.grid_sample(low[b:b + 1], grid, mode="bilinear", padding_mode="border", align_corners=False))
        deps.append(depth[b, v, u])
    if not outs:  # no target at all: a zero loss that still touches the graph
        return low[:, :, :1, :1], torch.zeros_like(depth[:, :1, :1])
    return torch.cat(outs, -1), torch.cat(deps).view(1, 1, -1)


# ------------------------------------------------------------------ distributed
def dist_env() -> tuple[int, int]:
    """(rank, world_size) from torchrun's environment (1 process without it)."""
    return int(os.environ.get("RANK", "0")), int(os.environ.get("WORLD_SIZE", "1"))


def init_distributed(rank: int, world: int, backend: str | None = None) -> None:
    import torch
    import torch.distributed as tdist

    if world > 1 and not tdist.is_initialized():
        backend = backend or ("nccl" if torch.cuda.is_available() else "gloo")
        os.environ.setdefault("MASTER_ADDR", "127.0.0.1")
        os.environ.setdefault("MASTER_PORT", "29511")
        tdist.init_process_group(backend, rank=rank, world_size=world)


def init_weights(name: str, mcfg, device: str = "cpu") -> dict:
    """The state dict of checkpoint ``name`` (a path or a shipped name such as "v2/binary") to start a run
    from; MonoMapError naming ``train.init`` if it is missing, unreadable or another network or bins."""
    from mono_map.depth.inference import load_checkpoint, resolve_checkpoint

    path = resolve_checkpoint(Path(name).expanduser())
    if not path.is_file():
        raise MonoMapError(f"train.init: {name}: checkpoint not found")
    model, _ = load_checkpoint(path, device)
    if model.cfg.to_dict() != mcfg.to_dict():
        diff = sorted(k for k, v in mcfg.to_dict().items() if model.cfg.to_dict().get(k) != v)
        raise MonoMapError(f"train.init: {path}: another network than the config's (differs in {', '.join(diff)})")
    return model.state_dict()


# ------------------------------------------------------------------ training loop
def train(cfg: RunConfig, resume: bool = True, rank: int | None = None, world: int | None = None,
          device: str | None = None, data: tuple | None = None, log=None, validator=None) -> dict:
    """Train per ``cfg``; returns metadata (steps, wall time, final loss, paths).

    ``data`` = (images, depths) skips the cache (tests). ``validator(model) -> dict`` (with at least
    ``abs_rel``; e.g. :func:`mono_map.eval.validation.validator_for`) runs every ``validate_every``
    steps on rank 0, appends to ``<work>/curve.jsonl`` and keeps the best model as ``best.pt``. With world > 1 the process group must be
    initialised (``init_distributed``); every rank draws its own batches (seed + rank).
    """
    import torch
    import torch.distributed as tdist

    from mono_map.depth.inference import load_checkpoint, save_checkpoint
    from mono_map.depth.losses import head_loss
    from mono_map.depth.networks import DepthNet
    from mono_map.progress import progress

    env_rank, env_world = dist_env()
    rank = env_rank if rank is None else rank
    world = env_world if world is None else world
    log = log or (lambda msg: print(msg, file=sys.stderr, flush=True))
    t = cfg.train
    torch.set_num_threads(max(1, t.threads))
    torch.manual_seed(t.seed)
    device = device or (f"cuda:{rank % torch.cuda.device_count()}" if torch.cuda.is_available() else "cpu")
    mcfg = cfg.model_config()
    model = DepthNet(mcfg).to(device)
    work = Path(t.work_dir).expanduser() / cfg.name
    last = work / "last.pt"
    start, wall_before, cpu_before = 0, 0.0, 0.0
    if t.init and not (resume and last.is_file()):
        model.load_state_dict(init_weights(t.init, mcfg, device))
        if rank == 0:
            log(f"{cfg.name}: starting from the weights of {t.init}")
    opt = torch.optim.Adam(model.parameters(), lr=t.lr)
    if resume and last.is_file():
        m, payload = load_checkpoint(last, device)
        model.load_state_dict(m.state_dict())
        if "optimizer" in payload:
            opt.load_state_dict(payload["optimizer"])
        start = int(payload["training"].get("step", 0))
        wall_before = float(payload["training"].get("wall_time_s", 0.0))
        cpu_before = float(payload["training"].get("cpu_time_s", 0.0))
        if rank == 0:
            log(f"resuming {cfg.name} from {last} at step {start}")
    sampler = None
    if data is not None:
        images, depths = data
    elif cfg.data.trainset:
        sampler = TrainsetSampler(cfg.data)
        images = depths = None
    else:
        images, depths = build_cache(cfg, mcfg)[:2]
    if t.channels_last:
        model = model.to(memory_format=torch.channels_last)
    if world > 1:
        model_ddp = torch.nn.parallel.DistributedDataParallel(model, device_ids=None if device == "cpu" else [device])
    else:
        model_ddp = model
    model.train()
    decay_step = int(math.ceil(t.lr_decay_at * t.steps))
    aug = augmentation(t)
    t0, c0 = time.time(), time.process_time()
    losses: list[float] = []
    meta = {}
    curve_path = work / "curve.jsonl"  # work/ is made by the first file written into it (none if a run fails first)
    best = _best_so_far(curve_path)
    steps = range(start, t.steps)
    it = progress(steps, total=len(steps), desc=f"train {cfg.name}", unit="step") if rank == 0 else steps
    n_frames = len(sampler) if sampler is not None else len(depths)
    for step in it:
        lr = learning_rate(t, step, decay_step)
        for g in opt.param_groups:
            g["lr"] = lr
        rng = np.random.default_rng([t.seed, rank, step])
        if sampler is not None:
            if step % 100 == 0:          # frames rendered meanwhile join the pool (a complete cache: no change)
                n_frames = sampler.refresh()
            x, y = sampler.batch(t.batch_size, t.crop, rng, aug)
        else:
            x, y = sample_batch(images, depths, t.batch_size, t.crop, rng, aug)
        x, y = torch.from_numpy(x).to(device), torch.from_numpy(y).to(device)
        if t.channels_last:
            x = x.contiguous(memory_format=torch.channels_last)
        with torch.autocast(device.split(":")[0], dtype=torch.bfloat16, enabled=t.bf16):
            low = model_ddp(x, upsample=False)
        out, tgt = outputs_at_targets(low.float(), y)
        loss = head_loss(model.head, out, tgt, mcfg.bins, beyond=mcfg.beyond, wta_epsilon=mcfg.wta_epsilon)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        if not torch.isfinite(loss):
            raise MonoMapError(f"{cfg.source}: training diverged at step {step} (loss {loss.item()})")
        losses.append(loss.item())
        done = step + 1
        if rank == 0 and (done % t.log_every == 0 or done == t.steps):
            el = time.time() - t0
            eta = el / (done - start) * (t.steps - done)
            log(f"[{cfg.name}] step {done}/{t.steps} loss {np.mean(losses[-t.log_every:]):.4f} lr {lr:.1e} "
                f"frames {n_frames} elapsed {el/60:.1f} min ETA {eta/60:.1f} min")
        cpu = cpu_before + time.process_time() - c0
        if rank == 0 and validator is not None and t.validate_every and (done % t.validate_every == 0
                                                                           or done == t.steps):
            v = validator(model)
            v.update(step=done, cpu_hours=round(cpu / 3600, 6), wall_hours=round((wall_before + time.time() - t0) / 3600, 6),
                     train_frames=n_frames, loss=float(np.mean(losses[-t.log_every:])))
            work.mkdir(parents=True, exist_ok=True)
            with open(curve_path, "a") as fh:
                fh.write(json.dumps(v) + "\n")
            log(f"[{cfg.name}] validation at step {done}: AbsRel {v['abs_rel']:.3f} d1 {v['delta1']:.3f} "
                f"AUC-ARE {v['auc_are']:.4f} sky->beyond {v['sky_beyond_acc']}")
            if best is None or v["abs_rel"] < best:
                best = v["abs_rel"]
                meta = _metadata(cfg, done, wall_before + time.time() - t0, losses, world, n_frames, cpu)
                meta["validation"] = v
                save_checkpoint(work / "best.pt", model, meta)
        if rank == 0 and (done % t.checkpoint_every == 0 or done == t.steps):
            meta = _metadata(cfg, done, wall_before + time.time() - t0, losses, world, n_frames, cpu)
            save_checkpoint(last, model, meta, optimizer_state=opt.state_dict())
            if t.keep_checkpoints:
                save_checkpoint(work / f"step{done}.pt", model, meta)
    if world > 1:
        tdist.barrier()
    meta = _metadata(cfg, t.steps, wall_before + time.time() - t0, losses, world, n_frames,
                     cpu_before + time.process_time() - c0)
    meta["param_checksum"] = float(sum(p.detach().double().sum().item() for p in model.parameters()))
    if rank == 0:
        out = Path(t.output).expanduser() if t.output else work / "final.pt"
        save_checkpoint(out, model, meta)
        meta["output"] = str(out)
        log(f"[{cfg.name}] wrote {out} ({out.stat().st_size/1e6:.1f} MB), wall time {meta['wall_time_s']/60:.1f} min")
    return meta


def learning_rate(t: TrainConfig, step: int, decay_step: int) -> float:
    """Step decay (x lr_decay from decay_step on) or cosine from lr to lr·lr_decay over t.steps."""
    if t.schedule == "cosine":
        f = min(step / max(t.steps, 1), 1.0)
        return t.lr * (t.lr_decay + (1 - t.lr_decay) * 0.5 * (1 + math.cos(math.pi * f)))
    return t.lr * (t.lr_decay if step >= decay_step else 1.0)


def _best_so_far(curve_path: Path) -> float | None:
    if not curve_path.is_file():
        return None
    vals = [json.loads(line)["abs_rel"] for line in curve_path.read_text().splitlines() if line.strip()]
    return min(vals) if vals else None


def _metadata(cfg: RunConfig, step: int, wall: float, losses: list, world: int, n_frames: int,
              cpu: float = 0.0) -> dict:
    return {
        "name": cfg.name, "step": step, "wall_time_s": round(wall, 1), "cpu_time_s": round(cpu, 1),
        "world_size": world,
        "final_loss": float(np.mean(losses[-50:])) if losses else None,
        "config_file": cfg.source, "data": {**asdict(cfg.data), "n_frames": int(n_frames)},
        "train": asdict(cfg.train), "model": dict(cfg.model),
        "command": f"mono-map train --config {cfg.source}",
        "finished_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    }

