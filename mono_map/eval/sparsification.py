"""Sparsification curves of depth uncertainty (paper Fig. 4-5, Table II).

Pixels (pooled over the test set) are sorted by predicted uncertainty, most confident first; the
curve gives an error metric on the x most confident fraction, x in (0, 1]. The oracle sorts by the
true per-pixel error of that metric; a random order gives a flat curve at the overall value.
AUC = area under the curve over x in [0, 1] (trapezoid); lower is better.
"""

from __future__ import annotations

import numpy as np

CURVE_METRICS = ("are", "rmse", "1-d1")


def pixel_errors(gt: np.ndarray, pred: np.ndarray) -> dict[str, np.ndarray]:
    """Per-pixel error terms: absolute relative error, squared error (m²), δ1 failure (0/1)."""
    gt = np.asarray(gt, np.float64)
    pred = np.asarray(pred, np.float64)
    return {"are": np.abs(pred - gt) / gt, "sq": (pred - gt) ** 2,
            "bad": (np.maximum(gt / pred, pred / gt) >= 1.25).astype(np.float64),
            "logratio": np.abs(np.log(pred / gt))}


def fractions(n: int = 100) -> np.ndarray:
    return np.arange(1, n + 1) / n


def _curve_from_order(errs: dict[str, np.ndarray], order: np.ndarray, fr: np.ndarray) -> dict[str, np.ndarray]:
    n = order.size
    counts = np.maximum(1, np.round(fr * n).astype(np.int64))
    out = {}
    for name, key in (("are", "are"), ("rmse", "sq"), ("1-d1", "bad")):
        c = np.cumsum(errs[key][order])
        mean = c[counts - 1] / counts
        out[name] = np.sqrt(mean) if name == "rmse" else mean
    return out


def sparsification(gt: np.ndarray, pred: np.ndarray, uncertainty: np.ndarray, n_points: int = 100,
                   seed: int = 0) -> dict:
    """Curves (model, oracle) for ARE, RMSE, 1-δ1 and their AUCs, from pooled 1-D pixel arrays.

    Ties in uncertainty (e.g. regression heads without uncertainty) are broken at random.
    """
    gt, pred, unc = (np.asarray(a, np.float64).ravel() for a in (gt, pred, uncertainty))
    if not (gt.size == pred.size == unc.size) or gt.size == 0:
        raise ValueError("sparsification: need equally sized, non-empty arrays")
    errs = pixel_errors(gt, pred)
    fr = fractions(n_points)
    tie = np.random.default_rng(seed).random(gt.size)
    model = _curve_from_order(errs, np.lexsort((tie, unc)), fr)
    oracle = {}
    for name, key in (("are", "are"), ("rmse", "sq"), ("1-d1", "logratio")):
        oracle[name] = _curve_from_order(errs, np.lexsort((tie, errs[key])), fr)[name]
    random = _curve_from_order(errs, np.argsort(tie), fr)
    return {
        "fractions": fr,
        "model": model, "oracle": oracle, "random": random,
        "auc": {k: auc(fr, v) for k, v in model.items()},
        "auc_oracle": {k: auc(fr, v) for k, v in oracle.items()},
        "auc_random": {k: auc(fr, v) for k, v in random.items()},
    }


def auc(fr: np.ndarray, values: np.ndarray) -> float:
    """Area under a curve sampled at fractions fr (extended flat to x = 0)."""
    x = np.concatenate([[0.0], fr])
    y = np.concatenate([[values[0]], values])
    return float(np.sum((x[1:] - x[:-1]) * (y[1:] + y[:-1]) / 2))
