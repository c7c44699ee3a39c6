"""mapping/octree.py: keys, Morton codes, trees from cells, .bt/.ot I/O and leaf expansion."""

from __future__ import annotations

import numpy as np
import pytest

from mono_map.config import OctoMapConfig
from mono_map.errors import MonoMapError
from mono_map.mapping.octree import (TREE_DEPTH, TREE_MAX_VAL, coord_to_key, key_to_coord, load_tree, morton_codes,
                                     morton_order, morton_to_keys, occupied_keys, octree_from_cells, pack_keys,
                                     tree_leaves, unpack_keys, write_tree_bt, write_tree_ot)


def test_keys_are_octomaps():
    """Our keys and cell centres are OctoMap's own (coordToKey / keyToCoord of the same tree)."""
    octomap = pytest.importorskip("octomap")
    tree = octomap.OcTree(0.2)
    pts = np.array([[0.0, 0.0, 0.0], [-0.01, 0.19, 0.21], [12.34, -5.67, 89.0]])
    keys = coord_to_key(pts, 0.2)
    for p, k in zip(pts, keys):
        theirs = tree.coordToKey(p)
        assert [theirs[0], theirs[1], theirs[2]] == k.tolist()
        assert np.allclose(tree.keyToCoord(theirs), key_to_coord(k[None], 0.2)[0], atol=1e-6)
    assert tree.getTreeDepth() == TREE_DEPTH and TREE_MAX_VAL == 1 << (TREE_DEPTH - 1)


def test_morton_codes_round_trip_and_order():
    rng = np.random.default_rng(0)
    keys = rng.integers(0, 2 * TREE_MAX_VAL, (1000, 3))
    codes = morton_codes(keys)
    assert np.array_equal(morton_to_keys(codes), keys)
    assert np.array_equal(unpack_keys(pack_keys(keys)), keys)
    # the eight children of one node are contiguous, x bit highest
    cube = np.array([[x, y, z] for x in (4, 5) for y in (6, 7) for z in (8, 9)])
    assert np.array_equal(np.sort(morton_codes(cube)) - morton_codes(cube[:1])[0], np.arange(8))
    assert np.array_equal(morton_order(cube[::-1]), np.arange(8)[::-1])


def test_tree_from_cells_round_trips_through_bt_and_ot(tmp_path):
    """Cells → tree (one .ot stream) → .bt / .ot files → leaves: the occupied cells come back, and a
    full 2×2×2 block of equal cells is one pruned leaf that expands to its eight cells."""
    pytest.importorskip("octomap")
    cfg = OctoMapConfig()
    block = np.array([[TREE_MAX_VAL + x, TREE_MAX_VAL + y, TREE_MAX_VAL + z]
                      for x in (0, 1) for y in (0, 1) for z in (0, 1)])
    lone = np.array([[TREE_MAX_VAL + 10, TREE_MAX_VAL - 3, TREE_MAX_VAL + 7]])
    free = np.array([[TREE_MAX_VAL + 20, TREE_MAX_VAL, TREE_MAX_VAL]])
    keys = np.concatenate([block, lone, free])
    values = np.array([2.0] * 8 + [1.0, -1.0], np.float32)
    tree = octree_from_cells(keys, values, cfg)
    leaves = tree_leaves(tree)
    assert leaves.cells == 10 and len(leaves.start) == 3 and leaves.length.max() == 8
    want = np.sort(morton_codes(np.concatenate([block, lone])))
    assert np.array_equal(morton_codes(occupied_keys(leaves)), want)
    write_tree_ot(tree, tmp_path / "m.ot")
    write_tree_bt(tree, tmp_path / "m.bt")
    for name in ("m.ot", "m.bt"):
        back = tree_leaves(load_tree(tmp_path / name))
        assert np.array_equal(morton_codes(occupied_keys(back)), want)
    assert np.allclose(tree_leaves(load_tree(tmp_path / "m.ot")).value, leaves.value)


def test_load_tree_refuses_what_is_not_a_tree(tmp_path):
    with pytest.raises(MonoMapError, match="not found"):
        load_tree(tmp_path / "missing.bt")
    (tmp_path / "text.bt").write_text("hello\n")
    with pytest.raises(MonoMapError, match="not an OctoMap file"):
        load_tree(tmp_path / "text.bt")


def test_leaves_read_from_the_stream_equal_octomaps_leaf_iterator(monkeypatch):
    """tree_leaves parses the tree's .ot stream in C; the same leaves (intervals, states, log-odds) as
    OctoMap's own leaf iterator, on a tree with pruned blocks at several depths, far keys and free cells."""
    pytest.importorskip("octomap")
    rng = np.random.default_rng(3)
    cfg = OctoMapConfig()
    parts, vals = [], []
    for size, value in ((4, 2.0), (2, -1.5), (8, -2.0)):          # whole blocks: prune into one leaf each
        base = TREE_MAX_VAL + rng.integers(-2000, 2000, 3) // size * size
        parts.append(np.array([[x, y, z] for x in range(size) for y in range(size) for z in range(size)]) + base)
        vals += [value] * size ** 3
    parts.append(rng.integers(1, 2 * TREE_MAX_VAL - 1, (3000, 3)))  # scattered cells over the whole key range
    vals += rng.normal(0, 1.5, 3000).tolist()
    keys, first = np.unique(np.concatenate(parts), axis=0, return_index=True)
    tree = octree_from_cells(keys, np.asarray(vals, np.float32)[first], cfg)
    fast = tree_leaves(tree)
    monkeypatch.setenv("MONO_MAP_NO_C", "1")
    slow = tree_leaves(tree)
    assert len(fast.start) == tree.getNumLeafNodes() < len(keys)     # some blocks were pruned
    assert (fast.length > 1).sum() >= 3
    for name in ("start", "length", "occupied", "value"):
        assert np.array_equal(getattr(fast, name), getattr(slow, name)), name
