"""The oracle stand-in's errors: independent per pixel, or shared by the views (fixed in the world)."""

from __future__ import annotations

import numpy as np
import pytest

from mono_map.data.kitti import open_sequence
from mono_map.errors import MonoMapError
from mono_map.eval.shared_error import common_surface_pixels, log_errors, shared_share
from mono_map.mapping.oracle import NoisyGroundTruthPredictor


def test_shared_field_is_smooth_with_the_asked_scale():
    o = NoisyGroundTruthPredictor(shared_sigma=0.1, shared_wavelength=10.0)
    x = np.random.default_rng(1).uniform(-500, 500, (100_000, 3))
    f = o.shared_field(x)
    assert 0.09 < f.std() < 0.11 and abs(f.mean()) < 0.005
    assert np.corrcoef(f, o.shared_field(x + [0.2, 0, 0]))[0, 1] > 0.99          # smooth over a cell
    assert abs(np.corrcoef(f, o.shared_field(x + [0, 30, 0]))[0, 1]) < 0.2      # not one offset everywhere
    assert np.array_equal(f, NoisyGroundTruthPredictor(shared_sigma=0.1).shared_field(x))   # fixed by the seed


def log_errors_at_common_points(seq, oracle, i, j):
    """Log-depth errors of the oracle at the pixels of frames i and j that see one surface point."""
    pi, pj = common_surface_pixels(seq, i, j)
    return (log_errors(oracle.predict_frame(seq, i).depth, seq.depth(i), pi),
            log_errors(oracle.predict_frame(seq, j).depth, seq.depth(j), pj))


def test_shared_error_is_the_same_for_a_surface_point_in_every_view(tiny_root):
    seq = open_sequence(tiny_root, "tiny")
    shared = NoisyGroundTruthPredictor(sigma=1e-6, edge_sigma=0.0, shared_sigma=0.1)
    a, b = log_errors_at_common_points(seq, shared, 0, 2)
    assert len(a) > 200 and a.std() > 0.03
    assert np.max(np.abs(a - b)) < 0.01                       # the views share it
    assert shared_share(a, b)["correlation"] > 0.99
    independent = NoisyGroundTruthPredictor(sigma=0.1, edge_sigma=0.0)
    a, b = log_errors_at_common_points(seq, independent, 0, 2)
    s = shared_share(a, b)
    assert abs(s["correlation"]) < 0.1 and s["rms_difference"] > 0.12 and 0.09 < s["rms"] < 0.11   # not shared


def test_common_surface_pixels_see_one_point(tiny_root):
    """The pixels paired by the ground truth are one surface point: back-projected, they coincide (to the depth
    tolerance and the sub-pixel offset); occluded points are not paired."""
    from mono_map.mapping.points import pixel_points_to_world

    seq = open_sequence(tiny_root, "tiny")
    pi, pj = common_surface_pixels(seq, 1, 3)
    assert len(pi) > 500
    xi = pixel_points_to_world(pi[:, 1], pi[:, 0], seq.depth(1)[pi[:, 0], pi[:, 1]], seq.calib.K2, seq.T_world_cam2(1))
    xj = pixel_points_to_world(pj[:, 1], pj[:, 0], seq.depth(3)[pj[:, 0], pj[:, 1]], seq.calib.K2, seq.T_world_cam2(3))
    assert np.percentile(np.linalg.norm(xi - xj, axis=1), 99) < 0.05
    same = common_surface_pixels(seq, 2, 2)[0]
    assert len(same) == np.count_nonzero(seq.depth(2) > 0)      # a frame with itself: every pixel


def test_shared_error_is_in_the_claimed_spread(tiny_root):
    seq = open_sequence(tiny_root, "tiny")
    o = NoisyGroundTruthPredictor(sigma=0.02, edge_sigma=0.0, shared_sigma=0.05)
    p = o.predict_frame(seq, 1, with_probs=True, probs_step=2)
    smooth = seq.depth(1) > 0
    claimed = np.sqrt(0.02 ** 2 + 0.05 ** 2)
    assert np.allclose(p.entropy[smooth], 0.5 * np.log(2 * np.pi * np.e * claimed ** 2), atol=1e-4)
    assert p.probs is not None and np.isfinite(p.probs).all()


@pytest.mark.parametrize("kw", [dict(shared_sigma=-0.1), dict(shared_sigma=1.5), dict(sigma=np.nan), dict(sigma=0.0),
                                dict(shared_wavelength=0.0), dict(edge_sigma=2.0)])
def test_bad_oracle_settings_are_one_line(kw):
    with pytest.raises(MonoMapError, match="oracle"):
        NoisyGroundTruthPredictor(**kw)
