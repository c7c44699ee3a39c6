"""``mono-map train``, ``predict``, ``eval-depth`` (heavy imports inside the functions)."""

from __future__ import annotations

import sys
from pathlib import Path

from mono_map.cli.options import (add_data_root, add_flip, add_frames, add_model, add_out, add_precision, add_seq,
                                  add_threads, check_threads)
from mono_map.errors import MonoMapError
from mono_map.frames import FrameSelection, parse_frames


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "train", help="train a depth network on the synthetic training towns (never sequence 00)",
        description="Train per a TOML/JSON config (mono_map/depth/configs/*.toml). Resumes from "
                    "<work_dir>/<name>/last.pt. Multi-process: torchrun --nproc_per_node N -m mono_map train --config F.")
    p.add_argument("--config", required=True, help="training config (.toml or .json)")
    add_data_root(p, help="KITTI root (default: $MONO_MAP_DATA or ./data/kitti)")
    p.add_argument("--steps", type=int, default=None, help="override train.steps")
    p.add_argument("--output", default=None, help="override train.output (final checkpoint path)")
    add_precision(p, help="override train.bf16: bf16 autocast pays only on CPUs with AMX or AVX-512 BF16 "
                          "(on an EPYC without AVX-512 a resnet18-half step took 7.5x as long as fp32)")
    add_threads(p, default=None, help="override train.threads (torch intra-op threads)")
    p.add_argument("--no-resume", action="store_true", help="start from scratch even if a checkpoint exists")
    p.set_defaults(func=run_train)

    p = subparsers.add_parser("predict", help="predict depth + entropy for a sequence or an image folder")
    src = p.add_mutually_exclusive_group(required=True)
    add_seq(src, default=None)
    src.add_argument("--images", help="folder of .png/.jpg images")
    add_data_root(p)
    add_frames(p, what="with --seq, the frames")
    add_model(p)
    add_out(p, default="outputs/predict", help="output folder")
    p.add_argument("--npz", action="store_true", help="also save the K×h×w distributions (float16, model resolution)")
    p.add_argument("--space", choices=("log", "linear"), default="log", help="expectation space")
    add_flip(p)
    p.set_defaults(func=run_predict)

    p = subparsers.add_parser("eval-depth", help="depth metrics, uncertainty AUCs, oracle hypotheses of the heads")
    add_seq(p, help="evaluation sequence (00: the held-out town)")
    add_data_root(p)
    add_frames(p, says="0:500:10, fewer in a shorter sequence")
    add_model(p, repeat=True, help="checkpoint path or shipped name (binary, v2/<head>, v1/<head>; default: all shipped)")
    p.add_argument("--gt", choices=("lidar", "dense"), default="lidar", help="ground truth: projected LiDAR or dense depth_2")
    p.add_argument("--kitti-object", default=None, help="evaluate on a real KITTI object 'training' folder instead")
    p.add_argument("--trainset-town", default=None,
                   help="evaluate on a town of the training cache instead (e.g. val09, or a training town to "
                        "measure the fit on training frames); --frames index its frames")
    p.add_argument("--trainset", default="default", help="training cache directory (default ~/.cache/mono-map/trainset)")
    p.add_argument("--split", default=None,
                   help="evaluate the frames of a KITTI raw split found under --data-root (a raw root): 'eigen' "
                        "(Eigen's 697 test frames) or a file of 'DATE/DRIVE FRAME l' lines; Eigen's protocol "
                        "(raw-calibration LiDAR, Garg crop, 1e-3-80 m) beside full-image numbers")
    p.add_argument("--cap", type=float, default=80.0, help="maximum ground-truth depth (m)")
    p.add_argument("--garg-crop", action="store_true", help="evaluate inside Garg's crop only")
    add_out(p, default="outputs/eval_depth", help="output folder (JSON, Markdown, PNG)")
    add_threads(p, default=2)
    p.add_argument("--fast", action="store_true", help="distribution statistics at the decoder's stride 4, then up-sampled")
    add_flip(p)
    p.set_defaults(func=run_eval_depth)


EVAL_FRAMES = FrameSelection("0:500:10", stop=500, step=10, up_to=True)  # eval-depth's default


