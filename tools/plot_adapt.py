"""Pictures of an adaptation: predicted depth before/after beside the LiDAR, and top-down maps side by side.

    PYTHONPATH=. .venv/bin/python tools/plot_adapt.py depth --data-root ../shared/kitti_real/odometry --seq real01 \\
        --frames 10,40,70 --model binary --model outputs/adapt/<adapted>.pt --label shipped --label adapted \\
        --out docs/images/real01_depth_adapt.png
    PYTHONPATH=. .venv/bin/python tools/plot_adapt.py topdown --map "LiDAR-FOV=outputs/real01/lidar-fov.bt" \\
        --map "keep 0.8 shipped=..." --map "keep 0.8 adapted=..." --out docs/images/real01_topdown_adapt.png
    PYTHONPATH=. .venv/bin/python tools/plot_adapt.py changes --data-root data/kitti --seq 00 --frames 10,50,90 \
        --model binary --model ADAPTED.pt [--model ADAPTED2.pt ...] --label shipped --label adapted ... \
        --gt dense --out docs/images/adapt_changes_00.jpg

Depth pictures: one column per frame; rows = image, projected LiDAR, then each model's expected depth, all as
inverse depth on one colour scale (magma, 1/80 … 1/3 m⁻¹), with each model's AbsRel on that frame in its row.

Changes pictures: one column per frame; rows = each later model's δ1 changes against the first model's (ground
truth: dense depth_2 or the LiDAR): red = a new failure (ratio to the truth ≥ 1.25) too near, magenta = a new failure
too far, green = a failure fixed, cyan = failing in both; the counts of new and fixed failures in the row's title.
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
        lidar = np.zeros_like(img)
        v, u = np.nonzero(gt > 0)
        lidar[v, u] = colourise(1.0 / gt[v, u], lo, hi, "magma")
        lidar = cv2.dilate(lidar, np.ones((3, 3), np.uint8))
        rows = [(img, f"frame {i}"), (lidar, "LiDAR")]
        for label, pred in models:
            d = pred.predict(img).depth
            e = image_errors(gt, d)
            rows.append((colourise(1.0 / d, lo, hi, "magma"), f"{label}: AbsRel {e['abs_rel']:.3f}"))
        cols.append(np.concatenate([labelled_tile(im, text, width) for im, text in rows], 0))
    return side_by_side(cols)


def labelled_tile(im: np.ndarray, text: str, width: int) -> np.ndarray:
    """``im`` resized to ``width`` pixels wide with ``text`` written in its top-left corner."""
    import cv2

    h, w = im.shape[:2]
    im = cv2.resize(im, (width, round(h * width / w)), interpolation=cv2.INTER_AREA).copy()
    # a dark outline from thin strokes shifted by a pixel: one thick stroke advances wider and left a ghost
    # of the last glyph after the white text
    for dx, dy in ((-1, 0), (1, 0), (0, -1), (0, 1)):
        cv2.putText(im, text, (8 + dx, 22 + dy), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.putText(im, text, (8, 22), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (255, 255, 255), 1, cv2.LINE_AA)
    return im


def side_by_side(cols: list[np.ndarray]) -> np.ndarray:
    """Columns of equal height next to each other, 6 white pixels apart."""
    gap = np.full((cols[0].shape[0], 6, 3), 255, np.uint8)
    out = cols[0]
    for c in cols[1:]:
        out = np.concatenate([out, gap, c], 1)
    return out


CHANGE_COLOURS = {"new, too near": (255, 0, 0), "new, too far": (255, 0, 255), "fixed": (0, 255, 0),
                  "failing in both": (0, 255, 255)}


def failure_changes(gt: np.ndarray, before: np.ndarray, after: np.ndarray) -> dict[str, np.ndarray]:
    """Per pixel (H,W) bool: the δ1 failures (max ratio to ``gt`` ≥ 1.25) of ``after`` against ``before`` — new ones
    too near and too far, fixed ones, ones in both; pixels without ground truth (0) in none."""
    ok = gt > 0
    g = np.where(ok, gt, 1.0)
    bad = [ok & (np.maximum(g / d, d / g) >= 1.25) for d in (before, after)]
    return {"new, too near": ~bad[0] & bad[1] & (after < g), "new, too far": ~bad[0] & bad[1] & (after >= g),
            "fixed": bad[0] & ~bad[1], "failing in both": bad[0] & bad[1]}


def change_rows(seq, frames: list[int], models: list[tuple[str, object]], gt_kind: str, width: int = 620) -> np.ndarray:
    """The changes picture as an RGB uint8 array (columns: frames; rows: the models after the first)."""
    import cv2

    cols = []
    for i in frames:
        img = seq.image(i)
        gt = seq.depth(i) if gt_kind == "dense" else seq.lidar_depth(i)
        if gt is None:
            from mono_map.errors import MonoMapError

            raise MonoMapError(f"--gt dense: sequence {seq.name} has no dense depth (synthetic only; --gt lidar)")
        gt = np.where((gt > 1e-3) & (gt <= 80.0), gt, 0.0)
        depths = [pred.predict(img).depth for _, pred in models]
        tiles = []
        for (label, _), d in zip(models[1:], depths[1:]):
            ch = failure_changes(gt, depths[0], d)
            im = img // 2
            for name, colour in CHANGE_COLOURS.items():
                im[ch[name]] = colour
            if gt_kind == "lidar":   # sparse points: grown to be seen
                im = np.where(cv2.dilate((gt > 0).astype(np.uint8), np.ones((3, 3), np.uint8))[..., None] > 0,
                              cv2.dilate(im, np.ones((3, 3), np.uint8)), im)
            n_new = int(ch["new, too near"].sum() + ch["new, too far"].sum())
            tiles.append(labelled_tile(im, f"frame {i}, {label}: {n_new} new, {int(ch['fixed'].sum())} fixed", width))
        cols.append(np.concatenate(tiles, 0))
    return side_by_side(cols)


def main(argv: list[str] | None = None) -> int:
    from mono_map.cli.options import add_data_root, add_frames, add_model, add_seq

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="what", required=True)
    for what in ("depth", "changes"):   # the two pictures of models on frames of a sequence
        d = sub.add_parser(what)
        add_data_root(d)
        add_seq(d, required=True)
        add_frames(d, default="0", what="frames to show")
        add_model(d, repeat=True)
        d.add_argument("--label", action="append", default=None)
        d.add_argument("--out", required=True, help="picture (.png or .jpg)")
        if what == "changes":
            d.add_argument("--gt", choices=("dense", "lidar"), default="dense")
    t = sub.add_parser("topdown")
    t.add_argument("--map", action="append", required=True, help="TITLE=path.bt (repeatable)")
    t.add_argument("--out", required=True)
    args = ap.parse_args(argv)

    import torch

    from mono_map.errors import MonoMapError

    torch.set_num_threads(1)
    try:
        if args.what in ("depth", "changes"):
            from mono_map.data.kitti import open_sequence
            from mono_map.depth.inference import DepthPredictor
            from mono_map.frames import parse_frames
            from mono_map.viz.plots import write_picture

            names = args.model or [None]                  # None: the shipped binary model
            labels = args.label or [m or "binary" for m in names]
            if len(labels) != len(names):
                raise MonoMapError("--label: give one per --model")
            if args.what == "changes" and len(names) < 2:
                raise MonoMapError("--model: changes needs the model before and at least one after")
            seq = open_sequence(args.data_root, args.seq)
            frames = parse_frames(args.frames).resolve(len(seq))
            models = [(lab, DepthPredictor.load(m)) for lab, m in zip(labels, names)]
            pic = (depth_rows(seq, frames, models) if args.what == "depth"
                   else change_rows(seq, frames, models, args.gt))
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
