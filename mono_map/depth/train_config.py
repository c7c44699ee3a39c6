"""Training configuration: the dataclasses of a run ([data], [train], the [model] table), the config file's
schema (:class:`RunFile`), loading and validation (one MonoMapError naming file, section and key), and the
command line's overrides.
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field, replace
from pathlib import Path

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
    random_convolution: float = field(default=0.0, metadata=bounded(lo=0, hi=1))  # fraction of crops filtered by a
                                                     # random convolution after the colour policy (0 = off)
    scale: tuple = (1.0, 1.0)                        # enlarge each frame by s ~ U(lo, hi) >= 1 before the crop,


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