def run_train(args) -> int:
    from mono_map.depth.inference import default_precision
    from mono_map.depth.train import dist_env, init_distributed, train
    from mono_map.depth.train_config import load_run_config, override

    if args.data_root is not None:
        from mono_map.data.prepare import check_data_root

        check_data_root(args.data_root)
    cfg = override(load_run_config(args.config), steps=args.steps, output=args.output, data_root=args.data_root,
                   precision=args.precision, threads=args.threads)
    if cfg.train.bf16 and default_precision() == "fp32":
        print(f"train: warning: {cfg.source} asks for bf16 autocast, but this CPU has no AMX or AVX-512 BF16, "
              "so bfloat16 is emulated and slow; --precision fp32 overrides", file=sys.stderr)
    rank, world = dist_env()
    init_distributed(rank, world)
    validator = None
    if cfg.train.validate_every and rank == 0:
        from mono_map.eval.validation import validator_for

        m = cfg.model_config()
        validator = validator_for(cfg.data, m.head, m.bins, m.beyond)
    train(cfg, resume=not args.no_resume, validator=validator)
    return 0


def run_predict(args) -> int:
    from mono_map.depth.inference import DepthPredictor
    from mono_map.io import prepare_output_dir, staged_dir
    from mono_map.progress import progress
    from mono_map.viz.codec import colourise

    if args.images and args.frames is not None:
        raise MonoMapError("--frames: selects frames of a --seq, not of an --images folder")
    selection = parse_frames(args.frames)
    if args.images and not Path(args.images).is_dir():
        raise MonoMapError(f"--images: {args.images}: no such folder")
    out = prepare_output_dir(args.out)
    pred = DepthPredictor.load(args.model, space=args.space, flip=args.flip)
    if args.seq:
        from mono_map.data.prepare import prepare_sequence

        seq = prepare_sequence(args.data_root, args.seq, selection)
        idx = selection.resolve(len(seq))
        items = [(f"{i:06d}", (lambda i=i: seq.image(i))) for i in idx]
    else:
        from mono_map.data.kitti_files import PNG_GRAY_TYPES, read_image_rgb, read_png_header

        folder = Path(args.images)
        files = sorted(p for p in folder.glob("*") if p.suffix.lower() in (".png", ".jpg", ".jpeg"))
        if not files:
            raise MonoMapError(f"{folder}: no .png/.jpg images")
        for f in files:  # every file checked before the first prediction is written
            if f.suffix.lower() == ".png":
                if read_png_header(f)[2] in PNG_GRAY_TYPES:
                    raise MonoMapError(f"{f}: grayscale image; a colour (RGB) image is needed")
            elif f.read_bytes()[:3] != b"\xff\xd8\xff":
                raise MonoMapError(f"{f}: unreadable image (not a JPEG file)")
        items = [(p.stem, (lambda p=p: read_image_rgb(p))) for p in files]
    with staged_dir(out) as stage:  # every prediction appears when all are done, none if one fails
        for sub in ("depth", "entropy", "beyond", "vis") + (("npz",) if args.npz else ()):
            (stage / sub).mkdir()
        for name, load in progress(items, total=len(items), desc="predict", unit="frame"):
            predict_one(pred, name, load(), stage, args.npz)
    print(f"wrote {len(items)} predictions to {out}/(depth|entropy|vis{'|npz' if args.npz else ''})")
    return 0


def predict_one(pred, name: str, img, out: Path, npz: bool) -> None:
    """Write one image's depth (KITTI uint16 PNG), entropy (uint16, nats × 10000), probability of no
    surface within range (``beyond/``, uint8, × 255), picture and optionally its distributions under ``out``."""
    import cv2
    import numpy as np

    from mono_map.data.depth_png import write_depth_png
    from mono_map.io import atomic_path
    from mono_map.viz.codec import colourise

    logk = float(np.log(pred.bins.num_bins))
    p = pred.predict(img)
    write_depth_png(out / "depth" / f"{name}.png", p.depth)
    with atomic_path(out / "entropy" / f"{name}.png") as tmp:  # uint16, nats × 10000
        cv2.imwrite(str(tmp), np.clip(np.round(p.entropy * 10000), 0, 65535).astype(np.uint16))
    with atomic_path(out / "beyond" / f"{name}.png") as tmp:
        cv2.imwrite(str(tmp), np.clip(np.round(p.p_beyond * 255), 0, 255).astype(np.uint8))
    rows = [img, colourise(1.0 / p.depth, 1.0 / pred.bins.max_depth, 1.0 / 3.0, "magma"),
            colourise(p.entropy, 0.0, logk if pred.cfg.head != "gaussian" else 2.0, "viridis")]
    if pred.cfg.beyond:   # a fourth row: where the model sees no surface within range (sky)
        rows.append(colourise(p.p_beyond, 0.0, 1.0, "gray"))
    vis = np.concatenate(rows, 0)
    with atomic_path(out / "vis" / f"{name}.jpg") as tmp:
        cv2.imwrite(str(tmp), cv2.cvtColor(vis, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, 90])
    if npz:
        raw, _ = pred.raw_outputs([img])
        probs = pred.decode(raw, with_probs=True)["probs"]
        with atomic_path(out / "npz" / f"{name}.npz") as tmp:
            np.savez_compressed(tmp, probs=None if probs is None else probs[0].numpy().astype(np.float16),
                                bin_centres=pred.bins.centres, depth=p.depth, entropy=p.entropy,
                                p_beyond=p.p_beyond)


