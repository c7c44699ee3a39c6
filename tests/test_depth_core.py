"""Bins, soft targets and distribution statistics (paper Sec. III)."""

import math

import numpy as np
import pytest
import torch

from mono_map.depth import distribution as dist
from mono_map.depth.bins import DepthBins
from mono_map.depth.losses import soft_target
from mono_map.errors import MonoMapError


BINS = DepthBins(64, 1.0, 80.0)


def test_bin_formula_matches_paper_eq1():
    k = np.arange(1, 65)
    d_paper = math.log(1.0) + (k - 1) / 64 * (math.log(80.0) - math.log(1.0))  # Eq. 1, k = 1..K
    np.testing.assert_allclose(BINS.log_edges[:-1], d_paper, atol=1e-12)
    assert BINS.edges[0] == pytest.approx(1.0) and BINS.edges[-1] == pytest.approx(80.0)
    # centres: log midpoints, strictly inside their bins
    assert np.all(BINS.centres > BINS.edges[:-1]) and np.all(BINS.centres < BINS.edges[1:])
    np.testing.assert_allclose(BINS.centres, np.sqrt(BINS.edges[:-1] * BINS.edges[1:]))


def test_continuous_index_roundtrip_and_clipping():
    d = np.array([1.0, 2.5, 10.0, 79.0])
    np.testing.assert_allclose(BINS.index_to_depth(BINS.continuous_index(d)), d, rtol=1e-9)
    np.testing.assert_allclose(BINS.continuous_index(BINS.centres), np.arange(64), atol=1e-9)
    assert BINS.continuous_index(np.array([0.1]))[0] == pytest.approx(-0.5)
    assert BINS.continuous_index(np.array([500.0]))[0] == pytest.approx(63.5)
    t = torch.tensor([3.0, 30.0], dtype=torch.float64)
    np.testing.assert_allclose(BINS.continuous_index(t).numpy(), BINS.continuous_index(t.numpy()))


def test_bad_bins_raise():
    with pytest.raises(MonoMapError):
        DepthBins(64, 5.0, 1.0)


@pytest.mark.parametrize("bins", [BINS, DepthBins(100, 0.5, 80.0), DepthBins(32, 1.0, 80.0)])
def test_soft_target_25_percent_property(bins):
    """Bins whose centre is within 25 % of the true depth get q̃ > 0.5, the others <= 0.5."""
    depths = torch.tensor(np.exp(np.linspace(np.log(2 * bins.min_depth), np.log(bins.max_depth / 2), 97)))
    q = soft_target(depths.view(-1, 1, 1), bins)[:, :, 0, 0].numpy()  # (N, K)
    c = bins.centres[None, :]
    ratio = np.maximum(c / depths.numpy()[:, None], depths.numpy()[:, None] / c)
    inside = ratio < 1.25 - 1e-9
    outside = ratio > 1.25 + 1e-9
    assert inside.sum() > 2 * len(depths)  # several bins inside for every depth
    assert np.all(q[inside] > 0.5)
    assert np.all(q[outside] <= 0.5)
    # peak value 1 at the true bin centre
    q0 = soft_target(torch.tensor(bins.centres[10]).view(1, 1, 1), bins)[0, :, 0, 0]
    assert q0.argmax().item() == 10 and q0.max().item() == pytest.approx(1.0)


def test_entropy_one_hot_and_uniform():
    one_hot = torch.zeros(1, 64, 2, 3)
    one_hot[:, 17] = 1
    assert dist.entropy(one_hot).abs().max().item() < 1e-6
    uniform = torch.full((1, 64, 2, 3), 1 / 64)
    np.testing.assert_allclose(dist.entropy(uniform).numpy(), math.log(64), rtol=1e-6)


def test_entropy_of_logits_is_the_entropy_of_their_softmax():
    logits = torch.randn(2, 64, 3, 4, generator=torch.Generator().manual_seed(0)) * 3
    np.testing.assert_allclose(dist.entropy_of_logits(logits).numpy(),
                               dist.entropy(torch.softmax(logits, 1)).numpy(), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(dist.entropy_of_logits(torch.zeros(1, 64, 1, 1)).numpy(), math.log(64), rtol=1e-6)


def test_expected_depth_of_peaked_distribution_is_its_bin():
    logits = torch.full((2, 64, 4, 5), -50.0)
    logits[0, 20] = 50.0
    logits[1, 55] = 50.0
    p = dist.probs_from_logits(logits)
    for space in ("log", "linear"):
        d = dist.expected_depth(p, BINS, space)
        np.testing.assert_allclose(d[0].numpy(), BINS.centres[20], rtol=1e-5)
        np.testing.assert_allclose(d[1].numpy(), BINS.centres[55], rtol=1e-5)
    np.testing.assert_allclose(dist.argmax_depth(p, BINS)[1].numpy(), BINS.centres[55], rtol=1e-6)


def test_log_expectation_is_at_most_linear():
    p = dist.probs_from_logits(torch.randn(1, 64, 3, 3))
    assert torch.all(dist.expected_depth(p, BINS, "log") <= dist.expected_depth(p, BINS, "linear") + 1e-4)


def test_modes_of_bimodal_distribution():
    k = torch.arange(64, dtype=torch.float32).view(1, -1, 1, 1)
    p = 0.7 * torch.exp(-0.5 * ((k - 12) / 2) ** 2) + 0.3 * torch.exp(-0.5 * ((k - 45) / 2) ** 2)
    p = (p / p.sum(1, keepdim=True)).expand(2, 64, 3, 4).contiguous()
    depths, probs = dist.top_modes(p, BINS, 3)
    assert depths.shape == (2, 3, 3, 4)
    np.testing.assert_allclose(depths[:, 0].numpy(), BINS.centres[12], rtol=1e-6)
    np.testing.assert_allclose(depths[:, 1].numpy(), BINS.centres[45], rtol=1e-6)
    # only two modes: the third repeats the best one
    np.testing.assert_allclose(depths[:, 2].numpy(), BINS.centres[12], rtol=1e-6)
    assert torch.all(probs[:, 0] > probs[:, 1])


def test_gaussian_and_ordinal_probs_are_distributions():
    mean = torch.full((1, 2, 2), math.log(10.0))
    p = dist.gaussian_to_probs(mean, torch.full((1, 2, 2), math.log(0.01)), BINS)
    np.testing.assert_allclose(p.sum(1).numpy(), 1.0, rtol=1e-5)
    assert abs(dist.argmax_depth(p, BINS)[0, 0, 0].item() / 10.0 - 1) < 0.07
    o = dist.ordinal_to_probs(torch.randn(1, 63, 2, 2))
    np.testing.assert_allclose(o.sum(1).numpy(), 1.0, rtol=1e-5)
    assert o.shape == (1, 64, 2, 2) and torch.all(o >= 0)
