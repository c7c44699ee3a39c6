"""Distribution-aware integration (``--integrate distribution``): the expected OctoMap update per cell."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from mono_map.config import OctoMapConfig
from mono_map.errors import MonoMapError
from mono_map.mapping.distribution import (check_distribution, distribution_update, expected_updates, far_depth,
                                           quantise_updates)
from mono_map.mapping.integrate import MapIntegrator
from mono_map.mapping.octree import coord_to_key, key_to_coord, tree_leaves
from mono_map.mapping.points import camera_origin, pixels_to_world


K = np.array([[120.0, 0.0, 64.0], [0.0, 120.0, 24.0], [0.0, 0.0, 1.0]])
HIT, MISS = np.float32(np.log(0.7 / 0.3)), np.float32(np.log(0.4 / 0.6))


def pose(i: int) -> np.ndarray:
    a = 0.15 * i
    T = np.eye(4)
    T[:3, :3] = [[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]]
    T[:3, 3] = [0.9 * i + 0.013, 0.31, 0.47 * i - 0.021]
    return T


def depth_frame(i: int, h: int = 48, w: int = 128) -> np.ndarray:
    """A street-like depth image: a wall at 12-30 m, a box in front, the ground below the horizon."""
    rng = np.random.default_rng(i)
    v, u = np.mgrid[0:h, 0:w]
    d = 12.0 + 18.0 * (u / w) + rng.normal(0, 0.05, (h, w))
    d[(u > 40) & (u < 70) & (v > 10) & (v < 30)] = 5.0 + 0.5 * i
    ground = v > 30
    d[ground] = np.minimum(d[ground], 1.65 * 120.0 / (v[ground] - 24.0 + 1e-9))
    return np.clip(d, 1.0, 80.0).astype(np.float32)


def tree_cells(tree) -> dict:
    leaves = tree_leaves(tree)
    codes, leaf = leaves.expand()
    return dict(zip(codes.tolist(), leaves.value[leaf].astype(np.float32).tolist()))


def integrate_point_masses(integ: MapIntegrator, depth: np.ndarray, T: np.ndarray, cfg: OctoMapConfig,
                           quantum: float = 0.0, snap_free: bool = False):
    mask = np.ones(depth.shape, bool)
    v, u = np.nonzero(mask)
    d = depth[v, u].astype(np.float64)
    probs = np.ones((len(d), 1), np.float32)
    edges = np.stack([d, d], axis=1)                    # one zero-width bin: a point mass at the depth
    fd = far_depth(probs, np.zeros(len(d)), edges, 1e-3)
    assert np.array_equal(fd, d)
    upd = distribution_update(camera_origin(T), pixels_to_world(depth, mask, K, T), fd, probs, None, edges,
                              cfg.resolution, integ.hit, integ.miss, cfg.max_range, quantum=quantum,
                              snap_free=snap_free)
    return integ.insert_updates(upd)


@pytest.fixture(params=["1-thread", "2-threads", "pairs"])
def weights_path(request, monkeypatch):
    """The kernel on one thread, split over two threads (even for small frames), and the sort-combined
    (index, update) pairs used for boxes too large for the dense buffer."""
    from mono_map.mapping import distribution, kernel_threads

    monkeypatch.setenv("MONO_MAP_RAY_THREADS", "2" if request.param == "2-threads" else "1")
    if request.param == "2-threads":
        monkeypatch.setattr(kernel_threads, "PARALLEL_MIN_RAYS", 1)
    if request.param == "pairs":
        monkeypatch.setattr(distribution, "_DENSE_MAX_CELLS", 0)
    return request.param


@pytest.mark.parametrize("max_range", [-1.0, 15.0])
def test_point_masses_reproduce_keep_1_bit_for_bit(max_range, weights_path):
    cfg = OctoMapConfig(resolution=0.2, max_range=max_range)
    keep, dist = MapIntegrator(cfg), MapIntegrator(cfg)
    for i in range(4):
        depth, T = depth_frame(i), pose(i)
        a = keep.insert(pixels_to_world(depth, np.ones(depth.shape, bool), K, T), camera_origin(T))
        b = integrate_point_masses(dist, depth, T, cfg)
        assert len(a.keys.free) == len(b.keys.free) and len(a.keys.occupied) == len(b.keys.occupied)
    ca, cb = tree_cells(keep.tree), tree_cells(dist.tree)
    assert len(ca) > 10_000
    assert ca == cb                                       # same cells, same float32 log-odds
    assert keep.tree.memoryUsage() == dist.tree.memoryUsage()
    assert keep.tree.getNumLeafNodes() == dist.tree.getNumLeafNodes()


@pytest.mark.parametrize("snap_free", [False, True])
def test_point_masses_reproduce_keep_1_with_quantised_updates(snap_free):
    """--quantum and --snap-free round only fractional updates: exact hits and misses, hence point masses,
    are untouched."""
    cfg = OctoMapConfig(resolution=0.2)
    keep, dist = MapIntegrator(cfg), MapIntegrator(cfg)
    for i in range(3):
        depth, T = depth_frame(i), pose(i)
        keep.insert(pixels_to_world(depth, np.ones(depth.shape, bool), K, T), camera_origin(T))
        integrate_point_masses(dist, depth, T, cfg, quantum=0.1, snap_free=snap_free)
    assert tree_cells(keep.tree) == tree_cells(dist.tree)
    assert keep.tree.memoryUsage() == dist.tree.memoryUsage()


def test_snapped_free_updates_are_whole_misses_or_nothing():
    dl = np.array([HIT, MISS, 0.37, -0.26, MISS / 2, MISS / 2 * 0.99, -0.9, 0.049, 0.0], np.float32)
    s = quantise_updates(dl, HIT, MISS, 0.0, snap_free=True)
    assert s.dtype == np.float32
    assert s[0] == HIT and s[2] == np.float32(0.37) and s[7] == np.float32(0.049)   # positives untouched
    assert s[1] == MISS and s[3] == MISS and s[4] == MISS and s[6] == MISS          # ≤ half a miss → a miss
    assert s[5] == 0 and s[8] == 0                                                  # weaker → nothing
    q = quantise_updates(dl, HIT, MISS, 0.1, snap_free=True)                        # with a quantum: positives
    assert np.isclose(q[2], 0.4) and q[7] == 0 and set(q[q < 0].tolist()) == {float(MISS)}
    # free space seen by snapped updates holds a keep map's values: k whole misses, so eight siblings prune
    probs, edges = np.full(8, 0.1, np.float32), np.geomspace(4.0, 20.0, 9)
    fd = far_depth(probs[None, :], np.array([0.2]), edges, 0.05)
    far = ORIGIN + np.array([0.0, 0.0, fd[0]])
    b = distribution_update(ORIGIN, far[None, :], fd, probs[None, :], np.array([0.2]), edges, 0.2, HIT, MISS,
                            snap_free=True)
    assert (b.dl[b.dl < 0] == MISS).all() and (b.dl < 0).any() and (b.dl != 0).all()


def test_quantised_updates_lie_on_the_lattice():
    dl = np.array([HIT, MISS, 0.37, -0.26, 0.049, -0.051, 0.0], np.float32)
    q = quantise_updates(dl, HIT, MISS, 0.1)
    assert q[0] == HIT and q[1] == MISS                                  # exact updates kept
    assert np.allclose(q[2:], [0.4, -0.3, 0.0, -0.1, 0.0], atol=1e-6)
    assert (np.abs(q[2:] - dl[2:]) <= 0.05 + 1e-6).all()
    assert np.array_equal(quantise_updates(dl, HIT, MISS, 0.0), dl)      # off
    # a broad one-ray distribution: every update on the lattice, none zero, the sign of each kept
    probs, edges = np.full(8, 0.1, np.float32), np.geomspace(4.0, 20.0, 9)
    fd = far_depth(probs[None, :], np.array([0.2]), edges, 0.05)
    far = ORIGIN + np.array([0.0, 0.0, fd[0]])
    a = distribution_update(ORIGIN, far[None, :], fd, probs[None, :], np.array([0.2]), edges, 0.2, HIT, MISS)
    b = distribution_update(ORIGIN, far[None, :], fd, probs[None, :], np.array([0.2]), edges, 0.2, HIT, MISS,
                            quantum=0.1)
    exact = (b.dl == HIT) | (b.dl == MISS)
    assert exact.any() and (~exact).any() and (b.dl != 0).all()
    assert np.allclose(b.dl[~exact], np.round(b.dl[~exact] / 0.1) * 0.1, atol=1e-6)
    da = dict(zip(map(tuple, a.keys.tolist()), a.dl.tolist()))
    for key, v in zip(map(tuple, b.keys.tolist()), b.dl.tolist()):
        assert np.sign(v) == np.sign(da[key]) and abs(v - da[key]) <= 0.05 + 1e-6


@pytest.mark.parametrize("quantum, snap_free", [(0.2, True), (0.1, False), (0.0, True), (0.0, False), (0.3, True)])
def test_compiled_quantise_split_equals_quantise_updates(quantum, snap_free):
    """The frame path's one-pass rounding and sign split gives quantise_updates' values bit for bit, the zeros
    dropped, the negatives first, each part in input order (ties of the rounding included: np.round's half-even)."""
    from mono_map.mapping.distribution_c import quantise_split_c
    from mono_map.mapping.raycast_c import load_kernel

    kernel = load_kernel()
    if kernel is None:
        pytest.skip("no C compiler: the distribution path itself needs the kernel")
    rng = np.random.default_rng(3)
    dl = rng.uniform(-0.5, 0.9, 5000).astype(np.float32)
    dl[::7] = HIT
    dl[3::11] = MISS
    dl[5::13] = 0.0
    dl[:8] = np.float32([0.1, 0.3, 0.5, -0.1, -0.3, MISS / 2, np.nextafter(MISS / 2, np.float32(0)), 0.25])  # ties, edges
    lin = rng.permutation(10_000)[:len(dl)].astype(np.int64)
    want = quantise_updates(dl, HIT, MISS, quantum, snap_free)
    neg, pos = want < 0, want > 0
    out_lin, out_dl, n_neg = quantise_split_c(kernel, lin, dl, HIT, MISS, quantum, snap_free)
    assert n_neg == neg.sum() and len(out_lin) == neg.sum() + pos.sum()
    assert np.array_equal(out_lin, np.r_[lin[neg], lin[pos]])
    assert np.array_equal(out_dl.view(np.uint32), np.r_[want[neg], want[pos]].view(np.uint32))


ORIGIN = np.array([0.1, 0.1, 0.05])   # on a cell centre in x and y: rays along +z stay on one cell column


def one_ray(probs, edges, p_beyond=None, res=0.2, eps=1e-3):
    """Cell updates of one ray along +z: (depth of the cell centres, dl, far depth, depth per metre of ray)."""
    probs = np.asarray(probs, np.float32)[None, :]
    edges = np.asarray(edges, np.float64)
    pb = np.zeros(1) if p_beyond is None else np.array([p_beyond])
    fd = far_depth(probs, pb, edges, eps)
    far = ORIGIN + np.array([0.0, 0.0, fd[0]])
    upd = distribution_update(ORIGIN, far[None, :], fd, probs, pb, edges, res, HIT, MISS)
    assert (upd.keys[:, :2] == upd.keys[0, :2]).all()
    centre_z = key_to_coord(upd.keys, res)[:, 2]
    length = key_to_coord(coord_to_key(far[None, :], res), res)[0, 2] - ORIGIN[2]
    scale = fd[0] / length
    order = np.argsort(centre_z)
    return (centre_z[order] - ORIGIN[2]) * scale, upd.dl[order], fd[0], scale


def test_kernel_paths_agree_on_distributions(monkeypatch):
    from mono_map.mapping import distribution, kernel_threads

    rng = np.random.default_rng(7)
    edges = np.geomspace(1.0, 80.0, 33)
    n = 3000
    probs = rng.dirichlet(np.ones(32) * 0.2, size=n).astype(np.float32) * 0.95
    pb = np.full(n, 0.05)
    T = pose(1)
    dirs = rng.normal(size=(n, 3))
    dirs[:, 2] = np.abs(dirs[:, 2]) + 1.0
    fd = far_depth(probs, pb, edges, 0.05)
    far = camera_origin(T) + dirs / dirs[:, 2:3] * fd[:, None]

    def run():
        u = distribution_update(camera_origin(T), far, fd, probs, pb, edges, 0.2, HIT, MISS)
        order = np.lexsort(u.keys.T)
        return u.keys[order], u.dl[order]

    monkeypatch.setenv("MONO_MAP_RAY_THREADS", "1")
    k1, d1 = run()
    monkeypatch.setenv("MONO_MAP_RAY_THREADS", "2")
    monkeypatch.setattr(kernel_threads, "PARALLEL_MIN_RAYS", 1)
    k2, d2 = run()
    monkeypatch.setattr(distribution, "_DENSE_MAX_CELLS", 0)
    k3, d3 = run()
    assert len(k1) > 50_000 and (d1 > 0).any() and (d1 < 0).any()
    for k, d in ((k2, d2), (k3, d3)):
        assert np.array_equal(k, k1) and np.array_equal(d, d1)


def test_kernel_matches_reference_formula():
    edges = np.geomspace(1.0, 80.0, 17)
    rng = np.random.default_rng(3)
    p = rng.dirichlet(np.ones(16)).astype(np.float32) * 0.9
    z, dl, fd, scale = one_ray(p, edges, p_beyond=0.1)
    assert len(z) > 100
    t_out = np.arange(1, len(z) + 1) * 0.2 - ORIGIN[2]            # cell faces along the ray (metres)
    t_in = np.r_[0.0, t_out[:-1]]
    ref = expected_updates(p[None], np.array([0.1]), edges, t_in[None] * scale, t_out[None] * scale, HIT, MISS)[0]
    np.testing.assert_allclose(dl[:-1], ref[:-1], atol=1e-6)      # the end cell reaches past its centre


def test_uniform_distribution_gives_no_occupancy_and_weak_updates():
    edges = np.geomspace(1.0, 80.0, 65)
    z, dl, _, _ = one_ray(np.full(64, 1 / 64), edges)
    assert dl.max() < 0.01 * HIT                            # at most 1 % of a hit anywhere
    far = z > 10.0
    assert np.abs(dl[far]).max() < 0.5 * abs(MISS)          # beyond 10 m: under half a LiDAR miss
    point = one_ray([1.0], [20.0, 20.0])[1]
    assert point.max() == HIT                               # a point mass gives the full hit


def test_two_modes_give_occupancy_at_both_and_free_space_before():
    # two point masses: half at 10 m, half at 20 m (bins [10,10], [10,20] empty, [20,20])
    z, dl, fd, _ = one_ray([0.5, 0.0, 0.5], [10.0, 10.0, 20.0, 20.0])
    assert fd == 20.0
    at10 = np.abs(z - 10.0) < 0.1
    at20 = np.abs(z - 20.0) < 0.1
    assert dl[at10].max() > 0 and dl[at20].max() > 0
    assert np.isclose(dl[at10].max(), 0.5 * HIT + 0.5 * MISS, atol=1e-6)
    assert np.isclose(dl[at20].max(), 0.5 * HIT, atol=1e-6)
    assert (dl[z < 9.8] == MISS).all()                      # free space before the first mode
    between = (z > 10.2) & (z < 19.8)
    assert np.allclose(dl[between], 0.5 * MISS, atol=1e-6)  # half free between the modes
    assert z.max() < 20.2                                   # nothing after the last mode


def test_more_mass_in_a_cell_never_lowers_its_update():
    edges = np.geomspace(1.0, 80.0, 33)
    rng = np.random.default_rng(0)
    p = rng.dirichlet(np.ones(32), size=200)
    z_in, z_out = np.array([[7.0, 20.0]]), np.array([[7.5, 21.0]])
    base = expected_updates(p, None, edges, z_in, z_out, HIT, MISS)
    j = np.searchsorted(edges, 7.2) - 1                      # the bin holding the first cell
    for src in range(32):
        if src == j:
            continue
        q = p.copy()
        moved = 0.5 * q[:, src]
        q[:, src] -= moved
        q[:, j] += moved                                     # mass moved into the cell's bin
        more = expected_updates(q, None, edges, z_in, z_out, HIT, MISS)
        assert (more[:, 0] >= base[:, 0] - 1e-12).all()


def test_eps_truncation_bounds_the_ray():
    edges = np.geomspace(1.0, 80.0, 65)
    centre = np.log(10.0)
    lc = 0.5 * (np.log(edges[1:]) + np.log(edges[:-1]))
    p = np.exp(-0.5 * ((lc - centre) / 0.1) ** 2)
    p /= p.sum()
    for eps in (1e-2, 1e-4):
        z, dl, fd, _ = one_ray(p, edges, eps=eps)
        beyond = 1.0 - np.cumsum(p)
        first = np.argmax(beyond < eps)
        assert edges[first] <= fd <= edges[first + 1]
        assert z.max() <= fd + 0.2 * np.sqrt(3)              # no cell past the far depth's cell
    assert one_ray(p, edges, eps=1e-4)[2] > one_ray(p, edges, eps=1e-2)[2]
    # mass beyond range (p_beyond >= eps): the ray runs to the last edge
    _, _, fd, _ = one_ray(p * 0.5, edges, p_beyond=0.5)
    assert fd == 80.0


@pytest.mark.parametrize("probs, pb, match", [
    ([[np.nan, 1.0]], None, "NaN"),
    ([[-0.1, 1.0]], None, "negative"),
    ([[0.7, 0.6]], None, "summing above 1"),
    ([[0.5, 0.5]], [0.2], "summing above 1"),
    ([[0.5, 0.5]], [-0.2], "negative"),
])
def test_bad_distributions_are_one_clear_error(probs, pb, match):
    with pytest.raises(MonoMapError, match=match):
        check_distribution(np.array(probs), None if pb is None else np.array(pb), np.array([1.0, 2.0, 3.0]))
    with pytest.raises(MonoMapError, match=match):
        distribution_update(np.zeros(3), np.ones((1, 3)), np.ones(1), np.array(probs),
                            None if pb is None else np.array(pb), np.array([1.0, 2.0, 3.0]), 0.2, HIT, MISS)


def test_bad_edges_are_one_clear_error():
    with pytest.raises(MonoMapError, match="non-decreasing"):
        check_distribution(np.array([[0.5, 0.5]]), None, np.array([1.0, 3.0, 2.0]))


def test_far_depth_kernel_matches_numpy(monkeypatch):
    edges = np.geomspace(1.0, 80.0, 33)
    rng = np.random.default_rng(5)
    p = (rng.dirichlet(np.ones(32) * 0.3, size=500) * rng.uniform(0.5, 1.0, (500, 1))).astype(np.float32)
    pb = 1.0 - p.sum(axis=1, dtype=np.float64)
    pb[::3] = 0.0
    fast = far_depth(p, pb, edges, 0.05)
    monkeypatch.setenv("MONO_MAP_NO_C", "1")
    np.testing.assert_allclose(far_depth(p, pb, edges, 0.05), fast, rtol=1e-9)
    assert (fast[pb >= 0.05] == 80.0).all()


class WallSequence:
    """A hand-built 'synthetic sequence': the camera looks along +z at a wall 10 m away (depth_2 = 10 m),
    the top rows are sky (no depth)."""

    name = "wall"

    def __init__(self, n=2, h=48, w=128):
        self.n, self.h, self.w = n, h, w
        self.calib = type("Calib", (), {"K2": K})()
        self.times = np.arange(n, dtype=float)
        self.image_size = (h, w)
        self.path = None

    def __len__(self):
        return self.n

    def T_world_cam2(self, i):
        T = np.eye(4)
        T[:3, 3] = [0.0, 0.0, 0.5 * i]
        return T

    def depth(self, i):
        d = np.full((self.h, self.w), 10.0 - 0.5 * i, np.float32)   # the wall stays at world z = 10 m
        d[:8] = 0.0
        return d


def test_depth_gt_map_of_a_hand_built_wall():
    from mono_map.mapping.pipeline import build_map
    from mono_map.mapping.jobs import MapJob

    res = build_map(WallSequence(), MapJob.spec("depth-gt"), show_progress=False)
    leaves = tree_leaves(res.tree)
    codes, leaf = leaves.expand()
    from mono_map.mapping.octree import morton_to_keys

    z = key_to_coord(morton_to_keys(codes), 0.2)[:, 2]
    occ = leaves.occupied[leaf]
    assert occ.sum() > 100
    assert np.all(np.abs(z[occ] - 10.0) <= 0.2)                  # occupied exactly at the wall
    assert (z[~occ] < 10.0).all()                                # free space in front of it only
    assert res.stats["source"] == "depth-gt" and res.stats["points_kept"] == 2 * 40 * 128


def test_oracle_distribution_build_with_an_observer(tiny_root):
    """The whole build path on the oracle's distributions: observers get every frame, cells become occupied."""
    from mono_map.data.kitti import open_sequence
    from mono_map.mapping.pipeline import build_map
    from mono_map.mapping.jobs import MapJob
    from mono_map.mapping.distribution import DistributionConfig
    from mono_map.mapping.oracle import NoisyGroundTruthPredictor

    seq = open_sequence(tiny_root, "tiny")
    seen = []
    res = build_map(seq,
                    MapJob.spec("mono", range(0, 2), stride=2, integrate="distribution",
                                distribution=DistributionConfig(eps=0.1, ray_step=2)),
                    predictor=NoisyGroundTruthPredictor(sigma=0.01, edge_sigma=0.0), observers=[seen.append],
                    show_progress=False)
    assert len(seen) == 2 and len(seen[0].occupied_keys_changed) > 0
    assert res.stats["integrate"] == "distribution" and res.stats["keep"] is None
    assert res.stats["points_kept"] == sum(f["n_points"] for f in res.per_frame) > 0


def test_heads_without_probabilities_are_one_clear_error(tiny_root):
    from mono_map.data.kitti import open_sequence
    from mono_map.depth.inference import DepthPrediction
    from mono_map.mapping.pipeline import build_map
    from mono_map.mapping.jobs import MapJob

    class NoProbs:
        def predict(self, image, with_probs=False, probs_step=1):
            h, w = image.shape[:2]
            return DepthPrediction(depth=np.full((h, w), 10.0, np.float32), entropy=np.ones((h, w), np.float32))

    seq = open_sequence(tiny_root, "tiny")
    with pytest.raises(MonoMapError, match="no bin probabilities"):
        build_map(seq, MapJob.spec("mono", range(0, 1), integrate="distribution"), predictor=NoProbs(),
                  show_progress=False)


def test_narrow_bins_place_a_sharp_pixel_at_its_local_mean():
    from mono_map.mapping.distribution import narrow_bins

    edges = np.geomspace(1.0, 80.0, 65)
    lc = 0.5 * (np.log(edges[1:]) + np.log(edges[:-1]))
    p = np.zeros((1, 64), np.float32)
    p[0, 40], p[0, 41] = 0.7, 0.3                          # a sharp pixel between two bin centres
    q, e = narrow_bins(p, edges, 0.2)
    check_distribution(q, None, e)                          # a valid distribution
    local_mean = np.exp(0.7 * lc[40] + 0.3 * lc[41])
    fd_lo = far_depth(q, np.zeros(1), e, 0.5)[0]           # the median falls in the modal bin's narrow support
    assert abs(np.log(fd_lo / local_mean)) < 0.1 * (lc[1] - lc[0])
    assert np.isclose(q.sum(), 1.0) and (np.diff(e[0]) >= 0).all()


def test_p_beyond_is_mass_beyond_every_cell_and_probs_are_conditional():
    """DepthPrediction's bin probabilities are conditional on a surface within range: the frame path
    integrates (1 - p_beyond) · probs with p_beyond as mass beyond every cell, and skips pixels with
    p_beyond > 1 - eps."""
    from mono_map.depth.bins import DepthBins
    from mono_map.depth.inference import DepthPrediction
    from mono_map.mapping.distribution_frame import distribution_frame
    from mono_map.mapping.inputs import bin_edges
    from mono_map.mapping.distribution import DistributionConfig
    from mono_map.mapping.points import pixel_points_to_world

    cfg = OctoMapConfig(resolution=0.2)
    depth, T = depth_frame(0), pose(0)
    edges = bin_edges(None)
    bins = DepthBins()
    assert len(edges) == bins.num_bins + 1
    idx = np.clip(np.searchsorted(edges, depth, side="right") - 1, 0, bins.num_bins - 1)
    probs = np.zeros((bins.num_bins,) + depth.shape, np.float32)
    np.put_along_axis(probs, idx[None], 1.0, axis=0)                 # conditional: each pixel sums to 1
    pb = np.full(depth.shape, 0.3, np.float32)
    pb[:, :8] = 0.9                                                  # nothing within range: skipped at eps 0.2
    dcfg = DistributionConfig(eps=0.2, ray_step=1, min_update=0.0, temperature=1.0, quantum=0.0, snap_free=False)
    valid = np.ones(depth.shape, bool)

    got = MapIntegrator(cfg)
    _, n = distribution_frame(got, DepthPrediction(depth=depth, entropy=np.zeros_like(depth), probs=probs,
                                                   p_beyond=pb), valid, K, T, edges, dcfg, 0)
    assert n == depth.size - 8 * depth.shape[0]

    v, u = np.nonzero(pb <= 1 - dcfg.eps)
    rows = np.moveaxis(probs, 0, -1)[v, u]
    b = pb[v, u].astype(np.float64)
    unconditional = (rows * (1 - b)[:, None]).astype(np.float32)
    fd = far_depth(unconditional, b, edges, dcfg.eps)
    ref = MapIntegrator(cfg)
    ref.insert_updates(distribution_update(camera_origin(T), pixel_points_to_world(u, v, fd, K, T), fd, unconditional,
                                           b, edges, cfg.resolution, ref.hit, ref.miss, cfg.max_range, 0.0))
    got_cells, ref_cells = tree_cells(got.tree), tree_cells(ref.tree)
    assert got_cells == ref_cells

    # read as unconditional (p_beyond ignored), the same probabilities (same pixels) claim more occupancy
    sure = MapIntegrator(cfg)
    distribution_frame(sure, DepthPrediction(depth=depth, entropy=np.zeros_like(depth), probs=probs),
                       pb <= 1 - dcfg.eps, K, T, edges, dcfg, 0)
    sure_cells = tree_cells(sure.tree)
    common = sorted(set(sure_cells) & set(got_cells))
    assert len(common) > 1000                                       # rays to other far points: other cells too
    diff = np.array([got_cells[c] - sure_cells[c] for c in common])
    assert np.median(diff) <= 0 and diff.sum() < 0
    assert sum(v > 0 for v in got_cells.values()) < sum(v > 0 for v in sure_cells.values())


@pytest.mark.parametrize("integrate", ["keep", "distribution"])
def test_probability_colouring_observers_get_updated_cells(tiny_root, integrate):
    """With an observer colouring by probability, every frame's update carries the cells it updated with
    the probability the final tree holds for them (last frame); without one, none are computed."""
    from mono_map.data.kitti import open_sequence
    from mono_map.mapping.pipeline import build_map
    from mono_map.mapping.jobs import MapJob
    from mono_map.mapping.oracle import NoisyGroundTruthPredictor

    class Recorder(list):
        def __init__(self, colour):
            super().__init__()
            self.colour = colour

        def __call__(self, update):
            self.append(update)

    seq = open_sequence(tiny_root, "tiny")
    prob, height = Recorder("probability"), Recorder("height")
    res = build_map(seq, MapJob.spec("mono", range(0, 2), keep=1.0, stride=2, integrate=integrate),
                    predictor=NoisyGroundTruthPredictor(sigma=0.01, edge_sigma=0.0), observers=[prob, height],
                    show_progress=False)
    last = prob[-1]
    assert len(last.updated_cells) == len(last.updated_probability) > 100
    assert ((last.updated_probability > 0.5) & (last.updated_probability < 1)).all()   # the occupied ones
    rng = np.random.default_rng(0)
    for j in rng.choice(len(last.updated_cells), 50, replace=False):
        node = res.tree.search(last.updated_cells[j])
        assert abs(node.getOccupancy() - last.updated_probability[j]) < 1e-5
    assert height[-1] is last                                       # one update object for every observer
    alone = Recorder("height")
    build_map(seq, MapJob.spec("mono", range(0, 1), keep=1.0, stride=2, integrate=integrate), observers=[alone],
              predictor=NoisyGroundTruthPredictor(sigma=0.01, edge_sigma=0.0), show_progress=False)
    assert alone[0].updated_cells is None and alone[0].updated_probability is None


@pytest.mark.parametrize("temperature", [0.5, 0.3, 2.0])
def test_temperature_sharpens_keeps_the_mass_and_is_the_same_in_chunks(temperature):
    from mono_map.mapping.distribution import apply_temperature

    rng = np.random.default_rng(5)
    p = (rng.dirichlet(np.full(16, 0.4), size=1003) * rng.uniform(0.2, 1.0, (1003, 1))).astype(np.float32)
    p[7] = 0.0                                                            # a pixel with no mass stays empty
    whole = np.asarray(p, np.float64) ** (1.0 / temperature)
    s = whole.sum(axis=1, keepdims=True)
    want = (whole * (np.asarray(p, np.float64).sum(axis=1, keepdims=True) / np.where(s > 0, s, 1.0))).astype(np.float32)
    got = apply_temperature(p, temperature, rows=100)                     # 11 chunks, the last one short
    assert got.dtype == np.float32 and np.array_equal(got, want)          # the same to the bit as in one piece
    assert np.allclose(got.sum(axis=1), p.sum(axis=1), atol=1e-5) and not got[7].any()
    peak_up = got.max(axis=1)[p.sum(axis=1) > 0] > p.max(axis=1)[p.sum(axis=1) > 0]
    assert peak_up.all() if temperature < 1 else (~peak_up).all()        # T < 1 sharpens, T > 1 flattens
    assert apply_temperature(p, 1.0) is p


def test_unconditional_mass_is_the_two_step_formula_to_the_bit():
    from mono_map.mapping.distribution import apply_temperature, unconditional_mass

    rng = np.random.default_rng(6)
    p = rng.dirichlet(np.full(12, 0.5), size=777).astype(np.float32)
    pb = rng.uniform(0, 1, 777)
    for t in (1.0, 0.5):
        want = (np.asarray(apply_temperature(p, t), np.float64) * (1.0 - pb)[:, None]).astype(np.float32)
        got = unconditional_mass(p, pb, t, rows=50)
        assert got.dtype == np.float32 and np.array_equal(got, want)
        assert np.allclose(got.sum(axis=1), 1.0 - pb, atol=1e-5)


def street_rays(n_frames: int = 2, seed: int = 11):
    """Rays of street-like depth frames with broad random distributions around each pixel's depth (many rays
    share a far cell, as in a real frame): per frame (origin, far points, far depths, probs, p_beyond, edges)."""
    rng = np.random.default_rng(seed)
    edges = np.geomspace(1.0, 80.0, 65)
    out = []
    for i in range(n_frames):
        depth, T = depth_frame(i), pose(i)
        d = depth.reshape(-1).astype(np.float64)
        centre = np.searchsorted(edges, d) - 1
        logits = -0.5 * ((np.arange(64)[None, :] - centre[:, None]) / rng.uniform(0.1, 3.0, (len(d), 1))) ** 2
        probs = np.exp(logits) * rng.uniform(0.5, 1.0, logits.shape)
        probs = (probs / probs.sum(axis=1, keepdims=True) * 0.97).astype(np.float32)
        pb = np.full(len(d), 0.03)
        fd = far_depth(probs, pb, edges, 0.3)
        mask = np.ones(depth.shape, bool)
        out.append((camera_origin(T), pixels_to_world(fd.reshape(depth.shape).astype(np.float32), mask, K, T), fd,
                    probs, pb, edges))
    return out


@pytest.mark.parametrize("max_range", [-1.0, 14.0])
@pytest.mark.parametrize("miss, min_update", [(MISS, 0.05), (np.float32(np.log(0.45 / 0.55)), 0.1)])
def test_skipping_surely_free_cells_gives_the_same_snapped_updates(max_range, miss, min_update, weights_path):
    """With ``snap_free`` the kernel skips the cells where a ray's update surely snaps to a whole miss: the
    snapped updates equal snapping the exact per-cell updates (all cells, all values), with OctoMap's miss and
    a weaker one."""
    from mono_map.mapping.distribution import snap_threshold

    for origin, far, fd, probs, pb, edges in street_rays():
        exact = distribution_update(origin, far, fd, probs, pb, edges, 0.2, HIT, miss, max_range,
                                    min_update=min_update)
        want = quantise_updates(exact.dl, HIT, miss, 0.2, snap_free=True)
        fast = distribution_update(origin, far, fd, probs, pb, edges, 0.2, HIT, miss, max_range,
                                   min_update=min_update, quantum=0.2, snap_free=True)
        keys = exact.keys[want != 0]
        a, b = np.lexsort(keys.T), np.lexsort(fast.keys.T)
        assert len(keys) > 20_000 and (want == miss).mean() > 0.5 and (want > 0).any()
        assert np.array_equal(keys[a], fast.keys[b]) and np.array_equal(want[want != 0][a], fast.dl[b])
    thr = np.float32(snap_threshold(float(HIT), float(MISS), 0.2, 0.05))
    snapped = quantise_updates(np.array([thr, np.nextafter(thr, np.float32(0))]), HIT, MISS, 0.2, snap_free=True)
    assert snapped[0] == MISS and snapped[1] == 0 and thr <= -0.05      # the largest value that snaps to a miss


def test_the_checks_row_mass_is_the_kernels_own_sum(monkeypatch):
    """distribution_update hands the check's per-row sums to the kernel: the same bits as the kernel summing
    each ray's bins itself (bin order, float64), so the updates are identical."""
    from mono_map.mapping import distribution_c
    from mono_map.mapping.distribution import row_stats

    origin, far, fd, probs, pb, edges = street_rays(1)[0]
    mass = np.empty(len(probs))
    row_stats(probs, pb, mass)
    assert np.array_equal(mass, np.cumsum(probs.astype(np.float64), axis=1)[:, -1])   # sequential, bin order
    given = distribution_update(origin, far, fd, probs, pb, edges, 0.2, HIT, MISS, quantum=0.2, snap_free=True)
    plain = distribution_c.ray_weights_c
    monkeypatch.setattr(distribution_c, "ray_weights_c", lambda *a, **k: plain(*a, **{**k, "mass": None}))
    summed = distribution_update(origin, far, fd, probs, pb, edges, 0.2, HIT, MISS, quantum=0.2, snap_free=True)
    a, b = np.lexsort(given.keys.T), np.lexsort(summed.keys.T)      # two threads: cells in either order
    assert len(given.dl) > 20_000 and (given.dl > 0).any()
    assert np.array_equal(given.keys[a], summed.keys[b]) and np.array_equal(given.dl[a], summed.dl[b])


@pytest.mark.parametrize("n", [300, 9000])                    # one call; two threads' halves
def test_ray_distributions_of_selected_rows_are_those_of_the_gathered_rows(monkeypatch, n):
    from mono_map.mapping import raycast_c
    from mono_map.mapping.distribution import ray_distributions

    rng = np.random.default_rng(12)
    edges = np.geomspace(1.0, 80.0, 17)
    grid = (rng.dirichlet(np.full(16, 0.3), size=2 * n) * 0.9).astype(np.float32)
    rows = np.sort(rng.choice(2 * n, n, replace=False))
    pb = rng.uniform(0, 0.1, n)
    want = ray_distributions(grid[rows], pb, 0.5, edges, 0.4)
    got = ray_distributions(grid, pb, 0.5, edges, 0.4, rows=rows)
    assert np.array_equal(want[0], got[0]) and np.array_equal(want[1], got[1])
    with pytest.raises(IndexError):
        ray_distributions(grid, pb[:2], 0.5, edges, 0.4, rows=np.array([0, 2 * n]))
    monkeypatch.setattr(raycast_c, "load_kernel", lambda: None)            # the numpy formulas: the same rows
    slow = ray_distributions(grid, pb, 0.5, edges, 0.4, rows=rows)
    np.testing.assert_allclose(slow[0], got[0], rtol=1e-6, atol=1e-9)


def test_compiled_ray_distributions_match_the_numpy_formulas(monkeypatch):
    from mono_map.mapping.distribution import ray_distributions, unconditional_mass

    rng = np.random.default_rng(8)
    edges = np.geomspace(1.0, 80.0, 17)
    n = 5003                                                      # rows in blocks of 4, and a tail
    p = (rng.dirichlet(np.full(16, 0.3), size=n) * rng.uniform(0.3, 1.0, (n, 1))).astype(np.float32)
    p[3] = 0.0
    pb = rng.uniform(0, 1, n)
    for t in (1.0, 0.5, 0.7):
        mass, fd = ray_distributions(p, pb, t, edges, 0.4)
        assert np.array_equal(fd, far_depth(mass, pb, edges, 0.4))   # row by row: the same bits
        want = unconditional_mass(p, pb, t)
        if t == 1.0:
            assert np.array_equal(mass, want)                     # no sums involved: to the bit
        np.testing.assert_allclose(mass, want, rtol=2e-6, atol=1e-12)
        np.testing.assert_allclose(fd, far_depth(want, pb, edges, 0.4), rtol=1e-5)
        q = p.copy()
        again, fd2 = ray_distributions(q, pb, t, edges, 0.4, overwrite=True)
        assert np.array_equal(again, mass) and np.array_equal(fd2, fd) and np.shares_memory(again, q)
    monkeypatch.setenv("MONO_MAP_NO_C", "1")
    from mono_map.mapping import raycast_c

    monkeypatch.setattr(raycast_c, "_TRIED", False)
    monkeypatch.setattr(raycast_c, "_LIB", None)
    mass, fd = ray_distributions(p, pb, 0.5, edges, 0.4)
    assert np.array_equal(mass, unconditional_mass(p, pb, 0.5))


@pytest.mark.parametrize("n, k", [(300, 8), (9000, 11)])   # one call; two threads' halves (> 2 × 4096 rows)
def test_distribution_checks_agree_compiled_and_numpy(monkeypatch, n, k):
    from mono_map.mapping import distribution, raycast_c

    rng = np.random.default_rng(9)
    p = rng.dirichlet(np.ones(k), size=n).astype(np.float32) * 0.9
    pb = rng.uniform(0, 0.1, n)
    p[5, 2], p[9, 1], p[12, 3], pb[4] = np.nan, -0.25, -np.inf, np.inf
    p[11] *= 1.5
    p[n - 7, k - 1], p[n - 3, 0] = -0.5, np.nan          # in the second half, the last / first bin
    compiled = distribution.row_stats(p, pb)
    monkeypatch.setattr(raycast_c, "load_kernel", lambda: None)
    numpy_ = distribution.row_stats(p, pb)
    assert compiled == pytest.approx(numpy_, rel=1e-9)
    assert compiled["bad_p"] == 3 and compiled["neg_p"] == 2 and compiled["bad_b"] == 1 and compiled["n_over"] >= 1
    assert compiled["min_p"] == -0.5


def test_oracle_probabilities_at_a_pixel_step_are_its_full_maps_there(tiny_root):
    from mono_map.data.kitti import open_sequence
    from mono_map.mapping.oracle import NoisyGroundTruthPredictor

    seq, oracle = open_sequence(tiny_root, "tiny"), NoisyGroundTruthPredictor()
    full = oracle.predict_frame(seq, 1, with_probs=True)
    grid = oracle.predict_frame(seq, 1, with_probs=True, probs_step=2)
    assert grid.probs_step == 2 and np.moveaxis(grid.probs, 0, -1).flags.c_contiguous
    assert np.array_equal(grid.probs, full.probs[:, ::2, ::2]) and np.array_equal(grid.p_beyond, full.p_beyond)
    assert np.array_equal(grid.depth, full.depth)


def test_probabilities_at_a_step_the_rays_cannot_use_are_one_clear_error(tiny_root):
    from mono_map.data.kitti import open_sequence
    from mono_map.mapping.pipeline import build_map
    from mono_map.mapping.jobs import MapJob
    from mono_map.mapping.distribution import DistributionConfig
    from mono_map.mapping.oracle import NoisyGroundTruthPredictor

    class EveryThird(NoisyGroundTruthPredictor):
        def predict_frame(self, seq, i, image=None, with_probs=False, probs_step=1):
            return super().predict_frame(seq, i, image, with_probs=with_probs, probs_step=3)

    seq = open_sequence(tiny_root, "tiny")
    with pytest.raises(MonoMapError, match="every 3 pixels cannot serve rays every 2"):
        build_map(seq,
                  MapJob.spec("mono", range(0, 1), integrate="distribution",
                              distribution=DistributionConfig(ray_step=2)),
                  predictor=EveryThird(), show_progress=False)
    # rays every 6th pixel are served by probabilities every 3rd: the same map as from full-resolution ones
    maps = []
    for pred in (EveryThird(), NoisyGroundTruthPredictor()):
        r = build_map(seq,
                      MapJob.spec("mono", range(0, 2), integrate="distribution",
                                  distribution=DistributionConfig(ray_step=6)),
                      predictor=pred, show_progress=False)
        maps.append(tree_cells(r.tree))
    assert len(maps[0]) > 100 and maps[0] == maps[1]



@pytest.mark.parametrize("threads", ["1", "2"])
def test_an_interrupted_frame_leaves_the_reused_buffers_clean(monkeypatch, threads):
    """An error (e.g. Ctrl-C) in the middle of a frame's kernel calls must not leave updates in the buffers the
    next frame reuses: the same frame integrated again gives the same updates as before the interrupt."""
    from mono_map.mapping import kernel_threads, raycast_c

    monkeypatch.setenv("MONO_MAP_RAY_THREADS", threads)
    monkeypatch.setattr(kernel_threads, "PARALLEL_MIN_RAYS", 1)
    o1, f1, d1, p1, b1, e1 = street_rays(1, seed=5)[0]

    def second():
        u = distribution_update(o1, f1, d1, p1, b1, e1, 0.2, HIT, MISS, min_update=0.05)
        order = np.lexsort(u.keys.T)
        return u.keys[order], u.dl[order]

    want = second()
    kernel = raycast_c.load_kernel()
    real, counter, calls = kernel.weights, itertools.count(), []

    def failing(*args):
        k = next(counter)                   # atomic: the two threads' calls get distinct numbers
        calls.append(k)
        out = real(*args)                   # the buffer is written, then the "interrupt" comes
        if k == (0 if threads == "1" else 2):   # one call on one thread; 16 chunks on two
            raise KeyboardInterrupt
        return out

    monkeypatch.setattr(kernel, "weights", failing)
    with pytest.raises(KeyboardInterrupt):
        distribution_update(o1, f1, d1, p1, b1, e1, 0.2, HIT, MISS, min_update=0.05)
    monkeypatch.setattr(kernel, "weights", real)
    got = second()
    assert calls and np.array_equal(got[0], want[0]) and np.array_equal(got[1], want[1])
