"""Fused integration (``--integrate fused``): a thin surface fused across views + the distribution's free space."""

from __future__ import annotations

import numpy as np
import pytest

from mono_map.config import OctoMapConfig
from mono_map.depth.bins import DepthBins
from mono_map.depth.inference import DepthPrediction
from mono_map.errors import MonoMapError
from mono_map.mapping.jobs import MapJob
from mono_map.mapping.pipeline import build_map
from mono_map.mapping.distribution import DistributionConfig
from mono_map.mapping.fused import FusedConfig, SurfaceFusion, check_fused_config, log_spread, mode_shift, pixel_weights
from mono_map.mapping.fused_frames import due_surface_points
from mono_map.mapping.integrate import MapIntegrator
from mono_map.mapping.octree import key_to_coord, morton_to_keys, pack_keys, tree_leaves
from mono_map.mapping.points import camera_origin, pixels_to_world

K = np.array([[120.0, 0.0, 64.0], [0.0, 120.0, 24.0], [0.0, 0.0, 1.0]])
H, W = 48, 128
BINS = DepthBins()


class Seq:
    """A tiny hand-built sequence: the camera drives forward along z towards a wall at world z = 14 m with a box
    in front, the ground 1.65 m below; ``depth`` is the exact depth, ``noisy`` adds per-frame noise."""

    name = "hand"
    times = np.arange(8, dtype=float)

    def __init__(self, n: int = 6):
        self.n = n
        self.calib = type("Calib", (), {"K2": K})()
        self.image_size = (H, W)

    def __len__(self):
        return self.n

    def T_world_cam2(self, i):
        T = np.eye(4)
        T[:3, 3] = [0.1 * i, 0.0, 0.4 * i]
        return T

    def image(self, i):
        return np.zeros((H, W, 3), np.uint8)

    def depth(self, i):
        v, u = np.mgrid[0:H, 0:W].astype(np.float64)
        cz = 0.4 * i
        d = np.full((H, W), 14.0 - cz)
        box = (u > 40) & (u < 70) & (v > 8) & (v < 26)
        d[box] = 8.0 - cz
        ray_y = (v - K[1, 2]) / K[1, 1]                      # the ground plane y = +1.65 (camera y points down)
        with np.errstate(divide="ignore"):
            g = np.where(ray_y > 0, 1.65 / ray_y, np.inf)
        d = np.minimum(d, g)
        return d.astype(np.float32)


class LogNormalPredictor:
    """Per pixel a log-normal over the bins around ``depth_fn(i)`` with log-spread ``sigma`` (H×W or scalar)."""

    bins = BINS

    def __init__(self, depth_fn, sigma):
        self.depth_fn, self.sigma = depth_fn, sigma

    def predict_frame(self, seq, i, image=None, with_probs=False, probs_step=1):
        from mono_map.mapping.oracle import lognormal_bin_probs

        d = self.depth_fn(i).astype(np.float32)
        sig = np.broadcast_to(np.float32(self.sigma) if np.isscalar(self.sigma) else self.sigma(i), d.shape)
        probs, pb = lognormal_bin_probs(d, sig, BINS)
        within = 1 - pb
        probs = np.where(within > 0, probs / np.where(within > 0, within, 1), 0).astype(np.float32)
        s = probs_step
        return DepthPrediction(depth=d, entropy=np.log(sig + 1e-3).astype(np.float32),
                               probs=np.ascontiguousarray(probs[:, ::s, ::s]) if with_probs else None,
                               p_beyond=pb, probs_step=s)


def occupied_keys_of(tree) -> np.ndarray:
    leaves = tree_leaves(tree)
    codes, leaf = leaves.expand()
    return morton_to_keys(codes[leaves.occupied[leaf]])


def free_keys_of(tree) -> np.ndarray:
    leaves = tree_leaves(tree)
    codes, leaf = leaves.expand()
    return morton_to_keys(codes[~leaves.occupied[leaf]])


