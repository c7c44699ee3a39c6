#!/usr/bin/env python3
"""Surface precision of maps' occupied cells split by distance to the camera path and by height.

    .venv/bin/python tools/archive/surface_by_distance.py --seq 00 --frames 0:500 \\
        --surface outputs/seq00/depth-gt_res0.2_f0-500.bt \\
        model=outputs/seq00/mono-keep0.8_res0.2_f0-500.bt oracle=outputs/seq00/mono-keep0.8_model-oracle_res0.2_f0-500.bt

Each occupied finest cell counts as on a surface as in ``eval``'s surface precision (within one cell of an
occupied cell of the ``--surface`` map, the depth-gt map of the same frames). Distance: horizontal (x, z of the
cam0 world frame) to the nearest cam0 position of the frames; height: above the road, taken as
``--camera-height`` metres below the world origin (cam0 of the sequence's first pose; KITTI's cam0 is 1.65 m
above the ground; y points down) — flat ground is assumed.
Prints two Markdown tables (cells / % on a surface per bin and map, the surface map's own cells beside).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from mono_map.data.kitti import open_sequence
from mono_map.eval.map_metrics import near_surface
from mono_map.frames import parse_frames
from mono_map.mapping.octree import key_to_coord, load_tree, occupied_keys, tree_leaves

DISTANCES = (0, 10, 20, 30, 40, 60, 100)
HEIGHTS = (-5, 1, 3, 6, 12, 40)


def path_distance(xz: np.ndarray, path: np.ndarray, chunk: int = 200_000) -> np.ndarray:
    """(N,) horizontal distance (m) of points ``xz`` (N, 2) to the nearest of ``path`` (M, 2)."""
    out = np.empty(len(xz))
    for s in range(0, len(xz), chunk):
        p = xz[s:s + chunk]
        out[s:s + chunk] = np.sqrt(((p[:, None, :] - path[None]) ** 2).sum(-1)).min(1)
    return out


def table(title: str, edges, values: dict, near: dict) -> str:
    names = list(values)
    lines = [f"| {title} | " + " | ".join(f"{n}: cells / on a surface (%)" for n in names) + " |",
             "|---|" + "---:|" * len(names)]
    for a, b in zip(edges[:-1], edges[1:]):
        cells = []
        for n in names:
            m = (values[n] >= a) & (values[n] < b)
            cells.append(f"{m.sum():,} / {100 * near[n][m].mean():.1f}" if m.any() else "0 / –")
        lines.append(f"| {a}–{b} | " + " | ".join(cells) + " |")
    lines.append("| all | " + " | ".join(f"{len(near[n]):,} / {100 * near[n].mean():.1f}" for n in names) + " |")
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("maps", nargs="+", metavar="NAME=MAP.bt")
    p.add_argument("--surface", required=True, help="the depth-gt map of the same frames (.bt)")
    p.add_argument("--seq", default="00")
    p.add_argument("--frames", default="0:500")
    p.add_argument("--data-root", default=None)
    p.add_argument("--camera-height", type=float, default=1.65)
    args = p.parse_args(argv)
    named = {}
    for item in args.maps:
        name, sep, path = item.partition("=")
        if not sep or not name:
            raise SystemExit(f"surface_by_distance: {item!r}: expected NAME=MAP.bt")
        named[name] = Path(path)
    for path in [*named.values(), Path(args.surface)]:
        if not path.is_file():
            raise SystemExit(f"surface_by_distance: {path}: no such map")
    seq = open_sequence(args.data_root, args.seq)
    frames = parse_frames(args.frames).resolve(len(seq))
    path_xz = np.stack([seq.T_world_cam0(i)[[0, 2], 3] for i in frames])
    surface_leaves = tree_leaves(load_tree(args.surface))
    surface = occupied_keys(surface_leaves)
    named["depth-gt"] = Path(args.surface)
    dist, height, near = {}, {}, {}
    for name, path in named.items():
        leaves = surface_leaves if name == "depth-gt" else tree_leaves(load_tree(path))
        if not np.isclose(leaves.resolution, surface_leaves.resolution):
            raise SystemExit(f"surface_by_distance: {path}: {leaves.resolution} m cells, the surface map's are "
                             f"{surface_leaves.resolution} m")
        keys = occupied_keys(leaves)
        xyz = key_to_coord(keys, leaves.resolution)
        near[name] = near_surface(keys, surface)
        dist[name] = path_distance(xyz[:, [0, 2]], path_xz)
        height[name] = args.camera_height - xyz[:, 1]
    print(table("distance to the path (m)", DISTANCES, dist, near) + "\n")
    print(table("height above the road (m)", HEIGHTS, height, near))
    return 0


if __name__ == "__main__":
    sys.exit(main())
