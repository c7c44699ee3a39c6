"""Recipes of synthetic sequences: ``sequences/NAME.toml`` → a frozen :class:`Recipe`.

A recipe fixes everything a sequence depends on: the real KITTI trajectory it drives
(``trajectory``, sub-sampled by ``pose_stride`` from ``first_pose``), the number of
frames, the random seed and the street layout.  Same recipe → byte-identical files.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

from mono_map.errors import MonoMapError
from mono_map.schema import bounded, check_fields


@dataclass(frozen=True)
class StreetParams:
    """Road cross-section (metres).  The car drives the centre of the right lane."""

    lane_width: float = field(default=3.5, metadata=bounded(lo=0, lo_open=True))
    parking_width: float = field(default=2.3, metadata=bounded(lo=0, lo_open=True))  # parking strip on each side of the two lanes
    sidewalk_width: float = field(default=3.0, metadata=bounded(lo=0, lo_open=True))
    curb_height: float = field(default=0.15, metadata=bounded(lo=0))


@dataclass(frozen=True)
class BuildingParams:
    density: float = field(default=0.85, metadata=bounded(lo=0, hi=1))  # probability that a frontage slot gets a building
    height_min: float = field(default=6.0, metadata=bounded(lo=0, lo_open=True))  # metres
    height_max: float = field(default=16.0, metadata=bounded(lo=0, lo_open=True))
    width_min: float = field(default=8.0, metadata=bounded(lo=0, lo_open=True))
    width_max: float = field(default=20.0, metadata=bounded(lo=0, lo_open=True))
    depth_min: float = field(default=8.0, metadata=bounded(lo=0, lo_open=True))
    depth_max: float = field(default=14.0, metadata=bounded(lo=0, lo_open=True))
    setback_max: float = field(default=3.0, metadata=bounded(lo=0))  # extra distance behind the sidewalk
    glass_fraction: float = field(default=0.6, metadata=bounded(lo=0, hi=1))  # fraction of windows that are reflective glass (others curtained)
    storefront_fraction: float = field(default=0.3, metadata=bounded(lo=0, hi=1))  # buildings with a glass shop front on the ground floor
    brick_fraction: float = field(default=0.4, metadata=bounded(lo=0, hi=1))  # brick facades (others plaster)


@dataclass(frozen=True)
class CarParams:
    density: float = field(default=0.6, metadata=bounded(lo=0, hi=1))  # fraction of the parking strips filled
    black_fraction: float = field(default=0.15, metadata=bounded(lo=0, hi=1))  # black-painted cars/vans the LiDAR barely returns (paper Fig. 3)
    van_fraction: float = field(default=0.12, metadata=bounded(lo=0, hi=1))  # box vans / small trucks among them
    detail: float = field(default=0.0, metadata=bounded(lo=0, hi=1))  # share of vehicles (parked and in the lanes) with painted details: lights, plates, stripes, lettering, grime (0 = flat paint, as before)


@dataclass(frozen=True)
class TrafficParams:
    """Vehicles standing in the driving lanes, and large vehicles (trucks, buses, tankers) among them.

    All zero (the default) = no lane traffic: a recipe without a ``[traffic]`` section builds the town it
    built before (the section is left out of :meth:`Recipe.content_hash` at its default).
    """

    adjacent_density: float = field(default=0.0, metadata=bounded(lo=0, hi=1))  # fraction of the adjacent (left) lane filled with standing vehicles, beside and ahead of the camera
    ahead_spacing: float = field(default=0.0, metadata=bounded(lo=0))  # metres between vehicles standing in the camera's own lane (0 = none); frames whose camera would be inside or < 3 m behind one are not rendered (training towns only)
    large_fraction: float = field(default=0.0, metadata=bounded(lo=0, hi=1))  # share of large vehicles (box trucks, buses, tankers, semi-trailers; L 7-13 m, H 3-4 m) among the lane vehicles
    van_fraction: float = field(default=0.2, metadata=bounded(lo=0, hi=1))  # share of vans among the other lane vehicles (the rest are cars)
    kerb_large_density: float = field(default=0.0, metadata=bounded(lo=0, hi=1))  # probability that a kerb slot (both sides) left free by the parked cars gets a parked large vehicle

    def enabled(self) -> bool:
        return self.adjacent_density > 0 or self.ahead_spacing > 0 or self.kerb_large_density > 0


@dataclass(frozen=True)
class TreeParams:
    spacing: float = field(default=14.0, metadata=bounded(lo=0, lo_open=True))  # metres between tree slots along each sidewalk
    density: float = field(default=0.6, metadata=bounded(lo=0, hi=1))  # probability a slot gets a tree
    canopy: float = field(default=0.0, metadata=bounded(lo=0, hi=1))  # probability a slot gets a large canopy tree too, its crown (radius 3-5.5 m, bottom >= 4.5 m up) over the road (0 = none, as before)


@dataclass(frozen=True)
class PropParams:
    pole_spacing: float = field(default=30.0, metadata=bounded(lo=0, lo_open=True))  # street-light poles, metres along each side
    fence_fraction: float = field(default=0.5, metadata=bounded(lo=0, hi=1))  # probability a free frontage stretch gets a fence
    hedge_fraction: float = field(default=0.0, metadata=bounded(lo=0, hi=1))  # probability a frontage stretch still free gets a hedge (0 = none, as before)


@dataclass(frozen=True)
class LightParams:
    sun_azimuth_deg: float = field(default=40.0, metadata=bounded(lo=-360, hi=360))  # in the world x-z plane, from +z towards +x
    sun_elevation_deg: float = field(default=35.0, metadata=bounded(lo=-360, hi=360))
    haze_distance: float = field(default=220.0, metadata=bounded(lo=0, lo_open=True))  # metres; transmittance exp(-d / haze_distance)
    exposure: float = field(default=1.0, metadata=bounded(lo=0, lo_open=True))


@dataclass(frozen=True)
class Recipe:
    """A synthetic sequence: trajectory + seed + layout.  ``frames`` is the full length."""

    name: str
    seed: int
    frames: int
    trajectory: str                   # real KITTI odometry trajectory (mono_map/data/kitti_assets/poses/XX.txt.gz)
    pose_stride: int = 1              # frame i uses pose first_pose + i * pose_stride
    first_pose: int = 0
    description: str = ""
    street: StreetParams = field(default_factory=StreetParams)
    buildings: BuildingParams = field(default_factory=BuildingParams)
    cars: CarParams = field(default_factory=CarParams)
    trees: TreeParams = field(default_factory=TreeParams)
    props: PropParams = field(default_factory=PropParams)
    light: LightParams = field(default_factory=LightParams)
    traffic: TrafficParams = field(default_factory=TrafficParams)
    path: str = ""                    # where it was loaded from (not part of the hash)

    def content_hash(self) -> str:
        """sha256 (hex, 16 chars) of everything that changes the generated files."""
        d = dataclasses.asdict(self)
        d.pop("path")
        d.pop("description")
        if self.traffic == TrafficParams():
            d.pop("traffic")          # the towns before lane traffic existed keep their hash
        elif self.traffic.kerb_large_density == 0:
            d["traffic"].pop("kerb_large_density")    # added after the first towns with traffic: theirs too
        if self.cars.detail == 0:
            d["cars"].pop("detail")                   # added later: the towns before it keep their hash
        if self.trees.canopy == 0:
            d["trees"].pop("canopy")                  # added later (issue 31's greenery): the towns before keep theirs
        if self.props.hedge_fraction == 0:
            d["props"].pop("hedge_fraction")
        return hashlib.sha256(json.dumps(d, sort_keys=True).encode()).hexdigest()[:16]


_SECTIONS = {"street": StreetParams, "buildings": BuildingParams, "cars": CarParams,
             "trees": TreeParams, "props": PropParams, "light": LightParams,
             "traffic": TrafficParams}


def recipe_path(name_or_path: str | os.PathLike) -> Path:
    """``"00"`` → ``recipes_dir()/00.toml``; a path to a ``.toml`` file is returned as is."""
    from mono_map.paths import recipes_dir

    s = str(name_or_path)
    if s.endswith(".toml") or os.sep in s:
        return Path(s)
    return recipes_dir() / f"{s}.toml"


def load_recipe(name_or_path: str | os.PathLike) -> Recipe:
    """Load and validate a recipe by name (``sequences/NAME.toml``) or path."""
    path = recipe_path(name_or_path)
    if not path.is_file():
        raise MonoMapError(f"{path}: no such recipe")
    try:
        data = tomllib.loads(path.read_text())
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise MonoMapError(f"{path}: not valid TOML ({exc})") from None
    return recipe_from_dict(data, path)


def recipe_from_dict(data: dict, path: Path | str = "<recipe>") -> Recipe:
    kwargs: dict = {}
    top = {f.name: f for f in dataclasses.fields(Recipe)}
    for key, value in data.items():
        if key in _SECTIONS:
            if not isinstance(value, dict):
                raise MonoMapError(f"{path}: [{key}] must be a table")
            kwargs[key] = _section(_SECTIONS[key], value, path, key)
        elif key in top and key != "path":
            kwargs[key] = value
        else:
            raise MonoMapError(f"{path}: unknown key '{key}'")
    kwargs.setdefault("name", Path(path).stem)
    for req in ("seed", "frames", "trajectory"):
        if req not in kwargs:
            raise MonoMapError(f"{path}: missing key '{req}'")
    for key in ("seed", "frames", "pose_stride", "first_pose"):
        if key in kwargs and (not isinstance(kwargs[key], int) or isinstance(kwargs[key], bool)):
            raise MonoMapError(f"{path}: '{key}' must be an integer")
    kwargs["trajectory"] = str(kwargs["trajectory"])
    kwargs["name"] = str(kwargs["name"])
    recipe = Recipe(path=str(path), **kwargs)
    _validate(recipe, path)
    return recipe


def _section(cls, values: dict, path, section: str):
    """A [section] checked against its dataclass's declared fields (:mod:`mono_map.schema`)."""
    return cls(**check_fields(cls, values, f"{path} [{section}]"))


