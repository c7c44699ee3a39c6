"""Training-time augmentation: what a real camera does to an image, and scale/crop with the geometry kept.

Photometric augmentation works on an (h, w, 3) float32 image in [0, 1] and returns one of the same
shape, dtype and range. Two policies (``train.photometric``):

- ``"godard"``: Godard et al.'s gamma 0.8-1.2, brightness 0.5-2.0 and colour shift 0.8-1.2 on half the
  crops (the paper's augmentation; the default, identical to the training before this module).
- ``"camera"``: nine camera families, each applied with its own probability, in the order a camera
  applies them: optics (vignetting, blur), exposure (global gain in stops, a vertical gain ramp for
  over-exposed roads or skies, clipped), white balance, sensor noise (shot + read), the tone curve
  (gamma, contrast, saturation), JPEG compression.

Random convolution (``train.random_convolution``, after either policy; Xu et al., "Robust and Generalizable
Visual Representation Learning via Random Convolutions", ICLR 2021): on a fraction of the crops the image is
filtered by a freshly drawn 3→3 channel convolution (kernel 1, 3, 5 or 7 px, normal weights) and mixed with
itself — local texture and colour change at random, shapes and edges stay where they are.

Geometric augmentation (``train.scale``): the frame is enlarged by ``s >= 1`` before the crop. A
resize by ``s`` multiplies the focal length by ``s``; the network only ever sees the training focal
length, so the metric z-depth targets are divided by ``s`` instead (``z' = z / s``): the enlarged image
is then exactly what the training camera (same focal length, same height above the road) sees of a
world ``s`` times smaller. A random vertical crop of the enlarged frame moves the horizon, as pitch and
another principal point do. Sky (+inf) stays sky, 0 (no value) stays 0.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

FAMILIES = ("vignetting", "blur", "exposure", "white_balance", "noise", "gamma", "contrast", "saturation", "jpeg")
POLICIES = ("godard", "camera")
LUMA = np.array([0.299, 0.587, 0.114], np.float32)


@dataclass(frozen=True)
class CameraAugment:
    """Probability of each camera family per crop (0 switches a family off) and its ranges."""
    p_vignetting: float = 0.3
    p_blur: float = 0.25
    p_exposure: float = 0.5
    p_white_balance: float = 0.4
    p_noise: float = 0.4
    p_gamma: float = 0.4
    p_contrast: float = 0.4
    p_saturation: float = 0.4
    p_jpeg: float = 0.3
    stops: tuple = (-1.5, 1.5)             # global exposure gain, 2**stops
    p_overexpose: float = 0.3              # of an exposure: +1 to +2.5 stops (clips roads and skies)
    ramp_stops: tuple = (-1.5, 1.5)        # vertical gain ramp, stops from top to bottom row

    def only(self, families: tuple) -> "CameraAugment":
        """This policy with every family not in ``families`` switched off (``()`` keeps all)."""
        if not families:
            return self
        from dataclasses import replace

        return replace(self, **{f"p_{f}": 0.0 for f in FAMILIES if f not in families})

    def scaled(self, factor: float) -> "CameraAugment":
        """Every family's probability times ``factor`` (0-1; 1 = unchanged, 0.5 = a milder policy)."""
        from dataclasses import replace

        return replace(self, **{f"p_{f}": getattr(self, f"p_{f}") * factor for f in FAMILIES})


# ------------------------------------------------------------------ the families (pure, parameters explicit)
def vignetting(img: np.ndarray, strength: float, centre: tuple = (0.5, 0.5)) -> np.ndarray:
    """Radial fall-off 1 - strength·r² (r = 1 at the image corner farthest from ``centre``, fractions of w, h)."""
    h, w = img.shape[:2]
    y, x = np.mgrid[0:h, 0:w].astype(np.float32)
    cx, cy = centre[0] * (w - 1), centre[1] * (h - 1)
    r2 = (x - cx) ** 2 + (y - cy) ** 2
    gain = 1.0 - strength * r2 / max(float(r2.max()), 1e-6)
    return np.clip(img * gain[..., None], 0.0, 1.0).astype(np.float32)


