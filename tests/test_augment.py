"""Training augmentation (depth/augment.py): each camera family does what it says, ranges and seeds hold,
the default policy draws exactly what the training drew before, scale/crop keeps the geometry."""

import math

import numpy as np
import pytest

from mono_map.depth import augment as A
from mono_map.depth.train_config import TrainConfig, load_run_config, validate_augmentation
from mono_map.depth.train_data import Augmentation, augment_crop, sample_batch
from mono_map.errors import MonoMapError


def _scene(h=64, w=96, seed=0):
    """A textured float image in [0,1] with a bright sky-like top and a darker road-like bottom."""
    rng = np.random.default_rng(seed)
    base = np.linspace(0.8, 0.3, h, dtype=np.float32)[:, None, None] * np.ones((1, w, 3), np.float32)
    tint = np.array([1.0, 0.9, 0.7], np.float32)
    return np.clip(base * tint + 0.15 * rng.random((h, w, 3), dtype=np.float32) - 0.07, 0, 1).astype(np.float32)


def _luma(img):
    return img @ A.LUMA


def _grad(img):
    return float(np.abs(np.diff(img, axis=1)).mean() + np.abs(np.diff(img, axis=0)).mean())


def test_exposure_brightens_and_overexposure_clips_the_road():
    img = _scene()
    up, down = A.exposure(img, 1.0), A.exposure(img, -1.0)
    assert _luma(up).mean() > _luma(img).mean() > _luma(down).mean()
    road = A.exposure(img, 2.0, ramp_stops=2.0)               # over-exposed, most at the bottom rows
    assert (road[-8:] >= 1.0).mean() > 0.9 and (road[-8:] >= 1.0).mean() > (road[:8] >= 1.0).mean()
    sky = A.exposure(img, 0.0, ramp_stops=-2.0)                # negative ramp: the top rows gain
    assert _luma(sky[:8]).mean() > _luma(img[:8]).mean() and _luma(sky[-8:]).mean() < _luma(img[-8:]).mean()


def test_white_balance_shifts_colour_not_brightness():
    img = _scene()
    out = A.white_balance(img, np.array([1.0, 1.0, 1.6]))
    assert out[..., 2].mean() / out[..., 0].mean() > 1.3 * img[..., 2].mean() / img[..., 0].mean()
    assert abs(_luma(out).mean() - _luma(img).mean()) < 0.05


def test_gamma_contrast_saturation_act_as_named():
    img = _scene()
    assert _luma(A.gamma(img, 1.5)).mean() < _luma(img).mean() < _luma(A.gamma(img, 0.7)).mean()
    assert _luma(A.contrast(img, 1.4)).std() > _luma(img).std() > _luma(A.contrast(img, 0.6)).std()
    spread = lambda x: float((x.max(-1) - x.min(-1)).mean())  # noqa: E731
    assert spread(A.saturation(img, 1.5)) > spread(img) > spread(A.saturation(img, 0.3))
    assert spread(A.saturation(img, 0.0)) < 1e-6


def test_vignetting_darkens_the_corners_more_than_the_centre():
    img = np.full((64, 96, 3), 0.6, np.float32)
    out = A.vignetting(img, 0.5)
    assert out[32, 48].mean() > 0.59 and out[0, 0].mean() < 0.35 and out[-1, -1].mean() < 0.35


def test_blur_and_noise_and_jpeg():
    img = _scene()
    assert _grad(A.blur(img, 1.2)) < 0.7 * _grad(img)
    n = A.noise(img, 0.01, 0.02, np.random.default_rng(1))
    assert 0.02 < np.std(n - img) < 0.2 and abs(float((n - img).mean())) < 0.01
    j = A.jpeg(img, 30)
    assert j.shape == img.shape and j.dtype == np.float32
    err = np.abs(j - img)
    assert err.max() > 0 and err.mean() < 0.06                # lossy, but the same picture


