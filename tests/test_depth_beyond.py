"""Beyond-range (sky) supervision: every head learns to say "no surface within the bin range"."""

import math

import pytest
import torch

from mono_map.depth.bins import DepthBins
from mono_map.depth.heads import HEADS, decode, get_head
from mono_map.depth.losses import head_loss

BINS = DepthBins(16, 1.0, 80.0)


def _fit(head_name: str, target: torch.Tensor, steps: int = 300) -> dict:
    """Optimise a free (1,C,H,W) output against a target depth map; decode it."""
    head = get_head(head_name)
    torch.manual_seed(0)
    out = torch.zeros(1, head.out_channels(BINS, beyond=True), *target.shape[-2:], requires_grad=True)
    with torch.no_grad():
        out.normal_(0, 0.1)
    opt = torch.optim.Adam([out], lr=0.1)
    for _ in range(steps):
        loss = head_loss(head, out, target, BINS, beyond=True)
        opt.zero_grad()
        loss.backward()
        opt.step()
    return decode(head, out.detach(), BINS, beyond=True)


@pytest.mark.parametrize("name", sorted(HEADS))
def test_sky_pixel_trains_towards_beyond_and_surface_pixel_away(name):
    target = torch.tensor([[[math.inf, 10.0]]])           # pixel 0 sky, pixel 1 a surface at 10 m
    r = _fit(name, target)
    assert r["p_beyond"][0, 0, 0] > 0.9
    assert r["p_beyond"][0, 0, 1] < 0.1
    if get_head(name).kind != "regression":
        assert abs(float(r["depth"][0, 0, 1]) - 10.0) < 2.0


def test_depth_beyond_max_depth_counts_as_no_surface():
    r = _fit("softmax", torch.tensor([[[200.0, 5.0]]]))
    assert r["p_beyond"][0, 0, 0] > 0.9 and r["p_beyond"][0, 0, 1] < 0.1


def test_binary_beyond_means_all_labels_off():
    """For the multi-label head "beyond" is no bin firing: every sigmoid is pushed to 0."""
    head = get_head("binary")
    out = torch.zeros(1, BINS.num_bins, 1, 1, requires_grad=True)
    head_loss(head, out, torch.tensor([[[math.inf]]]), BINS, beyond=True).backward()
    assert (out.grad > 0).all()          # d BCE / d logit = sigmoid - 0 > 0 for every bin
    out.grad = None
    head_loss(head, out, torch.tensor([[[10.0]]]), BINS, beyond=True).backward()
    assert (out.grad < 0).any() and (out.grad > 0).any()


def test_without_beyond_p_beyond_is_zero_and_sky_is_clipped():
    head = get_head("softmax")
    out = torch.randn(1, head.out_channels(BINS), 2, 2)
    assert head.out_channels(BINS) == BINS.num_bins
    assert head.out_channels(BINS, beyond=True) == BINS.num_bins + 1
    r = decode(head, out, BINS)
    assert torch.equal(r["p_beyond"], torch.zeros(1, 2, 2))
    assert torch.isfinite(head_loss(head, out, torch.full((1, 2, 2), math.inf), BINS))


def test_bin_probabilities_sum_to_one_given_a_surface():
    for name in ("binary", "softmax", "ordinal", "gaussian"):
        head = get_head(name)
        out = torch.randn(1, head.out_channels(BINS, beyond=True), 3, 3)
        r = decode(head, out, BINS, with_probs=True, beyond=True)
        torch.testing.assert_close(r["probs"].sum(1), torch.ones(1, 3, 3), atol=1e-4, rtol=0)
        assert ((r["p_beyond"] >= 0) & (r["p_beyond"] <= 1)).all()


def test_mc_dropout_samples_average_p_beyond():
    head = get_head("binary-dropout")
    out = torch.randn(5, 1, head.out_channels(BINS, beyond=True), 2, 2)
    r = decode(head, out, BINS, beyond=True)
    each = torch.stack([decode(head, out[s], BINS, beyond=True)["p_beyond"] for s in range(5)]).mean(0)
    torch.testing.assert_close(r["p_beyond"], each)
