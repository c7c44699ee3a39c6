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
