"""Depth metrics against hand-computed values; sparsification and oracle hypotheses."""

import math

import numpy as np
import pytest

from mono_map.eval.depth_metrics import distance_bands, depth_errors, garg_crop_mask, image_errors, mean_errors
from mono_map.eval.hypotheses import oracle_errors, oracle_select
from mono_map.eval.sparsification import auc, sparsification


def test_metrics_hand_computed():
    gt = np.array([10.0, 20.0])
    pred = np.array([12.0, 10.0])
    e = depth_errors(gt, pred)
    assert e["abs_rel"] == pytest.approx((0.2 + 0.5) / 2)
    assert e["sq_rel"] == pytest.approx((4 / 10 + 100 / 20) / 2)
    assert e["rmse"] == pytest.approx(math.sqrt((4 + 100) / 2))
    assert e["rmse_log"] == pytest.approx(math.sqrt((math.log(1.2) ** 2 + math.log(2) ** 2) / 2))
    assert e["log10"] == pytest.approx((math.log10(1.2) + math.log10(2)) / 2)
    assert e["a1"] == 0.5 and e["a2"] == 0.5 and e["a3"] == 0.5  # ratios 1.2 and 2.0 (> 1.25³ = 1.95)
    assert depth_errors(np.array([10.0]), np.array([19.0]))["a3"] == 1.0  # 1.9 < 1.95


def test_image_errors_mask_cap_and_crop():
    gt = np.zeros((10, 20))
    gt[5, 5] = 10.0
    gt[6, 6] = 90.0  # beyond the 80 m cap: ignored
    pred = np.full((10, 20), 11.0)
    e = image_errors(gt, pred)
    assert e["abs_rel"] == pytest.approx(0.1)
    m = garg_crop_mask(100, 200)
    assert not m[0].any() and m[60, 100] and not m[:, 0].any()
    assert mean_errors([e, image_errors(np.zeros((3, 3)), pred[:3, :3])])["abs_rel"] == pytest.approx(0.1)


def test_distance_bands_hand_computed():
    """Each band [lo, hi) of ground truth (the last one closed): its share, the median of pred / gt, its AbsRel;
    an empty band says so."""
    gt = np.array([3.0, 7.0, 7.0, 9.0, 15.0, 80.0])
    pred = np.array([3.3, 7.0, 3.5, 18.0, 15.0, 40.0])
    b = distance_bands(gt, pred)
    assert [(x["lo"], x["hi"]) for x in b] == [(0, 5), (5, 10), (10, 20), (20, 40), (40, 80)]
    assert [x["n_pixels"] for x in b] == [1, 3, 1, 0, 1]                     # 80 m counts in the last band
    assert sum(x["share"] for x in b) == pytest.approx(1.0) and b[1]["share"] == pytest.approx(0.5)
    assert b[0]["median_ratio"] == pytest.approx(1.1) and b[0]["abs_rel"] == pytest.approx(0.1)
    assert b[1]["median_ratio"] == pytest.approx(1.0)                          # ratios 1, 0.5, 2
    assert b[1]["abs_rel"] == pytest.approx((0 + 0.5 + 1.0) / 3)
    assert b[3]["median_ratio"] is None and b[3]["abs_rel"] is None
    assert b[4]["median_ratio"] == pytest.approx(0.5)


def test_sparsification_oracle_below_model_below_random():
    rng = np.random.default_rng(1)
    n = 20000
    gt = rng.uniform(2, 60, n)
    noise_scale = rng.uniform(0.01, 0.4, n)
    pred = gt * np.exp(rng.normal(0, noise_scale))
    informative = sparsification(gt, pred, noise_scale)       # uncertainty tracks the error scale
    uninformative = sparsification(gt, pred, rng.random(n))
    for k in ("are", "rmse", "1-d1"):
        assert informative["auc_oracle"][k] <= informative["auc"][k] + 1e-12
        assert informative["auc"][k] < uninformative["auc"][k]
        assert informative["auc_oracle"][k] <= informative["auc_random"][k]
        # at 100 % every ordering gives the overall value
        assert informative["model"][k][-1] == pytest.approx(informative["random"][k][-1])
    assert informative["model"]["are"][-1] == pytest.approx(np.mean(np.abs(pred - gt) / gt))


def test_auc_of_constant_curve():
    fr = np.arange(1, 11) / 10
    assert auc(fr, np.full(10, 3.0)) == pytest.approx(3.0)


def test_oracle_hypotheses():
    gt = np.array([10.0, 20.0, 5.0])
    hyp = np.array([[12.0, 40.0, 5.0], [9.5, 21.0, 50.0], [30.0, 20.0, 4.0]])
    np.testing.assert_allclose(oracle_select(gt, hyp), [9.5, 20.0, 5.0])
    res = oracle_errors(gt, hyp, ms=(1, 2, 3))
    assert res[1]["abs_rel"] == pytest.approx((0.2 + 1.0 + 0.0) / 3)
    assert res[3]["abs_rel"] <= res[2]["abs_rel"] <= res[1]["abs_rel"]
    assert res[3]["abs_rel"] == pytest.approx(0.05 / 3)
