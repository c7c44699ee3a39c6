"""Traffic in the driving lanes and large vehicles (mono_map/data/synth/traffic.py, issue 31)."""

import hashlib
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from mono_map.data.synth import materials as M
from mono_map.data.synth import generate_sequence, load_recipe
from mono_map.data.synth.placement import LARGE
from mono_map.data.synth.randomize import (TownSpec, detailed_towns, jam_towns, randomized_recipe, traffic_towns,
                                           training_towns, validation_town)
from mono_map.data.synth.recipe import TrafficParams
from mono_map.data.synth.town import build_town
from mono_map.data.synth.traffic import (EGO_AHEAD, EGO_BEHIND, EGO_HALF_WIDTH, LANE_CLEARANCE, clear_frames,
                                         rectangles_overlap)
from mono_map.data.synth.trajectory import frame_poses
from mono_map.errors import MonoMapError

# Recorded with the code before lane traffic existed (commit 55c7d7b): a recipe without [traffic] must
# keep its content hash (the rendered sequences and the training cache key on it) and its town and pixels.
HASHES_BEFORE = {"00": "fa93e2f05d4aaf47", "05": "b7af44eff0e39e00", "06": "31dbe4aa67f1b6c7",
                 "07": "6a91b080a88cbf16", "08": "cdce61458aafaedf", "09": "749244ea084f1c62",
                 "10": "0b7f40a37bc00f97", "tiny": "3f0967354fefdba0"}
TOWN_HASHES_BEFORE = {"val09": "32d5daf90668ef53", "t01_0a": "064d1a3f026e3ba9", "t02_0a": "f954163070af53df",
                      "t03_0a": "3167176714920f39", "t04_0a": "cf1fe3b3f108b37c", "t05_0a": "57c40b2231d34c14",
                      "t06_0a": "3034f1ccf1c1231d"}
TINY_TOWN_BEFORE = "e0bc39febc6707fa"         # sha256 of the tiny town's arrays
# The rendered pixels before traffic existed. Depth and LiDAR are compared exactly (sha256 of the arrays); the colour
# image by its per-channel sums within RGB_SUM_TOLERANCE: numpy picks its SIMD kernels of the shading's float math by
# CPU (AVX512_SPR on the Xeons with AMX, AVX512_ICL on an AMD EPYC, ...), which moves a handful of 8-bit values by one
# level (4 of tiny frame 2's 1.4 M between two dispatch levels), while a vehicle or any change of the scene moves the
# sums by thousands.
TINY_FRAME2_BEFORE = ("b07609eb334f62ac", (23282573, 25358287, 28127346))   # tiny frame 2: depth + LiDAR, rgb sums
TRAINSET_FRAME1_BEFORE = ("a109c0df15882fa7", (10026703, 10160940, 8429642))  # frame 1 of a training-cache town
RGB_SUM_TOLERANCE = 64


def _same_pixels(rgb, *rest, before) -> bool:
    """``rgb`` (H, W, 3) uint8 and the other arrays of a render are those of ``before`` (see TINY_FRAME2_BEFORE)."""
    sums = np.asarray(rgb).reshape(-1, 3).sum(axis=0, dtype=np.int64)
    return _digest(*rest) == before[0] and int(np.abs(sums - np.array(before[1])).max()) <= RGB_SUM_TOLERANCE


def _digest(*arrays) -> str:
    h = hashlib.sha256()
    for a in arrays:
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()[:16]


TRAFFIC = TrafficParams(adjacent_density=0.8, ahead_spacing=40.0, large_fraction=0.6, kerb_large_density=0.5)
# the first towns with traffic (rendered into the training cache before kerb_large_density existed)
H_TOWN_HASHES = {"h01_0a": "09148306e7c7ed88", "h02_0a": "e07346b66f2a7b6c", "h03_0a": "71c9347fdb86a897",
                 "h04_0a": "0f774c551d694a17", "h05_0a": "ec99c34c496a7834", "h06_0a": "9c91750e04f97844"}


@pytest.fixture(scope="module")
def busy_tiny():
    """tiny's stretch of 00, 40 frames, with lane traffic in both lanes: (recipe, town, poses, kept mask)."""
    recipe = replace(load_recipe("tiny"), frames=40, traffic=TRAFFIC)
    town = build_town(recipe)
    poses = frame_poses(recipe)
    return recipe, town, poses, clear_frames(town.lane_vehicles, poses)


