#!/usr/bin/env python3
"""What does keeping the lowest-entropy pixels remove? Per frame, against the dense ground truth depth_2
of a synthetic sequence: relative error of kept vs removed pixels, and how sky pixels (depth_2 = 0, never
supervised by the LiDAR) are predicted and selected.

    .venv/bin/python tools/archive/diag_entropy_selection.py --seq 00 --frames 0:500:25 --keep 0.8
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from mono_map.data.depth_png import read_depth_png
from mono_map.data.prepare import prepare_sequence
from mono_map.frames import parse_frames
from mono_map.mapping.inputs import load_predictor
from mono_map.mapping.select import select_pixels


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seq", default="00")
    ap.add_argument("--frames", default="0:500:25", help="start:stop:step")
    ap.add_argument("--keep", type=float, default=0.8)
    ap.add_argument("--model", default=None, help="checkpoint (default: shipped binary)")
    ap.add_argument("--data-root", default=None)
    args = ap.parse_args()
    selection = parse_frames(args.frames)
    seq = prepare_sequence(args.data_root, args.seq, selection)
    depth_dir = Path(seq.root) / "sequences" / args.seq / "depth_2"
    if not depth_dir.is_dir():
        print(f"{depth_dir}: no dense ground truth (synthetic sequences only)", file=sys.stderr)
        return 2
    predictor = load_predictor(args.model)
    rows = []
    for i in selection.resolve(len(seq)):
        p = predictor.predict(seq.image(i))
        gt = read_depth_png(depth_dir / f"{i:06d}.png")
        sky = gt <= 0
        kept, valid = select_pixels(p.depth, p.entropy, args.keep, return_valid=True)  # as mono-map build
        surf = valid & ~sky
        err = np.abs(p.depth[surf] - gt[surf]) / gt[surf]
        k = kept[surf]
        rows.append([np.median(err[k]), np.median(err[~k]), (err[k] > 0.5).mean(), (err[~k] > 0.5).mean(),
                     sky.mean(), kept[sky].mean() if sky.any() else np.nan, kept[~sky].mean(),
                     np.median(p.entropy[sky]) if sky.any() else np.nan, np.median(p.entropy[~sky]),
                     np.median(p.depth[sky]) if sky.any() else np.nan, np.median(err)])
    r = np.nanmean(np.array(rows), axis=0)
    print(f"sequence {args.seq}, frames {args.frames} ({len(rows)} frames), keep {args.keep:g}, means over frames of:")
    print(f"  non-sky pixels: median ARE {r[10]:.3f}; kept {r[0]:.3f} vs removed {r[1]:.3f}; "
          f"share with ARE > 0.5: kept {r[2]:.3f} vs removed {r[3]:.3f}")
    print(f"  sky: {100 * r[4]:.1f} % of pixels, kept {100 * r[5]:.1f} % (non-sky kept {100 * r[6]:.1f} %), "
          f"median entropy {r[7]:.2f} nats (non-sky {r[8]:.2f}), median predicted depth {r[9]:.1f} m")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