def blur(img: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian blur (defocus, motion smear) of ``sigma`` pixels."""
    import cv2

    if sigma <= 0:
        return img
    return np.clip(cv2.GaussianBlur(img, (0, 0), sigmaX=sigma, sigmaY=sigma, borderType=cv2.BORDER_REFLECT),
                   0.0, 1.0).astype(np.float32)


def exposure(img: np.ndarray, stops: float, ramp_stops: float = 0.0) -> np.ndarray:
    """Gain 2**stops, times a vertical ramp from 2**(-ramp/2) (top row) to 2**(ramp/2) (bottom row)
    (a positive ramp over-exposes the road, a negative one the sky), clipped at 1 like a sensor."""
    h = img.shape[0]
    ramp = np.linspace(-0.5, 0.5, h, dtype=np.float32) * ramp_stops
    gain = np.exp2(stops + ramp).astype(np.float32)
    return np.clip(img * gain[:, None, None], 0.0, 1.0).astype(np.float32)


def white_balance(img: np.ndarray, gains: np.ndarray) -> np.ndarray:
    """Per-channel gains (R, G, B), normalised so the luma weight sum is 1 (brightness kept)."""
    g = np.asarray(gains, np.float32)
    g = g / float(LUMA @ g)
    return np.clip(img * g, 0.0, 1.0).astype(np.float32)


def noise(img: np.ndarray, shot: float, read: float, rng: np.random.Generator) -> np.ndarray:
    """Sensor noise: Gaussian with variance shot·x + read² per pixel and channel."""
    sd = np.sqrt(shot * img + read ** 2).astype(np.float32)
    return np.clip(img + sd * rng.standard_normal(img.shape, dtype=np.float32), 0.0, 1.0).astype(np.float32)


def gamma(img: np.ndarray, g: float) -> np.ndarray:
    """Tone curve x**g (g > 1 darkens the mid-tones)."""
    return np.clip(img ** np.float32(g), 0.0, 1.0).astype(np.float32)


def contrast(img: np.ndarray, c: float) -> np.ndarray:
    """Stretch about the mean luma by ``c`` (c > 1 more contrast)."""
    m = float((img @ LUMA).mean())
    return np.clip((img - m) * np.float32(c) + m, 0.0, 1.0).astype(np.float32)


def saturation(img: np.ndarray, s: float) -> np.ndarray:
    """Blend with the grey (luma) image: 0 grey, 1 unchanged, > 1 more colourful."""
    grey = (img @ LUMA)[..., None]
    return np.clip(grey + (img - grey) * np.float32(s), 0.0, 1.0).astype(np.float32)


def jpeg(img: np.ndarray, quality: int) -> np.ndarray:
    """Round trip through a JPEG of ``quality`` (1-100) at 8 bits."""
    import cv2

    u8 = np.round(np.clip(img, 0, 1) * 255).astype(np.uint8)
    ok, buf = cv2.imencode(".jpg", u8[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    out = cv2.imdecode(buf, cv2.IMREAD_COLOR)[..., ::-1]
    return (out.astype(np.float32) / 255.0)


# ------------------------------------------------------------------ policies
def godard(img: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Godard et al.'s augmentation on an (h,w,3) float image in [0,1]: gamma 0.8-1.2,
    brightness 0.5-2.0, per-channel colour shift 0.8-1.2, clipped to [0,1]."""
    img = img ** rng.uniform(0.8, 1.2)
    img = img * rng.uniform(0.5, 2.0)
    img = img * rng.uniform(0.8, 1.2, size=3).astype(np.float32)
    return np.clip(img, 0.0, 1.0)


def camera(img: np.ndarray, rng: np.random.Generator, cfg: CameraAugment = CameraAugment()) -> np.ndarray:
    """Each of the nine families with its probability, parameters drawn from ``rng`` (deterministic per seed)."""
    img = np.asarray(img, np.float32)
    if rng.random() < cfg.p_vignetting:
        img = vignetting(img, rng.uniform(0.1, 0.6), (rng.uniform(0.3, 0.7), rng.uniform(0.3, 0.7)))
    if rng.random() < cfg.p_blur:
        img = blur(img, rng.uniform(0.4, 1.5))
    if rng.random() < cfg.p_exposure:
        st = rng.uniform(1.0, 2.5) if rng.random() < cfg.p_overexpose else rng.uniform(*cfg.stops)
        img = exposure(img, st, rng.uniform(*cfg.ramp_stops))
    if rng.random() < cfg.p_white_balance:
        img = white_balance(img, np.exp2(rng.normal(0.0, 0.2, 3)))
    if rng.random() < cfg.p_noise:
        img = noise(img, rng.uniform(0.0, 0.01), rng.uniform(0.0, 0.03), rng)
    if rng.random() < cfg.p_gamma:
        img = gamma(img, float(np.exp(rng.uniform(np.log(0.6), np.log(1.6)))))
    if rng.random() < cfg.p_contrast:
        img = contrast(img, rng.uniform(0.6, 1.5))
    if rng.random() < cfg.p_saturation:
        img = saturation(img, rng.uniform(0.2, 1.6))
    if rng.random() < cfg.p_jpeg:
        img = jpeg(img, int(rng.integers(25, 96)))
    return img


def photometric(img: np.ndarray, rng: np.random.Generator, policy: str, cfg: CameraAugment = CameraAugment()):
    """The training crop's colour augmentation per ``policy`` ("godard": on half the crops; "camera")."""
    if policy == "godard":
        return godard(img, rng) if rng.random() < 0.5 else img
    return camera(img, rng, cfg)


def random_convolution(img: np.ndarray, rng: np.random.Generator, sizes: tuple = (1, 3, 5, 7)) -> np.ndarray:
    """RandConv-mix on an (h,w,3) float image in [0,1]: a 3→3 convolution with kernel size k drawn from
    ``sizes`` and weights ~ N(0, 1/(3·k²)) (reflected borders), each output channel rescaled to the input's
    mean and standard deviation, then α·img + (1−α)·filtered with α ~ U(0,1), clipped to [0,1]."""
    import cv2

    img = np.asarray(img, np.float32)
    k = int(rng.choice(np.asarray(sizes)))
    w = rng.normal(0.0, 1.0 / np.sqrt(3.0 * k * k), size=(3, 3, k, k)).astype(np.float32)
    out = np.empty_like(img)
    mean, std = img.reshape(-1, 3).mean(0), img.reshape(-1, 3).std(0)
    for o in range(3):
        f = sum(cv2.filter2D(np.ascontiguousarray(img[..., c]), -1, w[o, c], borderType=cv2.BORDER_REFLECT)
                for c in range(3))
        out[..., o] = (f - f.mean()) / max(float(f.std()), 1e-6) * std[o] + mean[o]
    a = np.float32(rng.uniform(0.0, 1.0))
    return np.clip(a * img + (1 - a) * out, 0.0, 1.0).astype(np.float32)


# ------------------------------------------------------------------ geometry
def scale_crop(img: np.ndarray, depth: np.ndarray, s: float, top: int, left: int, ch: int, cw: int):
    """Enlarge (img (H,W,3), depth metres (H,W): 0 none, +inf sky) by ``s >= 1`` (pixel centres kept),
    divide the depths by ``s`` (the focal length stays the training one), crop (ch, cw) at (top, left).

    The image is resized bilinearly, the depths by nearest neighbour (no mixing across edges)."""
    import cv2

    if s < 1.0:
        raise ValueError(f"scale_crop: s must be >= 1, got {s}")
    H, W = depth.shape
    if s == 1.0:
        return img[top:top + ch, left:left + cw], depth[top:top + ch, left:left + cw]
    Hs, Ws = int(round(H * s)), int(round(W * s))
    # output pixel (v, u) of the crop samples the input at ((v + top + 0.5) / s - 0.5, ...)
    M = np.array([[s, 0.0, 0.5 * s - 0.5 - left], [0.0, s, 0.5 * s - 0.5 - top]], np.float64)
    if top + ch > Hs or left + cw > Ws:
        raise ValueError("scale_crop: crop outside the enlarged frame")
    im = cv2.warpAffine(np.ascontiguousarray(img), M, (cw, ch), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)
    d = cv2.warpAffine(np.ascontiguousarray(depth, np.float32), M, (cw, ch), flags=cv2.INTER_NEAREST,
                       borderMode=cv2.BORDER_REPLICATE)
    return im, (d / np.float32(s)).astype(np.float32)
