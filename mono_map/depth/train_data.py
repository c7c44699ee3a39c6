"""Training data: the one-off cache of training frames (images resized to the model's input scale, LiDAR
depth targets min-pooled to it, .npy under data/cache/), the randomised-town cache's sampler, and the
batches of random crops with their augmentations (gamma, brightness, colour shift or a camera's,
depth/augment.py; optional scale with the focal length kept; horizontal flips).
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mono_map.depth.train_config import DataConfig, RunConfig, TrainConfig
from mono_map.errors import MonoMapError


@dataclass(frozen=True)
class Augmentation:
    """What a batch does to its crops (built once from a TrainConfig by :func:`augmentation`)."""
    colour: bool = True                # photometric augmentation at all (train.augment)
    policy: str = "godard"
    camera: object = None              # augment.CameraAugment for policy "camera"
    scale: tuple = (1.0, 1.0)
    random_convolution: float = 0.0    # fraction of the crops filtered by a random convolution (augment.py)


def augmentation(t: TrainConfig) -> Augmentation:
    from mono_map.depth.augment import CameraAugment

    cam = CameraAugment().only(tuple(t.camera_families)).scaled(float(t.camera_p_scale))
    return Augmentation(colour=t.augment, policy=t.photometric, camera=cam,
                        scale=tuple(float(v) for v in t.scale), random_convolution=float(t.random_convolution))


def augment_crop(img: np.ndarray, dep: np.ndarray, ch: int, cw: int, rng: np.random.Generator, aug: Augmentation):
    """One training crop of a frame (img (H,W,3) uint8, dep (H,W) metres): scale/crop, colour, 50 % flip ->
    (float32 image in [0,1], float32 depths). With the default Augmentation the random draws are exactly
    those of the training before depth/augment.py (same crops, same colours, same flips)."""
    from mono_map.depth.augment import photometric, random_convolution, scale_crop

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
    if aug.random_convolution > 0 and rng.random() < aug.random_convolution:   # off: no draw (runs before it reproduce)
        img = random_convolution(img, rng)
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