def _models(args) -> list[str]:
    from mono_map.depth.inference import default_checkpoint, shipped_names

    if args.model:
        return args.model
    found = shipped_names()
    if not found:
        raise MonoMapError(f"{default_checkpoint('binary').parent}: no shipped checkpoints; pass --model")
    return found


def run_eval_depth(args) -> int:
    import torch

    from mono_map.eval.depth_evaluation import evaluate_model, markdown_report, object_frames, scrambled_colour
    from mono_map.depth.inference import DepthPredictor, shipped_names
    from mono_map.io import prepare_output_dir

    selection = parse_frames(args.frames, default=EVAL_FRAMES)
    if args.cap <= 0 or args.cap != args.cap:
        raise MonoMapError(f"--cap: must be a positive depth in metres, got {args.cap}")
    check_threads(args.threads)
    if args.kitti_object and not Path(args.kitti_object).is_dir():
        raise MonoMapError(f"--kitti-object: {args.kitti_object}: no such folder")
    selection_split = check_split_args(args) if args.split else None
    prepare_output_dir(args.out)
    torch.set_num_threads(max(1, args.threads))
    predictors = {}
    shipped = shipped_names()
    for m in _models(args):
        p = DepthPredictor.load(m, fast=args.fast, flip=args.flip)
        key = m if m in shipped else p.training.get("name") or p.head   # the run's name (e.g. v2-binary-k32)
        key = key if key not in predictors else f"{key} ({m})"
        key += " --flip" if args.flip else ""
        predictors[key] = p
    if selection_split is not None:
        return run_split(args, selection_split, predictors)
    if args.kitti_object:
        frames = object_frames(args.kitti_object)
        for name, a in scrambled_colour(frames):
            print(f"eval-depth: warning: {Path(args.kitti_object) / 'image_2' / name}.png: its colour channels do not "
                  f"agree (smallest correlation {a:.2f}): a scrambled file? scored anyway", file=sys.stderr)
        make = lambda: iter(frames)  # noqa: E731
        n, title, where = len(frames), f"Depth evaluation on real KITTI object frames ({args.kitti_object})", "object"
    elif args.trainset_town:
        from mono_map.eval.depth_evaluation import open_town, trainset_frames

        town = open_town(args.trainset, args.trainset_town)
        idx = selection.resolve(town.frames)
        frames = trainset_frames(town, idx, args.gt)
        make = lambda: iter(frames)  # noqa: E731
        n, where = len(frames), f"trainset_{args.trainset_town}"
        title = (f"Depth evaluation on training-cache town {args.trainset_town} ({selection.describe(idx)}, 192×634, "
                 f"ground truth: {args.gt}, cap {args.cap:g} m)")
    else:
        from mono_map.data.prepare import prepare_sequence

        seq = prepare_sequence(args.data_root, args.seq, selection)
        idx = selection.resolve(len(seq))

        def make():
            for i in idx:
                gt = seq.lidar_depth(i) if args.gt == "lidar" else seq.depth(i)
                if gt is None:
                    raise MonoMapError(f"{seq.depth_dir}: no dense depth for frame {i} (--gt dense)")
                yield f"{i:06d}", seq.image(i), gt

        n, where = len(idx), f"seq{args.seq}"
        title = (f"Depth evaluation on sequence {args.seq} ({selection.describe(idx)}, ground truth: {args.gt}"
                 f"{', Garg crop' if args.garg_crop else ''}, cap {args.cap:g} m)")
    results = {h: evaluate_model(p, make(), n, cap=args.cap, garg_crop=args.garg_crop, desc=f"eval {h}")
               for h, p in predictors.items()}
    publish_depth_report(Path(args.out), where, markdown_report(results, title),
                         {"title": title, "args": cli_args(args), "results": results}, results)
    return 0


