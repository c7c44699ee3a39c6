"""Which frames of a sequence serve a frame as photometric sources: chosen by the cameras' baseline, not by
frame offset (a stopped car gives no depth signal). Used by adaptation (:mod:`mono_map.depth.adapt`) and the
multi-view posterior (:mod:`mono_map.depth.multiview`)."""

from __future__ import annotations

import numpy as np


def choose_sources(positions: np.ndarray, min_baseline: float, max_baseline: float, max_offset: int,
                   per_side: int = 1) -> dict[int, list[int]]:
    """For every frame j (rows of ``positions``, camera centres in metres) the nearest frame before and the
    nearest after (within ``max_offset`` positions of the list) whose baseline lies in
    [min_baseline, max_baseline]; with ``per_side`` = n > 1 up to n per side, each at least twice the previous
    one's baseline (a wider baseline for far surfaces). In frame order; frames with no such neighbour are
    left out."""
    n = len(positions)
    out = {}
    for j in range(n):
        found = []
        for direction in (-1, 1):
            need, side = min_baseline, []
            for k in range(1, max_offset + 1):
                i = j + direction * k
                if not 0 <= i < n or len(side) == per_side:
                    break
                b = float(np.linalg.norm(positions[i] - positions[j]))
                if b > max_baseline:
                    break
                if b >= need:
                    side.append(i)
                    need = max(2 * b, min_baseline)
            found += side[::-1] if direction == -1 else side
        if found:
            out[j] = found
    return out
