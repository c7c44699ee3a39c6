"""The multi-view posterior (depth/multiview.py): a plane sweep over the model's bins from neighbouring frames."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from mono_map.depth.bins import DepthBins
from mono_map.depth.inference import DepthPrediction
from mono_map.depth.multiview import MultiviewConfig, MultiviewPosterior, check_multiview_config, plane_warp
from mono_map.depth.photometric import warp
from mono_map.errors import MonoMapError
from mono_map.geometry import scaled_intrinsics
from mono_map.mapping.fused import FusedConfig, check_fused_config

H, W = 64, 160
K = np.array([[120.0, 0.0, 80.0], [0.0, 120.0, 32.0], [0.0, 0.0, 1.0]])
BINS = DepthBins()
WALL = 10.0


def texture(x, y):
    """A smooth random-looking texture of world (x, y) metres, in [0, 1]."""
    rng = np.random.default_rng(3)
    t = np.zeros_like(x)
    for _ in range(12):
        fx, fy, ph = rng.uniform(2, 12), rng.uniform(2, 12), rng.uniform(0, 6.3)
        t += np.sin(fx * x + ph) * np.cos(fy * y + 2 * ph)
    return 0.5 + 0.5 * t / 12 * 3


class WallSeq:
    """A camera sliding sideways (``step`` m a frame along x) in front of a textured fronto-parallel wall at
    z = WALL; ``pose_scale`` multiplies the reported translations (wrong-scale poses); ``moving``: the wall
    moves with the camera (every image the same)."""

    def __init__(self, n=5, step=0.5, pose_scale=1.0, moving=False):
        self.n, self.step, self.pose_scale, self.moving = n, step, pose_scale, moving
        self.calib = type("Calib", (), {"K2": K})()

    def __len__(self):
        return self.n

    def T_world_cam2(self, i):
        T = np.eye(4)
        T[0, 3] = self.step * i * self.pose_scale
        return T

    def image(self, i):
        v, u = np.mgrid[0:H, 0:W].astype(np.float64)
        cx = 0.0 if self.moving else self.step * i
        x = cx + (u - K[0, 2]) / K[0, 0] * WALL
        y = (v - K[1, 2]) / K[1, 1] * WALL
        g = np.clip(texture(x, y), 0, 1)
        return (np.repeat(g[..., None], 3, -1) * 255).round().astype(np.uint8)


def flat_prediction(step=1):
    probs = np.full((BINS.num_bins, H // step, W // step), 1.0 / BINS.num_bins, np.float32)
    depth = np.full((H, W), float(np.exp(BINS.log_centres.mean())), np.float32)
    return DepthPrediction(depth=depth, entropy=np.full((H, W), np.log(BINS.num_bins), np.float32), probs=probs,
                           probs_step=step)


def modes(seq, step=1, **kw):
    r = MultiviewPosterior(MultiviewConfig(scale=1, **kw), BINS)
    q = r.refine(seq, 2, flat_prediction(step))
    return np.asarray(q.probs).argmax(0), r, q


def test_plane_warp_is_photometric_warp_at_a_constant_depth():
    rng = np.random.default_rng(0)
    src = torch.as_tensor(rng.uniform(0, 1, (1, H, W)).astype(np.float32))
    T = np.eye(4)
    T[:3, 3] = [0.4, -0.05, 0.3]
    c, s = np.cos(0.03), np.sin(0.03)
    T[:3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
    depths = np.array([3.0, 11.0])
    mine, ok = plane_warp(src, K, T, depths)
    for k, d in enumerate(depths):
        ref, ref_ok = warp(src.unsqueeze(0), torch.full((1, 1, H, W), float(d)), torch.as_tensor(K[None]).float(),
                           torch.as_tensor(T[None]).float())
        assert torch.equal(ok[k], ref_ok[0, 0])
        assert torch.allclose(mine[k][:, ok[k]], ref[0][:, ok[k]], atol=1e-3)
        assert ok[k].float().mean() > 0.5


def test_true_poses_put_the_posterior_mode_at_the_true_bin_where_the_prior_is_flat():
    mode, r, q = modes(WallSeq())
    true_bin = int(np.searchsorted(BINS.edges, WALL) - 1)
    inner = mode[8:-8, 20:-20]
    assert r.last_informative > 0.8
    assert np.mean(np.abs(inner - true_bin) <= 1) > 0.9
    # the expected depth follows the posterior (a sharp likelihood: the flat prior has no say)
    _, _, q = modes(WallSeq(), temperature=0.005)
    assert abs(float(np.median(q.depth[8:-8, 20:-20])) - WALL) < 0.1 * WALL


def test_the_likelihood_uses_metric_poses():
    """The same images with poses claiming twice the baseline put the wall twice as far."""
    mode, _, _ = modes(WallSeq(pose_scale=2.0))
    far_bin = int(np.searchsorted(BINS.edges, 2 * WALL) - 1)
    assert np.mean(np.abs(mode[8:-8, 20:-20] - far_bin) <= 1) > 0.9


def test_the_posterior_is_read_at_the_priors_pixels():
    mode, _, q = modes(WallSeq(), step=2)
    true_bin = int(np.searchsorted(BINS.edges, WALL) - 1)
    assert mode.shape == (H // 2, W // 2)
    assert np.mean(np.abs(mode[4:-4, 10:-10] - true_bin) <= 1) > 0.9


def test_a_static_camera_or_a_scene_moving_with_it_leaves_the_prior_unchanged():
    pred = flat_prediction()
    r = MultiviewPosterior(MultiviewConfig(scale=1), BINS)
    assert r.refine(WallSeq(step=0.0), 2, pred) is pred            # no neighbour with a baseline
    assert r.last_informative == 0.0
    q = r.refine(WallSeq(moving=True), 2, pred)                    # auto-masked: unwarped sources match
    assert r.last_informative < 0.05
    same = np.all(np.asarray(q.probs) == pred.probs, axis=0)
    assert same.mean() > 0.95
    # a peaked prior survives a flat likelihood: the posterior of a confident pixel keeps its mode
    probs = np.zeros_like(pred.probs)
    probs[20] = 1.0
    peaked = DepthPrediction(depth=pred.depth, entropy=pred.entropy, probs=probs, probs_step=1)
    assert np.all(np.asarray(r.refine(WallSeq(moving=True), 2, peaked).probs).argmax(0) == 20)


def test_scaled_intrinsics_keep_pixel_centres():
    Ks = scaled_intrinsics(K, (W // 4) / W, (H // 4) / H)
    # the full image's pixel u = 4j + 1.5 is the centre of reduced pixel j
    x = np.array([0.3, -0.2, 1.0])
    full = K @ x
    small = Ks @ x
    assert np.allclose(small[:2] / small[2], (full[:2] / full[2] + 0.5) / 4 - 0.5)


@pytest.mark.parametrize("kw, option", [({"sources": 3}, "--fused-multiview"),
                                        ({"temperature": 0.0}, "--fused-multiview-temperature"),
                                        ({"min_baseline": 5.0}, "--fused-multiview-min-baseline"),
                                        ({"prior_power": -1.0}, "--fused-multiview-prior-power")])
def test_bad_multiview_settings_are_one_line(kw, option):
    with pytest.raises(MonoMapError, match="^" + option) as e:
        check_multiview_config(MultiviewConfig(**kw))
    assert "\n" not in str(e.value)


@pytest.mark.parametrize("field, value, option", [("multiview", 3, "--fused-multiview"),
                                                  ("multiview", 1.5, "--fused-multiview"),
                                                  ("multiview_temperature", -1.0, "--fused-multiview-temperature")])
def test_bad_fused_multiview_settings_are_one_line(field, value, option):
    with pytest.raises(MonoMapError, match="^" + option + ":"):
        check_fused_config(FusedConfig(**{field: value}))


@pytest.mark.parametrize("power", [1.0, 2.0])
def test_the_posterior_and_its_moment_changes_are_the_definitions(power):
    """posterior_change against the definitions: q ∝ p^a·exp(ℓ) where informative (and the product has mass),
    the prior elsewhere; the change of Σ q log c and of −Σ q log q (x·log x per bin) against the prior's; bins
    with zero prior mass included."""
    from mono_map.depth.multiview import posterior_change

    rng = np.random.default_rng(int(power))
    h, w, k = 7, 9, BINS.num_bins
    p = rng.gamma(0.3, size=(h, w, k)) * (rng.random((h, w, k)) > 0.3)
    p[0, 0] = 0.0
    p[0, 0, 5] = 1.0                                           # a point mass
    p = (p / p.sum(-1, keepdims=True)).astype(np.float32)
    ll = -rng.exponential(3.0, size=(h, w, k)).astype(np.float32)
    info = rng.random((h, w)) > 0.3
    q, dm, de = posterior_change(torch.from_numpy(p), torch.from_numpy(ll), torch.from_numpy(info),
                                 BINS.log_centres, power)
    q, dm, de = q.numpy(), dm.numpy(), de.numpy()
    p64 = p.astype(np.float64)
    want = p64 ** power * np.exp(ll.astype(np.float64))
    want = np.where(info[..., None], want / want.sum(-1, keepdims=True), p64)
    assert np.abs(q - want).max() < 1e-5
    lc = np.asarray(BINS.log_centres, dtype=np.float64)

    def entropy(x):
        return -np.where(x > 0, x * np.log(np.where(x > 0, x, 1.0)), 0.0).sum(-1)
    assert np.abs(dm - (want @ lc - p64 @ lc)).max() < 1e-4
    assert np.abs(de - (entropy(want) - entropy(p64))).max() < 1e-4
    assert (dm[~info] == 0).all() and (de[~info] == 0).all() and np.array_equal(q[~info], p[~info])
    assert np.abs(de[info]).max() > 0.1                        # the test has something to compare


def test_the_compiled_sweep_gives_the_torch_forms_costs(monkeypatch):
    """csrc/sweep.c against the torch forms on the textured wall seen from two neighbours: sweep_cost (the same
    planes seen, costs within float rounding of the warp's homography — torch's matmul sums in its own order —,
    the unwarped error identical), windowed_cost (windows 1, 3, 5) and resample to a finer grid."""
    from mono_map.depth import multiview, sweep_c

    lib = sweep_c.library()
    if lib is None:
        pytest.fail("the compiled sweep did not load (compiler missing?)")
    rng = np.random.default_rng(0)
    h, w = 40, 96
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    tgt = torch.from_numpy(texture(u / 9.0, v / 7.0).astype(np.float32)).unsqueeze(0)
    srcs = [torch.from_numpy(np.clip(texture(u / 9.0 + dx, v / 7.0) + rng.normal(0, 0.01, (h, w)), 0, 1)
                             .astype(np.float32)).unsqueeze(0) for dx in (0.4, -0.3)]
    Ks = np.array([[60.0, 0.0, 48.0], [0.0, 60.0, 20.0], [0.0, 0.0, 1.0]])
    Ts = []
    for t in ([2.0, 0.0, -0.8], [-1.6, 0.05, 1.2]):
        T = np.eye(4)
        T[:3, 3] = t
        Ts.append(T)

    def both(f):
        compiled = f()
        with monkeypatch.context() as m:
            m.setattr(sweep_c, "library", lambda: None)
            return compiled, f()
    (c_c, i_c), (c_t, i_t) = both(lambda: multiview.sweep_cost(tgt, srcs, Ks, Ts, BINS.centres))
    seen = torch.isfinite(c_t)
    assert 0.2 < seen.float().mean() < 1.0                     # some planes leave a source's image
    assert torch.equal(torch.isfinite(c_c), seen)
    assert (c_c[seen] - c_t[seen]).abs().max() < 1e-3
    assert torch.equal(i_c, i_t)
    # the windowed cost and its reading at a finer grid's pixels, compiled and in torch, from the same sweep
    for window in (1, 3, 5):
        (wc, ic), (wt, it) = both(lambda: multiview.windowed_cost(c_t, i_t, window))
        assert 0.5 < it.float().mean() < 1.0 and torch.equal(ic, it)      # both kinds of pixel
        assert (wc - wt).abs().max() < 1e-6
    (rc, rt) = both(lambda: multiview.resample(wt, (h // 2 + 1, w // 2), (2 * h, 2 * w), 4))
    assert rc.shape == rt.shape == (h // 2 + 1, w // 2, len(BINS.centres))
    assert (rc - rt).abs().max() < 1e-5