def within_one_cell(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Per row of ``a``: is a cell of ``b`` within one cell (26-neighbourhood)."""
    bset = set(pack_keys(b).tolist())
    out = np.zeros(len(a), bool)
    for dx in (-1, 0, 1):
        for dy in (-1, 0, 1):
            for dz in (-1, 0, 1):
                out |= np.isin(pack_keys(a + [dx, dy, dz]), list(bset))
    return out


DCFG = DistributionConfig(ray_step=1, temperature=1.0)


def fused_build(seq, predictor, frames, fcfg=FusedConfig(), dcfg=DCFG, observers=()):
    return build_map(seq, MapJob.spec("mono", frames, integrate="fused", distribution=dcfg, fused=fcfg),
                     predictor=predictor, observers=observers, show_progress=False)


@pytest.mark.parametrize("subpixel, ray_step, gate, euclid", [(0, 1, 0, 0), (1, 1, 0, 0), (0, 1, 3, 0), (0, 1, 0, 1),
                                                               (1, 1, 0, 1)])
def test_exact_depth_gives_the_depth_gt_surface_within_one_cell(subpixel, ray_step, gate, euclid):
    seq = Seq(6)
    gt = build_map(seq, MapJob.spec("depth-gt", range(6)), show_progress=False)
    fused = fused_build(seq, LogNormalPredictor(seq.depth, 1e-4), range(6),
                        FusedConfig(min_weight=1.0, subpixel=subpixel, snap_step=1, gate=gate, euclid=euclid),
                        DistributionConfig(ray_step=ray_step, temperature=1.0))
    a, b = occupied_keys_of(fused.tree), occupied_keys_of(gt.tree)
    assert len(a) > 500
    near = within_one_cell(a, b)
    assert near.mean() > 0.99                # the fused surface on the true one (a few cells at the box's silhouette)
    assert within_one_cell(b, a).mean() > 0.9                   # and the true surface is nearly all there
    assert fused.stats["integrate"] == "fused" and fused.stats["surface_hits"] > 0


def test_two_noisy_copies_fuse_to_fewer_occupied_cells_than_either_hard_insertion():
    seq = Seq(1)
    rng = np.random.default_rng(0)
    noisy = [seq.depth(0) * np.exp(rng.normal(0, 0.03, (H, W))).astype(np.float32) for _ in range(2)]
    T = seq.T_world_cam2(0)
    hard = []
    for d in noisy:
        integ = MapIntegrator(OctoMapConfig())
        integ.insert(pixels_to_world(d, np.ones(d.shape, bool), K, T), camera_origin(T))
        hard.append(len(occupied_keys_of(integ.tree)))

    class Twice(Seq):
        def T_world_cam2(self, i):
            return T

    fused = fused_build(Twice(2), LogNormalPredictor(lambda i: noisy[i], 0.03), range(2), FusedConfig(min_weight=1.0))
    n = len(occupied_keys_of(fused.tree))
    assert 0 < n < min(hard)


def test_a_confident_frame_outweighs_an_uncertain_one():
    """The same view twice: one frame says 10 m confidently, the other 11 m uncertainly: the fused surface a ray
    snaps to is at 10 m, in either order."""
    cfg = FusedConfig(min_weight=0.5, trunc_max=2.0, trunc_min=3.0)
    ones = np.ones((H, W), np.float32)
    w = pixel_weights(np.array([0.01, 0.6], np.float32), cfg)
    assert w[0] > 5 * w[1]
    snapped = []
    for order in ((0, 1), (1, 0)):
        f = SurfaceFusion(cfg, 0.2)
        for k in order:
            f.integrate((10.1 + k) * ones, w[k] * ones, 1.5 * ones, K, np.eye(4))
        z = f.snap_depths(10.6 * ones, K, np.eye(4), window=1.0)
        assert (z > 0).mean() > 0.9
        assert np.all(np.abs(z[z > 0] - 10.1) < 0.1)
        snapped.append(z)
    assert np.allclose(snapped[0], snapped[1], atol=1e-4)


def test_mode_shift_moves_two_modes_onto_the_larger_and_leaves_a_symmetric_one_alone():
    lc = BINS.log_centres
    p = np.zeros((BINS.num_bins, 4), np.float32)
    p[20, 0] = 1.0                                         # a point mass: no shift
    p[[10, 11, 12], 1] = [0.25, 0.5, 0.25]                 # one symmetric mode inside the window: no shift
    p[[5, 40], 2] = [0.4, 0.6]                             # two modes: from their mean onto bin 40
    p[[30, 31, 44], 3] = [0.3, 0.4, 0.3]                   # a two-bin mode and a far third: onto the pair
    s = mode_shift(p, BINS.edges)
    assert abs(s[0]) < 1e-6 and abs(s[1]) < 1e-6
    assert np.isclose(s[2], lc[40] - (0.4 * lc[5] + 0.6 * lc[40]), atol=1e-5)
    peak = lc[31] + 0.5 * (0.3 - 0.0) / (0.3 - 2 * 0.4 + 0.0) * (lc[1] - lc[0])     # the parabola's vertex
    assert lc[30] < peak < lc[31]
    assert np.isclose(s[3], peak - (0.3 * lc[30] + 0.4 * lc[31] + 0.3 * lc[44]), atol=1e-5)


class BimodalPredictor(LogNormalPredictor):
    """A confident mode (weight 0.7) at the true depth and a second one (0.3) 60 % farther: the expected
    depth lies between them, in empty space."""

    def predict_frame(self, seq, i, image=None, with_probs=False, probs_step=1):
        from mono_map.mapping.oracle import lognormal_bin_probs

        d = self.depth_fn(i).astype(np.float32)
        sig = np.full(d.shape, np.float32(self.sigma))
        probs = sum(w * lognormal_bin_probs(d * f, sig, BINS)[0] for w, f in ((0.7, 1.0), (0.3, 1.6)))
        probs = (probs / probs.sum(axis=0, keepdims=True)).astype(np.float32)
        depth = np.exp((probs * BINS.log_centres[:, None, None]).sum(axis=0)).astype(np.float32)
        s = probs_step
        return DepthPrediction(depth=depth, entropy=np.zeros(d.shape, np.float32),
                               probs=np.ascontiguousarray(probs[:, ::s, ::s]) if with_probs else None,
                               p_beyond=np.zeros(d.shape, np.float32), probs_step=s)


def test_the_mode_puts_a_two_mode_surface_on_the_true_one_where_the_mean_does_not():
    seq = Seq(4)
    gt = occupied_keys_of(build_map(seq, MapJob.spec("depth-gt", range(4)), show_progress=False).tree)
    near = {}
    for mode in (0, 1):
        fused = fused_build(seq, BimodalPredictor(seq.depth, 0.01), range(4),
                            FusedConfig(min_weight=1.0, mode=mode, multiview=0, max_spread=1.0, spread_ref=1.0))
        occ = occupied_keys_of(fused.tree)
        assert len(occ) > 100
        near[mode] = within_one_cell(occ, gt).mean()
    assert near[1] > 0.9 and near[0] < 0.5


def test_surface_cells_are_never_freed_by_rays_that_end_on_them():
    """One frame of exact depth: every cell a snapped ray ends in is occupied (the free half's own rays, which
    also end there, never free it) and lies on the true surface (the depth-gt map's end cells)."""
    seq = Seq(1)
    gt = build_map(seq, MapJob.spec("depth-gt", range(1)), show_progress=False)
    fused = fused_build(seq, LogNormalPredictor(seq.depth, 1e-4), range(1), FusedConfig(min_weight=0.5))
    occ = occupied_keys_of(fused.tree)
    assert len(occ) > 300
    assert fused.stats["surface_hits"] == len(occ)          # one frame: its hit cells, each still occupied
    assert within_one_cell(occ, occupied_keys_of(gt.tree)).mean() > 0.95     # one view: silhouettes blur


def test_point_masses_through_the_free_half_give_the_keep_1_free_cells():
    seq = Seq(3)
    keep = build_map(seq, MapJob.spec("depth-gt", range(3)), show_progress=False)      # keep 1.0 of the exact depth
    dcfg = DistributionConfig(ray_step=1, temperature=1.0, quantum=0.0, snap_free=False, min_update=0.0)

    class PointMass(LogNormalPredictor):
        def predict_frame(self, seq_, i, image=None, with_probs=False, probs_step=1):
            p = super().predict_frame(seq_, i, image, with_probs, probs_step)
            return p

    # a point mass per pixel: one zero-width bin at the pixel's exact depth (the free half's own point masses)
    from mono_map.mapping.distribution_frame import distribution_frame

    integ = MapIntegrator(OctoMapConfig())
    for i in range(3):
        d = seq.depth(i)
        valid = (d >= 1.0) & (d <= 80.0)
        pred = DepthPrediction(depth=d, entropy=np.zeros_like(d), probs=np.ones((1, H, W), np.float32),
                               p_beyond=np.zeros_like(d))
        edges = None
        # per-pixel edges are not a predictor's output: use the free half directly with point masses
        from mono_map.mapping.distribution import distribution_update
        from mono_map.mapping.distribution_frame import free_updates

        v, u = np.nonzero(valid)
        dd = d[v, u].astype(np.float64)
        T = seq.T_world_cam2(i)
        upd = distribution_update(camera_origin(T), pixels_to_world(d, valid, K, T), dd,
                                  np.ones((len(dd), 1), np.float32), None, np.stack([dd, dd], 1), 0.2,
                                  integ.hit, integ.miss, quantum=dcfg.quantum, snap_free=dcfg.snap_free)
        integ.insert_updates(free_updates(upd))
        del pred, edges
    a = set(pack_keys(free_keys_of(integ.tree)).tolist())
    b = set(pack_keys(free_keys_of(keep.tree)).tolist())
    occ = set(pack_keys(occupied_keys_of(keep.tree)).tolist())
    assert len(b) > 1000
    # the keep-1.0 map's free cells are exactly the free half's free cells that no end point re-occupied
    assert b == a - occ
    del PointMass, distribution_frame


def test_log_spread_and_weights():
    edges = BINS.edges
    p = np.zeros((BINS.num_bins, 3), np.float32)
    p[20, 0] = 1.0                                  # a point in one bin: spread 0, weight 1
    p[10:30, 1] = 1 / 20                           # smeared: wide spread, small weight
    p[[10, 40], 2] = 0.5                           # two modes: wide spread
    s = log_spread(p, edges)
    assert s[0] == 0 and s[1] > 0.3 and s[2] > s[1]
    w = pixel_weights(s, FusedConfig())
    assert w[0] == 1.0 and w[2] < w[1] < 0.2


@pytest.mark.parametrize("field,value,option", [
    ("spread_ref", 0.0, "--fused-spread-ref"), ("min_weight", -1.0, "--fused-min-weight"),
    ("trunc_max", float("nan"), "--fused-trunc-max"), ("trunc_behind", 0.5, "--fused-trunc-behind"),
    ("max_depth", float("inf"), "--fused-max-depth"), ("lag", -1, "--fused-lag"),
    ("snap_window", 0.0, "--fused-snap-window"),
    ("trunc_sigma", -2.0, "--fused-trunc-sigma"), ("max_spread", 0.0, "--fused-max-spread"),
    ("mode", 2, "--fused-mode"), ("gate", -1.0, "--fused-gate"),
    ("gate", float("nan"), "--fused-gate"), ("euclid", 2, "--fused-euclid")])
def test_bad_settings_are_one_line_naming_the_option(field, value, option):
    import dataclasses

    with pytest.raises(MonoMapError, match=option) as exc:
        check_fused_config(dataclasses.replace(FusedConfig(), **{field: value}))
    assert "\n" not in str(exc.value)


def test_bad_settings_are_refused_by_build_map_before_any_frame():
    seq = Seq(2)
    with pytest.raises(MonoMapError, match="--fused-min-weight"):
        fused_build(seq, LogNormalPredictor(seq.depth, 0.02), range(2), FusedConfig(min_weight=0.0))


def test_the_surface_streams_to_observers_as_it_refines():
    """Observers see the surface appear ``lag`` frames after a frame was fused (the rest at the last frame);
    the cells they were told became occupied, minus those that stopped, are the final map's occupied cells."""
    seq = Seq(5)
    seen = []
    fused = fused_build(seq, LogNormalPredictor(seq.depth, 0.02), range(5), FusedConfig(min_weight=1.0, lag=2),
                        observers=[seen.append])
    assert len(seen) == 5
    became = [len(u.occupied_keys_changed) for u in seen]
    assert became[0] == became[1] == 0 and became[2] > 0 and became[4] > 0
    shown = sum(became) - sum(len(u.freed_keys_changed) for u in seen)
    assert shown == len(occupied_keys_of(fused.tree)) > 0




@pytest.mark.parametrize("gate", [0.0, 2.0])
def test_the_gate_keeps_a_pixels_own_depth_where_the_fused_surface_confirms_it(gate):
    """A wall fused at 10 m; pixels asking at 10.1 m (half a cell off) and at 10.9 m (4.5 cells off). Without
    the gate both snap onto the wall; with a 2-cell gate the near ones keep their own 10.1 m and the far ones
    give no hit."""
    fusion = SurfaceFusion(FusedConfig(gate=gate, lag=0), 0.2, initial_blocks=256)
    wall = np.full((H, W), 10.0, np.float32)
    for _ in range(2):
        fusion.integrate(wall, np.ones_like(wall), np.full_like(wall, 0.6), K, np.eye(4))
    fusion.pending.clear()
    ask = np.where(np.arange(W)[None, :] < W // 2, np.float32(10.1), np.float32(10.9)) * np.ones((H, 1), np.float32)
    fusion.pending.append((ask, K, np.eye(4), None))
    pts = np.concatenate(due_surface_points(fusion, flush=True))
    z = pts[:, 2]
    if gate:                      # (the image's last row sees no voxel of its own)
        assert 0.95 * H * W / 2 <= len(z) <= H * W / 2 and np.allclose(z, 10.1, atol=1e-4)
    else:
        assert len(z) >= 0.95 * H * W and np.abs(z - 10.0).max() < 0.1


def test_a_fused_maps_key_names_the_gate_only_when_it_is_on():
    """Maps made before the gate existed keep their keys (and are reused); a gated map is another map."""
    off = MapJob.spec("mono", range(3), integrate="fused").key()["integration"]["fused"]
    on = MapJob.spec("mono", range(3), integrate="fused", fused=FusedConfig(gate=3)).key()["integration"]["fused"]
    assert "gate" not in off and on["gate"] == 3
    on = MapJob.spec("mono", range(3), integrate="fused", fused=FusedConfig(euclid=1)).key()["integration"]["fused"]
    assert "euclid" not in off and on["euclid"] == 1


def road_depth(Kr, h, w, height):
    """z-depth (h, w) of a flat road ``height`` m below a level camera (0 above the horizon and beyond 40 m)."""
    dy = (np.arange(h, dtype=np.float32)[:, None] - np.float32(Kr[1, 2])) / np.float32(Kr[1, 1]) * np.ones((1, w), np.float32)
    d = np.where(dy > 1e-3, height / np.maximum(dy, 1e-3), 0.0)
    return np.where(d <= 40, d, 0.0).astype(np.float32)


@pytest.mark.parametrize("euclid", [0, 1])
def test_on_a_road_seen_at_grazing_angles_the_normal_puts_each_hit_in_its_own_cell(euclid):
    """A flat road 1.65 m below a camera driving 0.37 m a frame (its cells cut by the road at varying heights):
    distances along the optical axis are metres at grazing angles, and the hits they snap to land in the cell
    above or below the road's (the true cells are then freed by the rays); distances along the normal give each
    pixel the cell of its own surface point."""
    from mono_map.geometry import depth_normals

    Kr = np.array([[180.0, 0.0, 155.0], [0.0, 180.0, 47.0], [0.0, 0.0, 1.0]])
    h, w, res = 94, 310, 0.2
    fusion = SurfaceFusion(FusedConfig(euclid=euclid, lag=0), res, initial_blocks=2048)
    frames = []
    for k in range(6):
        T = np.eye(4)
        T[1, 3], T[2, 3] = 0.013 * k, 0.37 * k                 # the world's road stays at y = 1.65 m
        d = road_depth(Kr, h, w, 1.65 - T[1, 3])
        fusion.integrate(d, np.ones_like(d), np.full_like(d, 0.6), Kr, T, None,
                         depth_normals(d, Kr)[0] if euclid else None)
        frames.append((d, T))
    d, T = frames[3]
    z = fusion.snap_depths(d, Kr, T, 1.0, normals=depth_normals(d, Kr)[0] if euclid else None)
    v, u = np.nonzero((z > 0) & (d > 0))
    assert len(v) > 0.8 * (d > 0).sum()

    def cells(zz):
        from mono_map.geometry import backproject_pixels, transform_points

        return np.floor(transform_points(T, backproject_pixels(Kr, u, v, zz)) / res).astype(np.int64)

    own = (cells(z[v, u]) == cells(d[v, u])).all(axis=1).mean()
    if euclid:
        assert own > 0.99 and np.abs(z[v, u] - d[v, u]).max() < 0.01
    else:
        assert own < 0.5


def test_normals_of_a_depth_image_take_the_surface_each_pixel_is_on():
    """A road below a wall: the road's normal is up (cos = height / depth), the wall's faces the camera (cos 1),
    also in the rows where the two meet."""
    from mono_map.geometry import depth_normals

    Kr = np.array([[100.0, 0.0, 50.0], [0.0, 100.0, 10.0], [0.0, 0.0, 1.0]])
    d = road_depth(Kr, 40, 100, 1.5)
    d = np.where((d == 0) | (d > 10.0), np.float32(10.0), d)       # a wall at 10 m from the row the road reaches it
    n, cos = depth_normals(d, Kr)
    road, wall = d < 9.9, d >= 10.0
    ray_y = (np.arange(40)[:, None] - 10.0) / 100.0 * np.ones((1, 100))
    assert np.allclose(n[road], [0, -1, 0], atol=1e-3) and np.allclose(cos[road], ray_y[road], rtol=1e-3)
    assert np.allclose(n[wall], [0, 0, -1], atol=1e-3) and np.allclose(cos[wall], 1.0, atol=1e-5)


def test_the_hit_cell_tool_counts_more_own_cells_along_the_normal(tiny_root):
    """tools/fused_hit_cells.py on tiny's exact depth: shares in [0, 1], more hits in their own cell along the
    normal than along the optical axis, and a picture of the first checked frame."""
    from mono_map.data.kitti import open_sequence
    from tool_loader import load_tool

    tool = load_tool("fused_hit_cells")
    seq = open_sequence(tiny_root, "tiny")
    (axis,), pic_axis = tool.hit_cells(seq, list(range(6)), [3], euclid=False)
    (normal,), pic_normal = tool.hit_cells(seq, list(range(6)), [3], euclid=True)
    for r in (axis, normal):
        assert 0 <= r["no_hit"] < 0.2 and 0 <= r["own"] <= 1
    assert normal["own"] > axis["own"]
    assert pic_axis.shape == pic_normal.shape == seq.depth(3)[::2, ::2].shape
    assert np.nanmedian(np.abs(pic_normal[np.isfinite(pic_normal)])) < 0.05


@pytest.mark.parametrize("euclid", [0, 1])
def test_the_compiled_snap_gives_the_numpy_forms_depths(euclid, monkeypatch):
    """The two compiled passes of the snap (csrc/fused.c) against the numpy form: a road and a wall in front
    of a camera moving forward and to the side (cells at negative coordinates too), fused from noisy frames,
    snapped along the axis and along the normals: the same pixels found, the same depths (float64 rounding)."""
    from mono_map.geometry import depth_normals
    from mono_map.mapping import fused_c

    if fused_c.library() is None:
        pytest.fail("the compiled snap did not load (compiler missing?)")
    Kr = np.array([[180.0, 0.0, 155.0], [0.0, 180.0, 47.0], [0.0, 0.0, 1.0]])
    h, w, res = 94, 310, 0.2
    rng = np.random.default_rng(euclid)
    fusion = SurfaceFusion(FusedConfig(euclid=euclid, lag=0), res, initial_blocks=2048)
    frames = []
    for k in range(6):
        T = np.eye(4)
        T[0, 3], T[1, 3], T[2, 3] = -0.3 * k, 0.013 * k, 0.37 * k
        d = road_depth(Kr, h, w, 1.65 - T[1, 3])
        d = np.where((d == 0) | (d > 12 - T[2, 3]), np.float32(12 - T[2, 3]), d)       # a wall at z = 12 m
        d = (d * np.exp(rng.normal(0, 0.02, d.shape))).astype(np.float32)
        fusion.integrate(d, np.ones_like(d), np.full_like(d, 0.6), Kr, T, None,
                         depth_normals(d, Kr)[0] if euclid else None)
        frames.append((d, T))
    d, T = frames[2]
    normals = depth_normals(d, Kr)[0] if euclid else None
    compiled = fusion.snap_depths(d, Kr, T, 1.0, normals=normals)
    monkeypatch.setattr(fused_c, "library", lambda: None)
    numpy_form = fusion.snap_depths(d, Kr, T, 1.0, normals=normals)
    found = numpy_form > 0
    assert found.sum() > 0.5 * (d > 0).sum()
    assert np.array_equal(compiled > 0, found)
    assert np.abs(compiled - numpy_form).max() < 1e-4


@pytest.mark.parametrize("euclid", [0, 1])
def test_the_compiled_tsdf_update_gives_the_numpy_forms_field(euclid, monkeypatch):
    """SurfaceFusion.integrate's compiled update (csrc/fused.c) against its numpy form: the same noisy road and
    wall fused into two grids, read back at every cell around the surfaces: the same summed weights (float32
    sums of the same weights), the same signed distances to float rounding."""
    from mono_map.geometry import backproject_pixels, depth_normals, transform_points
    from mono_map.mapping import fused_c

    lib = fused_c.library()
    if lib is None:
        pytest.fail("the compiled fused kernels did not load (compiler missing?)")
    Kr = np.array([[180.0, 0.0, 155.0], [0.0, 180.0, 47.0], [0.0, 0.0, 1.0]])
    h, w, res = 94, 310, 0.2
    grids = {}
    for name in ("compiled", "numpy"):
        monkeypatch.setattr(fused_c, "library", (lambda: lib) if name == "compiled" else (lambda: None))
        rng = np.random.default_rng(7)
        fusion = SurfaceFusion(FusedConfig(euclid=euclid, lag=0), res, initial_blocks=2048)
        for k in range(5):
            T = np.eye(4)
            T[0, 3], T[1, 3], T[2, 3] = -0.3 * k, 0.013 * k, 0.37 * k
            d = road_depth(Kr, h, w, 1.65 - T[1, 3])
            d = np.where((d == 0) | (d > 12 - T[2, 3]), np.float32(12 - T[2, 3]), d)
            d = (d * np.exp(rng.normal(0, 0.02, d.shape))).astype(np.float32)
            wgt = rng.uniform(0.2, 1.0, d.shape).astype(np.float32)
            trunc = np.full_like(d, 0.6)
            assert fusion.integrate(d, wgt, trunc, Kr, T, None, depth_normals(d, Kr)[0] if euclid else None) > 1000
        grids[name] = fusion
    v, u = np.mgrid[0:h:2, 0:w:2].reshape(2, -1)
    d = road_depth(Kr, h, w, 1.65)[v, u]
    d = np.where((d == 0) | (d > 12), np.float32(12), d)
    pts = np.concatenate([transform_points(np.eye(4), backproject_pixels(Kr, u, v, d + dz)) for dz in
                          np.arange(-0.8, 0.81, 0.2)])
    (tc, wc), (tn, wn) = grids["compiled"].sample(pts), grids["numpy"].sample(pts)
    assert (wn > 0).mean() > 0.5
    assert np.array_equal(wc > 0, wn > 0) and np.abs(wc - wn).max() < 1e-5
    assert np.abs(tc - tn).max() < 1e-5


def test_a_fused_build_without_the_compiled_fused_kernels_gives_the_same_map(monkeypatch):
    """End to end, the fused maps' compiled kernels swapped for their numpy / torch forms (the snap, the TSDF
    update, the sweep; the ray casts of the free half have no such form) against the compiled build on the hand
    scene with noisy depth: the same occupied and free cells up to a few of float rounding."""
    from mono_map.depth import sweep_c
    from mono_map.mapping import fused_c

    seq = Seq(6)
    rng = np.random.default_rng(5)
    noise = {i: np.exp(rng.normal(0, 0.03, (H, W))).astype(np.float32) for i in range(6)}
    pred = LogNormalPredictor(lambda i: seq.depth(i) * noise[i], 0.05)
    if fused_c.library() is None or sweep_c.library() is None:
        pytest.fail("the compiled fused kernels did not load (compiler missing?)")
    compiled = fused_build(seq, pred, range(6), FusedConfig(lag=2))
    monkeypatch.setattr(fused_c, "library", lambda: None)
    monkeypatch.setattr(sweep_c, "library", lambda: None)
    fallback = fused_build(seq, pred, range(6), FusedConfig(lag=2))
    for keys in (occupied_keys_of, free_keys_of):
        a, b = (set(pack_keys(keys(m.tree)).tolist()) for m in (compiled, fallback))
        assert len(a) > 100
        assert len(a ^ b) <= 0.002 * len(a)
