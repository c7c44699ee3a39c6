"""Cost of reading the fused surface (``SurfaceFusion.sample``, mono_map/mapping/fused.py): every sample of a
frame's snap (each ray-grid pixel at 11 depths within the 1 m window) looks up its cell in open3d's
VoxelBlockGrid. Candidate: every point's block looked up in open3d's hash map at once. Baseline (the code
before 2026-12-05's eighth stop): the distinct blocks found first (a dense box of blocks up to 20,000, else
by sorting the packed block codes), looked up, then indexed back.

    PYTHONPATH=. .venv/bin/python benchmarks/bench_fused_sample.py --data-root DATA [--seq 06] [--runs 5]
        [--fuse 60 --frame 50] [--build 40:70 --build-runs 3]

A TSDF is fused from the ground-truth depth of ``--fuse`` frames of a synthetic sequence (its depth_2, to 40 m
as the build), then frame ``--frame``'s snap points (every ray-grid pixel with a depth, as the build) are read by
both, alternating, ``--runs`` times each (the values are
checked equal); also the whole ``snap_depths`` of that frame with each; with ``--build`` whole fused builds
(the shipped model, the default settings) with each lookup. Prints min / median / max seconds
and the per-run ratios. Run it on an idle machine.
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np


def sample_distinct_first(fusion, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The baseline: the distinct blocks of ``points`` looked up once, then indexed back (as before)."""
    from mono_map.mapping.octree import TREE_MAX_VAL, pack_keys, sorted_unique, unpack_keys

    o3c = fusion.o3c
    lat = np.floor(np.asarray(points, dtype=np.float64) / fusion.res).astype(np.int64)
    blk = lat >> 3
    loc = lat - (blk << 3)
    tsdf_out = np.zeros(len(lat), np.float32)
    w_out = np.zeros(len(lat), np.float32)
    lo, hi = blk.min(axis=0), blk.max(axis=0)
    dims = hi - lo + 1
    if int(np.prod(dims)) <= 20_000:
        grid = np.stack(np.meshgrid(*[np.arange(a, b + 1) for a, b in zip(lo, hi)], indexing="ij"), -1)
        query = grid.reshape(-1, 3)
        where = np.ravel_multi_index(tuple((blk - lo).T), tuple(dims))
    else:
        codes = pack_keys(blk + TREE_MAX_VAL)
        uniq = sorted_unique(codes)
        where = np.searchsorted(uniq, codes)
        query = unpack_keys(uniq) - TREE_MAX_VAL
    buf, found = fusion.vbg.hashmap().find(o3c.Tensor(np.ascontiguousarray(query, dtype=np.int32)))
    buf = np.where(found.numpy().astype(bool).reshape(-1), buf.numpy().astype(np.int64).reshape(-1), -1)
    b = buf[where]
    ok = b >= 0
    flat = b[ok] * 512 + loc[ok, 0] + 8 * loc[ok, 1] + 64 * loc[ok, 2]
    tsdf_out[ok] = fusion.vbg.attribute("tsdf").reshape((-1,)).numpy()[flat]
    w_out[ok] = fusion.vbg.attribute("weight").reshape((-1,)).numpy()[flat]
    return tsdf_out, w_out


def stats(xs: list[float]) -> str:
    return f"{min(xs):.3f} / {statistics.median(xs):.3f} / {max(xs):.3f}"


