"""Several maps of the same frames in one pass: :func:`run_builders` steps any number of
:class:`~mono_map.mapping.build.MapBuilder` through the frames together, each frame's image read and each
predictor run once for all of them (:class:`~mono_map.mapping.inputs.FrameInputs`, prepared one frame ahead
in a second thread); keep maps seeing the same pixels share one selection and ray cast per frame
(:func:`share_ray_casts`). :func:`build_map` (one map) and :func:`build_maps` (several) wrap it.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from typing import Callable, Iterable, Sequence

from mono_map.errors import MonoMapError
from mono_map.mapping.build import BuildResult, MapBuilder, make_builder
from mono_map.mapping.inputs import FrameInputs, load_predictor, prepare_inputs, probs_steps
from mono_map.mapping.nested import KeepGroup


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
    first map's includes the group's one selection and ray cast); a map's work that needs no map (the
    multi-view posterior of a fused map, ``MapBuilder.prepare``) runs ahead with the prediction. The maps are
    the same as frame by frame. Observers are closed at the end, also on error. Take each map with
    ``builder.result(frames)`` afterwards (one octree in memory at a time)."""
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

    def ahead_of(i: int) -> FrameInputs:       # the frame's predictions and every map's work that needs no map
        inputs = prepare_inputs(seq, i, steps, predictors)
        for b in builders:
            b.prepare(i, inputs)
        return inputs
    try:
        ahead = pool.submit(ahead_of, frames[0]) if pool and frames else None
        for n, i in enumerate(iterator):
            if pool is None:
                inputs = FrameInputs(seq, i, steps)
            else:
                inputs = ahead.result()
                if n + 1 < len(frames):
                    ahead = pool.submit(ahead_of, frames[n + 1])
            for b in builders:
                b.step(i, inputs)
    finally:
        if pool is not None:
            pool.shutdown(wait=True, cancel_futures=True)
        for b in builders:
            _close(b.observers)


def build_map(seq, job, *, predictor=None, observers: Sequence[Callable] = (), show_progress: bool = True,
              **options) -> BuildResult:
    """Integrate the frames of ``job`` (a :class:`~mono_map.mapping.jobs.MapJob`, e.g.
    ``MapJob.spec("mono", range(6), keep=0.8)``; no frames: all of ``seq``'s) into a new OctoMap.

    The job's source: "mono" (the depth predictor, the ``keep`` lowest-entropy fraction of valid pixels),
    "depth-gt" (ground-truth depth_2, every pixel in the bin range), "lidar" or "lidar-fov" (keep and the
    predictor are ignored); its integration (mono only): "keep" (the paper: kept pixels' expected depths as
    end points), "distribution" (every valid pixel's distribution, keep ignored) or "fused" (the
    distribution's free space + the surface fused across views: :mod:`mono_map.mapping.fused`).
    predictor, observers (callables ``obs(FrameUpdate)``, closed with ``close()`` at the end, also on error)
    and ``options`` (depth_range, stats_every, method, rank) as :func:`~mono_map.mapping.build.make_builder`'s.
    Raises MonoMapError on bad input; nothing is written here.
    """
    return build_maps(seq, [dict(job=job, predictor=predictor, observers=observers, **options)],
                      show_progress=show_progress)[0]


def make_builders(seq, maps: Sequence[dict]) -> list[MapBuilder]:
    """Checked builders of the maps ``maps`` (each :func:`~mono_map.mapping.build.make_builder`'s keyword
    arguments: ``job``, ``predictor``, ``observers``, options); mono maps that name the same model (None:
    the shipped one) and pass no predictor share one loaded predictor, so :func:`run_builders` predicts each
    frame once."""
    loaded: dict[tuple, object] = {}
    builders = []
    for kw in maps:
        kw = dict(kw)
        job = kw.pop("job")
        if job.kind.predicted and kw.get("predictor") is None:
            if (job.model, job.flip) not in loaded:
                loaded[job.model, job.flip] = load_predictor(job.model, flip=job.flip)
            kw["predictor"] = loaded[job.model, job.flip]
        builders.append(make_builder(seq, job, **kw))
    return builders


def build_maps(seq, maps: Sequence[dict], *, show_progress: bool = True) -> list[BuildResult]:
    """Build several maps of the same frames in one pass (:func:`make_builders`, :func:`run_builders`): a
    keep sweep costs one prediction pass. ``maps``: :func:`make_builders`'s; a job without frames is built
    over all of ``seq``'s. Every map is checked before any frame is read; nothing is written here."""
    import dataclasses

    maps = [dict(m, job=dataclasses.replace(m["job"], frames=tuple(range(len(seq)))))
            if not m["job"].frames else m for m in maps]
    frames = list(maps[0]["job"].frames) if maps else []
    if not frames:
        raise MonoMapError("--frames: no frames selected")
    if any(list(m["job"].frames) != frames for m in maps):
        raise ValueError("build_maps: the maps of one pass must share their frames")
    builders = make_builders(seq, maps)
    run_builders(seq, builders, frames, show_progress)
    return [b.result(frames) for b in builders]