def test_recipes_without_traffic_keep_their_hash_town_and_pixels():
    from mono_map.data.synth import FrameRenderer

    for name, h in HASHES_BEFORE.items():
        assert load_recipe(name).content_hash() == h, name
    specs = {s.name: s for s in [validation_town()] + training_towns()[:6]}
    for name, h in TOWN_HASHES_BEFORE.items():
        assert randomized_recipe(specs[name]).content_hash() == h, name
        new_keys = ("traffic", "kerb_trucks", "vehicle_detail", "jam", "greenery")
        assert specs[name].to_dict() == {k: v for k, v in vars(specs[name]).items() if k not in new_keys}
    recipe = load_recipe("tiny")
    assert recipe.traffic == TrafficParams() and not recipe.traffic.enabled()
    town = build_town(recipe)
    # vehicles record their frame (ground centre, forward, size) for painted details since [cars] detail; the
    # rest of the arrays, and the pixels below, are what they were
    from mono_map.data.synth import materials as M

    vehicles = np.unique(town.tri_object[town.tri_material == M.CAR_PAINT])
    assert len(vehicles) and (town.obj_params[vehicles, 2] > 0).all()
    origin, params = town.obj_origin.copy(), town.obj_params.copy()
    origin[vehicles], params[vehicles] = 0, 0
    assert _digest(town.vertices, town.triangles, town.tri_material, town.tri_object, town.obj_color,
                   town.obj_flags, origin, params) == TINY_TOWN_BEFORE
    assert town.lane_vehicles.shape == (0, 4, 2) and "lane_vehicles" not in town.stats
    assert _same_pixels(*FrameRenderer(recipe, town, nthreads=1).render(2), before=TINY_FRAME2_BEFORE)
    from mono_map.data.synth.trainset import TownRenderer

    spec = TownSpec(name="t04_test", trajectory="04", first_pose=100, pose_stride=3, frames=3, seed=12345)
    tr = TownRenderer(spec, 1)
    assert tr.frames == 3 and tr.pose_index.tolist() == [0, 1, 2]
    assert _same_pixels(*tr.render(1), before=TRAINSET_FRAME1_BEFORE)
    # a [traffic] section at its defaults is the same recipe
    assert replace(recipe, traffic=TrafficParams()).content_hash() == HASHES_BEFORE["tiny"]
    assert replace(recipe, traffic=TRAFFIC).content_hash() != HASHES_BEFORE["tiny"]


def test_large_vehicles_have_their_size(busy_tiny):
    _, town, _, _ = busy_tiny
    large = np.flatnonzero(town.obj_flags & LARGE)
    assert town.stats["large_vehicles"] == len(large) >= 3
    assert town.stats["lane_vehicles"] == len(town.lane_vehicles) > town.stats["large_vehicles"]
    for oid in large:
        V = town.vertices[np.unique(town.triangles[town.tri_object == oid])].astype(np.float64)
        height = V[:, 1].max() - V[:, 1].min()                       # y is down; wheels touch the ground
        xz = V[:, [0, 2]] - V[:, [0, 2]].mean(0)
        axes = np.linalg.eigh(xz.T @ xz)[1]                          # columns: across, along
        width, length = np.ptp(xz @ axes, axis=0)
        assert 3.0 - 1e-3 <= height <= 4.0 + 1e-3
        assert 7.0 - 1e-3 <= length <= 13.0 + 1e-3 and 2.4 - 0.1 <= width <= 2.6 + 0.05


def _vehicle_scene(town):
    import open3d as o3d

    veh = np.isin(town.tri_material, [M.CAR_PAINT, M.CAR_GLASS, M.TYRE]) | \
        ((town.tri_material == M.METAL) & (town.tri_object >= 0) & ((town.obj_flags[town.tri_object] & LARGE) > 0))
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(town.vertices), o3d.core.Tensor(town.triangles[veh].astype(np.uint32)))
    return scene