def cli_args(args) -> dict:
    """The command line's options as a JSON-able dict (for a report's provenance)."""
    return {k: v for k, v in vars(args).items() if k != "func"}


def publish_depth_report(out: Path, where: str, md: str, payload: dict, results: dict) -> None:
    """Write depth_<where>.json/.md and the sparsification and hypotheses pictures into ``out`` as one set
    (all published or, on a failure or a signal, none), then print the report."""
    from mono_map.io import staged_dir, write_json_atomic, write_text_atomic
    from mono_map.viz.plots import plot_hypotheses, plot_sparsification

    with staged_dir(out) as stage:
        write_json_atomic(stage / f"depth_{where}.json", payload)
        write_text_atomic(stage / f"depth_{where}.md", md)
        plot_sparsification(results, stage / f"sparsification_{where}.png")
        plot_hypotheses(results, stage / f"hypotheses_{where}.png")
    print(md)
    print(f"wrote {out}/depth_{where}.(json|md), sparsification_{where}.png, hypotheses_{where}.png")


def check_split_args(args):
    """``eval-depth --split``: refuse options it does not take, then find the split's frames (before any work)."""
    from mono_map.data.prepare import check_data_root
    from mono_map.eval.depth_evaluation import split_frames

    for option, given in (("--kitti-object", args.kitti_object), ("--trainset-town", args.trainset_town),
                          ("--frames", args.frames), ("--garg-crop", args.garg_crop), ("--gt dense", args.gt == "dense")):
        if given:
            raise MonoMapError(f"{option}: not with --split (the split names its frames; its protocol fixes the "
                               "ground truth and crop)")
    if args.cap != 80.0:
        raise MonoMapError("--cap: not with --split (Eigen's protocol caps at 80 m)")
    root = check_data_root(args.data_root)
    if not root.is_dir():
        raise MonoMapError(f"--data-root: {root}: no such folder (a KITTI raw root holding YYYY_MM_DD/ folders)")
    sel = split_frames(root, args.split)
    if not sel.frames:
        eg = (f"{sel.missing_drives[0][:10]}/{sel.missing_drives[0]}/image_02/data" if sel.missing_drives
              else "the drives' listed frames")
        raise MonoMapError(f"--split: none of the {sel.n_listed} frames of {sel.path} found under {root} "
                           f"(expected DATE/DRIVE/image_02/data/NNNNNNNNNN.png, e.g. {eg})")
    print(f"eval-depth: {len(sel.frames)} of the {sel.n_listed} frames of {sel.path.name} found under {root} "
          f"({len({f[0] for f in sel.frames})} drives; {len(sel.missing_drives)} listed drives missing)",
          file=sys.stderr)
    return sel


def run_split(args, sel, predictors: dict) -> int:
    """eval-depth --split: each model under Eigen's protocol and over the full image (one pass); Table I + the
    usual report."""
    from mono_map.eval.depth_evaluation import eigen_frames, evaluate_model, markdown_report, table_one

    n = len(sel.frames)
    results = {h: evaluate_model(p, eigen_frames(sel), n, cap=80.0, garg_crop=True, desc=f"eval {h}")
               for h, p in predictors.items()}
    where = "eigen" if args.split == "eigen" else f"split_{sel.path.stem}"
    title = f"Depth evaluation on the {sel.path.name} split ({n} of {sel.n_listed} frames found)"
    payload = {"title": title, "split": str(sel.path), "n_listed": sel.n_listed, "n_found": n,
               "missing_drives": sel.missing_drives, "args": cli_args(args), "results": results}
    md = (table_one(results, title, n, sel.n_listed) + "\n"
          + markdown_report(results, f"{title}: Eigen's protocol in detail").replace("# ", "## ", 1))
    publish_depth_report(Path(args.out), where, md, payload, results)
    return 0
