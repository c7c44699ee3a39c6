"""Run a trained depth checkpoint on RGB images: expected depth + entropy (+ distributions).

Images are resized (aspect kept) to fit the model's input size, padded by edge replication
to exactly that size (a multiple of 32), run, cropped back, and the depth / entropy maps are
bilinearly up-sampled to the full input resolution.
"""

from __future__ import annotations

import functools
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from mono_map.depth.heads import decode
from mono_map.depth.networks import DepthNet, ModelConfig
from mono_map.errors import MonoMapError
from mono_map.paths import CHECKPOINT_DIR

CHECKPOINT_FORMAT = "mono-map-depth"
CHECKPOINT_VERSION = 1
ORACLE = "oracle"                 # --model oracle: the noisy ground truth (mapping/oracle.py), no checkpoint
MC_SEED = 0                       # the dropout masks of MC-dropout predictions (DepthPredictor._forward)


@dataclass
class DepthPrediction:
    depth: np.ndarray                 # H×W float32, metres, expected depth at full input resolution
    entropy: np.ndarray               # H×W float32, nats (non-distribution heads: their uncertainty)
    probs: np.ndarray | None = None   # K×H'×W' float32 (softmax over logits), only if asked, at the pixels
    #                                   [::probs_step, ::probs_step] (H' = ceil(H / probs_step))
    argmax: np.ndarray | None = None  # H×W float32, metres, centre of the most likely bin
    p_beyond: np.ndarray | None = None  # H×W float32, probability of no surface within the bin range (sky)
    probs_step: int = 1               # probs sample every probs_step-th pixel row and column


def default_precision(cpuinfo: str | None = None) -> str:
    """"bf16" on CPUs with bfloat16 matrix instructions — AMX (``amx_bf16``) or AVX-512 BF16
    (``avx512_bf16``) — else "fp32" (emulated bfloat16 is slower than fp32). Measured on the project's
    machines, full ``predict`` of a 376×1241 frame, one thread: 28 vs 62 ms network time with AMX (Xeon),
    71 vs 133 ms with AVX-512 BF16 (AMD EPYC); depths change by < 1 cm. ``$MONO_MAP_PRECISION`` overrides.
    ``cpuinfo``: the text of /proc/cpuinfo (read when None)."""
    from mono_map.schema import env_value

    chosen = env_value("MONO_MAP_PRECISION")  # checked: anything but fp32/bf16 is refused naming it
    if chosen is not None:
        return chosen
    if cpuinfo is None:
        try:
            cpuinfo = Path("/proc/cpuinfo").read_text()
        except OSError:
            return "fp32"
    flags = {f for line in cpuinfo.splitlines() if line.startswith("flags") for f in line.split(":", 1)[-1].split()}
    return "bf16" if flags & {"amx_bf16", "avx512_bf16"} else "fp32"


def check_probs_step(step) -> int:
    """A valid ``probs_step`` (a positive integer) or MonoMapError."""
    if int(step) != step or step < 1:
        raise MonoMapError(f"probs_step: must be a positive integer, got {step}")
    return int(step)


