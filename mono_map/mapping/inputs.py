"""One frame's shared inputs to the maps of a pass: image_2 read and every predictor run once.

:class:`FrameInputs` holds a frame's image and predictions for every map built from it;
:func:`prepare_inputs` fills one ahead of time (the next frame is predicted in a second thread while the
maps integrate this one, :func:`mono_map.mapping.pipeline.run_builders`); :func:`load_predictor` loads
the predictor a mono map is built with.
"""

from __future__ import annotations

import math
from typing import Callable, Mapping, Sequence

import numpy as np

from mono_map.depth.bins import DepthBins


def load_predictor(model: str | None = None, flip: bool = False):
    """The predictor a mono map is built with: ``"oracle"`` → the noisy ground-truth stand-in, else
    ``DepthPredictor.load(model, fast=True, precision=default_precision())`` (None → shipped binary
    checkpoint; ``flip``: each image predicted mirrored too). The fast path computes the per-pixel statistics at the decoder's stride 4 and
    up-samples them (~4x less CPU; eval-depth measures no accuracy loss, see docs/model.md); bf16 on
    CPUs with AMX (~2x faster network)."""
    if model == "oracle":
        from mono_map.mapping.oracle import NoisyGroundTruthPredictor

        return NoisyGroundTruthPredictor()
    from mono_map.depth.inference import DepthPredictor, default_precision

    return DepthPredictor.load(model, fast=True, precision=default_precision(), flip=flip)


def run_predictor(predictor, seq, i: int, image: np.ndarray, with_probs: bool = False, probs_step: int = 1):
    """Predictors with ``predict_frame(seq, i, image)`` (e.g. the ground-truth oracle) get the frame;
    others the image (``DepthPredictor.predict``). with_probs: also the bin probabilities, at every
    ``probs_step``-th pixel row and column (K×H×W for step 1)."""
    kw = {"with_probs": True, "probs_step": probs_step} if with_probs else {}
    if hasattr(predictor, "predict_frame"):
        return predictor.predict_frame(seq, i, image, **kw)
    return predictor.predict(image, **kw)


def bins_of(predictor) -> DepthBins:
    """The DepthBins of a predictor (DepthBins' defaults if it has none)."""
    b = getattr(predictor, "bins", None) or DepthBins()
    return DepthBins(b.num_bins, b.min_depth, b.max_depth)


def bin_edges(predictor) -> np.ndarray:
    """(K+1,) depth-bin edges (metres) of a predictor (DepthBins' defaults if it has none)."""
    return bins_of(predictor).edges


class FrameInputs:
    """One frame's image_2 and predictions, read and predicted once for every map built from the frame
    (the keep sweep of ``eval --table`` and the demo's two monocular maps share one prediction pass).
    ``probs_steps``: predictor id → the pixel step at which some map needs its bin probabilities
    (distribution mode: the rays' ``ray_step``)."""

    def __init__(self, seq, i: int, probs_steps: Mapping[int, int] | None = None):
        self.seq, self.i, self.probs_steps = seq, i, dict(probs_steps or {})
        self._image: np.ndarray | None = None
        self._predictions: dict[int, object] = {}
        self._shared: dict[tuple, object] = {}

    def shared(self, key: tuple, make: Callable[[], object]):
        """``make()`` the first time ``key`` is asked for in this frame, the same object afterwards (work
        that several maps of the frame share, e.g. a :class:`~mono_map.mapping.nested.NestedFrame`)."""
        if key not in self._shared:
            self._shared[key] = make()
        return self._shared[key]

    def image(self) -> np.ndarray:
        """H×W×3 uint8 RGB image_2 of the frame."""
        if self._image is None:
            self._image = self.seq.image(self.i)
        return self._image

    def prediction(self, predictor):
        """``predictor``'s DepthPrediction of the frame (computed on the first call)."""
        key = id(predictor)
        if key not in self._predictions:
            self._predictions[key] = run_predictor(predictor, self.seq, self.i, self.image(),
                                                   with_probs=key in self.probs_steps,
                                                   probs_step=self.probs_steps.get(key, 1))
        return self._predictions[key]


def probs_steps(builders: Sequence) -> dict[int, int]:
    """Predictor id → the pixel step at which the distribution-mode builders need its bin probabilities
    (the greatest common divisor of their ray steps, so one prediction serves them all); a mono map with the
    multi-view posterior needs them too (at its ray step)."""
    steps: dict[int, int] = {}
    for b in builders:
        if b.dist_mode or getattr(b, "multiview", None) is not None:
            k = id(b.predictor)
            steps[k] = math.gcd(steps.get(k, 0), int(b.dcfg.ray_step))
    return steps


def prepare_inputs(seq, i: int, steps: Mapping[int, int], predictors: Sequence) -> FrameInputs:
    """Frame ``i``'s shared work: image_2 read and every predictor run once (:class:`FrameInputs`)."""
    inputs = FrameInputs(seq, i, steps)
    for p in predictors:
        inputs.prediction(p)
    return inputs

