"""Exact batched integration vs OctoMap's own insertPointCloud / graph2tree / compare_octrees."""

from __future__ import annotations

import shutil
import subprocess

import numpy as np
import octomap
import pytest

from mono_map.config import OctoMapConfig
from mono_map.errors import MonoMapError
from mono_map.eval.map_metrics import compare_leaves
from mono_map.mapping import kernel_threads, ot_c, raycast, raycast_c
from mono_map.mapping.integrate import MapIntegrator, octree_memory_usage
from mono_map.mapping.mirror import LogOddsMirror
from mono_map.mapping.octree import key_to_coord, morton_codes, tree_leaves
from mono_map.mapping.scangraph import write_scan_graph


def random_scans(seed: int, n_frames: int = 3, n_points: int = 1500):
    """Clouds around a moving origin: a noisy 'room' (box walls) plus random far points."""
    rng = np.random.default_rng(seed)
    scans = []
    for i in range(n_frames):
        origin = np.array([0.7 * i, 0.0, 1.5]) + rng.uniform(-0.3, 0.3, 3)
        d = rng.normal(size=(n_points, 3))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        r = rng.uniform(1.0, 9.0, n_points)
        r[: n_points // 3] = 6.0 / np.maximum(np.abs(d[: n_points // 3, 0]), 0.3)  # a wall-ish band
        scans.append((origin + d * r[:, None], origin))
    return scans


def octree_sets(tree, res):
    """Finest cells of a tree: dict Morton code -> log-odds (pruned leaves expanded)."""
    leaves = tree_leaves(tree)
    codes, leaf = leaves.expand()
    return dict(zip(codes.tolist(), leaves.value[leaf].tolist()))


def key_codes(keys):
    return set(morton_codes(keys).tolist())


@pytest.fixture(params=["c", "c-2threads", "numpy"])
def kernel(request, monkeypatch):
    """Run a test with the compiled DDA kernel (one thread, and split over two threads even for
    small scans) and with the numpy fallback."""
    if request.param == "numpy":
        monkeypatch.setenv("MONO_MAP_NO_C", "1")
    else:
        if raycast_c.load_kernel() is None:
            pytest.fail("the compiled kernel must build here (gcc is part of the machine)")
        monkeypatch.setenv("MONO_MAP_RAY_THREADS", "2" if request.param == "c-2threads" else "1")
        if request.param == "c-2threads":
            monkeypatch.setattr(kernel_threads, "PARALLEL_MIN_RAYS", 1)
    yield request.param


@pytest.mark.parametrize("max_range", [-1.0, 6.0])
def test_key_sets_equal_insertPointCloud(kernel, max_range):
    res = 0.2
    for points, origin in random_scans(1, n_frames=2):
        ks = raycast.compute_update(points, origin, res, max_range=max_range)
        tree = octomap.OcTree(res)
        tree.insertPointCloud(points, origin, maxrange=max_range, discretize=True)
        cells = octree_sets(tree, res)
        free = {k for k, v in cells.items() if v < 0}
        occ = {k for k, v in cells.items() if v > 0}
        assert key_codes(ks.free) == free
        assert key_codes(ks.occupied) == occ
        assert not (free & occ)


def test_non_discretized_rays_match(kernel):
    """computeUpdate without discretisation (the raw end points) as well."""
    res = 0.25
    points, origin = random_scans(5, n_frames=1, n_points=800)[0]
    ks = raycast.compute_update(points, origin, res, discretize_points=False)
    tree = octomap.OcTree(res)
    tree.insertPointCloud(points, origin, discretize=False)
    cells = octree_sets(tree, res)
    assert key_codes(ks.free) == {k for k, v in cells.items() if v < 0}
    assert key_codes(ks.occupied) == {k for k, v in cells.items() if v > 0}


@pytest.mark.parametrize("sync_every", [1, None])
def test_batched_map_equals_insertPointCloud(kernel, sync_every):
    """Several frames, non-default sensor model, the tree made from the mirror after every frame or once at
    the end: same cells, states, log-odds, memory and .ot bytes; the counted statistics are the tree's."""
    cfg = OctoMapConfig(resolution=0.2, prob_hit=0.75, prob_miss=0.35)
    fast = MapIntegrator(cfg, sync_every=sync_every)
    ref = MapIntegrator(cfg, method="insertPointCloud")
    for points, origin in random_scans(2, n_frames=4):
        fast.insert(points, origin)
        ref.insert(points, origin)
        counted, b = fast.stats(), ref.tree
        assert counted["tree_nodes"] == b.size() and counted["leaf_count"] == b.getNumLeafNodes()
        assert counted["memory_bytes"] == b.memoryUsage()
    a = fast.finish()
    assert fast.mirror is None and fast.stats() == counted
    cells_a, cells_b = octree_sets(a, 0.2), octree_sets(b, 0.2)
    assert cells_a.keys() == cells_b.keys()
    assert all(cells_a[k] == cells_b[k] for k in cells_a)          # exact log-odds
    assert a.memoryUsage() == b.memoryUsage() and a.getNumLeafNodes() == b.getNumLeafNodes()
    assert a.write() == b.write()                                   # byte-identical .ot
    with pytest.raises(MonoMapError, match="finish"):
        fast.insert(*random_scans(2, n_frames=1)[0])


def test_counted_statistics_follow_changes():
    """The block cache of the compiled counts: after pruning (a whole 8x8x8 block and a 2x2x2 group becoming
    equal, then unequal again) the counts equal a freshly made tree's; the memory model is OctoMap's own."""
    fast = MapIntegrator(OctoMapConfig(resolution=0.2))
    leaves = []
    full = np.stack(np.meshgrid(*[np.arange(8)] * 3, indexing="ij"), axis=-1).reshape(-1, 3) + 32768
    for step, (keys, dl) in enumerate([(full, 0.85), (full[:8], -0.4), (full[:8], 0.4), (full[100:], 2.0),
                                       (full[(full % 2 == 0).all(1)], -3.0)]):
        fast.mirror.update(raycast_c.load_kernel(), keys, np.full(len(keys), dl, np.float32), fast.cmin, fast.cmax,
                           fast.occ_thres)
        fast._pending = True
        counted = fast.stats()
        tree = fast.tree
        assert (counted["tree_nodes"], counted["leaf_count"]) == (tree.size(), tree.getNumLeafNodes()), step
        assert counted["memory_bytes"] == tree.memoryUsage() == octree_memory_usage(tree.size(),
                                                                                     tree.getNumLeafNodes())
        leaves.append(tree.getNumLeafNodes())
    assert leaves[0] == 1 and leaves[1] > 1 and leaves[2] == 1        # collapsed, split, collapsed again


def dense_scan(seed: int):
    """A scan with many end points per cell (snapped near a coarse grid), some in the origin's own cell,
    some far beyond a 6 m range and a LiDAR-like fan."""
    rng = np.random.default_rng(seed)
    origin = np.array([0.05, -0.13, 1.51])
    grid = rng.integers(-40, 40, size=(600, 3)) * 0.2 + 0.1
    pts = np.repeat(grid, 6, axis=0) + rng.uniform(-0.09, 0.09, (3600, 3))    # ~6 points per cell
    az = rng.uniform(-np.pi, np.pi, 3000)
    el = rng.uniform(-0.4, 0.05, 3000)
    r = rng.uniform(3.0, 30.0, 3000)
    fan = origin + np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=1) * r[:, None]
    near = origin + rng.uniform(-0.04, 0.04, (20, 3))                         # the origin's cell: empty rays
    return np.concatenate([pts, fan, near]), origin


