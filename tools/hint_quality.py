"""How good are Depth Hints (``mono-map adapt --hints``) on a sequence, measured against its LiDAR.

For every ``--every``-th adaptation target: the hints exactly as ``adapt`` computes them (the plane sweep over
the bins from the frame's sources, at the loss resolution, ``--hint-contrast`` floors), the model's expected
depth, and both photometric errors. Reported per contrast floor: the share of LiDAR pixels with a hint, the
hints' AbsRel / median ARE / share within 25 %; and at the pixels the hint mask keeps (hint error below the
model's): the hints' and the model's AbsRel, and where the hint is the closer of the two. LiDAR is read at the
loss grid's pixels (nearest, 1–80 m). Real data is for measuring only.

    PYTHONPATH=. .venv/bin/python tools/hint_quality.py --seq real01 --data-root ../shared/kitti_real/odometry \\
        [--frames all] [--model binary] [--every 5] [--contrast 0 --contrast 0.05] [--out outputs/hint_quality]
"""

from __future__ import annotations

import argparse
import sys

import numpy as np


def measure(model_name, data_root, seq_name, frames, every: int, contrasts: list[float]) -> list[dict]:
    import cv2
    import torch

    from mono_map.data.prepare import prepare_sequence
    from mono_map.depth.adapt import AdaptConfig, load_frames
    from mono_map.depth.adapter import Adapter, base_statistics
    from mono_map.depth.hints import compute_hints, hint_mask
    from mono_map.depth.inference import default_precision, load_checkpoint, resolve_checkpoint
    from mono_map.depth.photometric import min_reprojection_error
    from mono_map.depth.sources import choose_sources
    from mono_map.errors import MonoMapError

    model, _ = load_checkpoint(resolve_checkpoint(model_name))
    seq = prepare_sequence(data_root, seq_name, frames, render=False)
    cfg = AdaptConfig(precision=default_precision())
    data = load_frames(seq, frames.resolve(len(seq)), model.cfg.input_height, model.cfg.input_width)
    sources = choose_sources(data.poses[:, :3, 3], cfg.min_baseline, cfg.max_baseline, cfg.max_offset, cfg.per_side)
    picked = {t: sources[t] for t in sorted(sources)[::every]}
    if not picked:
        raise MonoMapError(f"{seq.path}: no frame has a source 0.3-4 m away (too little motion)")
    beyond, _ = base_statistics(model, data.images, cfg.precision)   # sky: as adapt
    adapter = Adapter(model.eval(), beyond, data, sources, cfg)
    fh, fw = data.content[0] // cfg.loss_scale, data.content[1] // cfg.loss_scale
    preds = {}
    with torch.no_grad():
        for t in picked:
            x, tgt, srcs, poses, mask, K = adapter.batch([t])
            depth, _ = adapter.depth_and_beyond(adapter.forward(x), tgt.shape[-2:])
            err, _ = min_reprojection_error(tgt, srcs, depth, K, poses)
            gt = cv2.resize(seq.lidar_depth(data.indices[t]), (fw, fh), interpolation=cv2.INTER_NEAREST)
            preds[t] = (depth[0, 0, :fh, :fw].numpy(), err, mask, gt)
    rows = []
    for c in contrasts:
        hints = compute_hints(adapter.small, adapter.K.numpy(), data.poses, picked, model.cfg.bins,
                              adapter.content[0, 0], min_contrast=c, progress_desc=f"hints (contrast {c:g})")
        hint_all, hint_kept, pred_kept, n_gt = [], [], [], 0
        for t, (pred, err, mask, gt) in preds.items():
            hd = hints.depth[t, 0, :fh, :fw].numpy()
            kept = (hint_mask(hints.depth[[t]], hints.error[[t]], err) & mask)[0, 0, :fh, :fw].numpy()
            g = (gt > 1) & (gt < 80)
            n_gt += int(g.sum())
            hint_all.append(np.abs(hd - gt)[g & (hd > 0)] / gt[g & (hd > 0)])
            hint_kept.append(np.abs(hd - gt)[g & kept] / gt[g & kept])
            pred_kept.append(np.abs(pred - gt)[g & kept] / gt[g & kept])
        a, hk, pk = (np.concatenate(v) for v in (hint_all, hint_kept, pred_kept))
        rows.append({"contrast": c, "frames": len(preds), "lidar_pixels": n_gt, "hinted_share": len(a) / max(n_gt, 1),
                     "hint_abs_rel": mean(a), "hint_median_are": float(np.median(a)) if len(a) else float("nan"),
                     "hint_within_25": mean(a < 0.25), "kept_share": len(hk) / max(n_gt, 1),
                     "kept_hint_abs_rel": mean(hk), "kept_model_abs_rel": mean(pk), "kept_hint_closer": mean(hk < pk)})
    return rows


def mean(x: np.ndarray) -> float:
    """The mean, NaN for no values (a floor that leaves no hint)."""
    return float(x.mean()) if len(x) else float("nan")


def markdown(rows: list[dict]) -> str:
    L = ["| contrast floor | LiDAR px with a hint | hint AbsRel | hint median ARE | hint within 25 % | kept by the mask "
         "| kept: hint AbsRel | kept: model AbsRel | kept: hint closer |", "|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        L.append(f"| {r['contrast']:g} | {100 * r['hinted_share']:.1f} % | {r['hint_abs_rel']:.3f} | "
                 f"{r['hint_median_are']:.3f} | {100 * r['hint_within_25']:.1f} % | {100 * r['kept_share']:.1f} % | "
                 f"{r['kept_hint_abs_rel']:.3f} | {r['kept_model_abs_rel']:.3f} | {100 * r['kept_hint_closer']:.1f} % |")
    return "\n".join(L) + "\n"


def main(argv: list[str] | None = None) -> int:
    from mono_map.cli.options import add_data_root, add_frames, add_model, add_out, add_seq, add_threads

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_seq(ap, required=True, help="sequence name under the data root (e.g. real01)")
    add_data_root(ap)
    add_frames(ap, says="all", what="frames the hints are computed from")
    add_model(ap, help="checkpoint whose prediction the hints compete with (default binary)")
    ap.add_argument("--every", type=int, default=5, help="every N-th adaptation target is measured (default 5)")
    ap.add_argument("--contrast", type=float, action="append", default=None,
                    help="hint contrast floor(s) (repeatable; default 0 and 0.05)")
    add_out(ap, default="outputs/hint_quality")
    add_threads(ap, default=1)
    args = ap.parse_args(argv)

    import torch

    from mono_map.errors import MonoMapError
    from mono_map.frames import parse_frames
    from mono_map.io import prepare_output_dir, write_json_atomic, write_text_atomic

    try:
        if args.every < 1:
            raise MonoMapError(f"--every: must be >= 1, got {args.every}")
        contrasts = args.contrast if args.contrast is not None else [0.0, 0.05]
        if any(not (np.isfinite(c) and c >= 0) for c in contrasts):
            raise MonoMapError(f"--contrast: must be numbers >= 0, got {contrasts}")
        torch.set_num_threads(max(1, args.threads))
        out = prepare_output_dir(args.out)
        rows = measure(args.model, args.data_root, args.seq, parse_frames(args.frames or "all"), args.every, contrasts)
    except MonoMapError as exc:
        print(f"hint_quality: error: {exc}", file=sys.stderr)
        return 2
    md = markdown(rows)
    write_json_atomic(out / f"hint_quality_{args.seq}.json", {"args": vars(args), "rows": rows})
    write_text_atomic(out / f"hint_quality_{args.seq}.md", md)
    print(md)
    return 0


if __name__ == "__main__":
    sys.exit(main())
