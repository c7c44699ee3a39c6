"""Checkpoints: round trip, and clear MonoMapErrors for missing, corrupt or mismatched files."""

import numpy as np
import pytest
import torch

from mono_map.depth.inference import DepthPredictor, default_precision, fit_size, load_checkpoint, save_checkpoint
from mono_map.depth.networks import DepthNet, named_config
from mono_map.errors import MonoMapError


TINY = dict(widths=(8, 8, 8, 8), stem_width=8, spp_width=4, decoder_widths=(8, 8, 8),
            num_bins=16, input_height=64, input_width=128)


@pytest.fixture
def ckpt(tmp_path):
    torch.manual_seed(0)
    net = DepthNet(named_config("small", **TINY))
    path = tmp_path / "m.pt"
    save_checkpoint(path, net, {"step": 3})
    return path, net


def test_round_trip_and_prediction(ckpt):
    path, net = ckpt
    model, payload = load_checkpoint(path)
    assert payload["training"]["step"] == 3
    for a, b in zip(model.state_dict().values(), net.state_dict().values()):
        assert torch.equal(a, b)
    pred = DepthPredictor.load(path)
    img = (np.random.default_rng(0).random((75, 250, 3)) * 255).astype(np.uint8)
    p = pred.predict(img, with_probs=True)
    assert p.depth.shape == (75, 250) and p.probs.shape == (16, 75, 250)
    assert p.depth.dtype == np.float32 and np.all(p.depth >= 1.0) and np.all(p.depth <= 80.0)
    np.testing.assert_allclose(p.probs.sum(0), 1.0, rtol=1e-4)
    batch = pred.predict_batch([img, img])
    np.testing.assert_allclose(batch[0].depth, p.depth, rtol=1e-4)
    assert fit_size(376, 1241, 192, 640) == (192, 634)


def test_missing_and_corrupt(tmp_path, ckpt):
    with pytest.raises(MonoMapError, match="not found"):
        load_checkpoint(tmp_path / "nope.pt")
    bad = tmp_path / "corrupt.pt"
    bad.write_bytes(ckpt[0].read_bytes()[:5000])
    with pytest.raises(MonoMapError, match="corrupt.pt"):
        DepthPredictor.load(bad)
    junk = tmp_path / "junk.pt"
    torch.save({"hello": 1}, junk)
    with pytest.raises(MonoMapError, match="junk.pt.*format"):
        load_checkpoint(junk)


def test_mismatched_weights_and_bins(tmp_path, ckpt):
    path, net = ckpt
    payload = torch.load(path, weights_only=True)
    payload["model_config"]["head"] = "gaussian"  # head with 2 output maps, weights have 16
    torch.save(payload, tmp_path / "wrong_head.pt")
    with pytest.raises(MonoMapError, match="wrong_head.pt.*do not match"):
        load_checkpoint(tmp_path / "wrong_head.pt")
    payload = torch.load(path, weights_only=True)
    payload["bins"]["max_depth"] = 100.0
    torch.save(payload, tmp_path / "wrong_bins.pt")
    with pytest.raises(MonoMapError, match="wrong_bins.pt.*bins"):
        load_checkpoint(tmp_path / "wrong_bins.pt")


def test_default_precision_reads_the_cpu_flags(monkeypatch):
    """bfloat16 where the CPU has AMX or AVX-512 BF16 instructions, fp32 otherwise (also for a flag that only
    contains the name, e.g. 'avx512_bf16x'); $MONO_MAP_PRECISION overrides."""
    monkeypatch.delenv("MONO_MAP_PRECISION", raising=False)
    info = "processor\t: 0\nflags\t\t: fpu sse2 avx2 avx512f {}\nbugs\t\t: none\n"
    assert default_precision(info.format("amx_bf16 amx_tile")) == "bf16"
    assert default_precision(info.format("avx512_bf16")) == "bf16"
    assert default_precision(info.format("avx512_bf16x")) == "fp32"
    assert default_precision(info.format("")) == "fp32"
    monkeypatch.setenv("MONO_MAP_PRECISION", "fp32")
    assert default_precision(info.format("amx_bf16")) == "fp32"


def test_every_shipped_checkpoint_is_found_by_name_and_loads():
    from mono_map.depth.inference import DepthPredictor, default_checkpoint, shipped_names

    names = shipped_names()
    assert names[0] == "binary" and "v2/softmax" in names and "v1/ordinal" in names
    assert len({default_checkpoint(n).read_bytes() for n in names}) == len(names)   # each file once
    for name in names:
        p = DepthPredictor.load(name)
        run = name.split("/")[-1]                 # a head ("softmax") or a run of one ("mhl-3", "binary-k32")
        assert default_checkpoint(name).is_file() and (run == p.head or run.startswith(p.head + "-")), name


@pytest.mark.parametrize("fast", [True, False])
@pytest.mark.parametrize("step", [2, 3])
def test_probabilities_sampled_every_step_pixels_are_the_full_maps_there(ckpt, fast, step):
    """``probs_step``: only the sampled pixels are interpolated (channels last), the same values to float
    rounding as the full-resolution maps there; depth and the other maps unchanged."""
    path, _ = ckpt
    pred = DepthPredictor.load(path, fast=fast)
    img = (np.random.default_rng(1).random((75, 250, 3)) * 255).astype(np.uint8)
    full = pred.predict(img, with_probs=True)
    grid = pred.predict(img, with_probs=True, probs_step=step)
    assert full.probs_step == 1 and grid.probs_step == step
    assert grid.probs.shape == (16, -(-75 // step), -(-250 // step))
    assert np.moveaxis(grid.probs, 0, -1).flags.c_contiguous           # one pixel's bins side by side
    np.testing.assert_allclose(grid.probs, full.probs[:, ::step, ::step], rtol=0, atol=1e-6)
    assert np.array_equal(grid.depth, full.depth) and np.array_equal(grid.p_beyond, full.p_beyond)
    with pytest.raises(MonoMapError, match="probs_step"):
        pred.predict(img, with_probs=True, probs_step=0)


def test_bilinear_taps_are_torch_interpolation():
    from mono_map.depth.inference import bilinear_taps

    src = torch.arange(7, dtype=torch.float32) ** 2
    want = torch.nn.functional.interpolate(src.view(1, 1, 1, 7), size=(1, 19), mode="bilinear",
                                           align_corners=False).view(-1)
    i0, i1, w = bilinear_taps(7, 19, 1)
    np.testing.assert_allclose(torch.lerp(src[i0], src[i1], w).numpy(), want.numpy(), rtol=1e-6)
    i0, i1, w = bilinear_taps(7, 19, 4)
    np.testing.assert_allclose(torch.lerp(src[i0], src[i1], w).numpy(), want[::4].numpy(), rtol=1e-6)