def _validate(r: Recipe, path) -> None:
    from mono_map.data.synth.trajectory import available_trajectories, trajectory_length

    if r.trajectory not in available_trajectories():
        raise MonoMapError(f"{path}: trajectory '{r.trajectory}' is not one of {sorted(available_trajectories())}")
    if r.frames < 1 or r.pose_stride < 1 or r.first_pose < 0:
        raise MonoMapError(f"{path}: frames and pose_stride must be >= 1 and first_pose >= 0")
    last = r.first_pose + (r.frames - 1) * r.pose_stride
    n = trajectory_length(r.trajectory)
    if last >= n:
        raise MonoMapError(f"{path}: frame {r.frames - 1} needs pose {last} but trajectory {r.trajectory} has {n} poses")
    for name in ("density", "black_fraction", "van_fraction", "glass_fraction", "storefront_fraction",
                 "brick_fraction", "fence_fraction", "hedge_fraction", "canopy"):
        for sec in (r.buildings, r.cars, r.trees, r.props):
            v = getattr(sec, name, None)
            if v is not None and not 0.0 <= v <= 1.0:
                raise MonoMapError(f"{path}: {name} must be in [0, 1], got {v}")
    if 0 < r.traffic.ahead_spacing < 20.0:
        raise MonoMapError(f"{path}: [traffic] ahead_spacing must be 0 (none) or >= 20 m, got {r.traffic.ahead_spacing}")
    if r.buildings.height_min > r.buildings.height_max or r.buildings.width_min > r.buildings.width_max:
        raise MonoMapError(f"{path}: [buildings] min must not exceed max")
