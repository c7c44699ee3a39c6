"""A map job: everything that determines a map (:class:`MapJob`, the map's specification, made once at
the command line and passed whole down to :class:`~mono_map.mapping.build.MapBuilder`), its file name and
key, and whether a written map can be reused.

A :class:`MapJob` holds the data root, sequence and synthetic recipe marker, source, keep, integration,
OctoMap settings, frames, stride, the checkpoint's sha256 digest and the inference precision. Its
:meth:`MapJob.key` is stored in the map's ``.json`` and :func:`reusable` compares it before a written
map is reused; :meth:`MapJob.stem` is the file name, for people. :meth:`MapJob.of` makes the job of an
open sequence (its data identified), :meth:`MapJob.spec` a bare specification (library use, tests).
Building and publishing a job: :mod:`mono_map.mapping.publish`; its memory and reach checks:
:mod:`mono_map.mapping.limits`.
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
from mono_map.mapping.select import DEFAULT_KEEP
from mono_map.mapping.strategies import Integration, Source, integration_of, source_of


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
    build (:func:`mono_map.depth.inference.default_precision`); flip: each image predicted mirrored too
    (``--flip``)."""

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
    flip: bool = False

    @classmethod
    def of(cls, seq, source: str, frames, *, keep: float = 1.0, integrate: str = "keep",
           distribution: DistributionConfig | None = None, octomap: OctoMapConfig | None = None,
           stride: int = 1, model: str | None = None, digest: str | None = None,
           fused: FusedConfig | None = None, flip: bool = False) -> "MapJob":
        """The job of building ``frames`` of the open sequence ``seq`` (its root, name and synthetic
        marker are read from it); ``digest`` defaults to :func:`model_digest` of ``model`` (mono only)."""
        mono = source_of(source).predicted
        precision = None
        if mono and model != "oracle":
            from mono_map.depth.inference import default_precision

            precision = default_precision()
        if mono and not digest:
            from mono_map.depth.inference import model_digest

            digest = model_digest(model)
        return cls(sequence=getattr(seq, "name", None), data_root=str(Path(seq.root).resolve()),
                   source=source, frames=tuple(int(i) for i in frames), keep=float(keep), integrate=integrate,
                   distribution=distribution or DistributionConfig(), octomap=octomap or OctoMapConfig(),
                   stride=int(stride), model=model if mono else None,
                   digest=digest if mono else None, precision=precision,
                   synthetic=synthetic_marker(seq), data=data_fingerprint(seq, source, frames),
                   fused=fused or FusedConfig(), flip=bool(flip) and mono and model != "oracle")

    @classmethod
    def spec(cls, source: str = "mono", frames=(), *, keep: float = DEFAULT_KEEP, integrate: str = "keep",
             distribution: DistributionConfig | None = None, octomap: OctoMapConfig | None = None,
             stride: int = 1, model: str | None = None, fused: FusedConfig | None = None) -> "MapJob":
        """A map's settings without the data's identity (no sequence, digest or fingerprint: not for reuse),
        for building in the library and in tests: ``build_map(seq, MapJob.spec("mono", range(6), keep=0.8))``.
        ``model`` names the checkpoint a mono map's predictor is loaded from when none is given."""
        return cls(sequence=None, data_root=None, source=source, frames=tuple(int(i) for i in frames),
                   keep=float(keep), integrate=integrate, distribution=distribution or DistributionConfig(),
                   octomap=octomap or OctoMapConfig(), stride=int(stride),
                   model=model if source_of(source).predicted else None, fused=fused or FusedConfig())

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
            for name in ("stereo", "gate", "euclid"):   # off: the keys of fused maps made before the option existed
                if not getattr(self.fused, name):
                    integration["fused"].pop(name)
        return {"data_root": self.data_root, "sequence": self.sequence, "synthetic": dict(self.synthetic) or None,
                "data": dict(self.data) or None,
                "source": self.source, "keep": self.keep if self.mono and not self.distributional else None,
                "stride": self.stride if camera else None, "model": self.digest if self.mono else None,
                "frames": frames_tag(self.frames), "octomap": dataclasses.asdict(self.octomap),
                "integration": integration, "precision": self.precision,
                **({"flip": True} if self.flip else {})}    # the maps made before --flip keep their keys

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
        if self.flip:
            parts.append("flip")
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
