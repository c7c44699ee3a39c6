"""Build map jobs and publish their files: :func:`build_and_write` builds a map and publishes its ``.bt``,
``.json`` (and ``.ot``, ``.rrd``) together or not at all; :func:`build_and_write_all` does so for several
maps of the same frames in one pass (one prediction per frame for all of them)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from mono_map.mapping.jobs import MapJob

# rerun's file sink blocks for good on a full disk: a recording stops while this much is still free
RRD_MIN_FREE = 32 << 20


class DiskSpaceGuard:
    """Observer that stops a build before the disk under ``path`` fills (MonoMapError naming it)."""

    def __init__(self, path: Path, min_free: int = RRD_MIN_FREE):
        self.path, self.min_free = Path(path), min_free

    def __call__(self, update) -> None:
        from mono_map.errors import MonoMapError
        from mono_map.io import free_bytes

        free = free_bytes(self.path.parent)
        if free < self.min_free:
            raise MonoMapError(f"{self.path}: the disk is nearly full ({free / 2**20:.1f} MB left) at frame "
                               f"{update.index}; nothing was written")


@dataclass
class MapRequest:
    """One map of a build pass and where it goes: the job, its file stem (default :meth:`MapJob.stem`),
    extra observers, a rerun recording ``rrd`` made by ``logger(temporary rrd path)``, and ``write_ot``
    (also the probabilistic ``.ot`` that calibration needs — .bt keeps max-likelihood states only)."""

    job: MapJob
    name: str | None = None
    observers: tuple = ()
    rrd: Path | None = None
    logger: object = None
    write_ot: bool = False


def build_and_write(job: MapJob, seq, out_dir: Path, name: str | None = None, observers=(),
                    show_progress: bool = True, predictor=None, rrd: Path | None = None, logger=None,
                    write_ot: bool = False) -> tuple[Path, dict]:
    """Build ``job``'s map from the open sequence ``seq`` and publish ``<name>.bt``, ``<name>.json`` (and
    ``.ot``, ``rrd``) together (see :class:`MapRequest` and :func:`build_and_write_all`); (bt path, stats)."""
    return build_and_write_all([MapRequest(job, name, tuple(observers), rrd, logger, write_ot)], seq, out_dir,
                               predictor=predictor, show_progress=show_progress)[0]


def build_and_write_all(requests: list[MapRequest], seq, out_dir: Path, predictor=None,
                        show_progress: bool = True) -> list[tuple[Path, dict]]:
    """Build every requested map of the same frames in one pass over ``seq`` (each frame read and
    predicted once: :func:`mono_map.mapping.pipeline.build_maps`) and publish all maps' files together;
    if any build or any rename fails, nothing is published. predictor: None loads each mono job's model (once per
    model). Returns (bt path, stats) per request."""
    from mono_map.errors import MonoMapError
    from mono_map.io import atomic_outputs
    from mono_map.mapping.pipeline import make_builders, run_builders

    frames = list(requests[0].job.frames)
    if any(list(r.job.frames) != frames for r in requests):
        raise ValueError("build_and_write_all: the maps of one pass must share their frames")
    per_map = []
    for r in requests:
        bt = Path(out_dir) / f"{r.name or r.job.stem()}.bt"
        extra = ([bt.with_suffix(".ot")] if r.write_ot else []) + ([Path(r.rrd)] if r.rrd is not None else [])
        per_map.append((bt, [bt] + extra + [bt.with_suffix(".json")]))
    # one publication for every map's files: all of them or (a build or a rename failing) none
    with atomic_outputs(*[t for _, targets in per_map for t in targets]) as all_temps:
        maps, outputs, temps = [], [], iter(all_temps)
        for r, (bt, targets) in zip(requests, per_map):
            temp_of = {t: next(temps) for t in targets}
            observers = list(r.observers)
            if r.rrd is not None:
                observers = [DiskSpaceGuard(Path(r.rrd))] + observers + [r.logger(temp_of[Path(r.rrd)])]
            maps.append(dict(job=r.job, predictor=predictor if r.job.mono else None, observers=observers))
            outputs.append((bt, temp_of))
        builders = make_builders(seq, maps)
        try:
            run_builders(seq, builders, frames, show_progress)
        except RuntimeError as exc:  # rerun's flush timing out: its sink could not write the recording
            rrds = [str(r.rrd) for r in requests if r.rrd is not None]
            if not rrds:
                raise
            raise MonoMapError(f"{', '.join(rrds)}: rerun could not write the recording ({exc})") from None
        written = []
        for r, (bt, temp_of) in zip(requests, outputs):
            builder = builders.pop(0)     # dropped once written (it holds its tree): one octree in memory at a time
            written.append((bt, publish_map(r.job, builder.result(frames), bt, temp_of, r.write_ot)))
            del builder
    return written


def publish_map(job: MapJob, result, bt: Path, temp_of: dict, write_ot: bool) -> dict:
    """Write a built map's ``.ot`` (``write_ot``), ``.bt`` and ``.json`` to their temporary paths
    (``temp_of[target]``, published by the caller); returns the stats stored in the ``.json``."""
    from mono_map.io import quiet_native_output, write_json_atomic
    from mono_map.mapping.octree import write_tree_bt, write_tree_ot

    frames = list(job.frames)
    stats = dict(result.stats)
    stats["model"] = (job.model or "shipped binary checkpoint") if job.mono else None
    if frames != list(range(frames[0], frames[-1] + 1)):
        stats["frame_indices"] = frames
    if write_ot:  # before the .bt: writeBinary turns the tree max-likelihood in memory
        ot = bt.with_suffix(".ot")
        with _naming(ot), quiet_native_output():
            write_tree_ot(result.tree, temp_of[ot])
        stats["ot"] = str(ot)
    with _naming(bt), quiet_native_output():  # OctoMap's own warning on a full disk: reported below
        write_tree_bt(result.tree, temp_of[bt])
    stats["bt"] = str(bt)
    stats["bt_bytes"] = temp_of[bt].stat().st_size
    side = bt.with_suffix(".json")
    with _naming(side):
        write_json_atomic(temp_of[side], {"stats": stats, "job": job.key(), "job_hash": job.hash(),
                                          "per_frame": result.per_frame})
    return stats


def _naming(target: Path):
    """Errors while writing a temporary file are reported under the output's own name."""
    import contextlib

    from mono_map.errors import MonoMapError
    from mono_map.io import free_bytes

    @contextlib.contextmanager
    def ctx():
        try:
            yield
        except (OSError, MonoMapError) as exc:
            why = getattr(exc, "strerror", None) or "write failed"
            if free_bytes(target.parent) < (1 << 20):
                why = "No space left on device" if why == "write failed" else why
            raise MonoMapError(f"{target}: could not write it ({why}); nothing was published") from None
    return ctx()