def test_the_camera_car_never_intersects_a_vehicle(busy_tiny):
    """At every rendered frame, rays through the camera car's box (the camera 3 m ahead of its nose ... 4.5 m
    behind, ±1.2 m, 0.3-2 m above the road) meet no vehicle: a vehicle overlapping it would be hit, from
    outside or inside (ray casting is two-sided). The adjacent lane keeps its distance from every pass."""
    import open3d as o3d

    from mono_map.data.synth.placement import footprint_samples
    from mono_map.data.synth.trajectory import PathIndex, build_road_path, town_poses

    recipe, town, poses, keep = busy_tiny
    assert 0 < keep.sum() < len(keep)                       # the own lane's vehicles do cost frames
    scene = _vehicle_scene(town)
    lat = np.arange(-EGO_HALF_WIDTH, EGO_HALF_WIDTH + 1e-9, 0.2)
    along = np.arange(-EGO_BEHIND, EGO_AHEAD + 1e-9, 0.25)
    heights = np.array([0.3, 0.8, 1.3, 2.0])
    blocked_seen = 0
    for T, kept in zip(poses, keep):
        x, down, z, c = T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3]
        ground = c + down * 1.65
        rays = []
        for h in heights:
            for a in lat:                                     # back to front
                o = ground - down * h + x * a - z * EGO_BEHIND
                rays.append(np.r_[o, z])
            for b in along:                                   # left to right
                o = ground - down * h + z * b - x * EGO_HALF_WIDTH
                rays.append(np.r_[o, x])
        t = scene.cast_rays(o3d.core.Tensor(np.array(rays, np.float32)))["t_hit"].numpy()
        n_fwd = len(lat)
        per_h = n_fwd + len(along)
        t = t.reshape(len(heights), per_h)
        hit = (t[:, :n_fwd] <= EGO_BEHIND + EGO_AHEAD).any() or (t[:, n_fwd:] <= 2 * EGO_HALF_WIDTH).any()
        if kept:
            assert not hit
        blocked_seen += int(hit)
    assert blocked_seen >= 1                                  # the test sees the vehicles it is meant to see
    path = build_road_path(town_poses(recipe)[1])
    index = PathIndex(path, margin=70.0)
    adjacent = [f for f in town.lane_vehicles if index.min_distance(f.mean(0)[None]) > 1.0]   # and at the kerbs
    k = index.query(np.array([f.mean(0) for f in adjacent]))[0]
    lateral = np.einsum("ij,ij->i", np.array([f.mean(0) for f in adjacent]) - path.points[k][:, [0, 2]],
                        path.right[k][:, [0, 2]])
    assert (lateral < 0).sum() >= 2 and (lateral > 0).sum() >= 1    # left lane/kerb; right kerb (a truck parked)
    for f in adjacent:                                        # footprints, sampled: LANE_CLEARANCE from the path
        c3 = np.array([f.mean(0)[0], 0.0, f.mean(0)[1]])
        fw, rw = f[0] - f[3], f[0] - f[1]
        L, W = np.linalg.norm(fw), np.linalg.norm(rw)
        pts = footprint_samples(c3, np.array([fw[0] / L, 0, fw[1] / L]), np.array([rw[0] / W, 0, rw[1] / W]),
                                L / 2, W / 2, step=0.2)
        assert index.min_distance(pts) >= LANE_CLEARANCE - 1e-6


def test_lane_vehicles_appear_in_the_render_where_placed(busy_tiny):
    """The own lane's next vehicle ahead: the middle of its back, 0.6 m (a large one: 1.5 m) above the road,
    is in the depth image at its distance, and the camera ray through it hits that vehicle's mesh."""
    import open3d as o3d

    from mono_map.data.synth import FrameRenderer

    recipe, town, poses, keep = busy_tiny
    fr = FrameRenderer(recipe, town, nthreads=1)
    checked, large = 0, 0
    for i in np.flatnonzero(keep)[::3]:
        T_world_cam2 = poses[i] @ fr.T_cam0_cam2
        T_cam2_world = np.linalg.inv(T_world_cam2)
        best = None
        for f, oid in zip(town.lane_vehicles, town.lane_vehicle_ids):
            V = town.vertices[np.unique(town.triangles[town.tri_object == oid])]
            h = 1.5 if town.obj_flags[oid] & LARGE else 0.6
            back = (f[2] + f[3]) / 2                              # corners 2, 3: the vehicle's back
            p = T_cam2_world @ np.array([back[0], V[:, 1].max() - h, back[1], 1.0])   # y down: max = the road
            if abs(p[0]) < 0.5 and EGO_AHEAD - 0.5 < p[2] < 25 and (best is None or p[2] < best[0][2]):
                best = (p, oid)
        if best is None:
            continue
        p, oid = best
        uv = fr.K2 @ p[:3]
        u, v = int(round(uv[0] / uv[2])), int(round(uv[1] / uv[2]))
        _, depth, _ = fr.render(int(i))
        assert depth[v, u] == pytest.approx(p[2], abs=0.15)
        ray = np.r_[T_world_cam2[:3, 3], T_world_cam2[:3, :3] @ np.linalg.solve(fr.K2, [u, v, 1.0])]
        prim = fr.scene.cast_rays(o3d.core.Tensor(ray[None].astype(np.float32)))["primitive_ids"].numpy()[0]
        assert town.tri_object[prim] == oid
        checked += 1
        large += int(town.obj_flags[oid] & LARGE > 0)
    assert checked >= 2 and large >= 1


