"""Every head's loss decreases when overfitting one image; decoding gives sane outputs."""

import numpy as np
import pytest
import torch

from mono_map.depth.heads import HEADS, decode
from mono_map.depth.losses import head_loss
from mono_map.depth.networks import DepthNet, named_config


TINY = dict(widths=(8, 8, 8, 8), stem_width=8, spp_width=4, decoder_widths=(8, 8, 8),
            num_bins=16, input_height=64, input_width=128, mc_samples=4)


def _image_and_depth():
    g = torch.Generator().manual_seed(0)
    x = torch.rand(1, 3, 32, 96, generator=g)
    rows = torch.linspace(3.0, 40.0, 32).view(32, 1).expand(32, 96)
    depth = rows.clone()
    depth[:, :30] = 6.0  # a near "wall" on the left
    x[:, :, :, :30] *= 0.3
    depth[::3] = 0.0  # missing LiDAR rows: must be ignored
    return x, depth.unsqueeze(0)


@pytest.mark.parametrize("head", sorted(HEADS))
def test_loss_decreases_when_overfitting_one_image(head):
    torch.manual_seed(0)
    net = DepthNet(named_config("small", head=head, **TINY))
    bins = net.cfg.bins
    opt = torch.optim.Adam(net.parameters(), lr=3e-3)
    x, y = _image_and_depth()
    losses = []
    for _ in range(25):
        loss = head_loss(net.head, net(x), y, bins)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert np.isfinite(losses).all()
    assert np.mean(losses[-5:]) < 0.8 * np.mean(losses[:3]), losses
    net.eval()
    with torch.no_grad():
        out = net(x, mc_samples=net.cfg.mc_samples if net.head.dropout else 0)
    if net.head.dropout:
        assert out.shape[0] == net.cfg.mc_samples
    res = decode(net.head, out, bins, with_probs=True)
    assert res["depth"].shape == (1, 32, 96)
    assert torch.all(res["depth"] >= bins.min_depth - 1e-4) and torch.all(res["depth"] <= bins.max_depth + 1e-3)
    assert torch.isfinite(res["entropy"]).all()
    if res["probs"] is not None:
        np.testing.assert_allclose(res["probs"].sum(1).numpy(), 1.0, rtol=1e-4)


def test_invalid_pixels_do_not_contribute():
    bins = named_config("small", **TINY).bins
    out = torch.randn(1, 16, 4, 4, requires_grad=True)
    depth = torch.zeros(1, 4, 4)
    depth[0, 0, 0] = 10.0
    head_loss("binary", out, depth, bins).backward()
    g = out.grad.abs().sum(1)[0]
    assert g[0, 0] > 0 and g.sum() == g[0, 0]
