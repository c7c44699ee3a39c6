"""``mono-map adapt``: self-supervised adaptation of a depth checkpoint to a sequence (heavy imports inside the
functions)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from mono_map.cli.options import (add_data_root, add_frames, add_model, add_out, add_precision, add_seq, add_threads,
                                  check_threads)
from mono_map.frames import parse_frames


def register(subparsers) -> None:
    from mono_map.depth.adapt import HINT_LOSSES, STEREO_MODES, AdaptConfig

    d = AdaptConfig()
    p = subparsers.add_parser(
        "adapt", help="fine-tune the depth model on the sequence being mapped (self-supervised, its own poses)",
        description="Self-supervised adaptation: neighbouring frames warped into each frame through the predicted "
                    "depth and the sequence's metric poses (SSIM+L1, per-pixel minimum, auto-masking, smoothness). "
                    "Writes <out>/<base>-adapted-<seq>-<digest>.pt for --model of predict, eval-depth, build, eval. "
                    "Resumes from ~/.cache/mono-map/adapt/.")
    add_seq(p, required=True, help="sequence name under the data root (e.g. real01)")
    add_data_root(p)
    add_frames(p, says="the first 500, as build", what="frames to adapt on")
    add_model(p, help="base checkpoint path or shipped name (default binary)")
    add_out(p, default="outputs/adapt", help="folder of the adapted checkpoint")
    p.add_argument("--steps", type=int, default=d.steps, help=f"optimisation steps (default {d.steps})")
    p.add_argument("--lr", type=float, default=d.lr, help=f"Adam learning rate (default {d.lr:g})")
    p.add_argument("--batch-size", type=int, default=d.batch_size, help=f"target frames per step (default {d.batch_size})")
    p.add_argument("--min-baseline", type=float, default=d.min_baseline,
                   help=f"metres a source frame must be from the target (default {d.min_baseline:g})")
    p.add_argument("--max-baseline", type=float, default=d.max_baseline, help=f"... at most (default {d.max_baseline:g})")
    p.add_argument("--max-offset", type=int, default=d.max_offset,
                   help=f"sources are searched up to this many frames before and after a target (default {d.max_offset})")
    p.add_argument("--per-side", type=int, default=d.per_side,
                   help=f"sources before and after each target, each at >= 2x the previous baseline (default {d.per_side})")
    p.add_argument("--loss-scale", type=int, default=d.loss_scale, choices=(1, 2, 4),
                   help=f"photometric loss at 1/N of the network input size (default {d.loss_scale})")
    p.add_argument("--smoothness", type=float, default=d.smoothness,
                   help=f"weight of the edge-aware smoothness of the disparity (default {d.smoothness:g})")
    p.add_argument("--trim", type=float, default=d.trim,
                   help=f"leave out this fraction of each batch's highest-error pixels (default {d.trim:g})")
    p.add_argument("--replay", type=float, default=d.replay,
                   help="weight of supervised replay on --replay-seq, relative to the photometric loss at the start "
                        f"(default {d.replay:g} = off)")
    p.add_argument("--replay-seq", default=d.replay_seq, help="synthetic training sequence for replay (e.g. 06)")
    p.add_argument("--decoder-only", action=argparse.BooleanOptionalAction, default=not d.train_encoder,
                   help="keep the encoder's weights, adapt the decoder and head; --no-decoder-only adapts the whole "
                        f"network (default {'on' if not d.train_encoder else 'off'})")
    p.add_argument("--hints", type=float, default=d.hints,
                   help="weight of Depth Hints: the plane sweep's best depth (known poses, metric) supervises the pixels "
                        f"where its photometric error is lower than the prediction's (default {d.hints:g}; 0 = off)")
    p.add_argument("--hint-loss", choices=HINT_LOSSES, default=d.hint_loss,
                   help="the hint term: log = |log d - log hint| on the expected depth, head = the head's training "
                        f"loss towards the hint (default {d.hint_loss})")
    p.add_argument("--hint-contrast", type=float, default=d.hint_contrast,
                   help="a hint only where the sweep's mean cost exceeds its best plane's by more than this "
                        f"(SSIM+L1 units; default {d.hint_contrast:g}; 0 = every pixel the sweep is informative at)")
    p.add_argument("--stereo", choices=STEREO_MODES, default=d.stereo,
                   help="each frame's right colour camera (image_3, KITTI's stereo partner) as one more source: auto = "
                        f"if every frame has it, on = required, off = never (default {d.stereo})")
    p.add_argument("--mirror", type=float, default=d.mirror,
                   help="probability that a drawn target is mirrored left-right with its sources, intrinsics and poses "
                        f"(default {d.mirror:g} = off)")
    p.add_argument("--entropy-hold", type=float, default=d.entropy_hold,
                   help="weight of the hold of each pixel's entropy to the base model's, keeping its ranking of the "
                        f"pixels by confidence (default {d.entropy_hold:g} = off)")
    p.add_argument("--replay-root", default=None, help="data root of --replay-seq (default: --data-root)")
    p.add_argument("--eval-every", type=int, default=d.eval_every,
                   help=f"steps between held-out photometric checks (the stopping rule; default {d.eval_every})")
    p.add_argument("--seed", type=int, default=d.seed)
    add_precision(p)
    add_threads(p, default=1)
    p.add_argument("--no-resume", action="store_true", help="start again even if a run or checkpoint exists")
    p.set_defaults(func=run_adapt)


def run_adapt(args) -> int:
    import torch

    from mono_map.depth.adapt import AdaptConfig, adapt
    from mono_map.depth.inference import default_precision

    check_threads(args.threads)
    cfg = AdaptConfig(steps=args.steps, lr=args.lr, batch_size=args.batch_size, min_baseline=args.min_baseline,
                      max_baseline=args.max_baseline, max_offset=args.max_offset, per_side=args.per_side,
                      loss_scale=args.loss_scale, smoothness=args.smoothness, trim=args.trim, replay=args.replay,
                      replay_seq=args.replay_seq,
                      train_encoder=not args.decoder_only, eval_every=args.eval_every, seed=args.seed, precision=args.precision or default_precision(),
                      hints=args.hints, hint_loss=args.hint_loss, hint_contrast=args.hint_contrast, stereo=args.stereo,
                      mirror=args.mirror, entropy_hold=args.entropy_hold)
    cfg.validate()
    selection = parse_frames(args.frames) if args.frames is not None else None   # None: adapt's default
    torch.set_num_threads(args.threads)
    res = adapt(args.model, args.data_root, args.seq, selection, cfg, out_dir=args.out,
                resume=not args.no_resume, replay_root=args.replay_root,
                log=lambda m: print(m, file=sys.stderr))
    a = res.metadata["adapted"]
    c = a["curve"]
    print(f"adapted {Path(a['base']).name} to {a['sequence']} ({len(a['frames'])} frames, {a['targets']} targets, "
          f"{len(a['heldout'])} held out): held-out photometric error {c[0]['heldout_photometric']:.4f} -> "
          f"{min(r['heldout_photometric'] for r in c):.4f} (best at step {a['best_step']} of {res.metadata['steps']})")
    print(f"wrote {res.checkpoint}  (use it with --model {res.checkpoint})")
    return 0