@pytest.mark.parametrize("max_range", [-1.0, 6.0])
@pytest.mark.parametrize("discretize", [True, False])
def test_dense_scans_match_insertPointCloud(kernel, max_range, discretize):
    """End points deduplicated by cell (OctoMap's discretize) or not, rays cut at max_range, empty rays
    from the origin's cell: the same free / occupied sets as insertPointCloud; the reused bitmap is left zeroed."""
    res = 0.2
    for seed in (0, 1):
        points, origin = dense_scan(seed)
        ks = raycast.compute_update(points, origin, res, max_range=max_range, discretize_points=discretize)
        tree = octomap.OcTree(res)
        tree.insertPointCloud(points, origin, maxrange=max_range, discretize=discretize)
        cells = octree_sets(tree, res)
        assert key_codes(ks.free) == {k for k, v in cells.items() if v < 0}
        assert key_codes(ks.occupied) == {k for k, v in cells.items() if v > 0}
        assert len(ks.free) == len(key_codes(ks.free)) and len(ks.occupied) == len(key_codes(ks.occupied))
        if kernel != "numpy":
            assert not kernel_threads.zeroed_bitmap(int(np.prod(ks.hi - ks.lo + 1))).any()


def test_kernel_node_stream_equals_numpy_stream():
    """The .ot stream written from the mirror's blocks (compiled) is the numpy stream of the same cells, byte
    for byte, with collapsible 2x2x2 and 8x8x8 groups of equal values, partial blocks and scattered cells."""
    from mono_map.mapping.octree import child_order_codes, ot_header, ot_stream

    kernel = raycast_c.load_kernel()
    rng = np.random.default_rng(4)
    m = LogOddsMirror()
    full = np.stack(np.meshgrid(*[np.arange(8)] * 3, indexing="ij"), axis=-1).reshape(-1, 3)
    groups = [32768 + 8 * np.array([3, -2, 1]) + full,                  # one whole block, all equal: collapses
              32768 + 8 * np.array([4, -2, 1]) + full,                  # its neighbour, two values
              32760 + full[(full < 2).all(axis=1)],                     # a 2x2x2 group
              rng.integers(32000, 33500, size=(3000, 3))]               # scattered
    values = [np.full(512, 0.85, np.float32), np.where(full[:, 0] < 4, 0.4, -0.4).astype(np.float32),
              np.full(8, -1.2, np.float32), rng.choice([-0.4, 0.85, 1.2], 3000).astype(np.float32)]
    keys = np.concatenate(groups)
    vals = np.concatenate(values)
    keys, first = np.unique(keys, axis=0, return_index=True)
    vals = vals[first]
    idx = m.index(keys, create=True)
    m.pool[idx] = vals
    nodes, n = ot_c.ot_nodes_c(kernel, m.pool, child_order_codes(m.block_keys[:m.n_blocks] >> 3))
    ref, n_ref = ot_stream(keys, vals, 0.2)
    assert n == n_ref and ot_header(n, 0.2) + nodes.tobytes() == ref
    assert m.node_stream(kernel, 0.2).tobytes() == ref                 # header + nodes in one buffer
    tree = octomap.OcTree.read(ref)
    assert tree.getNumLeafNodes() < len(keys)                          # some groups did collapse
    assert ot_c.ot_counts_c(kernel, m.pool, m.block_codes()) == (tree.size(), tree.getNumLeafNodes())


