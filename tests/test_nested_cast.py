"""Keep maps sharing one ray cast: compute_nested_updates equals compute_update per level, and the builders
that share_ray_casts groups build the maps they build alone."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from mono_map.config import OctoMapConfig
from mono_map.data.kitti import open_sequence
from mono_map.errors import MonoMapError
from mono_map.mapping import kernel_threads, raycast, raycast_c
from mono_map.mapping.jobs import MapJob
from mono_map.mapping.nested import compute_nested_updates
from mono_map.mapping.pipeline import build_map, build_maps, make_builders, share_ray_casts
from mono_map.mapping.octree import morton_codes, tree_leaves
from mono_map.mapping.oracle import NoisyGroundTruthPredictor


def codes(keys):
    c = morton_codes(keys)
    assert len(np.unique(c)) == len(c)           # every cell once
    return set(c.tolist())


def nested_scan(seed: int, n: int = 2500, n_levels: int = 3):
    """End points around an origin with many repeated cells, each at a random level (some levels empty)."""
    rng = np.random.default_rng(seed)
    origin = rng.uniform(-1, 1, 3)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    pts = origin + d * rng.uniform(0.5, 12.0, n)[:, None]
    pts[: n // 3] = np.round(pts[: n // 3] * 2) / 2                  # shared end cells across levels
    levels = rng.integers(0, n_levels, n)
    if seed % 2:
        levels[levels == 1] = 2                                      # an empty level in between
    return pts, levels, origin


@pytest.mark.parametrize("mode", ["c", "c-2threads", "numpy"])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_nested_updates_equal_each_scan_alone(mode, seed, monkeypatch):
    if mode == "numpy":
        monkeypatch.setenv("MONO_MAP_NO_C", "1")
    else:
        assert raycast_c.load_kernel() is not None
        monkeypatch.setenv("MONO_MAP_RAY_THREADS", "2" if mode == "c-2threads" else "1")
        if mode == "c-2threads":
            monkeypatch.setattr(kernel_threads, "PARALLEL_MIN_RAYS", 1)
    pts, levels, origin = nested_scan(seed)
    nested = compute_nested_updates(pts, levels, 3, origin, 0.2)
    assert len(nested) == 3
    for j, ks in enumerate(nested):
        alone = raycast.compute_update(pts[levels <= j], origin, 0.2)
        assert codes(ks.free) == codes(alone.free), j
        assert codes(ks.occupied) == codes(alone.occupied), j
        assert ks.n_rays == alone.n_rays and ks.n_endpoints == alone.n_endpoints
    # a later level's end cells leave the free sets from that level on: some cell is free at level 0 only
    assert codes(nested[0].free) - codes(nested[2].free)
    # the reused bitmap is left zeroed: a scan afterwards is the same as on a fresh bitmap
    again = raycast.compute_update(pts, origin, 0.2)
    kernel_threads.release_buffers()
    fresh = raycast.compute_update(pts, origin, 0.2)
    assert codes(again.free) == codes(fresh.free)


def test_nested_updates_refuse_bad_levels_in_one_line():
    pts, levels, origin = nested_scan(0, n=50)
    for bad, n_levels, what in ((levels + 5, 3, "levels: must lie in"), (levels[:-1], 3, "levels: 49 levels"),
                                (levels, 0, "n_levels")):
        with pytest.raises(MonoMapError, match=what) as e:
            compute_nested_updates(pts, bad, n_levels, origin, 0.2)
        assert "\n" not in str(e.value)


def test_share_ray_casts_groups_only_keep_maps_that_see_the_same_pixels(tiny_root):
    seq = open_sequence(tiny_root, "tiny")
    oracle, other = NoisyGroundTruthPredictor(), NoisyGroundTruthPredictor()
    limited = dataclasses.replace(OctoMapConfig(), max_range=20.0)
    def mono(predictor=oracle, **settings):
        return dict(job=MapJob.spec("mono", range(2), stride=4, **settings), predictor=predictor)

    maps = [mono(keep=0.5), mono(keep=1.0), mono(keep=0.8),
            dict(mono(keep=0.5), rank="metric"),                          # another ranking: alone
            mono(keep=0.7, octomap=limited),                              # a range limit: alone
            mono(other, keep=0.6),                                        # another prediction: alone
            mono(integrate="distribution"), dict(job=MapJob.spec("lidar-fov", range(2), stride=4))]
    builders = make_builders(seq, maps)
    share_ray_casts(builders)
    groups = [b.group for b in builders]
    assert groups[0] is not None and groups[0] == groups[1] == groups[2]
    assert groups[0].keeps == (0.5, 0.8, 1.0) and [groups[0].level(k) for k in (0.5, 0.8, 1.0)] == [0, 1, 2]
    assert groups[3:] == [None] * 5


def test_grouped_keep_maps_equal_maps_built_alone(tiny_root):
    seq = open_sequence(tiny_root, "tiny")
    keeps = (0.3, 1.0, 0.6)
    together = build_maps(seq, [dict(job=MapJob.spec("mono", range(0, 3), keep=k, stride=2),
                                     predictor=NoisyGroundTruthPredictor()) for k in keeps], show_progress=False)
    for k, res in zip(keeps, together):
        alone = build_map(seq, MapJob.spec("mono", range(0, 3), keep=k, stride=2),
                          predictor=NoisyGroundTruthPredictor(), show_progress=False)
        a, b = tree_leaves(res.tree), tree_leaves(alone.tree)
        assert np.array_equal(a.start, b.start) and np.array_equal(a.value, b.value) and a.occupied.any(), k
        for key in ("points_kept", "rays_cast", "memory_bytes", "leaf_count"):
            assert res.stats[key] == alone.stats[key], (k, key)
        assert [f["occupied_cells"] for f in res.per_frame] == [f["occupied_cells"] for f in alone.per_frame]
