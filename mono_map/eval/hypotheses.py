"""Oracle multi-hypothesis evaluation (paper Sec. IV-B, Fig. 6 / Table III).

Each pixel gets M depth hypotheses (the M most probable modes of its distribution); an oracle
keeps, per pixel, the hypothesis with the smallest absolute relative error |d - gt| / gt, and the standard metrics are computed on the kept depths.
"""

from __future__ import annotations

import numpy as np

from mono_map.eval.depth_metrics import depth_errors


def oracle_select(gt: np.ndarray, hypotheses: np.ndarray) -> np.ndarray:
    """gt (N,) metres, hypotheses (M, N) metres -> (N,) the per-pixel best hypothesis."""
    h = np.asarray(hypotheses, np.float64)
    best = np.abs(h - np.asarray(gt, np.float64)[None]).argmin(0)
    return np.take_along_axis(h, best[None], 0)[0]


def oracle_errors(gt: np.ndarray, hypotheses: np.ndarray, ms=(1, 3, 5)) -> dict[int, dict[str, float]]:
    """Metrics of the oracle choice among the first M hypotheses, for each M in ``ms``."""
    return {m: depth_errors(gt, oracle_select(gt, hypotheses[:m])) for m in ms}