def test_every_family_keeps_shape_dtype_and_range_and_is_seeded():
    img = _scene()
    for fam in A.FAMILIES:
        cfg = A.CameraAugment(**{f"p_{f}": (1.0 if f == fam else 0.0) for f in A.FAMILIES})
        a = A.camera(img, np.random.default_rng(3), cfg)
        b = A.camera(img, np.random.default_rng(3), cfg)
        assert a.shape == img.shape and a.dtype == np.float32, fam
        assert 0.0 <= a.min() and a.max() <= 1.0, fam
        np.testing.assert_array_equal(a, b, err_msg=fam)
        assert not np.array_equal(a, img), fam                # a family that is on changes the image
    half = A.CameraAugment().scaled(0.5)
    assert all(getattr(half, f"p_{f}") == 0.5 * getattr(A.CameraAugment(), f"p_{f}") for f in A.FAMILIES)
    off = A.CameraAugment().only(("blur",))
    assert off.p_blur > 0 and all(getattr(off, f"p_{f}") == 0 for f in A.FAMILIES if f != "blur")
    wild = np.clip(np.random.default_rng(4).normal(0.5, 0.6, (32, 48, 3)), 0, 1).astype(np.float32)
    for seed in range(20):                                      # all families at their probabilities
        out = A.camera(wild, np.random.default_rng(seed))
        assert out.dtype == np.float32 and 0.0 <= out.min() and out.max() <= 1.0


def test_random_convolution_changes_texture_and_colour_not_where_the_edges_are(tmp_path):
    """RandConv-mix: shape, dtype, range, seeded; the colours change, a step edge stays in its column; in a
    batch it is drawn only when asked (off: the crops of the runs before it)."""
    img = _scene(48, 64)
    img[:, 40:] = np.clip(img[:, 40:] * np.array([0.2, 0.5, 1.6], np.float32), 0, 1)   # a strong edge at column 40
    changed = 0
    for seed in range(12):
        a = A.random_convolution(img, np.random.default_rng(seed))
        np.testing.assert_array_equal(a, A.random_convolution(img, np.random.default_rng(seed)))
        assert a.shape == img.shape and a.dtype == np.float32 and 0.0 <= a.min() and a.max() <= 1.0
        changed += float(np.abs(a - img).mean()) > 0.01
        col = np.abs(np.diff(a, axis=1)).sum(axis=(0, 2))      # horizontal gradient per column pair
        assert abs(int(col.argmax()) - 39) <= 3, seed          # within the largest kernel's radius
    assert changed >= 9
    rng = np.random.default_rng(0)
    images = rng.integers(0, 255, (3, 40, 72, 3), dtype=np.uint8)
    depths = rng.uniform(2, 60, (3, 40, 72)).astype(np.float16)
    off = sample_batch(images, depths, 4, (32, 64), np.random.default_rng(5), Augmentation())
    zero = sample_batch(images, depths, 4, (32, 64), np.random.default_rng(5), Augmentation(random_convolution=0.0))
    on = sample_batch(images, depths, 4, (32, 64), np.random.default_rng(5), Augmentation(random_convolution=1.0))
    np.testing.assert_array_equal(off[0], zero[0])
    assert not np.array_equal(off[0], on[0]) and 0.0 <= on[0].min() and on[0].max() <= 1.0
    np.testing.assert_array_equal(off[1][:1], on[1][:1])        # the first crop's depths: same frame, crop, flip
    bad = tmp_path / "bad.toml"
    bad.write_text('[model]\nhead = "binary"\n[train]\nrandom_convolution = 1.5\n')
    with pytest.raises(MonoMapError, match=r"bad.toml \[train\]: random_convolution"):
        load_run_config(bad)


