"""A map job: everything that determines a map (:class:`MapJob`), its file name and key, and building +
publishing it.

A :class:`MapJob` holds the data root, sequence and synthetic recipe marker, source, keep, integration,
OctoMap settings, frames, stride, the checkpoint's sha256 digest and the inference precision. Its
:meth:`MapJob.key` is stored in the map's ``.json`` and :func:`reusable` compares it before a written
map is reused; :meth:`MapJob.stem` is the file name, for people. :func:`build_and_write` builds a map
and publishes its ``.bt``, ``.json`` (and ``.ot``, ``.rrd``) together or not at all;
:func:`build_and_write_all` does so for several maps of the same frames in one pass (one prediction per
frame for all of them); :func:`check_memory` refuses, before building, a job whose first frame would not
fit in memory.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path

from mono_map.config import OctoMapConfig
from mono_map.frames import frames_tag
from mono_map.mapping.distribution import DistributionConfig
from mono_map.mapping.fused import FusedConfig
from mono_map.mapping.strategies import Integration, Source, integration_of, source_of

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


def checkpoint_path(model: str | None) -> Path | None:
    """The checkpoint file ``--model`` names (None: the shipped binary model; a bare head name: its
    shipped checkpoint; 'oracle': none); MonoMapError if it does not exist."""
    from mono_map.depth.inference import default_checkpoint
    from mono_map.errors import MonoMapError

    if model == "oracle":
        return None
    if model is None:
        path = default_checkpoint("binary")
    elif not Path(model).suffix and not Path(model).exists():
        path = default_checkpoint(str(model))
    else:
        path = Path(model)
    if not path.is_file():
        raise MonoMapError(f"--model: {model}: checkpoint not found")
    return path


def model_digest(model: str | None) -> str:
    """What identifies the depth model: sha256 of its checkpoint file (first 16 hex), or 'oracle'."""
    path = checkpoint_path(model)
    if path is None:
        return "oracle"
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()[:16]


def synthetic_marker(seq) -> tuple[tuple[str, object], ...]:
    """What identifies a rendered synthetic sequence (recipe hash, generator version, frame count) from
    its ``synth.json``; () for real data."""
    if seq is None or not (seq.path / "synth.json").is_file():
        return ()
    try:
        info = json.loads((seq.path / "synth.json").read_text())
    except (ValueError, UnicodeDecodeError):
        return ()
    return tuple((k, info.get(k)) for k in ("recipe_hash", "generator_version", "n_frames"))


# the files each source reads besides poses, timestamps and calibration
SOURCE_FILES = {"mono": ("images",), "depth-gt": ("depth",), "lidar": ("scans",), "lidar-fov": ("scans",)}


def data_fingerprint(seq, source: str, frames) -> tuple[tuple[str, str], ...]:
    """What the frames a ``source`` map reads hold (:func:`mono_map.data.fingerprint.sequence_fingerprint`);
    () without an open sequence."""
    from mono_map.data.fingerprint import sequence_fingerprint

    if seq is None or not hasattr(seq, "image_files"):
        return ()
    parts = ("poses", "times", "calibration") + SOURCE_FILES.get(source, ("images", "scans", "depth"))
    return tuple(sorted(sequence_fingerprint(seq, frames, parts).items()))


@dataclass(frozen=True)
class MapJob:
    """Everything that determines a map. Settings a source ignores (keep for LiDAR, keep for a
    distribution map, stride for LiDAR, the model for non-mono sources) do not enter :meth:`key`.

    model: ``--model`` as given (None: the shipped checkpoint; names the file); digest: its
    checkpoint's sha256 (first 16 hex, or 'oracle'); precision: the inference precision of a mono
    build (:func:`mono_map.depth.inference.default_precision`)."""

    sequence: str | None
    data_root: str | None
    source: str
    frames: tuple[int, ...]
    keep: float = 1.0
    integrate: str = "keep"
    distribution: DistributionConfig = field(default_factory=DistributionConfig)
    octomap: OctoMapConfig = field(default_factory=OctoMapConfig)
    stride: int = 1
    model: str | None = None
    digest: str | None = None
    precision: str | None = None
    synthetic: tuple[tuple[str, object], ...] = ()
    data: tuple[tuple[str, str], ...] = ()   # what the frames hold (mono_map.data.fingerprint): part -> hash
    fused: FusedConfig = field(default_factory=FusedConfig)

    @classmethod
    def of(cls, seq, source: str, frames, *, keep: float = 1.0, integrate: str = "keep",
           distribution: DistributionConfig | None = None, octomap: OctoMapConfig | None = None,
           stride: int = 1, model: str | None = None, digest: str | None = None,
           fused: FusedConfig | None = None) -> "MapJob":
        """The job of building ``frames`` of the open sequence ``seq`` (its root, name and synthetic
        marker are read from it); ``digest`` defaults to :func:`model_digest` of ``model`` (mono only)."""
        mono = source_of(source).predicted
        precision = None
        if mono and model != "oracle":
            from mono_map.depth.inference import default_precision

            precision = default_precision()
        return cls(sequence=getattr(seq, "name", None), data_root=str(Path(seq.root).resolve()),
                   source=source, frames=tuple(int(i) for i in frames), keep=float(keep), integrate=integrate,
                   distribution=distribution or DistributionConfig(), octomap=octomap or OctoMapConfig(),
                   stride=int(stride), model=model if mono else None,
                   digest=(digest or model_digest(model)) if mono else None, precision=precision,
                   synthetic=synthetic_marker(seq), data=data_fingerprint(seq, source, frames),
                   fused=fused or FusedConfig())

    @property
    def kind(self) -> Source:
        """The source as a strategy (:mod:`mono_map.mapping.strategies`)."""
        return source_of(self.source)

    @property
    def integration(self) -> Integration:
        """The integration as this job's source uses it (end points unless a mono map's distributions)."""
        return integration_of(self.integrate, self.source)

    @property
    def mono(self) -> bool:
        return self.kind.predicted

    @property
    def distributional(self) -> bool:
        """A mono map integrating whole distributions (``--integrate distribution`` or ``fused``; keep ignored)."""
        return self.integration.distributional

    @property
    def is_fused(self) -> bool:
        """A mono map with ``--integrate fused`` (the distribution's free space + the fused surface)."""
        return self.integration.fused

    def key(self) -> dict:
        """Everything that determines the map, as JSON: stored in its .json, compared before reuse."""
        camera = self.kind.camera
        integration = {"method": "batched", "mode": self.integrate if self.mono else None,
                       "distribution": dataclasses.asdict(self.distribution) if self.distributional else None}
        if self.is_fused:                 # only fused maps carry the key: the other maps' keys stay as they were
            integration["fused"] = dataclasses.asdict(self.fused)
        return {"data_root": self.data_root, "sequence": self.sequence, "synthetic": dict(self.synthetic) or None,
                "data": dict(self.data) or None,
                "source": self.source, "keep": self.keep if self.mono and not self.distributional else None,
                "stride": self.stride if camera else None, "model": self.digest if self.mono else None,
                "frames": frames_tag(self.frames), "octomap": dataclasses.asdict(self.octomap),
                "integration": integration, "precision": self.precision}

    def hash(self) -> str:
        """sha256 (first 16 hex) of :meth:`key`: equal for two jobs iff they make the same map."""
        return hashlib.sha256(json.dumps(self.key(), sort_keys=True).encode()).hexdigest()[:16]

    def stem(self) -> str:
        """A file stem that encodes every setting changing the map (the .json's key decides reuse)."""
        if self.distributional:
            dd, dcfg = DistributionConfig(), self.distribution
            parts = [("mono-fused" if self.is_fused else "mono-dist") + (f"-eps{dcfg.eps:g}" if dcfg.eps != dd.eps else "")
                     + (f"-temp{dcfg.temperature:g}" if dcfg.temperature != dd.temperature else "")
                     + (f"-step{dcfg.ray_step}" if dcfg.ray_step != dd.ray_step else "")
                     + (f"-min{dcfg.min_update:g}" if dcfg.min_update != dd.min_update else "")
                     + (f"-spread{dcfg.bin_spread:g}" if dcfg.bin_spread != dd.bin_spread else "")
                     + (f"-q{dcfg.quantum:g}" if dcfg.quantum != dd.quantum else "")
                     + (("-snap" if dcfg.snap_free else "-nosnap") if dcfg.snap_free != dd.snap_free else "")]
            if self.is_fused and self.fused != FusedConfig():
                parts.append("fused-" + hashlib.sha256(json.dumps(dataclasses.asdict(self.fused), sort_keys=True)
                                                       .encode()).hexdigest()[:8])
        else:
            parts = [self.source if not self.mono else f"mono-keep{self.keep:g}"]
        if self.mono and self.model:
            parts.append("model-" + Path(str(self.model)).stem)
        if self.kind.camera and self.stride != 1:
            parts.append(f"stride{self.stride}")
        cfg, d = self.octomap, OctoMapConfig()
        parts.append(f"res{cfg.resolution:g}")
        if cfg.max_range != d.max_range:
            parts.append(f"maxrange{cfg.max_range:g}")
        for name in ("prob_hit", "prob_miss", "clamp_min", "clamp_max"):
            if getattr(cfg, name) != getattr(d, name):
                parts.append(f"{name.replace('_', '')}{getattr(cfg, name):g}")
        parts.append(frames_tag(self.frames))
        return "_".join(parts)

    def path(self, out_dir: Path) -> Path:
        """``<out_dir>/<stem>.bt``."""
        return Path(out_dir) / f"{self.stem()}.bt"


def read_map_sidecar(path: Path) -> dict | None:
    """The ``.json`` a build wrote beside ``<name>.bt``: {"stats", "job", ...}; None if absent;
    MonoMapError naming it if it is not one."""
    from mono_map.errors import MonoMapError

    side = Path(path).with_suffix(".json")
    if not side.is_file():
        return None
    try:
        data = json.loads(side.read_text())
    except (ValueError, UnicodeDecodeError, OSError) as exc:
        raise MonoMapError(f"{side}: unreadable map statistics ({exc.__class__.__name__}); "
                           "delete it or rebuild the map") from None
    if not isinstance(data, dict) or not isinstance(data.get("stats"), dict):
        raise MonoMapError(f"{side}: not a mono-map build's statistics (no 'stats' object); "
                           "delete it or rebuild the map")
    return data


def reusable(bt: Path, job: MapJob) -> tuple[bool, str]:
    """Whether ``bt`` (with its .json) was built by exactly ``job``; (False, why) otherwise."""
    from mono_map.errors import MonoMapError

    key = job.key()
    if not bt.is_file():
        return False, "not built yet"
    try:
        side = read_map_sidecar(bt)
    except MonoMapError as exc:
        return False, str(exc)
    if side is None:
        return False, f"{bt.with_suffix('.json').name} missing"
    if side.get("job") != key:
        from mono_map.data.fingerprint import describe_change

        stored = side.get("job") if isinstance(side.get("job"), dict) else {}
        diff = sorted(k for k in set(key) | set(stored) if key.get(k) != stored.get(k))
        if diff == ["data"]:  # the same settings, other frame contents: say what changed
            return False, describe_change(stored.get("data"), key["data"] or {})
        return False, f"built with other {', '.join(diff) or 'settings'}"
    if side["stats"].get("bt_bytes") not in (None, bt.stat().st_size):
        return False, f"{bt.name} does not match its .json"
    return True, ""


def memory_limit() -> tuple[float, str]:
    """Bytes a build may use, and where the figure comes from: ``$MONO_MAP_MEMORY_GB``, else the
    smaller of the available RAM (/proc/meminfo) and the address-space limit (ulimit -v)."""
    import resource

    from mono_map.schema import env_value

    gb = env_value("MONO_MAP_MEMORY_GB")  # checked: a positive, finite number of GB or refused naming it
    if gb is not None:
        return gb * 2**30, "$MONO_MAP_MEMORY_GB"
    limit, where = float("inf"), "no limit known"
    try:
        for line in open("/proc/meminfo"):
            if line.startswith("MemAvailable:"):
                limit, where = float(line.split()[1]) * 1024, "available RAM"
    except OSError:
        pass
    soft = resource.getrlimit(resource.RLIMIT_AS)[0]
    if soft != resource.RLIM_INFINITY and soft < limit:
        limit, where = float(soft), "ulimit -v"
    return limit, where


# Peak memory of one frame's integration, measured on tiny frame 0 (peak RSS above the start-up):
# LiDAR ≈ 90 B per ray-cell visit (0.05 m: 22 M visits, 1.9 GB); mono (shipped model, keep 0.8,
# 1241×376) ≈ 150 MB at 0.2 m, growing as (0.2 / res)^2.5 (0.1 m: 0.58 GB, 0.05 m: 3.3 GB).
BYTES_PER_VISIT = 90
MONO_BYTES_AT_02 = 150e6


def estimate_frame_bytes(seq, i: int, source: str, cfg, stride: int, keep: float) -> float:
    """Peak bytes to integrate frame ``i`` alone (see the constants above; an estimate, not a bound).
    Camera sources (mono, depth-gt) are estimated from their pixel count."""
    import numpy as np

    if source_of(source).camera:
        h, w = seq.image_size
        pixels = (-(-h // stride)) * (-(-w // stride)) * keep
        return MONO_BYTES_AT_02 * (0.2 / cfg.resolution) ** 2.5 * pixels / (376 * 1241 * 0.8)
    from mono_map.mapping.reference import lidar_measurement

    pts, origin = lidar_measurement(seq, i, source)
    lengths = np.linalg.norm(pts - origin, axis=1)
    if cfg.max_range > 0:
        lengths = np.minimum(lengths, cfg.max_range)
    return float(np.sum(lengths / cfg.resolution + 1)) * BYTES_PER_VISIT


def check_reach(seq, job: MapJob) -> None:
    """Refuse, before building, a job whose camera leaves the region an OctoMap of its resolution can
    address (16-bit keys: ±32767 cells around the world origin), naming the pose file and line."""
    import numpy as np

    from mono_map.errors import MonoMapError

    poses = getattr(seq, "poses_cam0", None)
    if poses is None:
        return
    frames = np.asarray(job.frames, dtype=np.int64)
    reach = 32767 * job.octomap.resolution
    far = np.abs(poses[frames, :3, 3]).max(axis=1)
    if far.max() >= reach:
        k = int(frames[int(far.argmax())])
        raise MonoMapError(f"{seq.pose_path}:{k + 1}: frame {k}'s pose is {far.max():.0f} m from the first camera, "
                           f"beyond what a {job.octomap.resolution:g} m OctoMap can address (±{reach:.0f} m); "
                           "is the pose right? (a coarser --res reaches further)")


def check_memory(seq, job: MapJob) -> None:
    """Refuse, before building, a job whose first frame alone would not fit in memory (a distribution
    build: one ray every ``ray_step``-th pixel of every valid one; depth-gt: every pixel)."""
    from mono_map.errors import MonoMapError

    keep, stride, cfg = job.keep, job.stride, job.octomap
    if job.kind.ground_truth:
        keep = 1.0
    elif job.distributional:
        keep, stride = 1.0, stride * job.distribution.ray_step
    need = estimate_frame_bytes(seq, job.frames[0], job.source, cfg, stride, keep)
    limit, where = memory_limit()
    if need > limit:
        raise MonoMapError(f"--res: {cfg.resolution:g} m cells: integrating frame {job.frames[0]} alone would need "
                           f"about {need / 2**30:.1f} GB, more than the {limit / 2**30:.1f} GB allowed ({where}); "
                           "use a coarser --res, a --max-range or a larger --stride")


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
            job = r.job
            maps.append(dict(source=job.source, keep=job.keep, octomap=job.octomap, stride=job.stride,
                             predictor=predictor if job.mono else None, model=job.model, observers=observers,
                             integrate=job.integrate, distribution=job.distribution, fused=job.fused))
            outputs.append((bt, temp_of))
        builders = make_builders(seq, maps, len(frames))
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