def bilinear_taps(n_in: int, n_out: int, step: int = 1) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Bilinear up-sampling from n_in to n_out samples (``align_corners=False``, as ``F.interpolate``) evaluated at
    outputs 0, step, 2·step, ...: (lower source index, upper source index, float32 weight of the upper)."""
    scale = torch.tensor(n_in / n_out, dtype=torch.float32)
    src = ((torch.arange(0, n_out, step, dtype=torch.float32) + 0.5) * scale - 0.5).clamp_min(0)
    i0 = src.long()
    i1 = torch.clamp(i0 + 1, max=n_in - 1)
    return i0, i1, src - i0


@functools.lru_cache(maxsize=16)
def interp_matrix(n_low: int, n_net: int, n_crop: int, n_out: int, step: int) -> torch.Tensor:
    """The 1-D map of :meth:`DepthPredictor.to_image` as one float32 matrix (ceil(n_out / step) × n_low):
    bilinear n_low -> n_net, crop to the first n_crop, bilinear n_crop -> n_out (skipped if equal), sampled at
    outputs 0, step, 2·step, ... (computed in float64; ≤ 3 non-zeros per row for 4× up-sampling)."""
    def taps(n_in, n_o, s):
        i0, i1, w = bilinear_taps(n_in, n_o, s)
        m = torch.zeros(len(i0), n_in, dtype=torch.float64)
        r = torch.arange(len(i0))
        m[r, i0] += 1 - w.double()
        m[r, i1] += w.double()
        return m

    first = taps(n_low, n_net, 1)[:n_crop]
    second = taps(n_crop, n_out, step) if n_crop != n_out else torch.eye(n_crop, dtype=torch.float64)[::step]
    return (second @ first).float()


def default_checkpoint(head: str = "binary") -> Path:
    """A shipped checkpoint by name: "binary" (model v2, the mapping model), "v2/<head>" (the other heads of
    the v2 comparison) or "v1/<head>" (v1 heads)."""
    return CHECKPOINT_DIR / f"{head}.pt"


def resolve_checkpoint(model: str | os.PathLike | None) -> Path:
    """The file a model name names — the one place a name becomes a checkpoint: None → the shipped
    binary model; a bare name without suffix that is no file ("softmax", "v2/softmax") → its shipped
    checkpoint (:func:`default_checkpoint`); anything else → that path. Existence is not checked."""
    if model is None:
        return default_checkpoint("binary")
    path = Path(model)
    if not path.suffix and not path.exists():
        return default_checkpoint(str(model))
    return path


def checkpoint_path(model: str | None) -> Path | None:
    """The checkpoint file ``--model`` names (:func:`resolve_checkpoint`; 'oracle', the noisy ground truth
    of a synthetic sequence: None); MonoMapError naming ``--model`` if it does not exist."""
    if model == ORACLE:
        return None
    path = resolve_checkpoint(model)
    if not path.is_file():
        raise MonoMapError(f"--model: {model}: checkpoint not found")
    return path


def model_digest(model: str | None) -> str:
    """What identifies the depth model ``--model`` names: sha256 of its checkpoint file (first 16 hex),
    or 'oracle'."""
    import hashlib

    path = checkpoint_path(model)
    if path is None:
        return ORACLE
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()[:16]


def shipped_names() -> list[str]:
    """Names of the shipped checkpoints (:func:`default_checkpoint`): "binary", then v2/…, then v1/…; a file
    identical to an earlier one (v2/binary while it is the mapping model) is listed once, by its first name."""
    import hashlib

    sub = [f"{d}/{p.stem}" for d in ("v2", "v1") for p in sorted((CHECKPOINT_DIR / d).glob("*.pt"))]
    names, seen = [], set()
    for name in (["binary"] if default_checkpoint("binary").is_file() else []) + sub:
        digest = hashlib.sha256(default_checkpoint(name).read_bytes()).hexdigest()
        if digest not in seen:
            seen.add(digest)
            names.append(name)
    return names


def fit_size(h: int, w: int, max_h: int, max_w: int) -> tuple[int, int]:
    """Largest (h', w') with the aspect ratio of (h, w) that fits into (max_h, max_w) pixels."""
    s = min(max_h / h, max_w / w)
    return min(max_h, max(1, round(h * s))), min(max_w, max(1, round(w * s)))


def resize_to_input(image: np.ndarray, H: int, W: int) -> tuple[np.ndarray, tuple[int, int]]:
    """RGB uint8 -> the network's H×W input: resized with the aspect kept (:func:`fit_size`, area
    interpolation) and edge-padded right and below; also the content size (fh, fw)."""
    import cv2

    h, w = image.shape[:2]
    fh, fw = fit_size(h, w, H, W)
    r = cv2.resize(image, (fw, fh), interpolation=cv2.INTER_AREA) if (fh, fw) != (h, w) else image
    return np.pad(r, ((0, H - fh), (0, W - fw), (0, 0)), mode="edge"), (fh, fw)


def save_checkpoint(path: str | os.PathLike, model: DepthNet, training: dict | None = None,
                    optimizer_state: dict | None = None) -> None:
    """Write config + bins + weights (+ training metadata / optimizer state) atomically."""
    from mono_map.io import atomic_path

    cfg = model.cfg
    payload = {
        "format": CHECKPOINT_FORMAT, "version": CHECKPOINT_VERSION,
        "model_config": cfg.to_dict(), "bins": cfg.bins.to_dict(),
        "bin_centres": torch.as_tensor(cfg.bins.centres),
        "state_dict": {k: v.detach().cpu() for k, v in model.state_dict().items()},
        "training": training or {},
    }
    if optimizer_state is not None:
        payload["optimizer"] = optimizer_state
    with atomic_path(path) as tmp:
        torch.save(payload, tmp)
        os.chmod(tmp, 0o644)  # a shipped file, readable like any other


def load_checkpoint(path: str | os.PathLike, device: str = "cpu") -> tuple[DepthNet, dict]:
    """Load and validate a checkpoint -> (model in eval mode, payload). Raises MonoMapError naming the file."""
    path = Path(path)
    if not path.is_file():
        raise MonoMapError(f"{path}: checkpoint not found")
    try:
        payload = torch.load(path, map_location=device, weights_only=True)
    except Exception as exc:  # noqa: BLE001 - any unpickling failure means a corrupt file
        raise MonoMapError(f"{path}: not a readable checkpoint (corrupt, truncated or not a torch file; "
                           f"{type(exc).__name__})") from None
    if not isinstance(payload, dict) or payload.get("format") != CHECKPOINT_FORMAT:
        raise MonoMapError(f"{path}: not a mono-map depth checkpoint (missing format tag)")
    if payload.get("version") != CHECKPOINT_VERSION:
        raise MonoMapError(f"{path}: checkpoint version {payload.get('version')} unsupported (expected {CHECKPOINT_VERSION})")
    for key in ("model_config", "bins", "state_dict"):
        if key not in payload:
            raise MonoMapError(f"{path}: checkpoint lacks '{key}'")
    if not isinstance(payload.get("training", {}), dict):
        raise MonoMapError(f"{path}: training: expected a table of metadata, got {payload['training']!r}")
    cfg = ModelConfig.from_dict(payload["model_config"], source=f"{path} model_config")
    if payload["bins"] != cfg.bins.to_dict():
        raise MonoMapError(f"{path}: stored bins {payload['bins']} disagree with the model config {cfg.bins.to_dict()}")
    if "bin_centres" in payload:
        try:
            centres = np.asarray(payload["bin_centres"], dtype=np.float64)
            same = centres.shape == cfg.bins.centres.shape and np.allclose(centres, cfg.bins.centres, rtol=1e-6)
        except (TypeError, ValueError):
            same = False
        if not same:
            raise MonoMapError(f"{path}: stored bin centres disagree with the bin formula")
    state = payload["state_dict"]
    if not isinstance(state, dict) or not all(isinstance(v, torch.Tensor) for v in state.values()):
        raise MonoMapError(f"{path}: state_dict: expected a table of weight tensors")
    model = DepthNet(cfg)
    own = model.state_dict()
    missing = sorted(set(own) - set(state))
    unexpected = sorted(set(state) - set(own))
    bad = [k for k in own if k in state and tuple(state[k].shape) != tuple(own[k].shape)]
    if missing or unexpected or bad:
        raise MonoMapError(f"{path}: weights do not match the '{cfg.name}/{cfg.head}' architecture "
                           f"(missing {missing[:3]}, unexpected {unexpected[:3]}, wrong shape {bad[:3]})")
    model.load_state_dict(state)
    for k, v in state.items():
        if v.is_floating_point() and not torch.isfinite(v).all():
            raise MonoMapError(f"{path}: weights contain NaN/inf ({k})")
    return model.to(device).eval(), payload


class DepthPredictor:
    """A loaded depth model. ``space`` picks the expectation: "log" exp(Σp log d) or "linear" Σp d."""

    def __init__(self, model: DepthNet, checkpoint: Path | None = None, device: str = "cpu",
                 space: str = "log", training: dict | None = None, fast: bool = False, precision: str = "fp32",
                 flip: bool = False):
        self.model = model.eval()
        self.cfg = model.cfg
        self.bins = model.cfg.bins
        self.checkpoint = checkpoint
        self.device = device
        self.space = space
        self.training = training or {}
        self.fast = fast  # True: statistics at the decoder's stride 4, then up-sampled (16x fewer pixels, ~4x less CPU measured: docs/model.md)
        if precision not in ("fp32", "bf16"):
            raise MonoMapError(f"precision: must be 'fp32' or 'bf16', got {precision!r}")
        self.precision = precision  # "bf16": bfloat16 autocast of the network (statistics in fp32)
        # flip: the mirrored image too, its outputs mirrored back and combined with the image's as two samples
        # (bin heads: the mixture of both distributions; monodepth2's post-processing, for distributions)
        self.flip = bool(flip)
        # channels_last: the network's convolutions ~18 % faster on CPU in fp32 too (docs/model.md)
        self.model = self.model.to(memory_format=torch.channels_last)

    @classmethod
    def load(cls, checkpoint: str | os.PathLike | None = None, device: str = "cpu",
             space: str = "log", fast: bool = False, precision: str = "fp32", flip: bool = False) -> "DepthPredictor":
        """None -> the shipped binary checkpoint; a bare head name (e.g. "softmax") -> its shipped checkpoint."""
        checkpoint = resolve_checkpoint(checkpoint)
        model, payload = load_checkpoint(checkpoint, device)
        return cls(model, Path(checkpoint), device, space, payload.get("training"), fast, precision, flip)

    @property
    def head(self) -> str:
        return self.cfg.head

    def _prepare(self, images: list[np.ndarray]) -> tuple[torch.Tensor, tuple[int, int], tuple[int, int]]:
        h, w = images[0].shape[:2]
        for im in images:
            if im.ndim != 3 or im.shape[2] != 3 or im.dtype != np.uint8:
                raise MonoMapError(f"image: expected H×W×3 uint8 RGB, got {im.shape} {im.dtype}")
            if im.shape[:2] != (h, w):
                raise MonoMapError("images: a batch must share one size")
        H, W = self.cfg.input_height, self.cfg.input_width
        batch = [resize_to_input(im, H, W)[0] for im in images]
        fh, fw = fit_size(h, w, H, W)
        x = torch.from_numpy(np.stack(batch)).permute(0, 3, 1, 2).float().div_(255.0)
        return x.to(self.device), (fh, fw), (h, w)

    def _forward(self, x: torch.Tensor) -> tuple[torch.Tensor, bool]:
        """Raw head outputs; MC-dropout heads sample the tail at stride 4 (32 full-size samples would not fit),
        with dropout masks drawn from a generator seeded with ``MC_SEED`` on every call: an image always gets
        the same prediction (evaluations repeat to the digit), and the caller's torch RNG is left as it was."""
        mc = self.cfg.mc_samples if get_dropout(self.model) else 0
        low = self.fast or mc > 0
        if mc > 0:
            with torch.random.fork_rng(devices=[]):
                torch.manual_seed(MC_SEED)
                return self._network(x, mc, low), low
        return self._network(x, mc, low), low

    def _network(self, x: torch.Tensor, mc: int, low: bool) -> torch.Tensor:
        """Raw outputs (B,C,H',W'), or (S,B,C,H',W') samples: MC dropout's and/or the mirrored image's (``flip``:
        the whole padded input mirrored, its outputs mirrored back; exact at stride 4 too, the input width being a
        multiple of 4)."""
        if not self.flip:
            return self._pass(x, mc, low)
        a, b = self._pass(x, mc, low), self._pass(x.flip(-1), mc, low).flip(-1)
        return torch.cat([a, b]) if mc > 0 else torch.stack([a, b])

    def _pass(self, x: torch.Tensor, mc: int, low: bool) -> torch.Tensor:
        x = x.contiguous(memory_format=torch.channels_last)
        if self.precision == "bf16":
            with torch.autocast(x.device.type, dtype=torch.bfloat16):
                out = self.model(x, mc_samples=mc, upsample=not low)
            return out.float()
        return self.model(x, mc_samples=mc, upsample=not low)

    def to_image(self, t: torch.Tensor, geom: tuple) -> torch.Tensor:
        """(B,C,h',w') maps at network resolution -> (B,C,h,w) at the input image's resolution (bilinear)."""
        (H, W), (fh, fw), (h, w), low = geom
        if low:  # stride-4 maps -> model input size
            t = F.interpolate(t, size=(H, W), mode="bilinear", align_corners=False)
        t = t[..., :fh, :fw]
        return F.interpolate(t, size=(h, w), mode="bilinear", align_corners=False) if (fh, fw) != (h, w) else t

    def to_grid(self, t: torch.Tensor, geom: tuple, step: int) -> torch.Tensor:
        """(B,C,h',w') maps at network resolution -> (B, ceil(h/step), ceil(w/step), C), channels last and
        contiguous: :meth:`to_image`'s bilinear up-sampling evaluated only at the image pixels [::step, ::step]
        (the same interpolation; float32 rounding may differ in the last bits, ~2e-7)."""
        (H, W), (fh, fw), (h, w), low = geom
        if low:  # both up-samplings as two small matrix products (3× faster than the two interpolations)
            B, C, hl, wl = t.shape
            rows, cols = interp_matrix(hl, H, fh, h, step), interp_matrix(wl, W, fw, w, step)
            out = torch.empty(B, rows.shape[0], cols.shape[0], C)
            for b in range(B):
                x = t[b].permute(2, 1, 0).reshape(wl, hl * C)                      # [col, row·C + c]
                y = (cols @ x).view(-1, hl, C).permute(1, 0, 2).reshape(hl, -1)    # [row, out col·C + c]
                torch.mm(rows, y, out=out[b].view(rows.shape[0], -1))
            return out
        t = t.contiguous(memory_format=torch.channels_last)
        t = t[..., :fh, :fw].permute(0, 2, 3, 1)              # (B, fh, fw, C), a view of channels-last memory
        if (fh, fw) == (h, w):
            return t[:, ::step, ::step].contiguous()
        r0, r1, wr = bilinear_taps(fh, h, step)
        c0, c1, wc = bilinear_taps(fw, w, step)
        rows = torch.lerp(t[:, r0], t[:, r1], wr[None, :, None, None])
        return torch.lerp(rows[:, :, c0], rows[:, :, c1], wc[None, None, :, None])

    def decode(self, outputs: torch.Tensor, space: str | None = None, with_probs: bool = False) -> dict:
        """Raw head outputs -> depth, entropy, argmax, p_beyond, probs (see :func:`heads.decode`)."""
        return decode(self.model.head, outputs, self.bins, space or self.space, with_probs=with_probs,
                      beyond=self.cfg.beyond)

    @torch.inference_mode()
    def raw_outputs(self, images: list[np.ndarray]) -> tuple[torch.Tensor, tuple]:
        """Raw head outputs (uncropped network resolution) and the geometry ``to_image`` needs."""
        x, (fh, fw), (h, w) = self._prepare(images)
        out, low = self._forward(x)
        return out, (tuple(x.shape[-2:]), (fh, fw), (h, w), low)

    @torch.inference_mode()
    def predict_batch(self, images: list[np.ndarray], with_probs: bool = False,
                      probs_step: int = 1) -> list[DepthPrediction]:
        """Predictions of same-size RGB images; ``with_probs``: also the bin probabilities, at every
        ``probs_step``-th pixel row and column (> 1: only those pixels are interpolated, ~step² less work)."""
        if not images:
            return []
        step = check_probs_step(probs_step)
        out, geom = self.raw_outputs(images)
        res = self.decode(out, with_probs=with_probs)
        stats = self.to_image(torch.stack([res["depth"], res["entropy"], res["argmax"], res["p_beyond"]], 1), geom)
        depth = stats[:, 0].clamp(self.bins.min_depth, self.bins.max_depth)
        probs = None
        if with_probs and res["probs"] is not None:
            # step 1: the K×H×W maps as always; else channels-last samples, handed out as K-first views
            probs = (self.to_image(res["probs"], geom) if step == 1 else
                     self.to_grid(res["probs"].float(), geom, step).permute(0, 3, 1, 2))
        preds = []
        for b in range(len(images)):
            preds.append(DepthPrediction(
                depth=depth[b].cpu().numpy().astype(np.float32), entropy=stats[b, 1].cpu().numpy().astype(np.float32),
                probs=None if probs is None else np.asarray(probs[b].cpu().numpy(), dtype=np.float32),
                argmax=stats[b, 2].cpu().numpy().astype(np.float32),
                p_beyond=stats[b, 3].clamp(0, 1).cpu().numpy().astype(np.float32), probs_step=step))
        return preds

    def predict(self, image: np.ndarray, with_probs: bool = False, probs_step: int = 1) -> DepthPrediction:
        return self.predict_batch([image], with_probs=with_probs, probs_step=probs_step)[0]


def get_dropout(model: DepthNet) -> bool:
    return model.head.dropout