def _old_sample_batch(images, depths, batch, crop, rng, augment):
    """The training's crop/colour/flip before depth/augment.py (verbatim), the reference for 'godard'."""
    n, H, W = depths.shape
    ch, cw = min(crop[0], H), min(crop[1], W)
    xs = np.empty((batch, 3, ch, cw), np.float32)
    ys = np.empty((batch, ch, cw), np.float32)
    for b in range(batch):
        i = int(rng.integers(n))
        top, left = int(rng.integers(H - ch + 1)), int(rng.integers(W - cw + 1))
        img = np.asarray(images[i, top:top + ch, left:left + cw], dtype=np.float32) / 255.0
        dep = np.asarray(depths[i, top:top + ch, left:left + cw], dtype=np.float32)
        if augment and rng.random() < 0.5:
            img = img ** rng.uniform(0.8, 1.2)
            img = img * rng.uniform(0.5, 2.0)
            img = img * rng.uniform(0.8, 1.2, size=3).astype(np.float32)
            img = np.clip(img, 0.0, 1.0)
        if rng.random() < 0.5:
            img, dep = img[:, ::-1], dep[:, ::-1]
        xs[b] = img.transpose(2, 0, 1)
        ys[b] = dep
    return xs, ys


def test_default_policy_reproduces_the_old_augmentation_bit_for_bit():
    rng = np.random.default_rng(0)
    images = rng.integers(0, 255, (5, 48, 80, 3), dtype=np.uint8)
    depths = np.where(rng.random((5, 48, 80)) < 0.3, rng.uniform(2, 60, (5, 48, 80)), 0).astype(np.float16)
    for seed in range(6):
        for colour in (True, False):
            old = _old_sample_batch(images, depths, 4, (32, 64), np.random.default_rng([seed, 0, 1]), colour)
            new = sample_batch(images, depths, 4, (32, 64), np.random.default_rng([seed, 0, 1]), colour)
            cfg_aug = Augmentation(colour=colour)                   # what TrainConfig() builds
            via = sample_batch(images, depths, 4, (32, 64), np.random.default_rng([seed, 0, 1]), cfg_aug)
            for a, b, c in zip(old, new, via):
                np.testing.assert_array_equal(a, b)
                np.testing.assert_array_equal(a, c)
    from mono_map.depth.train_data import augmentation

    assert augmentation(TrainConfig()).policy == "godard" and augmentation(TrainConfig()).scale == (1.0, 1.0)


def test_scale_crop_keeps_the_focal_length_and_the_camera_height():
    """A flat road seen by the training camera (focal f, height hc): z(v) = f·hc / (v - cy). After an
    enlargement by s and a crop at (top, left), the depths must be that same road seen by the same
    camera (same f, same hc) with the principal point moved to (cy + 0.5)·s - 0.5 - top."""
    H, W, f, hc, cy = 96, 160, 120.0, 1.65, 30.0
    v = np.arange(H, dtype=np.float64)[:, None] * np.ones((1, W))
    z = np.where(v > cy + 2, f * hc / np.maximum(v - cy, 1e-9), np.inf).astype(np.float32)   # sky above
    img = np.zeros((H, W, 3), np.uint8)
    for s, top, left in ((1.25, 17, 9), (1.5, 40, 33), (1.1, 0, 0)):
        im, d = A.scale_crop(img, z, s, top, left, 64, 96)
        assert im.shape == (64, 96, 3) and d.shape == (64, 96)
        cy2 = (cy + 0.5) * s - 0.5 - top
        vv = np.arange(64, dtype=np.float64)[:, None] * np.ones((1, 96))
        road = np.isfinite(d)
        expect = f * hc / (vv - cy2)
        # nearest-neighbour sampling: within the depth change of half an input row
        rel = np.abs(d[road] - expect[road]) / expect[road]
        half_row = 0.5 * s / np.maximum(vv[road] - cy2 - 0.5 * s, 0.5)
        assert road.any() and (rel <= half_row + 1e-4).all(), s
        assert np.isinf(d[vv < cy2 - s]).all()                     # sky stays sky, above the moved horizon
    zero = np.zeros((H, W), np.float32)
    assert (A.scale_crop(img, zero, 1.3, 5, 5, 64, 96)[1] == 0).all()   # no value stays no value
    with pytest.raises(ValueError):
        A.scale_crop(img, z, 0.9, 0, 0, 64, 96)


