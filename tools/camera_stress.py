"""How much each camera effect of depth/augment.py costs a model: val09 AbsRel with one effect applied.

    python tools/camera_stress.py [--model binary --model PATH ...] [--frames 24] [--json out.json]

Every frame of the validation town (the training cache's val09, never 00) is altered by ONE family at a
fixed, strong setting (over-exposure, a road over-exposed by a gain ramp, blur, noise, JPEG, ...) and
scored like the training's validation (AbsRel, δ1 against LiDAR within the bin range). A model that
learned to ignore an effect loses little on its row. Prints a Markdown table, one column per model.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


import numpy as np  # noqa: E402

from mono_map.depth import augment as A  # noqa: E402

CONDITIONS = {
    "none": lambda x, r: x,
    "vignetting 0.5": lambda x, r: A.vignetting(x, 0.5),
    "blur σ 1.2 px": lambda x, r: A.blur(x, 1.2),
    "exposure +1.5 stops (clipped)": lambda x, r: A.exposure(x, 1.5),
    "exposure −1.5 stops": lambda x, r: A.exposure(x, -1.5),
    "road over-exposed (+0.5, ramp +2)": lambda x, r: A.exposure(x, 0.5, 2.0),
    "sky over-exposed (+0.5, ramp −2)": lambda x, r: A.exposure(x, 0.5, -2.0),
    "white balance warm (1.3, 1, 0.75)": lambda x, r: A.white_balance(x, np.array([1.3, 1.0, 0.75])),
    "noise (shot 0.01, read 0.02)": lambda x, r: A.noise(x, 0.01, 0.02, r),
    "gamma 1.5": lambda x, r: A.gamma(x, 1.5),
    "contrast 0.6": lambda x, r: A.contrast(x, 0.6),
    "saturation 0.3": lambda x, r: A.saturation(x, 0.3),
    "JPEG quality 30": lambda x, r: A.jpeg(x, 30),
}


def stress(model, frames, conditions=CONDITIONS) -> dict:
    """{condition: validate() metrics} of ``model`` on ``frames`` (image uint8, LiDAR target) altered."""
    from mono_map.eval.validation import validate

    out = {}
    for name, f in conditions.items():
        rng = np.random.default_rng(0)
        alt = [(np.round(f(img.astype(np.float32) / 255.0, rng) * 255).astype(np.uint8), dep) for img, dep in frames]
        out[name] = validate(model, alt, model.cfg.head, model.cfg.bins, model.cfg.beyond)
    return out


def main(argv=None) -> int:
    from mono_map.cli.options import add_model
    from mono_map.depth.inference import load_checkpoint, resolve_checkpoint
    from mono_map.depth.train_config import DataConfig
    from mono_map.errors import MonoMapError
    from mono_map.eval.validation import validation_frames

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_model(ap, repeat=True)
    ap.add_argument("--frames", type=int, default=24, help="val09 frames (every 10th, as the training validates)")
    ap.add_argument("--trainset", default="default", help="training cache (default ~/.cache/mono-map/trainset)")
    ap.add_argument("--json", default=None, help="also write the numbers here")
    a = ap.parse_args(argv)
    try:
        if a.frames < 1:
            raise MonoMapError(f"--frames: must be >= 1, got {a.frames}")
        models = a.model or ["binary"]
        paths = [resolve_checkpoint(Path(m).expanduser()) for m in models]
        for m, p in zip(models, paths):
            if not p.is_file():
                raise MonoMapError(f"--model: {m}: checkpoint not found")
        frames = validation_frames(DataConfig(trainset=a.trainset, validation_town="val09", validation_frames=a.frames))
        if not frames:
            raise MonoMapError(f"--trainset: {a.trainset}: no rendered val09 frames (mono-map render-trainset)")
    except MonoMapError as exc:
        print(f"camera_stress: error: {exc}", file=sys.stderr)
        return 2
    import torch

    torch.set_num_threads(1)
    res = {}
    for m, p in zip(models, paths):
        model, _ = load_checkpoint(p)
        res[m] = stress(model, frames)
        print(f"{m}: done", file=sys.stderr, flush=True)
    print(f"val09, {len(frames)} frames, AbsRel (δ1) with one camera effect applied\n")
    print("| effect | " + " | ".join(models) + " |")
    print("|---|" + "---|" * len(models))
    for c in CONDITIONS:
        print(f"| {c} | " + " | ".join(f"{res[m][c]['abs_rel']:.4f} ({res[m][c]['delta1']:.3f})" for m in models) + " |")
    if a.json:
        Path(a.json).write_text(json.dumps(res, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
