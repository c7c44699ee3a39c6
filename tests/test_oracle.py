"""The oracle stand-in's errors: independent per pixel, or shared by the views (fixed in the world)."""

from __future__ import annotations

import numpy as np
import pytest

from mono_map.data.kitti import open_sequence
from mono_map.errors import MonoMapError
from mono_map.geometry import pose_inverse, project_points, transform_points
from mono_map.mapping.oracle import NoisyGroundTruthPredictor
from mono_map.mapping.points import pixels_to_world


def test_shared_field_is_smooth_with_the_asked_scale():
    o = NoisyGroundTruthPredictor(shared_sigma=0.1, shared_wavelength=10.0)
    x = np.random.default_rng(1).uniform(-500, 500, (100_000, 3))
    f = o.shared_field(x)
    assert 0.09 < f.std() < 0.11 and abs(f.mean()) < 0.005
    assert np.corrcoef(f, o.shared_field(x + [0.2, 0, 0]))[0, 1] > 0.99          # smooth over a cell
    assert abs(np.corrcoef(f, o.shared_field(x + [0, 30, 0]))[0, 1]) < 0.2      # not one offset everywhere
    assert np.array_equal(f, NoisyGroundTruthPredictor(shared_sigma=0.1).shared_field(x))   # fixed by the seed


def log_errors_at_common_points(seq, oracle, i, j):
    """Log-depth errors of frame i's pixels and of the frame-j pixels seeing the same surface point (its
    projection into j within 0.1 px of a pixel centre, its depth there within 1 cm)."""
    gi, gj = seq.depth(i), seq.depth(j)
    with np.errstate(divide="ignore"):          # log 0 where there is no surface: never read
        ei = np.log(oracle.predict_frame(seq, i).depth / np.where(gi > 0, gi, 1))
        ej = np.log(oracle.predict_frame(seq, j).depth / np.where(gj > 0, gj, 1))
    mask = gi > 0
    pts = pixels_to_world(gi, mask, seq.calib.K2, seq.T_world_cam2(i))
    uv, z = project_points(seq.calib.K2, transform_points(pose_inverse(seq.T_world_cam2(j)), pts))
    ok = np.isfinite(uv).all(axis=1)
    r = np.rint(uv[ok]).astype(int)
    near = (np.abs(uv[ok] - r) < 0.1).all(axis=1)
    h, w = gj.shape
    inside = near & (r[:, 0] >= 0) & (r[:, 0] < w) & (r[:, 1] >= 0) & (r[:, 1] < h)
    idx = np.flatnonzero(ok)[inside]
    r = r[inside]
    same = np.abs(gj[r[:, 1], r[:, 0]] - z[idx]) < 0.01
    return ei[mask][idx[same]], ej[r[same, 1], r[same, 0]]


def test_shared_error_is_the_same_for_a_surface_point_in_every_view(tiny_root):
    seq = open_sequence(tiny_root, "tiny")
    shared = NoisyGroundTruthPredictor(sigma=1e-6, edge_sigma=0.0, shared_sigma=0.1)
    a, b = log_errors_at_common_points(seq, shared, 0, 2)
    assert len(a) > 200 and a.std() > 0.03
    assert np.max(np.abs(a - b)) < 0.01                       # the views share it
    independent = NoisyGroundTruthPredictor(sigma=0.1, edge_sigma=0.0)
    a, b = log_errors_at_common_points(seq, independent, 0, 2)
    assert abs(np.corrcoef(a, b)[0, 1]) < 0.2 and np.mean(np.abs(a - b)) > 0.05   # these are not shared


def test_shared_error_is_in_the_claimed_spread(tiny_root):
    seq = open_sequence(tiny_root, "tiny")
    o = NoisyGroundTruthPredictor(sigma=0.02, edge_sigma=0.0, shared_sigma=0.05)
    p = o.predict_frame(seq, 1, with_probs=True, probs_step=2)
    smooth = seq.depth(1) > 0
    claimed = np.sqrt(0.02 ** 2 + 0.05 ** 2)
    assert np.allclose(p.entropy[smooth], 0.5 * np.log(2 * np.pi * np.e * claimed ** 2), atol=1e-4)
    assert p.probs is not None and np.isfinite(p.probs).all()


@pytest.mark.parametrize("kw", [dict(shared_sigma=-0.1), dict(shared_sigma=1.5), dict(sigma=np.nan),
                                dict(shared_wavelength=0.0), dict(edge_sigma=2.0)])
def test_bad_oracle_settings_are_one_line(kw):
    with pytest.raises(MonoMapError, match="oracle"):
        NoisyGroundTruthPredictor(**kw)
