#!/usr/bin/env python3
"""Where the fused surface puts a pixel's hit, fed exact depth: in the cell of the pixel's own surface point or not.

    PYTHONPATH=. python tools/fused_hit_cells.py --data-root DATA [--seq 06] [--frames 0:30] [--check 5,15,25]
        [--out docs/images/fused_hit_cells.png]

The ground-truth depth (depth_2) of ``--frames`` of a synthetic sequence is fused (every 2nd pixel, to 40 m, weight
1, the narrowest band: as the oracle with no noise) twice, with distances along the optical axis (the default)
and along each pixel's normal (``--fused-euclid 1``); then the pixels of the ``--check`` frames are snapped
(:meth:`SurfaceFusion.snap_depths`, 1 m window) and their hits compared with their own cells. Prints, per frame
and distance, the share of pixels whose hit is in their own cell, of those seen at grazing angles (cos < 0.2),
and with no hit; the picture shows, for the first checked frame, the image and the snapped depth minus the
true depth along each ray for both (red: behind, blue: in front, ±0.3 m; white: no hit).
"""

from __future__ import annotations

import argparse
import sys

import numpy as np

from mono_map.cli.options import add_data_root, add_frames, add_seq
from mono_map.errors import MonoMapError

RES, STEP, GRAZING = 0.2, 2, 0.2


def hit_cells(seq, frames: list[int], check: list[int], euclid: bool) -> tuple[list[dict], dict]:
    """Fuse ``frames``' exact depth; per ``check`` frame the shares of pixels (own cell, grazing own cell, no hit)
    and, for the first, the snapped-minus-true depth image (NaN: no hit or no depth)."""
    from mono_map.geometry import backproject_pixels, depth_normals, transform_points
    from mono_map.mapping.fused import FusedConfig, SurfaceFusion

    cfg = FusedConfig(euclid=int(euclid), multiview=0)
    fusion = SurfaceFusion(cfg, RES)
    K = seq.calib.K2.copy()
    K[:2] /= STEP
    depths = {}
    for i in frames:
        d = seq.depth(i)[::STEP, ::STEP].astype(np.float32)
        d = np.where((d > 0) & (d <= cfg.max_depth), d, 0).astype(np.float32)
        normals = depth_normals(d, K)[0] if euclid else None
        fusion.integrate(d, np.ones_like(d), np.full_like(d, cfg.trunc_min * RES), K, seq.T_world_cam2(i), None,
                         normals)
        depths[i] = d
    rows, picture = [], None
    for i in check:
        d, T = depths[i], seq.T_world_cam2(i)
        normals, cos = depth_normals(d, K)
        z = fusion.snap_depths(d, K, T, cfg.snap_window, normals=normals if euclid else None)
        v, u = np.nonzero(d > 0)

        def cells(zz):
            return np.floor(transform_points(T, backproject_pixels(K, u, v, zz)) / RES).astype(np.int64)

        zz, dd = z[v, u], d[v, u]
        has = zz > 0
        own = has & (cells(np.where(has, zz, dd)) == cells(dd)).all(axis=1)
        graze = cos[v, u] < GRAZING
        rows.append({"frame": i, "own": own.mean(), "own_grazing": own[graze].mean() if graze.any() else np.nan,
                     "no_hit": 1 - has.mean()})
        if picture is None:
            picture = np.full(d.shape, np.nan, np.float32)
            picture[v[has], u[has]] = (zz - dd)[has]
            picture[(d > 0) & ~(z > 0)] = np.inf
    return rows, picture


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_seq(p, default="06", help="synthetic sequence name under the data root (its depth_2 is fused)")
    add_data_root(p)
    add_frames(p, default="0:30", what="frames fused")
    p.add_argument("--check", default="5,15,25", help="frames whose hits are compared (among --frames; default 5,15,25)")
    p.add_argument("--out", default=None, help="PNG of the first checked frame (default: none)")
    a = p.parse_args()
    try:
        from mono_map.data.kitti import open_sequence
        from mono_map.frames import parse_frames

        seq = open_sequence(a.data_root, a.seq)
        frames = parse_frames(a.frames).resolve(len(seq))
        try:
            check = [int(x) for x in a.check.split(",")]
        except ValueError:
            raise MonoMapError(f"--check: a comma list of frame numbers, got {a.check!r}")
        if not set(check) <= set(frames):
            raise MonoMapError(f"--check: frames {sorted(set(check) - set(frames))} are not among --frames")
        if seq.depth(frames[0]) is None:
            raise MonoMapError(f"{seq.path}: no depth_2 (ground-truth depth): a synthetic sequence is needed")
    except MonoMapError as e:
        print(f"fused_hit_cells: {e}", file=sys.stderr)
        return 2
    pictures = {}
    print("| distance | frame | hit in its own cell | … at grazing angles (cos < 0.2) | no hit |")
    print("|---|---:|---:|---:|---:|")
    for euclid in (False, True):
        rows, pictures[euclid] = hit_cells(seq, frames, check, euclid)
        for r in rows:
            print(f"| {'normal' if euclid else 'optical axis'} | {r['frame']} | {100 * r['own']:.1f} % | "
                  f"{100 * r['own_grazing']:.1f} % | {100 * r['no_hit']:.1f} % |")
    if a.out:
        import cv2

        image = seq.image(check[0])[::STEP, ::STEP][..., ::-1]
        panels = [np.ascontiguousarray(image[:pictures[False].shape[0], :pictures[False].shape[1]])]
        for euclid in (False, True):
            e = pictures[euclid]
            col = cv2.applyColorMap(np.clip(128 + np.nan_to_num(e, posinf=0) * 128 / 0.3, 0, 255).astype(np.uint8),
                                    cv2.COLORMAP_JET)
            col[np.isnan(e)] = 0
            col[np.isinf(e)] = 255
            cv2.putText(col, "along the normal" if euclid else "along the optical axis (default)", (8, 22),
                        cv2.FONT_HERSHEY_SIMPLEX, 0.6, (255, 255, 255), 2)
            panels.append(col)
        cv2.imwrite(a.out, np.concatenate(panels, axis=0))
        print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
