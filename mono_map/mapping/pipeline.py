"""Several maps of the same frames in one pass: :func:`run_builders` steps any number of
:class:`~mono_map.mapping.build.MapBuilder` through the frames together, each frame's image read and each
predictor run once for all of them (:class:`~mono_map.mapping.inputs.FrameInputs`, prepared one frame ahead
in a second thread); keep maps seeing the same pixels share one selection and ray cast per frame
(:func:`share_ray_casts`). :func:`build_map` (one map) and :func:`build_maps` (several) wrap it.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from typing import Callable, Iterable, Sequence

from mono_map.config import OctoMapConfig
from mono_map.errors import MonoMapError
from mono_map.mapping.build import BuildResult, MapBuilder, make_builder
from mono_map.mapping.distribution import DistributionConfig
from mono_map.mapping.fused import FusedConfig
from mono_map.mapping.inputs import FrameInputs, load_predictor, prepare_inputs, probs_steps
from mono_map.mapping.nested import KeepGroup
from mono_map.mapping.select import DEFAULT_KEEP


def _close(observers: Iterable) -> None:
    for obs in observers:
        close = getattr(obs, "close", None)
        if callable(close):
            close()


def share_ray_casts(builders: Sequence[MapBuilder]) -> None:
    """Group the keep maps of one pass that see the same pixels (same predictor, ranking, stride, depth
    range and cell size; batched integration, unlimited range) so that each frame is selected and ray-cast
    once for all of them (:mod:`mono_map.mapping.nested`); a group needs two keeps or more. Maps outside a
    group step on their own, as before."""
    groups: dict[tuple, list[MapBuilder]] = {}
    for b in builders:
        b.group = None
        cfg = b.integrator.cfg
        if b.kind.predicted and not b.dist_mode and b.integrator.method == "batched" and cfg.max_range < 0:
            key = ("keep-group", id(b.predictor), b.rank, b.stride, tuple(b.depth_range), float(cfg.resolution))
            groups.setdefault(key, []).append(b)
    for key, members in groups.items():
        keeps = tuple(sorted({b.keep for b in members}))
        if len(keeps) > 1:
            for b in members:
                b.group = KeepGroup(keeps, key)


def run_builders(seq, builders: Sequence[MapBuilder], frames: Sequence[int], show_progress: bool = True) -> None:
    """Step every builder through ``frames`` in one pass: each frame's image is read and each predictor
    runs once, whatever the number of maps built from them. With a depth predictor that work runs one
    frame ahead in a second thread (the network releases the GIL, and so does the ray casting), so the
    next frame is predicted while the maps integrate this one; a builder's per-frame ``frame_s`` is its own
    work (selection, back-projection, integration; in a group of keep maps, :func:`share_ray_casts`, the
    first map's includes the group's one selection and ray cast). The maps are the same as frame by frame.
    Observers are closed at the end, also on error. Take each map with ``builder.result(frames)`` afterwards
    (one octree in memory at a time)."""
    steps = probs_steps(builders)
    share_ray_casts(builders)
    frames = list(frames)
    predictors = list({id(b.predictor): b.predictor for b in builders if b.kind.predicted}.values())
    iterator = frames
    if show_progress:
        from mono_map.progress import progress

        sources = sorted({b.source for b in builders})
        desc = f"build {'+'.join(sources)}" + (f" ×{len(builders)}" if len(builders) > 1 else "")
        iterator = progress(frames, total=len(frames), desc=desc, unit="frame")
    pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="mono-map-predict") if predictors else None
    try:
        ahead = pool.submit(prepare_inputs, seq, frames[0], steps, predictors) if pool and frames else None
        for n, i in enumerate(iterator):
            if pool is None:
                inputs = FrameInputs(seq, i, steps)
            else:
                inputs = ahead.result()
                if n + 1 < len(frames):
                    ahead = pool.submit(prepare_inputs, seq, frames[n + 1], steps, predictors)
            for b in builders:
                b.step(i, inputs)
    finally:
        if pool is not None:
            pool.shutdown(wait=True, cancel_futures=True)
        for b in builders:
            _close(b.observers)


def build_map(seq, source: str = "mono", keep: float = DEFAULT_KEEP, *, frames: Sequence[int] | None = None,
              octomap: OctoMapConfig | None = None, stride: int = 1, predictor=None,
              model: str | None = None, depth_range: tuple[float, float] | None = None,
              observers: Sequence[Callable] = (), stats_every: int = 100, method: str = "batched",
              show_progress: bool = True, integrate: str = "keep",
              distribution: DistributionConfig | None = None, rank: str = "entropy",
              fused: FusedConfig | None = None) -> BuildResult:
    """Integrate ``frames`` of ``seq`` into a new OctoMap.

    source: "mono" (depth predictor, ``keep`` lowest-entropy fraction of valid pixels), "depth-gt"
    (ground-truth depth_2, every pixel in the bin range), "lidar" or "lidar-fov" (``keep`` and the
    predictor are ignored). integrate (mono only): "keep" (the paper: kept pixels' expected depths
    as end points), "distribution" (every valid pixel's distribution, ``distribution`` settings;
    ``keep`` is ignored) or "fused" (the distribution's free space + the surface fused across views,
    ``fused`` settings: :mod:`mono_map.mapping.fused`). rank (keep maps): "entropy" (the paper's) or "metric" (entropy + log depth,
    :func:`mono_map.mapping.select.confidence_score`). predictor: anything with
    ``predict(image) -> DepthPrediction`` or ``predict_frame(seq, i, image)``; if None,
    ``load_predictor(model)`` (None → the shipped checkpoint). depth_range: valid predicted
    depths (metres), default the predictor's bin range (else DepthBins' 1–80 m).
    observers: callables ``obs(FrameUpdate)``, closed (``close()``) at the end, also on error.
    Leaf count / memory are measured every ``stats_every`` frames (a tree traversal) and carried
    in between. Raises MonoMapError on bad input; nothing is written here.
    """
    return build_maps(seq, [dict(source=source, keep=keep, octomap=octomap, stride=stride, predictor=predictor,
                                 model=model, depth_range=depth_range, observers=observers,
                                 stats_every=stats_every, method=method, integrate=integrate,
                                 distribution=distribution, rank=rank, fused=fused)],
                      frames=frames, show_progress=show_progress)[0]


def make_builders(seq, maps: Sequence[dict], n_frames: int) -> list[MapBuilder]:
    """Checked builders of the maps ``maps`` (each :func:`build_map`'s keyword arguments without
    ``frames``/``show_progress``); mono maps that name the same model (None: the shipped one) and pass
    no predictor share one loaded predictor, so :func:`run_builders` predicts each frame once."""
    loaded: dict[str | None, object] = {}
    builders = []
    for kw in maps:
        kw = dict(kw)
        if kw.get("source", "mono") == "mono" and kw.get("predictor") is None:
            model = kw.pop("model", None)
            if model not in loaded:
                loaded[model] = load_predictor(model)
            kw["predictor"] = loaded[model]
        builders.append(make_builder(seq, n_frames=n_frames, **kw))
    return builders


def build_maps(seq, maps: Sequence[dict], *, frames: Sequence[int] | None = None,
               show_progress: bool = True) -> list[BuildResult]:
    """Build several maps of the same ``frames`` in one pass (:func:`make_builders`, :func:`run_builders`):
    a keep sweep costs one prediction pass. Every map is checked before any frame is read; nothing is
    written here."""
    frames = list(range(len(seq))) if frames is None else list(frames)
    if not frames:
        raise MonoMapError("--frames: no frames selected")
    builders = make_builders(seq, maps, len(frames))
    run_builders(seq, builders, frames, show_progress)
    return [b.result(frames) for b in builders]

