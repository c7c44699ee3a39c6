"""Pictures of an adaptation: predicted depth before/after beside the LiDAR, and top-down maps side by side.

    PYTHONPATH=. .venv/bin/python tools/plot_adapt.py depth --data-root ../shared/kitti_real/odometry --seq real01 \\
        --frames 10,40,70 --model binary --model outputs/adapt/<adapted>.pt --label shipped --label adapted \\
        --out docs/images/real01_depth_adapt.png
    PYTHONPATH=. .venv/bin/python tools/plot_adapt.py topdown --map "LiDAR-FOV=outputs/real01/lidar-fov.bt" \\
        --map "keep 0.8 shipped=..." --map "keep 0.8 adapted=..." --out docs/images/real01_topdown_adapt.png

Depth pictures: one column per frame; rows = image, projected LiDAR, then each model's expected depth, all as
inverse depth on one colour scale (magma, 1/80 … 1/3 m⁻¹), with each model's AbsRel on that frame in its row.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np


def depth_rows(seq, frames: list[int], models: list[tuple[str, object]], width: int = 620) -> np.ndarray:
    """The picture as an RGB uint8 array (rows: image, LiDAR, each model; columns: frames)."""
    import cv2

    from mono_map.eval.depth_metrics import image_errors
    from mono_map.viz.codec import colourise

    lo, hi = 1 / 80.0, 1 / 3.0
    cols = []
    for i in frames:
        img = seq.image(i)
        gt = seq.lidar_depth(i)
        h, w = img.shape[:2]
        lidar = np.zeros_like(img)
        v, u = np.nonzero(gt > 0)
        lidar[v, u] = colourise(1.0 / gt[v, u], lo, hi, "magma")
        lidar = cv2.dilate(lidar, np.ones((3, 3), np.uint8))
        rows = [(img, f"frame {i}"), (lidar, "LiDAR")]
        for label, pred in models:
            d = pred.predict(img).depth
            e = image_errors(gt, d)
            rows.append((colourise(1.0 / d, lo, hi, "magma"), f"{label}: AbsRel {e['abs_rel']:.3f}"))
        scale = width / w
        tiles = []
        for im, text in rows:
            im = cv2.resize(im, (width, round(h * scale)), interpolation=cv2.INTER_AREA).copy()
            # a dark outline from thin strokes shifted by a pixel: one thick stroke advances wider and left a ghost
            # of the last glyph after the white text
            for dx, dy in ((-1, 0), (1, 0), (0, -1), (0, 1)):
                cv2.putText(im, text, (8 + dx, 22 + dy), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (0, 0, 0), 1, cv2.LINE_AA)
            cv2.putText(im, text, (8, 22), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (255, 255, 255), 1, cv2.LINE_AA)
            tiles.append(im)
        cols.append(np.concatenate(tiles, 0))
    gap = np.full((cols[0].shape[0], 6, 3), 255, np.uint8)
    out = cols[0]
    for c in cols[1:]:
        out = np.concatenate([out, gap, c], 1)
    return out


def main(argv: list[str] | None = None) -> int:
    from mono_map.cli.options import add_data_root, add_frames, add_model, add_seq

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="what", required=True)
    d = sub.add_parser("depth")
    add_data_root(d)
    add_seq(d, required=True)
    add_frames(d, default="0", what="frames to show")
    add_model(d, repeat=True)
    d.add_argument("--label", action="append", default=None)
    d.add_argument("--out", required=True, help="picture (.png or .jpg)")
    t = sub.add_parser("topdown")
    t.add_argument("--map", action="append", required=True, help="TITLE=path.bt (repeatable)")
    t.add_argument("--out", required=True)
    args = ap.parse_args(argv)

    import torch

    from mono_map.errors import MonoMapError

    torch.set_num_threads(1)
    try:
        if args.what == "depth":
            from mono_map.data.kitti import open_sequence
            from mono_map.depth.inference import DepthPredictor
            from mono_map.frames import parse_frames
            from mono_map.viz.plots import write_picture

            names = args.model or [None]                  # None: the shipped binary model
            labels = args.label or [m or "binary" for m in names]
            if len(labels) != len(names):
                raise MonoMapError("--label: give one per --model")
            seq = open_sequence(args.data_root, args.seq)
            frames = parse_frames(args.frames).resolve(len(seq))
            models = [(lab, DepthPredictor.load(m)) for lab, m in zip(labels, names)]
            pic = depth_rows(seq, frames, models)
            write_picture(args.out, pic)
        else:
            from mono_map.mapping.octree import load_tree
            from mono_map.viz.plots import render_topdown

            maps = []
            for spec in args.map:
                title, _, path = spec.partition("=")
                if not path:
                    raise MonoMapError(f"--map: {spec!r}: expected TITLE=path.bt")
                maps.append((title, load_tree(path)))
            render_topdown(maps, args.out)
    except MonoMapError as exc:
        print(f"plot_adapt: error: {exc}", file=sys.stderr)
        return 2
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
