"""Validation of a depth network while it trains: a held-out town of the training cache (never 00).

The command layer builds a validator (:func:`validator_for`) and hands it to
:func:`mono_map.depth.train.train`, so training itself depends on no evaluation code.
"""

from __future__ import annotations

from functools import partial

import numpy as np

from mono_map.depth.train_config import DataConfig
from mono_map.depth.train_data import frame_target, trainset_root


def validator_for(data: DataConfig, head, bins, beyond: bool):
    """``validator(model) -> metrics`` on the configured validation town, or None if there is none."""
    frames = validation_frames(data) if (data.trainset and data.validation_town) else []
    return partial(validate, frames=frames, head=head, bins=bins, beyond=beyond) if frames else None


def validation_frames(data: DataConfig) -> list[tuple[np.ndarray, np.ndarray]]:
    """(image, LiDAR target metres with +inf = sky) of the validation town's first frames (every 10th)."""
    from mono_map.data.synth.trainset import open_trainset

    towns = open_trainset(trainset_root(data), [data.validation_town])
    if not towns:
        return []
    t = towns[0]
    done = t.done_frames()[::10][:data.validation_frames]
    return [frame_target(t, int(f), "lidar", 1) for f in done]


def validate(model, frames, head, bins, beyond: bool) -> dict:
    """AbsRel, δ1 and sparsification AUC (ARE, by entropy) against LiDAR within the bin range, and
    beyond-range accuracy on sky pixels, of ``model`` on full validation frames."""
    import torch

    from mono_map.depth.heads import decode
    from mono_map.eval.sparsification import sparsification

    was = model.training
    model.eval()
    gts, ds, es, sky_ok, sky_n = [], [], [], 0, 0
    with torch.inference_mode():
        for img, dep in frames:
            H, W = img.shape[:2]
            Hp, Wp = -(-H // 32) * 32, -(-W // 32) * 32
            x = np.pad(img, ((0, Hp - H), (0, Wp - W), (0, 0)), mode="edge")
            x = torch.from_numpy(x).permute(2, 0, 1)[None].float() / 255.0
            r = decode(head, model(x)[..., :H, :W], bins, "log", beyond=beyond)
            d, e, pb = r["depth"][0].numpy(), r["entropy"][0].numpy(), r["p_beyond"][0].numpy()
            m = (dep > 0) & np.isfinite(dep) & (dep <= bins.max_depth)
            gts.append(dep[m]), ds.append(d[m]), es.append(e[m])
            sky = np.isinf(dep)
            sky_ok += int((pb[sky] > 0.5).sum())
            sky_n += int(sky.sum())
    model.train(was)
    gt, d, e = np.concatenate(gts), np.concatenate(ds), np.concatenate(es)
    ratio = np.maximum(d / gt, gt / d)
    sp = sparsification(gt, d, e)
    return {"abs_rel": float(np.mean(np.abs(d - gt) / gt)), "delta1": float(np.mean(ratio < 1.25)),
            "auc_are": float(sp["auc"]["are"]),
            "sky_beyond_acc": sky_ok / sky_n if sky_n else None, "frames": len(frames)}
