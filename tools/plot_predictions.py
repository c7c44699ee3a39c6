"""A picture of a model's predictions on frames of a sequence: image_2, inverse depth, entropy, p_beyond.

    python tools/plot_predictions.py --seq 00 --frames 0,250 --out docs/images/predict_v2_seq00.png [--model M] [--error]

One row per frame; inverse depth (1/m) and entropy (nats) share one colour scale across the rows;
p_beyond is the probability that the pixel sees no surface within the bin range (white = sky).
``--error`` adds the expected depth's error at the projected LiDAR points, log2(predicted / LiDAR depth):
red too far, blue too near, saturated at a factor of 2 (points dilated to 3×3 pixels to be seen).
"""

from __future__ import annotations

import argparse
import sys

import numpy as np

from mono_map.cli.options import add_data_root, add_frames, add_model, add_seq
from mono_map.data.prepare import prepare_sequence
from mono_map.depth.inference import DepthPredictor
from mono_map.frames import parse_frames
from mono_map.viz.plots import error_image, figure


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_seq(ap)
    add_data_root(ap)
    add_frames(ap, default="0,250")
    add_model(ap)
    ap.add_argument("--out", required=True)
    ap.add_argument("--error", action="store_true",
                    help="add a column: log2(predicted / LiDAR depth) at the LiDAR points (the sequence's velodyne)")
    a = ap.parse_args(argv)
    predictor = DepthPredictor.load(a.model)          # a bad checkpoint is refused before any data is read
    selection = parse_frames(a.frames)
    seq = prepare_sequence(a.data_root, a.seq, selection)
    frames = selection.resolve(len(seq))
    if a.error and not seq.velodyne_files:
        raise SystemExit(f"--error: {seq.path}: no velodyne scans to compare with")
    rows = []
    for i in frames:
        image = seq.image(i)
        p = predictor.predict(image)
        rows.append((i, image, 1.0 / p.depth, p.entropy, p.p_beyond, error_image(p.depth, seq.lidar_depth(i)) if a.error else None))
    inv_hi = max(float(r[2].max()) for r in rows)
    ent_hi = max(float(r[3].max()) for r in rows)
    with figure(a.out, 110, bbox_inches="tight") as plt:
        cols = 5 if a.error else 4
        fig, axes = plt.subplots(len(rows), cols, figsize=(5.5 * cols, 2.1 * len(rows) + 0.4), squeeze=False)
        for ax_row, (i, image, inv, ent, pb, err) in zip(axes, rows):
            panels = ((image, None, f"frame {i}: image_2"), (inv, ("magma", 0, inv_hi), "inverse depth (1/m)"),
                      (ent, ("viridis", 0, ent_hi), "entropy (nats)"), (pb, ("gray", 0, 1), "p_beyond"))
            if err is not None:
                panels += ((err, ("RdBu_r", -1, 1), "log2(pred / LiDAR): red too far, blue too near"),)
            for ax, (img, cmap, title) in zip(ax_row, panels):
                if cmap is None:
                    ax.imshow(img)
                else:
                    cm = plt.get_cmap(cmap[0]).copy()
                    cm.set_bad("0.55")        # NaN (no LiDAR point in the error column): grey
                    im = ax.imshow(img, cmap=cm, vmin=cmap[1], vmax=cmap[2])
                    fig.colorbar(im, ax=ax, fraction=0.025, pad=0.01)
                ax.set_title(title, fontsize=9)
                ax.axis("off")
    print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
