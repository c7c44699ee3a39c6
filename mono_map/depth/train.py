"""Training of the depth network on the synthetic training towns (never sequence 00).

Pipeline: a one-off cache of training frames (images resized to the model's input scale and
LiDAR depth targets min-pooled to it, stored as .npy under data/cache/) -> random crops with the
paper's augmentations (gamma, brightness, colour shift; Godard et al.) or a camera's (depth/augment.py),
optional scale with the focal length kept, and horizontal flips ->
Adam with step decay -> checkpoints (resumable) -> a shipped checkpoint without optimizer state.
Multi-process: launched by ``torchrun`` (env RANK/WORLD_SIZE) or ``torch.multiprocessing``; gloo on
CPU, nccl on GPU, DistributedDataParallel; rank 0 writes checkpoints.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import sys
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np

from mono_map.errors import MonoMapError
from mono_map.schema import bounded, check_fields

HELD_OUT = {"00"}


@dataclass(frozen=True)
class DataConfig:
    root: str | None = None                          # KITTI root (None -> mono_map.paths.data_root)
    sequences: tuple = field(default=("05", "06", "07", "08", "09", "10"), metadata=bounded(item=str))
    frames: int = field(default=0, metadata=bounded(lo=0))  # leading frames of each sequence (0 = all; generated if missing)
    frame_step: int = field(default=1, metadata=bounded(lo=1))  # use every n-th of them
    target: str = field(default="lidar", metadata=bounded(choices=("lidar", "dense")))  # velodyne into image_2 / depth_2 PNGs
    cache_dir: str = field(default="data/cache", metadata=bounded(nonempty=True))
    trainset: str = ""                               # randomised-town cache (data/synth/trainset.py); "" = sequences
    towns: tuple = field(default=(), metadata=bounded(item=str))  # trainset towns to train on (empty = all but the validation town)
    validation_town: str = "val09"                   # held-out trainset town for the learning curve ("" = none)
    validation_frames: int = field(default=24, metadata=bounded(lo=1))  # frames of it scored at every validation
    sky_stride: int = field(default=3, metadata=bounded(lo=1))  # lidar targets: no-surface (sky) labels on this pixel grid
    max_targets: int = field(default=12000, metadata=bounded(lo=0))  # target pixels sampled per crop (0 = all; dense targets)


@dataclass(frozen=True)
class TrainConfig:
    steps: int = field(default=1500, metadata=bounded(lo=1))
    batch_size: int = field(default=8, metadata=bounded(lo=1, hi=4096))
    crop: tuple = field(default=(128, 416), metadata=bounded(item=int, length=2, lo=32))  # random crop (H, W) of the resized frames, pixels
    lr: float = field(default=1e-4, metadata=bounded(lo=0, hi=1, lo_open=True))  # Adam initial learning rate (paper: 1e-4)
    lr_decay_at: float = field(default=0.75, metadata=bounded(lo=0, hi=1))  # fraction of steps after which lr *= lr_decay (paper: 45/60 epochs)
    lr_decay: float = field(default=0.1, metadata=bounded(lo=0, hi=1, lo_open=True))
    augment: bool = True
    seed: int = field(default=0, metadata=bounded(lo=0))
    threads: int = field(default=2, metadata=bounded(lo=1, hi=1024))
    checkpoint_every: int = field(default=250, metadata=bounded(lo=1))
    keep_checkpoints: bool = False                   # also keep <work_dir>/<name>/step<N>.pt (weights only)
    log_every: int = field(default=25, metadata=bounded(lo=1))
    work_dir: str = field(default="outputs/train", metadata=bounded(nonempty=True))  # resumable checkpoints (with optimizer state)
    output: str = ""                                 # final checkpoint ("" -> <work_dir>/<name>/final.pt)
    schedule: str = field(default="step", metadata=bounded(choices=("step", "cosine")))  # x lr_decay at lr_decay_at, or cosine to lr·lr_decay
    channels_last: bool = False                      # NHWC memory format (2-10 % faster here; with bf16 much more)
    bf16: bool = False                               # bfloat16 autocast of the forward pass (2x faster with AMX)
    validate_every: int = field(default=0, metadata=bounded(lo=0))  # steps between validations (0 = never)
    init: str = ""                                   # start from this checkpoint's weights (path or shipped name,
                                                     # e.g. "v2/binary"; same network and bins); fresh optimizer
    photometric: str = field(default="godard", metadata=bounded(choices=("godard", "camera")))  # colour augmentation (depth/augment.py): "godard" (the paper's,
                                                     # half the crops) or "camera" (nine camera families)
    camera_families: tuple = ()                      # "camera": only these families (empty = all nine)
    camera_p_scale: float = 1.0                      # "camera": every family's probability times this (0-1]
    scale: tuple = (1.0, 1.0)                        # enlarge each frame by s ~ U(lo, hi) >= 1 before the crop,
                                                     # depth targets / s (focal length kept; depth/augment.py)


@dataclass(frozen=True)
class RunConfig:
    name: str
    model: dict
    data: DataConfig = field(default_factory=DataConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    source: str = ""

    def model_config(self):
        from mono_map.depth.networks import named_config

        m = dict(self.model)
        arch = m.pop("arch", "small")
        return named_config(arch, source=f"{self.source or 'config'} [model]", **m)


@dataclass(frozen=True)
class RunFile:
    """The top level of a training config file (the schema :func:`load_run_config` checks)."""

    name: str = field(default="", metadata=bounded(nonempty=True))
    model: dict = field(default_factory=dict)
    data: dict = field(default_factory=dict)
    train: dict = field(default_factory=dict)


def load_run_config(path: str | os.PathLike) -> RunConfig:
    """Read a TOML or JSON training config: tables [model] (arch + ModelConfig overrides), [data], [train];
    every key is checked against its declared type and range (:mod:`mono_map.schema`), naming file,
    section and key."""
    path = Path(path)
    if not path.is_file():
        raise MonoMapError(f"{path}: config file not found")
    try:
        if path.suffix == ".json":
            raw = json.loads(path.read_text())
        else:
            import tomllib

            raw = tomllib.loads(path.read_text())
    except Exception as exc:  # noqa: BLE001
        raise MonoMapError(f"{path}: cannot parse config ({' '.join(str(exc).split())})") from None
    top = check_fields(RunFile, raw, str(path))
    data = check_fields(DataConfig, top.get("data", {}), f"{path} [data]")
    train = check_fields(TrainConfig, top.get("train", {}), f"{path} [train]")
    cfg = RunConfig(name=top.get("name", path.stem), model=dict(top.get("model", {})),
                    data=DataConfig(**data), train=TrainConfig(**train), source=str(path))
    root = Path(cfg.data.root).expanduser() if cfg.data.root else None
    if root is not None and root.exists() and not root.is_dir():
        raise MonoMapError(f"{path} [data]: root: {root} is a file, not a folder")
    check_train_outputs(cfg.train, f"{path} [train]: output", f"{path} [train]: work_dir")
    if "/" in cfg.name or cfg.name.startswith("."):
        raise MonoMapError(f"{path}: name: {cfg.name!r} must be a plain folder name (no '/', not starting with '.')")
    validate_run_config(cfg)
    return cfg


def check_train_outputs(t: TrainConfig, output_name: str, work_name: str) -> None:
    """Before training: the final checkpoint's path is not a folder, the work folder not a file (named as
    ``output_name`` / ``work_name``), so hours of training never end in a write that cannot succeed."""
    out = Path(t.output).expanduser() if t.output else None
    if out is not None and (out.is_dir() or str(t.output).endswith("/")):
        raise MonoMapError(f"{output_name}: {out} is a folder; give the checkpoint file's path (.pt)")
    if out is not None and out.parent.exists() and not out.parent.is_dir():
        raise MonoMapError(f"{output_name}: {out.parent} is a file, not a folder")
    work = Path(t.work_dir).expanduser()
    if work.exists() and not work.is_dir():
        raise MonoMapError(f"{work_name}: {work} is a file, not a folder")


def validate_run_config(cfg: RunConfig) -> None:
    src = cfg.source or "config"
    held = HELD_OUT & {str(s) for s in cfg.data.sequences}
    if held:
        raise MonoMapError(f"{src}: sequence {sorted(held)} is the held-out evaluation sequence; never train on it")
    if cfg.data.target not in ("lidar", "dense"):
        raise MonoMapError(f"{src}: data.target must be 'lidar' or 'dense', got {cfg.data.target!r}")
    if cfg.train.schedule not in ("step", "cosine"):
        raise MonoMapError(f"{src}: train.schedule must be 'step' or 'cosine', got {cfg.train.schedule!r}")
    if cfg.data.trainset and cfg.data.validation_town and cfg.data.validation_town in cfg.data.towns:
        raise MonoMapError(f"{src}: the validation town {cfg.data.validation_town} must not be a training town")
    if cfg.train.steps < 1 or cfg.train.batch_size < 1:
        raise MonoMapError(f"{src}: train.steps and train.batch_size must be >= 1")
    validate_augmentation(cfg.train, src)
    cfg.model_config()  # validates architecture / head


def validate_augmentation(t: TrainConfig, src: str = "config") -> None:
    """train.photometric, train.camera_families and train.scale: one MonoMapError naming the key."""
    from mono_map.depth.augment import FAMILIES, POLICIES

    if t.photometric not in POLICIES:
        raise MonoMapError(f"{src}: train.photometric must be one of {', '.join(POLICIES)}, got {t.photometric!r}")
    bad = [f for f in t.camera_families if f not in FAMILIES]
    if bad:
        raise MonoMapError(f"{src}: train.camera_families: unknown {bad} (known: {', '.join(FAMILIES)})")
    if t.camera_families and t.photometric != "camera":
        raise MonoMapError(f"{src}: train.camera_families needs train.photometric = \"camera\"")
    p = t.camera_p_scale
    if not isinstance(p, (int, float)) or not 0.0 < p <= 1.0:
        raise MonoMapError(f"{src}: train.camera_p_scale must be in (0, 1], got {p!r}")
    sc = t.scale
    if (len(sc) != 2 or not all(isinstance(v, (int, float)) and math.isfinite(v) for v in sc)
            or not 1.0 <= sc[0] <= sc[1] <= 2.0):
        raise MonoMapError(f"{src}: train.scale must be [lo, hi] with 1 <= lo <= hi <= 2, got {list(sc)}")


@dataclass(frozen=True)
class Augmentation:
    """What a batch does to its crops (built once from a TrainConfig by :func:`augmentation`)."""
    colour: bool = True                # photometric augmentation at all (train.augment)
    policy: str = "godard"
    camera: object = None              # augment.CameraAugment for policy "camera"
    scale: tuple = (1.0, 1.0)


def augmentation(t: TrainConfig) -> Augmentation:
    from mono_map.depth.augment import CameraAugment

    cam = CameraAugment().only(tuple(t.camera_families)).scaled(float(t.camera_p_scale))
    return Augmentation(colour=t.augment, policy=t.photometric, camera=cam,
                        scale=tuple(float(v) for v in t.scale))


def augment_crop(img: np.ndarray, dep: np.ndarray, ch: int, cw: int, rng: np.random.Generator, aug: Augmentation):
    """One training crop of a frame (img (H,W,3) uint8, dep (H,W) metres): scale/crop, colour, 50 % flip ->
    (float32 image in [0,1], float32 depths). With the default Augmentation the random draws are exactly
    those of the training before depth/augment.py (same crops, same colours, same flips)."""
    from mono_map.depth.augment import photometric, scale_crop

    H, W = dep.shape
    if aug.scale[1] > 1.0:
        s = float(rng.uniform(*aug.scale)) if aug.scale[1] > aug.scale[0] else aug.scale[0]
        Hs, Ws = int(round(H * s)), int(round(W * s))
        top, left = int(rng.integers(Hs - ch + 1)), int(rng.integers(Ws - cw + 1))
        img, dep = scale_crop(np.asarray(img), np.asarray(dep, np.float32), s, top, left, ch, cw)
    else:
        top, left = int(rng.integers(H - ch + 1)), int(rng.integers(W - cw + 1))
        img, dep = img[top:top + ch, left:left + cw], dep[top:top + ch, left:left + cw]
    img = np.asarray(img, dtype=np.float32) / 255.0
    dep = np.asarray(dep, dtype=np.float32)
    if aug.colour:
        img = photometric(img, rng, aug.policy, aug.camera)
    if rng.random() < 0.5:
        img, dep = img[:, ::-1], dep[:, ::-1]
    return img, dep


# ------------------------------------------------------------------ data cache
def downsample_depth(depth: np.ndarray, h: int, w: int, sparse: bool = True) -> np.ndarray:
    """Metres H×W -> h×w. Sparse maps: every valid pixel goes to its low-res pixel, keeping the nearest
    depth (no interpolation across holes); dense maps: nearest-neighbour resize."""
    H, W = depth.shape
    if not sparse:
        import cv2

        return cv2.resize(depth, (w, h), interpolation=cv2.INTER_NEAREST)
    v, u = np.nonzero(depth > 0)
    z = depth[v, u]
    uu = np.minimum((u + 0.5) * w / W, w - 1).astype(np.int64)
    vv = np.minimum((v + 0.5) * h / H, h - 1).astype(np.int64)
    out = np.full(h * w, np.inf, dtype=np.float32)
    np.minimum.at(out, vv * w + uu, z.astype(np.float32))
    out[np.isinf(out)] = 0.0
    return out.reshape(h, w)


def build_cache(cfg: RunConfig, model_cfg) -> tuple[np.ndarray, np.ndarray, Path]:
    """Load (or build once) the training cache -> images (N,h,w,3) uint8, depths (N,h,w) float16 metres."""
    import cv2

    from mono_map.data.prepare import prepare_sequence
    from mono_map.depth.inference import fit_size
    from mono_map.frames import first_frames
    from mono_map.paths import data_root
    from mono_map.progress import progress

    d = cfg.data
    root = data_root(d.root)
    jobs = []
    for name in d.sequences:
        seq = prepare_sequence(root, str(name), first_frames(d.frames) if d.frames else None)
        n = min(len(seq), d.frames) if d.frames else len(seq)
        jobs += [(seq, i) for i in range(0, n, d.frame_step)]
    if not jobs:
        raise MonoMapError(f"{cfg.source}: no training frames selected")
    from mono_map.data.fingerprint import sequence_fingerprint

    by_seq: dict = {}
    for s, i in jobs:
        by_seq.setdefault(s.name, (s, []))[1].append(i)
    parts = ("calibration", "images") + (("scans",) if d.target == "lidar" else ("depth",))
    contents = {name: sequence_fingerprint(s, idx, parts) for name, (s, idx) in by_seq.items()}
    key = json.dumps({"root": str(root.resolve()), "jobs": [(s.name, i) for s, i in jobs], "target": d.target,
                      "size": [model_cfg.input_height, model_cfg.input_width], "data": contents}, sort_keys=True)
    tag = hashlib.sha1(key.encode()).hexdigest()[:10]
    cache_dir = Path(d.cache_dir)
    img_path, dep_path = cache_dir / f"depth_train_{tag}_images.npy", cache_dir / f"depth_train_{tag}_depths.npy"
    if img_path.is_file() and dep_path.is_file():
        return np.load(img_path, mmap_mode="r"), np.load(dep_path, mmap_mode="r"), cache_dir
    images, depths = [], []
    for seq, i in progress(jobs, total=len(jobs), desc="caching training frames", unit="frame"):
        img = seq.image(i)
        h, w = fit_size(*img.shape[:2], model_cfg.input_height, model_cfg.input_width)
        dep = seq.lidar_depth(i) if d.target == "lidar" else seq.depth(i)
        if dep is None:
            raise MonoMapError(f"{seq.depth_dir}: no dense depth for frame {i} (data.target = 'dense')")
        images.append(cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA))
        depths.append(downsample_depth(dep, h, w, sparse=d.target == "lidar").astype(np.float16))
    from mono_map.io import atomic_path

    cache_dir.mkdir(parents=True, exist_ok=True)
    for path, arr in ((img_path, np.stack(images)), (dep_path, np.stack(depths))):
        with atomic_path(path) as tmp:
            np.save(tmp, arr)
    return np.load(img_path, mmap_mode="r"), np.load(dep_path, mmap_mode="r"), cache_dir


# ------------------------------------------------------------------ randomised-town cache
class TrainsetSampler:
    """Random crops from the randomised-town cache (:mod:`mono_map.data.synth.trainset`).

    Frames that finish rendering while training runs are picked up at every ``refresh()``.
    Targets are metres, 0 = no value, +inf = no surface (sky): ``lidar`` targets mark sky on a
    ``sky_stride`` grid (so sky does not outweigh the sparse returns), ``dense`` targets everywhere.
    """

    def __init__(self, data: DataConfig):
        self.data = data
        self.towns: list = []
        self.refresh()
        if not self.towns:
            raise MonoMapError(f"{data.trainset}: no training towns in the cache (render them with "
                               "mono-map render-trainset)")

    def refresh(self) -> int:
        """Re-scan the cache: towns created and frames finished since the last call join the pool."""
        from mono_map.data.synth.trainset import open_trainset

        names = list(self.data.towns) or None
        known = {t.path.name: t for t in self.towns}
        self.towns = [known.get(t.path.name, t) for t in open_trainset(trainset_root(self.data), names)
                      if t.path.name != self.data.validation_town]
        self.index = [(t, f) for t in self.towns for f in t.done_frames()]
        if self.towns and not self.index:
            raise MonoMapError(f"{self.data.trainset}: no rendered frames yet")
        return len(self.index)

    def __len__(self) -> int:
        return len(self.index)

    def frame(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        t, f = self.index[k]
        return frame_target(t, int(f), self.data.target, self.data.sky_stride)

    def batch(self, batch: int, crop: tuple, rng: np.random.Generator, augment: "bool | Augmentation"):
        """(B,3,h,w) float32 crops in [0,1], (B,h,w) targets; ``augment``: an Augmentation, or a bool for
        the default one with (True) or without (False) colour augmentation."""
        aug = augment if isinstance(augment, Augmentation) else Augmentation(colour=bool(augment))
        H, W = self.towns[0].meta["height"], self.towns[0].meta["width"]
        ch, cw = min(crop[0], H), min(crop[1], W)
        xs = np.empty((batch, 3, ch, cw), np.float32)
        ys = np.empty((batch, ch, cw), np.float32)
        for b in range(batch):
            img, dep = self.frame(int(rng.integers(len(self.index))))
            img, dep = augment_crop(img, dep, ch, cw, rng, aug)
            if self.data.max_targets:
                dep = subsample_targets(dep, self.data.max_targets, rng)
            xs[b] = img.transpose(2, 0, 1)
            ys[b] = dep
        return xs, ys


def trainset_root(data: DataConfig) -> Path:
    """The cache directory a config names ("default" = ``trainset.default_root()``)."""
    from mono_map.data.synth.trainset import default_root

    return default_root() if data.trainset == "default" else Path(data.trainset).expanduser()


def frame_target(town, f: int, target: str, sky_stride: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """(image uint8 (H,W,3), target metres (H,W): 0 none, +inf no surface) of a cached frame."""
    from mono_map.data.synth.trainset import decode_depth

    dense, sky = decode_depth(town.dense[f])
    if target == "dense":
        dep = dense
    else:
        dep, _ = decode_depth(town.lidar[f])
        grid = np.zeros_like(sky)
        grid[::sky_stride, ::sky_stride] = True
        sky = sky & grid & (dep == 0)
    dep = np.where(sky, np.inf, dep).astype(np.float32)
    return np.asarray(town.image[f]), dep


def subsample_targets(dep: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    """Keep at most ``n`` random target pixels of a crop (the rest set to 0 = no value)."""
    idx = np.flatnonzero(dep.ravel() > 0)
    if len(idx) <= n:
        return dep
    out = np.zeros(dep.size, np.float32)
    keep = rng.choice(idx, n, replace=False)
    out[keep] = dep.ravel()[keep]
    return out.reshape(dep.shape)


# ------------------------------------------------------------------ batches
def sample_batch(images, depths, batch: int, crop: tuple, rng: np.random.Generator, augment: "bool | Augmentation"):
    """Random crops (colour augmentation, 50 % horizontal flip; see augment_crop) -> (B,3,h,w) float32,
    (B,h,w) metres."""
    aug = augment if isinstance(augment, Augmentation) else Augmentation(colour=bool(augment))
    n, H, W = depths.shape
    ch, cw = min(crop[0], H), min(crop[1], W)
    xs = np.empty((batch, 3, ch, cw), np.float32)
    ys = np.empty((batch, ch, cw), np.float32)
    for b in range(batch):
        i = int(rng.integers(n))
        img, dep = augment_crop(images[i], depths[i], ch, cw, rng, aug)
        xs[b] = img.transpose(2, 0, 1)
        ys[b] = dep
    return xs, ys


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
def override(cfg: RunConfig, steps: int | None = None, output: str | None = None, data_root: str | None = None,
             precision: str | None = None, threads: int | None = None) -> RunConfig:
    """``cfg`` with the command line's overrides (None keeps the config's value): ``steps``, ``output``
    (final checkpoint path), ``data_root``, ``precision`` ("fp32" or "bf16" autocast) and ``threads``."""
    if steps is not None and steps < 1:
        raise MonoMapError(f"--steps: must be >= 1, got {steps}")
    if threads is not None and threads < 1:
        raise MonoMapError(f"--threads: must be >= 1, got {threads}")
    if precision not in (None, "fp32", "bf16"):
        raise MonoMapError(f"--precision: must be fp32 or bf16, got {precision!r}")
    t = cfg.train
    if output is not None:
        check_train_outputs(replace(t, output=output), "--output", "work_dir")
    t = replace(t, steps=t.steps if steps is None else steps, output=t.output if output is None else output,
                bf16=t.bf16 if precision is None else precision == "bf16",
                threads=t.threads if threads is None else threads)
    data = cfg.data if data_root is None else replace(cfg.data, root=data_root)
    return replace(cfg, train=t, data=data)


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
    from mono_map.depth.inference import default_checkpoint, load_checkpoint

    path = Path(name).expanduser()
    if not path.suffix and not path.exists():
        path = default_checkpoint(name)
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