def main() -> None:
    import torch

    from mono_map.cli.options import add_data_root, add_seq, add_threads, check_threads
    from mono_map.data.kitti import open_sequence
    from mono_map.mapping.fused import FusedConfig, SurfaceFusion

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_data_root(p)
    add_seq(p, default="06", help="synthetic sequence name under the data root (its depth_2 is fused)")
    p.add_argument("--fuse", type=int, default=10, help="frames fused (from 0)")
    p.add_argument("--frame", type=int, default=5, help="the frame whose snap points are read")
    p.add_argument("--runs", type=int, default=5)
    add_threads(p, default=2)
    p.add_argument("--build", default=None, help="also time whole fused builds of these frames (e.g. 40:70)")
    p.add_argument("--build-runs", type=int, default=3)
    a = p.parse_args()
    check_threads(a.threads)
    torch.set_num_threads(a.threads)
    seq = open_sequence(a.data_root, a.seq)
    if seq.depth(0) is None:
        raise SystemExit(f"{a.data_root}: sequence {a.seq} has no depth_2 (a synthetic sequence is needed)")
    candidate_method = SurfaceFusion.sample
    fusion = SurfaceFusion(FusedConfig(), 0.2)
    Ks = seq.calib.K2.copy()
    Ks[:2] /= 2                                            # the default ray grid: every 2nd pixel
    for i in range(a.fuse):
        d = seq.depth(i)[::2, ::2].astype(np.float32)
        d = np.where(d <= 40, d, 0).astype(np.float32)
        fusion.integrate(d, np.ones_like(d), np.full_like(d, 0.6), Ks, seq.T_world_cam2(i))
    d = seq.depth(a.frame)[::2, ::2].astype(np.float32)   # the build snaps every pixel with a depth (to 80 m)
    T = seq.T_world_cam2(a.frame)
    v, u = np.nonzero(d > 0)
    z = d[v, u][:, None].astype(np.float64) + np.arange(-5, 6) * 0.2
    pts = (np.stack([(u[:, None] - Ks[0, 2]) / Ks[0, 0] * z, (v[:, None] - Ks[1, 2]) / Ks[1, 1] * z, z], -1)
           @ T[:3, :3].T + T[:3, 3]).reshape(-1, 3)
    new, old = fusion.sample(pts), sample_distinct_first(fusion, pts)
    assert all(np.array_equal(x, y) for x, y in zip(new, old)), "the two lookups disagree"
    print(f"{a.seq}: {a.fuse} frames fused ({fusion.n_blocks:,} blocks); frame {a.frame}: {len(pts):,} snap points")
    candidate = fusion.sample
    for what, call in (("sample", lambda f: f(pts)),
                       ("snap_depths", lambda f: fusion.snap_depths(d, Ks, T, 1.0))):
        tb, tc = [], []
        for _ in range(a.runs):
            for times, fn in ((tb, lambda q: sample_distinct_first(fusion, q)), (tc, candidate)):
                fusion.sample = fn
                t = time.perf_counter()
                call(fn)
                times.append(time.perf_counter() - t)
        fusion.sample = candidate
        ratios = [b / c for b, c in zip(tb, tc)]
        print(f"{what}: baseline {stats(tb)} s, candidate {stats(tc)} s (min / median / max of {a.runs}); "
              f"ratio {stats(ratios)}")
    if a.build:                                           # whole fused builds with the shipped model
        from mono_map.frames import parse_frames
        from mono_map.mapping.inputs import load_predictor
        from mono_map.mapping.jobs import MapJob
        from mono_map.mapping.pipeline import build_map

        frames = tuple(parse_frames(a.build).resolve(len(seq)))
        pred = load_predictor(None)
        build_map(seq, MapJob.spec("mono", frames[:2], integrate="fused"), predictor=pred, show_progress=False)
        tb, tc = [], []
        for _ in range(a.build_runs):
            for times, fn in ((tb, sample_distinct_first), (tc, SurfaceFusion.sample)):
                SurfaceFusion.sample = fn
                t = time.perf_counter()
                build_map(seq, MapJob.spec("mono", frames, integrate="fused"), predictor=pred, show_progress=False)
                times.append(time.perf_counter() - t)
        SurfaceFusion.sample = candidate_method
        print(f"fused build of frames {a.build} ({len(frames)}): baseline {stats(tb)} s, candidate {stats(tc)} s "
              f"(min / median / max of {a.build_runs}); ratio {stats([b / c for b, c in zip(tb, tc)])}; "
              f"candidate {len(frames) / statistics.median(tc):.2f} frames/s")


if __name__ == "__main__":
    from mono_map.errors import MonoMapError

    try:
        main()
    except MonoMapError as e:
        raise SystemExit(f"bench_fused_sample: {e}")
