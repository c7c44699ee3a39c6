"""A picture of models on real KITTI object frames: image, LiDAR, and per model its inverse depth and error.

    python tools/plot_object_frames.py --model v2/binary-real --model v2/binary-randconv \\
        --names k007347,000002,k000003 --out docs/images/object_randconv.jpg [--real-root ../shared/kitti_real]

One row per frame (looked up in object/training and object/extra); inverse depth (1/m) on one colour scale
(1/80 … 1/3), the error as log2(predicted / LiDAR depth) at the LiDAR points (``viz.plots.error_image``: each point
spread to 3×3 pixels; red too far, blue too near, saturated at a factor of 2, grey no point); each model's panel is
titled with the frame's AbsRel (log-space expectation).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from mono_map.cli.options import add_model

REPO = Path(__file__).resolve().parents[1]


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_model(ap, repeat=True)
    ap.add_argument("--names", required=True, help="object frame names, comma-separated (e.g. k007347,000002)")
    ap.add_argument("--real-root", default=str(REPO.parent / "shared" / "kitti_real"),
                    help="the kitti_real folder (default ../shared/kitti_real)")
    ap.add_argument("--out", required=True, help="picture to write (.png or .jpg)")
    args = ap.parse_args(argv)

    from mono_map.depth.inference import DepthPredictor, checkpoint_path, default_precision
    from mono_map.errors import MonoMapError
    from mono_map.eval.depth_evaluation import object_frames
    from mono_map.viz.plots import error_image, write_picture

    root = Path(args.real_root) / "object"
    folders = [d for d in (root / "training", root / "extra") if d.is_dir()]
    if not folders:
        sys.exit(f"plot_object_frames: --real-root: no object/training or object/extra under {args.real_root}")
    names = [n for n in args.names.split(",") if n]
    models = args.model or ["binary"]
    try:
        for m in models:
            checkpoint_path(m)
        frames = {n: (im, d) for f in folders for n, im, d in object_frames(f)}
    except MonoMapError as exc:
        sys.exit(f"plot_object_frames: {exc}")
    missing = [n for n in names if n not in frames]
    if not names or missing:
        sys.exit(f"plot_object_frames: --names: not object frames under {root}: {', '.join(missing) or '(none given)'}")
    predictors = {m: DepthPredictor.load(m, precision=default_precision()) for m in models}

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    grey_nan = plt.get_cmap("RdBu_r").copy()
    grey_nan.set_bad("0.55")                 # no LiDAR point: grey, as tools/plot_predictions.py --error
    cols = 2 + 2 * len(models)
    fig, axes = plt.subplots(len(names), cols, figsize=(4.2 * cols, 1.5 * len(names)), dpi=110)
    ax = np.asarray(axes).reshape(len(names), cols)
    for r, n in enumerate(names):
        image, gt = frames[n]
        v, u = np.nonzero(gt > 0)

        def points(a, values, cmap, lo, hi):
            a.imshow(np.zeros_like(gt), cmap="gray", vmin=0, vmax=1)
            a.scatter(u, v, c=values, s=0.3, cmap=cmap, vmin=lo, vmax=hi)
            a.set_xlim(0, gt.shape[1])
            a.set_ylim(gt.shape[0], 0)

        ax[r, 0].imshow(image)
        ax[r, 0].set_ylabel(n, fontsize=8)
        points(ax[r, 1], 1.0 / gt[v, u], "magma", 1 / 80, 1 / 3)
        for k, m in enumerate(models):
            d = predictors[m].predict(image).depth
            absrel = float(np.mean(np.abs(d[v, u] - gt[v, u]) / gt[v, u]))
            ax[r, 2 + 2 * k].imshow(1.0 / np.maximum(d, 1e-3), cmap="magma", vmin=1 / 80, vmax=1 / 3)
            ax[r, 2 + 2 * k].set_title(f"{m}: AbsRel {absrel:.3f}", fontsize=8)
            ax[r, 3 + 2 * k].imshow(error_image(d, gt), cmap=grey_nan, vmin=-1, vmax=1)
            if r == 0:
                ax[r, 3 + 2 * k].set_title(f"{m}: log2(pred / LiDAR)", fontsize=8)
    ax[0, 0].set_title("image", fontsize=8)
    ax[0, 1].set_title("LiDAR (1/m)", fontsize=8)
    for a in ax.ravel():
        a.set_xticks([])
        a.set_yticks([])
    fig.tight_layout()
    fig.canvas.draw()
    pic = np.asarray(fig.canvas.buffer_rgba())[..., :3]
    plt.close(fig)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    write_picture(out, pic)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