def test_flip_and_scale_keep_targets_under_their_pixels():
    """z-depth is symmetric under a mirror about the optical axis, so a flip must move image and target
    together. The image carries the depth (×5) as its red channel: after augment_crop (flip, scale) the
    target still sits under its pixel, up to the depth change of half an input pixel."""
    H, W = 48, 80
    dep = (2.0 + 0.5 * np.arange(W, dtype=np.float32))[None, :] * np.ones((H, 1), np.float32)
    img = np.repeat(np.round(dep * 5).astype(np.uint8)[..., None], 3, -1)
    flipped = 0
    for seed in range(16):
        for aug in (Augmentation(colour=False), Augmentation(colour=False, scale=(1.1, 1.5))):
            r = np.random.default_rng(seed)
            im, d = augment_crop(img, dep, 32, 64, r, aug)
            s = 1.0
            if aug.scale != (1.0, 1.0):
                s = np.random.default_rng(seed).uniform(1.1, 1.5)
            np.testing.assert_allclose(im[..., 0] * 255 / 5, d * s, atol=0.26 + 0.1)
            flipped += int(d[0, 0] > d[0, -1])                    # depth grows to the right unless flipped
    assert 0 < flipped < 32


def test_augmentation_config_is_checked_with_one_line(tmp_path):
    validate_augmentation(TrainConfig(photometric="camera", camera_families=("blur", "jpeg"), scale=(1.0, 1.3)))
    for kw, word in ((dict(photometric="fancy"), "train.photometric"),
                     (dict(photometric="camera", camera_families=("bloom",)), "train.camera_families"),
                     (dict(camera_families=("blur",)), "train.camera_families"),
                     (dict(scale=(0.8, 1.2)), "train.scale"), (dict(scale=(1.3, 1.1)), "train.scale"),
                     (dict(scale=(1.0, math.nan)), "train.scale"), (dict(scale=(1.0,)), "train.scale"),
                     (dict(photometric="camera", camera_p_scale=0.0), "train.camera_p_scale"),
                     (dict(photometric="camera", camera_p_scale=1.5), "train.camera_p_scale")):
        with pytest.raises(MonoMapError, match=word):
            validate_augmentation(TrainConfig(**kw), "cfg")
    bad = tmp_path / "bad.toml"
    bad.write_text('[model]\nhead = "binary"\n[train]\nphotometric = "camera"\nscale = [1.0, 3.0]\n')
    with pytest.raises(MonoMapError, match=r"bad.toml: train.scale"):
        load_run_config(bad)


def test_camera_stress_scores_each_effect_against_the_clean_frames():
    """tools/camera_stress.py: the 'none' row is validate() on the frames as they are; an effect that
    changes the image changes the prediction it is scored on."""
    import torch

    from mono_map.depth.networks import DepthNet, named_config
    from mono_map.eval.validation import validate
    from tests.tool_loader import load_tool

    cs = load_tool("camera_stress")
    torch.manual_seed(0)
    model = DepthNet(named_config("small", head="binary", widths=[8, 8, 8, 8], stem_width=8, spp_width=4,
                                  decoder_widths=[8, 8, 8], num_bins=16, beyond=True))
    rng = np.random.default_rng(0)
    img = np.round(_scene(64, 96) * 255).astype(np.uint8)
    dep = np.where(rng.random((64, 96)) < 0.3, rng.uniform(2, 60, (64, 96)), 0).astype(np.float32)
    frames = [(img, dep)]
    conds = {k: cs.CONDITIONS[k] for k in ("none", "noise (shot 0.01, read 0.02)", "exposure −1.5 stops")}
    out = cs.stress(model, frames, conds)
    ref = validate(model, frames, model.cfg.head, model.cfg.bins, model.cfg.beyond)
    assert out["none"]["abs_rel"] == pytest.approx(ref["abs_rel"], rel=1e-6)
    assert out["noise (shot 0.01, read 0.02)"]["abs_rel"] != ref["abs_rel"]
    assert out["exposure −1.5 stops"]["abs_rel"] != ref["abs_rel"]
