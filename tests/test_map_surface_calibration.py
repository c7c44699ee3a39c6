"""Surface precision and calibration of maps, on hand-built trees."""

from __future__ import annotations

import numpy as np
import octomap
import pytest

from mono_map.eval.map_metrics import calibration, surface_precision
from mono_map.mapping.octree import morton_codes, morton_to_keys, tree_leaves

RES = 0.2


def tree_of(cells: dict) -> "octomap.OcTree":
    """A tree with finest cells at integer grid offsets (metres = index·RES) set to given log-odds."""
    t = octomap.OcTree(RES)
    t.setClampingThresMin(0.001)
    t.setClampingThresMax(0.999)
    for (i, j, k), v in cells.items():
        t.updateNode(np.array([(i + 0.5) * RES, (j + 0.5) * RES, (k + 0.5) * RES]), float(v), False)
    return t


def test_morton_round_trip():
    keys = np.random.default_rng(0).integers(0, 65536, (1000, 3))
    assert (morton_to_keys(morton_codes(keys)) == keys).all()


def test_surface_precision_counts_cells_within_one_cell_of_a_true_surface():
    wall = {(i, j, 10): 2.0 for i in range(10) for j in range(10)}          # the true surface: a wall at k = 10
    truth = tree_of(wall)
    cells = {(i, 0, 10): 2.0 for i in range(4)}                             # on the wall
    cells.update({(i, 1, 11): 2.0 for i in range(3)})                       # one cell in front: counts
    cells.update({(i, 2, 13): 2.0 for i in range(3)})                       # three cells off: does not
    cells.update({(i, 3, 5): -2.0 for i in range(5)})                       # free cells: ignored
    m = surface_precision(tree_leaves(tree_of(cells)), tree_leaves(truth))
    assert m["occupied_cells"] == 10 and m["on_surface_cells"] == 7
    assert m["surface_precision"] == pytest.approx(0.7)
    assert surface_precision(tree_leaves(truth), tree_leaves(truth))["surface_precision"] == 1.0


def test_surface_precision_expands_pruned_leaves():
    block = {(i, j, k): 2.0 for i in range(8) for j in range(8) for k in range(8)}   # prunes to one leaf
    t = tree_of(block)
    assert t.getNumLeafNodes() < 512
    truth = tree_of({(i, j, 0): 2.0 for i in range(8) for j in range(8)})  # the block's bottom face
    m = surface_precision(tree_leaves(t), tree_leaves(truth))
    assert m["occupied_cells"] == 512 and m["on_surface_cells"] == 128      # layers k = 0 and 1


def test_calibration_of_a_perfect_and_an_overconfident_map():
    rng = np.random.default_rng(1)
    ref_cells, good, bad = {}, {}, {}
    for n in range(2000):
        c = (n % 20, (n // 20) % 20, n // 400)
        p = rng.uniform(0.05, 0.95)
        occ = rng.uniform() < p
        ref_cells[c] = 2.0 if occ else -2.0
        good[c] = np.log(p / (1 - p))
        bad[c] = 4.0 if p > 0.5 else -4.0                                    # says 0.98 / 0.02
    ref = tree_leaves(tree_of(ref_cells))
    g = calibration(tree_leaves(tree_of(good)), ref)
    b = calibration(tree_leaves(tree_of(bad)), ref)
    assert g["cells"] == 2000 and b["cells"] == 2000
    assert g["ece"] < 0.05 < b["ece"]
    assert np.isclose(sum(g["weight"]), 1.0)
