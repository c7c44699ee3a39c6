#!/usr/bin/env python3
"""How much of a predictor's depth error the views share (mono_map/eval/shared_error.py; docs/fused.md).

    PYTHONPATH=. python tools/shared_error.py --seq 06 --frames 0:100:10 --gaps 1,3,10 --data-root DIR \\
        [--model PATH|oracle [--oracle-sigma S --oracle-shared-sigma B]] [--posterior]

For every frame i of ``--frames`` and every gap g, the pixels of frames i and i+g that see one surface point (by
the ground-truth depth; synthetic sequences) pair their log-depth errors. Per gap, pooled over the pairs: the
pairs, the rms error, the correlation of the paired errors (the share of the error's variance the views have in
common: ~1 for an error fixed to the surface, ~0 for noise drawn per frame) and the rms of their difference.
``--posterior``: the multi-view posterior's expected depth (what the fused map uses) instead of the prediction's.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np

from mono_map.cli.options import add_data_root, add_frames, add_model, add_oracle_noise, add_seq, oracle_predictor
from mono_map.data.kitti import open_sequence
from mono_map.depth.bins import DepthBins
from mono_map.depth.multiview import MultiviewConfig, MultiviewPosterior
from mono_map.errors import MonoMapError
from mono_map.eval.shared_error import common_surface_pixels, log_errors, shared_share
from mono_map.frames import parse_frames
from mono_map.mapping.inputs import load_predictor, run_predictor


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_seq(p, default="06")
    add_frames(p, default="0:100:10")
    add_data_root(p)
    add_model(p, oracle=True)
    p.add_argument("--gaps", default="1,3,10", help="comma list: frames between the two views")
    add_oracle_noise(p)
    p.add_argument("--posterior", action="store_true", help="the multi-view posterior's depth (its defaults)")
    args = p.parse_args(argv)
    try:
        gaps = sorted({int(g) for g in args.gaps.split(",")})
    except ValueError:
        gaps = []
    if not gaps or gaps[0] < 1:
        raise SystemExit(f"--gaps: a comma list of positive frame counts, got {args.gaps!r}")
    try:
        predictor = oracle_predictor(args)
    except MonoMapError as e:
        raise SystemExit(str(e))
    seq = open_sequence(args.data_root, args.seq)
    if seq.depth(0) is None:
        raise SystemExit(f"{args.seq}: no ground-truth depth (depth_2): synthetic sequences only")
    frames = parse_frames(args.frames).resolve(len(seq))
    if predictor is None:
        predictor = load_predictor(args.model)
    refiner = MultiviewPosterior(MultiviewConfig(), getattr(predictor, "bins", None) or DepthBins()) \
        if args.posterior else None
    cache: dict[int, np.ndarray] = {}

    def depth_of(i: int) -> np.ndarray:
        if i not in cache:
            pred = run_predictor(predictor, seq, i, seq.image(i), with_probs=refiner is not None, probs_step=2)
            cache[i] = (refiner.refine(seq, i, pred) if refiner is not None else pred).depth
            print(f"frame {i}", file=sys.stderr, flush=True)
        return cache[i]

    pairs = {g: ([], []) for g in gaps}
    for i in frames:
        for g in gaps:
            j = i + g
            if j >= len(seq):
                continue
            pi, pj = common_surface_pixels(seq, i, j)
            pairs[g][0].append(log_errors(depth_of(i), seq.depth(i), pi))
            pairs[g][1].append(log_errors(depth_of(j), seq.depth(j), pj))
        for k in [k for k in cache if k < i]:
            del cache[k]
    what = ("the multi-view posterior of " if refiner else "") + (args.model or "the shipped model")
    print(f"{args.seq}, frames {frames[0]}-{frames[-1]} ({len(frames)}), {what}" +
          (f" (σ {predictor.sigma:g}, edges {predictor.edge_sigma:g}, shared {predictor.shared_sigma:g})"
           if args.model == "oracle" else ""))
    print("| views apart | pairs | rms log error | correlation (shared share) | rms difference |\n|---:|---:|---:|---:|---:|")
    for g in gaps:
        if not pairs[g][0]:
            continue
        s = shared_share(np.concatenate(pairs[g][0]), np.concatenate(pairs[g][1]))
        print(f"| {g} | {s['n']:,} | {s['rms']:.4f} | {s['correlation']:.3f} | {s['rms_difference']:.4f} |")
    return 0


if __name__ == "__main__":
    try:
        sys.exit(main())
    except MonoMapError as exc:
        sys.exit(f"shared_error: error: {exc}")