def test_changed_cells_reported():
    fast = MapIntegrator(OctoMapConfig(resolution=0.2))
    origin = np.zeros(3)
    wall = np.array([[0.1, 0.1, 5.1]])
    r1 = fast.insert(wall, origin)
    assert len(r1.became_occupied) == 1 and np.allclose(r1.became_occupied[0], [0.1, 0.1, 5.1])
    r2 = fast.insert(wall, origin)
    assert len(r2.became_occupied) == 0                            # already occupied
    # the wall moves back: its old cell is now on a ray; after enough misses it stops being occupied
    freed = []
    for _ in range(6):
        freed += list(fast.insert(np.array([[0.1, 0.1, 9.1]]), origin).stopped_occupied)
    assert len(freed) == 1 and np.allclose(freed[0], [0.1, 0.1, 5.1])
    assert fast.tree.getLabels(np.array([[0.1, 0.1, 5.1]]))[0] == 0


@pytest.mark.skipif(shutil.which("compare_octrees") is None, reason="octomap-tools missing")
def test_compare_octrees_and_graph2tree_agree(tmp_path):
    """OctoMap's C++ tools: graph2tree builds the same tree; compare_octrees finds KLD 0 and equal size."""
    scans = random_scans(3, n_frames=3)
    fast = MapIntegrator()
    for p, o in scans:
        fast.insert(p, o)
    ours = tmp_path / "ours.ot"
    assert fast.tree.write(str(ours).encode())
    write_scan_graph(tmp_path / "s.graph", scans)
    subprocess.run(["graph2tree", "-i", str(tmp_path / "s.graph"), "-o", str(tmp_path / "g.bt"), "-res", "0.2",
                    "-g", "-discretize"], check=True, capture_output=True)
    out = subprocess.run(["compare_octrees", str(ours), str(tmp_path / "g.bt.ot")], capture_output=True,
                         text=True, check=True).stdout
    n_expanded = int(out.split("Expanded num. leafs:")[1].split()[0])
    kld = float(out.split("KLD:")[1].split()[0])
    assert kld == 0.0
    # the tool's expanded leaf count = the finest known cells our metrics count
    assert n_expanded == tree_leaves(fast.tree).cells


