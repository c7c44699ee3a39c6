"""Greenery in the synthetic towns (issue 31): hedges along the frontages, canopy trees over the road."""

from dataclasses import replace

import numpy as np
import pytest

from mono_map.data.synth import load_recipe
from mono_map.data.synth import materials as M
from mono_map.data.synth.randomize import (detailed_towns, greenery_towns, randomized_recipe, traffic_towns,
                                           training_towns, validation_town)
from mono_map.data.synth.town import build_town
from mono_map.data.synth.trajectory import PathIndex, build_road_path, town_poses
from mono_map.errors import MonoMapError


@pytest.fixture(scope="module")
def towns():
    """tiny's recipe as it is and with greenery: (recipe, plain town, green recipe, green town)."""
    recipe = load_recipe("tiny")
    green = replace(recipe, trees=replace(recipe.trees, canopy=0.9), props=replace(recipe.props, hedge_fraction=0.9))
    return recipe, build_town(recipe), green, build_town(green)


def test_greenery_only_adds_to_a_town(towns):
    """Everything of the town without greenery is there unchanged (the greenery draws from its own streams, after
    the rest); the hash of a recipe without greenery is what it was, with greenery another."""
    recipe, plain, green, town = towns
    n, f = len(plain.vertices), len(plain.triangles)
    assert len(town.triangles) > f
    assert np.array_equal(town.vertices[:n], plain.vertices) and np.array_equal(town.triangles[:f], plain.triangles)
    assert np.array_equal(town.tri_material[:f], plain.tri_material)
    assert np.array_equal(town.tri_object[:f], plain.tri_object)
    assert np.array_equal(town.obj_color[:len(plain.obj_color)], plain.obj_color)
    assert {k: v for k, v in town.stats.items() if k not in ("canopy_trees", "hedges", "triangles")} == \
        {k: v for k, v in plain.stats.items() if k != "triangles"}
    assert town.stats["canopy_trees"] > 0 and town.stats["hedges"] > 0
    assert "canopy_trees" not in plain.stats and "hedges" not in plain.stats
    assert replace(recipe, trees=replace(recipe.trees, canopy=0.0)).content_hash() == recipe.content_hash()
    assert green.content_hash() != recipe.content_hash()
    new = set(np.unique(town.tri_material[f:]).tolist())
    assert new == {M.TRUNK, M.FOLIAGE}


def test_canopy_crowns_reach_over_the_road_above_the_trucks_and_hedges_stay_off_it(towns):
    recipe, plain, green, town = towns
    st = green.street
    index = PathIndex(build_road_path(town_poses(green)[1]), margin=5.0)
    f = len(plain.triangles)
    objects = np.unique(town.tri_object[f:])
    over_road, crowns, hedges = 0, 0, 0
    for o in objects:
        tris = np.flatnonzero(town.tri_object == o)
        mats = town.tri_material[tris]
        leaf = np.unique(town.triangles[tris[mats == M.FOLIAGE]])
        xz = town.vertices[leaf][:, [0, 2]]
        dist = index.query(xz)[1]
        if (mats == M.TRUNK).any():               # a canopy tree: trunk on the sidewalk, crown >= 4.5 m up
            trunk = np.unique(town.triangles[tris[mats == M.TRUNK]])
            ground_y = town.vertices[trunk, 1].max() - 0.2        # y points down; the trunk starts 0.2 m below
            height = ground_y - town.vertices[leaf, 1]
            assert height.min() >= 4.5, height.min()
            assert index.query(town.vertices[trunk][:, [0, 2]])[1].min() >= 0.5 * st.lane_width + st.parking_width - 0.2
            crowns += 1
            over_road += int((dist < 0.5 * st.lane_width + st.parking_width).any())
        else:                      # a hedge: boxes of 8 vertices, behind the sidewalk, 0.8-2.35 m high
            y = town.vertices[leaf, 1].reshape(-1, 8)
            height = y.max(axis=1) - 0.2 - y.min(axis=1)      # each box starts 0.2 m below the ground
            assert 0.8 * 0.93 - 0.01 <= height.min() and height.max() <= 2.2 * 1.07 + 0.01
            assert dist.min() >= 0.5 * st.lane_width + st.parking_width + st.sidewalk_width - 0.3
            hedges += 1
    assert crowns == town.stats["canopy_trees"] and hedges >= town.stats["hedges"]
    assert over_road >= crowns // 2


def test_greenery_twins_are_a_family_of_their_own():
    """q, g, e: twins of the painted p, d, v towns, same seeds, greenery on; every other family keeps its spec."""
    painted = detailed_towns(training_towns()[:2] + traffic_towns(2) + traffic_towns(2, kerb_trucks=True))
    twins = greenery_towns(painted)
    assert [t.name for t in twins] == ["q01_0a", "q02_0a", "g01_0a", "g02_0a", "e01_0a", "e02_0a"]
    for p, g in zip(painted, twins):
        assert g.seed == p.seed and g.greenery and not p.greenery
        assert g.to_dict()["greenery"] is True and "greenery" not in p.to_dict()
        rp, rg = randomized_recipe(p), randomized_recipe(g)
        assert rp.trees.canopy == 0 and rp.props.hedge_fraction == 0
        assert 0.3 <= rg.trees.canopy <= 0.8 and 0.3 <= rg.props.hedge_fraction <= 0.8
        assert replace(rg, trees=rp.trees, props=rp.props, name=rp.name) == rp
    with pytest.raises(ValueError, match="t01_0a"):
        greenery_towns(training_towns()[:1])
    assert "greenery" not in validation_town().to_dict()


def test_greenery_values_are_checked(tmp_path):
    from mono_map.data.synth.recipe import load_recipe as load

    p = tmp_path / "bad.toml"
    p.write_text('seed = 1\nframes = 5\ntrajectory = "00"\n[trees]\ncanopy = 1.5\n')
    with pytest.raises(MonoMapError, match="canopy"):
        load(p)


def test_render_trainset_refuses_greenery_without_detailed(tmp_path, capsys):
    from mono_map.cli import main

    assert main(["render-trainset", "--root", str(tmp_path / "ts"), "--greenery"]) == 2
    err = capsys.readouterr().err
    assert "--greenery" in err and "--detailed" in err and "Traceback" not in err
    assert not (tmp_path / "ts").exists()
