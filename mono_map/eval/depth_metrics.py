"""Standard single-image depth metrics (Eigen et al. 2014), KITTI conventions.

Ground truth and predictions are metres; pixels with gt <= 0 (no value) or gt > cap are ignored,
predictions are clipped to [min_depth, cap]. Per-image metrics are averaged over images.
"""

from __future__ import annotations

import numpy as np

METRICS = ("abs_rel", "sq_rel", "rmse", "rmse_log", "log10", "a1", "a2", "a3")
LABELS = {"abs_rel": "AbsRel", "sq_rel": "SqRel", "rmse": "RMSE", "rmse_log": "RMSE-log", "log10": "log10",
          "a1": "δ<1.25", "a2": "δ<1.25²", "a3": "δ<1.25³"}


def garg_crop_mask(h: int, w: int) -> np.ndarray:
    """Garg et al.'s evaluation crop (rows 40.8-99.2 %, columns 3.6-96.4 % of the image)."""
    m = np.zeros((h, w), bool)
    m[int(0.40810811 * h):int(0.99189189 * h), int(0.03594771 * w):int(0.96405229 * w)] = True
    return m


def valid_mask(gt: np.ndarray, cap: float = 80.0, min_depth: float = 1e-3, garg_crop: bool = False) -> np.ndarray:
    m = (gt > min_depth) & (gt <= cap)
    if garg_crop:
        m &= garg_crop_mask(*gt.shape[-2:])
    return m


def depth_errors(gt: np.ndarray, pred: np.ndarray) -> dict[str, float]:
    """Metrics over matching 1-D arrays of valid ground truth and predicted depths (metres)."""
    gt = np.asarray(gt, np.float64)
    pred = np.asarray(pred, np.float64)
    if gt.size == 0:
        return {k: float("nan") for k in METRICS}
    ratio = np.maximum(gt / pred, pred / gt)
    return {
        "abs_rel": float(np.mean(np.abs(gt - pred) / gt)),
        "sq_rel": float(np.mean((gt - pred) ** 2 / gt)),
        "rmse": float(np.sqrt(np.mean((gt - pred) ** 2))),
        "rmse_log": float(np.sqrt(np.mean((np.log(gt) - np.log(pred)) ** 2))),
        "log10": float(np.mean(np.abs(np.log10(gt) - np.log10(pred)))),
        "a1": float(np.mean(ratio < 1.25)),
        "a2": float(np.mean(ratio < 1.25 ** 2)),
        "a3": float(np.mean(ratio < 1.25 ** 3)),
    }


def image_errors(gt: np.ndarray, pred: np.ndarray, cap: float = 80.0, min_depth: float = 1e-3,
                 garg_crop: bool = False) -> dict[str, float]:
    """Metrics of one H×W prediction against H×W ground truth (0 = no value)."""
    m = valid_mask(gt, cap, min_depth, garg_crop)
    return depth_errors(gt[m], np.clip(pred[m], min_depth, cap))


def mean_errors(per_image: list[dict[str, float]]) -> dict[str, float]:
    """Average per-image metrics (images without valid pixels are skipped)."""
    rows = [r for r in per_image if np.isfinite(r["abs_rel"])]
    return {k: float(np.mean([r[k] for r in rows])) if rows else float("nan") for k in METRICS}


DISTANCE_BANDS = (0.0, 5.0, 10.0, 20.0, 40.0, 80.0)   # metres of ground truth


def distance_bands(gt: np.ndarray, pred: np.ndarray, edges=DISTANCE_BANDS) -> list[dict]:
    """The error's shape over distance: for each band [lo, hi) of ground-truth depth (the last band includes
    its upper edge) over matching 1-D arrays of valid pixels (metres, pooled over images), the band's share of
    the pixels, the median of pred / gt (below 1: predicted too near) and the AbsRel (None for an empty band)."""
    gt = np.asarray(gt, np.float64)
    pred = np.asarray(pred, np.float64)
    out = []
    for j, (lo, hi) in enumerate(zip(edges[:-1], edges[1:])):
        s = (gt >= lo) & ((gt <= hi) if j == len(edges) - 2 else (gt < hi))
        n = int(s.sum())
        out.append({"lo": float(lo), "hi": float(hi), "n_pixels": n, "share": n / gt.size if gt.size else 0.0,
                    "median_ratio": float(np.median(pred[s] / gt[s])) if n else None,
                    "abs_rel": float(np.mean(np.abs(pred[s] - gt[s]) / gt[s])) if n else None})
    return out