@pytest.mark.skipif(shutil.which("eval_octree_accuracy") is None, reason="octomap-tools missing")
def test_eval_octree_accuracy_counts(tmp_path):
    """eval_octree_accuracy builds a map from scans 1-4 (not 5) and scores scan 5's cells:
    our ray casting + getLabels must give its correct / wrong / unknown counts."""
    scans = random_scans(4, n_frames=5, n_points=1200)
    write_scan_graph(tmp_path / "s.graph", scans, local=True)
    out = subprocess.run(["eval_octree_accuracy", str(tmp_path / "s.graph"), "-res", "0.2"],
                         capture_output=True, text=True, check=True).stdout
    tail = out.split("Voxels correct:")[1]
    correct = int(tail.split()[0])
    wrong = int(tail.split("#wrong:")[1].split()[0])
    unknown = int(tail.split("#unknown:")[1].split(".")[0])
    # the tool adds the origin back to the stored local points in float32
    world = [((p.astype(np.float32) - o.astype(np.float32)) + o.astype(np.float32), o) for p, o in scans]
    tree = octomap.OcTree(0.2)
    for p, o in world[:4]:
        tree.insertPointCloud(p.astype(np.float64), o, discretize=False)
    ks = raycast.compute_update(world[4][0].astype(np.float64), world[4][1], 0.2, discretize_points=False)
    lf = tree.getLabels(key_to_coord(ks.free, 0.2))
    lo = tree.getLabels(key_to_coord(ks.occupied, 0.2))
    assert (int((lf == 0).sum() + (lo == 1).sum()), int((lf == 1).sum() + (lo == 0).sum()),
            int((lf < 0).sum() + (lo < 0).sum())) == (correct, wrong, unknown)


def test_hand_built_metrics():
    """Volume weighting: a pruned block counts as its 8 cells; unknown in the map counts as wrong."""
    res = 1.0
    ref = octomap.OcTree(res)
    block = np.array([[x + 0.5, y + 0.5, z + 0.5] for x in (0, 1) for y in (0, 1) for z in (0, 1)])
    for _ in range(3):
        ref.updateNodes(block.tolist(), False)                  # 8 free cells -> pruned into one leaf
    ref.updateNodes([[5.5, 0.5, 0.5], [6.5, 0.5, 0.5]], True)   # 2 occupied
    m = octomap.OcTree(res)
    m.updateNodes([[0.5, 0.5, 0.5]], True)                     # wrong (free in ref)
    m.updateNodes([[1.5, 0.5, 0.5], [1.5, 1.5, 1.5]], False)   # right
    m.updateNodes([[5.5, 0.5, 0.5]], True)                     # right
    m.updateNodes([[20.5, 0.5, 0.5]], True)                    # outside the reference: ignored
    r = compare_leaves(tree_leaves(m), tree_leaves(ref))
    assert tree_leaves(ref).length.max() == 8
    assert r["ref_known_cells"] == 10 and r["ref_occupied_cells"] == 2
    assert r["covered_cells"] == 4 and r["correct_cells"] == 3
    assert r["accuracy"] == pytest.approx(0.3)
    assert r["coverage"] == pytest.approx(0.4)
    assert r["accuracy_covered"] == pytest.approx(0.75)
    assert r["precision"] == pytest.approx(0.5) and r["recall"] == pytest.approx(0.5)
    # brute force with getLabels on the reference's finest cells
    cells = np.concatenate([block, [[5.5, 0.5, 0.5], [6.5, 0.5, 0.5]]])
    ref_state = ref.getLabels(cells)
    assert (m.getLabels(cells) == ref_state).mean() == pytest.approx(r["accuracy"])