def test_traffic_values_are_checked(tmp_path):
    good = Path(load_recipe("tiny").path).read_text()
    bad = tmp_path / "bad.toml"
    for line, key in (("adjacent_density = 1.5", "adjacent_density"), ("large_fraction = -0.1", "large_fraction"),
                      ("ahead_spacing = 5.0", "ahead_spacing"), ("ahead_spacing = \"far\"", "ahead_spacing"),
                      ("trucks = 1", "trucks")):
        bad.write_text(good + f"\n[traffic]\n{line}\n")
        with pytest.raises(MonoMapError, match=key) as e:
            load_recipe(bad)
        assert "\n" not in str(e.value) and "bad.toml" in str(e.value)
    bad.write_text(good + "\n[traffic]\nadjacent_density = 0.5\nlarge_fraction = 0.5\n")
    r = load_recipe(bad)
    assert r.traffic.adjacent_density == 0.5 and r.content_hash() != HASHES_BEFORE["tiny"]
    bad.write_text(good + "\n[traffic]\nahead_spacing = 40.0\n")
    with pytest.raises(MonoMapError, match=r"ahead_spacing skips the frames.*render-trainset"):
        generate_sequence(load_recipe(bad), tmp_path / "kitti", quiet=True)
    assert not (tmp_path / "kitti").exists()                  # refused before any work


def test_traffic_towns_are_a_family_of_their_own(tmp_path):
    from mono_map.data.synth.trainset import TownCache, render_town

    towns = traffic_towns(6)
    old = training_towns()[:6]
    assert [t.name for t in towns] == ["h" + t.name[1:] for t in old]
    assert all(t.traffic for t in towns) and not any(t.traffic for t in old)
    assert not {t.seed for t in towns} & {t.seed for t in training_towns() + [validation_town()]}
    for t in towns:
        tp = randomized_recipe(t).traffic
        assert tp.enabled() and tp.large_fraction > 0 and tp.ahead_spacing >= 20 and tp.kerb_large_density == 0
        assert t.to_dict()["traffic"] is True and "kerb_trucks" not in t.to_dict()
        assert randomized_recipe(t).content_hash() == H_TOWN_HASHES[t.name]
    kerb = traffic_towns(6, kerb_trucks=True)
    assert [t.name for t in kerb] == ["k" + t.name[1:] for t in old]
    assert not {t.seed for t in kerb} & {t.seed for t in towns + training_towns()}
    assert all(randomized_recipe(t).traffic.kerb_large_density > 0 for t in kerb)
    spec = TownSpec(name="h04_test", trajectory="04", first_pose=0, pose_stride=1, frames=24, seed=777, traffic=True)
    assert render_town(tmp_path, spec) > 0
    tc = TownCache(tmp_path / "towns" / "h04_test")
    assert 0 < tc.frames <= spec.frames and np.asarray(tc.done).all()
    assert tc.meta["spec"]["traffic"] is True
    assert render_town(tmp_path, spec) == 0                   # complete: nothing to do


def test_jam_towns_are_a_family_of_their_own():
    """Traffic jams (j): the next lane nearly full, large vehicles, a vehicle close ahead, painted vehicles; other
    seeds than every other family; the other families keep their specs (and so their caches and hashes)."""
    jams, old = jam_towns(6), training_towns()[:6]
    assert [t.name for t in jams] == ["j" + t.name[1:] for t in old]
    others = training_towns() + [validation_town()] + traffic_towns(6) + traffic_towns(6, kerb_trucks=True)
    assert not {t.seed for t in jams} & {t.seed for t in others}
    for t in jams:
        r = randomized_recipe(t)
        tp = r.traffic
        assert 0.85 <= tp.adjacent_density <= 1 and 12 <= tp.ahead_spacing <= 25 and tp.large_fraction >= 0.5
        assert tp.kerb_large_density >= 0.4 and r.cars.detail > 0
        assert t.to_dict()["jam"] is True
    for t in others + detailed_towns(traffic_towns(6)):
        assert "jam" not in t.to_dict()
    assert all(randomized_recipe(t).content_hash() == H_TOWN_HASHES[t.name] for t in traffic_towns(6))


def test_rectangles_overlap():
    sq = np.array([[1, 1], [1, -1], [-1, -1], [-1, 1]], float)
    others = np.stack([sq + [1.9, 0], sq + [2.1, 0], sq * 0.2, sq @ np.array([[0.7071, 0.7071], [-0.7071, 0.7071]]) + [2.3, 2.3]])
    assert rectangles_overlap(sq, others).tolist() == [True, False, True, False]


@pytest.mark.parametrize("option", ["--traffic", "--jams"])
def test_render_trainset_refuses_a_bad_traffic_count(tmp_path, capsys, option):
    from mono_map.cli import main

    assert main(["render-trainset", "--root", str(tmp_path / "ts"), option, "-1"]) == 2
    err = capsys.readouterr().err
    assert option in err and "Traceback" not in err
    assert not (tmp_path / "ts").exists()
