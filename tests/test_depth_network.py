"""Hand-written ResNet blocks match the standard architectures; output shapes and MC sampling."""

import pytest
import torch

from mono_map.depth.networks import DepthNet, ResNetEncoder, named_config
from mono_map.errors import MonoMapError


def _params(m):
    return sum(p.numel() for p in m.parameters())


def test_encoders_have_the_standard_parameter_counts():
    # torchvision resnet50 / resnet18 without the final fc layer: 23,508,032 and 11,176,512
    assert _params(ResNetEncoder(named_config("paper-resnet50"))) == 23_508_032
    r18 = named_config("small", layers=(2, 2, 2, 2), widths=(64, 128, 256, 512), stem_width=64)
    assert _params(ResNetEncoder(r18)) == 11_176_512


def test_small_net_shapes_and_strides():
    cfg = named_config("small")
    net = DepthNet(cfg).eval()
    assert _params(net) < 2_000_000
    x = torch.rand(1, 3, 64, 192)
    with torch.no_grad():
        full = net(x)
        low = net(x, upsample=False)
    assert full.shape == (1, 64, 64, 192) and low.shape == (1, 64, 16, 48)
    feats = net.encoder(x)
    assert [f.shape[-1] for f in feats] == [96, 48, 24, 12, 6]


def test_mc_dropout_samples_differ_and_plain_heads_are_deterministic():
    torch.manual_seed(0)
    net = DepthNet(named_config("small", head="binary-dropout", widths=(8, 8, 8, 8), stem_width=8,
                                decoder_widths=(8, 8, 8), spp_width=4)).eval()
    with torch.no_grad():
        s = net(torch.rand(1, 3, 32, 64), mc_samples=3, upsample=False)
    assert s.shape[0] == 3 and not torch.allclose(s[0], s[1])
    assert not net.tail.training  # eval mode restored


def test_unknown_architecture_or_head():
    with pytest.raises(MonoMapError, match="architecture"):
        named_config("resnet-9000")
    with pytest.raises(MonoMapError, match="head"):
        named_config("small", head="mystery")
    with pytest.raises(MonoMapError, match="input_height: must be a multiple of 32"):
        named_config("small", input_height=100)


def test_mc_dropout_predictions_repeat_and_leave_the_callers_rng_alone():
    """An MC-dropout predictor gives an image the same prediction every time (seeded masks), unlike an
    unseeded draw, and does not advance the global torch RNG."""
    import dataclasses

    import numpy as np

    from mono_map.depth.inference import DepthPredictor

    torch.manual_seed(0)
    cfg = named_config("small", head="gaussian-dropout", widths=(8, 8, 8, 8), stem_width=8,
                       decoder_widths=(8, 8, 8), spp_width=4, mc_samples=4)
    pred = DepthPredictor(DepthNet(cfg).eval())
    img = (np.random.default_rng(0).random((40, 100, 3)) * 255).astype(np.uint8)
    state = torch.random.get_rng_state()
    a, b = pred.predict(img), pred.predict(img)
    assert torch.equal(torch.random.get_rng_state(), state)
    assert np.array_equal(a.depth, b.depth) and np.array_equal(a.entropy, b.entropy)
    x = torch.rand(1, 3, 64, 128)
    with torch.no_grad():                                    # the network alone: random masks every call
        assert not torch.equal(pred.model(x, mc_samples=4), pred.model(x, mc_samples=4))
    pred.cfg = dataclasses.replace(pred.cfg, mc_samples=0)  # dropout off: the deterministic network
    assert not np.array_equal(pred.predict(img).entropy, a.entropy)
