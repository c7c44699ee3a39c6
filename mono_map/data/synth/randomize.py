"""Domain randomisation of training towns: layout, lighting, palettes and camera, from one seed.

A training town is a stretch of a real KITTI trajectory (never 00) with a randomised
:class:`~mono_map.data.synth.recipe.Recipe` (street, buildings, cars, trees, props, sun) and a
randomised :class:`Appearance` (sky and sun colours, overcast, haze, exposure, white balance,
material palette, blur, noise, JPEG artefacts). Everything is a pure function of
``(TownSpec.seed, frame index)``: the same spec renders the same frames, byte for byte.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace

import numpy as np

from mono_map.data.synth import materials as M
from mono_map.data.synth.recipe import (BuildingParams, CarParams, LightParams, PropParams, Recipe, StreetParams,
                                        TrafficParams, TreeParams)

N_MATERIALS = 12


@dataclass(frozen=True)
class TownSpec:
    """One training town: a stretch of a real trajectory (poses first_pose + i·pose_stride)."""

    name: str
    trajectory: str
    first_pose: int
    pose_stride: int
    frames: int                 # poses of the window; a town with traffic ahead renders those clear of it
    seed: int
    traffic: bool = False       # vehicles in the driving lanes and large vehicles (the "h" family, issue 31)
    kerb_trucks: bool = False   # with traffic: large vehicles parked at the kerbs too (the "k" family)
    vehicle_detail: bool = False  # vehicles with painted details: the twins of the t, h, k towns (p, d, v families)
    jam: bool = False           # with traffic: a traffic jam, lanes and kerbs full, large vehicles close (the "j" family)
    greenery: bool = False      # hedges along the frontages, canopy trees over the road: twins of p, d, v (q, g, e families)

    def to_dict(self) -> dict:
        """The spec as stored in the cache; ``traffic``/``kerb_trucks``/``vehicle_detail``/``jam``/``greenery`` only
        when set, so older towns keep their identity."""
        d = asdict(self)
        for key in ("traffic", "kerb_trucks", "vehicle_detail", "jam", "greenery"):
            if not d[key]:
                d.pop(key)
        return d


@dataclass(frozen=True)
class Appearance:
    """Per-town look (colours linear RGB in [0, 1]); per-frame jitter is drawn in :func:`frame_jitter`."""

    zenith: tuple
    horizon: tuple
    sun_color: tuple
    ambient: tuple
    albedo_gain: tuple          # (N_MATERIALS, 3) multipliers of each material's albedo
    hue_shift: float            # radians, rotation of object colours (facades, cars, fences) about grey
    saturation: float           # object colour saturation factor
    exposure: float
    white_balance: tuple        # (3,) gains
    blur_sigma: float           # pixels at training resolution
    noise: float                # extra sensor noise std (of 1)
    jpeg_quality: int           # 0 = no JPEG compression

    def to_dict(self) -> dict:
        return asdict(self)


def randomized_recipe(spec: TownSpec) -> Recipe:
    """A recipe with layout and sun drawn from broad ranges around the hand-made training towns."""
    r = np.random.default_rng([spec.seed, 101])
    u = lambda a, b: float(r.uniform(a, b))  # noqa: E731
    h_min = u(5.0, 14.0)
    w_min = u(7.0, 14.0)
    traffic = TrafficParams()
    if spec.jam:                             # real01's scene: the next lane full, large vehicles beside, one ahead
        j = np.random.default_rng([spec.seed, 133])
        traffic = TrafficParams(adjacent_density=float(j.uniform(0.85, 1.0)),
                                ahead_spacing=float(j.uniform(12.0, 25.0)),
                                large_fraction=float(j.uniform(0.5, 0.9)), van_fraction=float(j.uniform(0.2, 0.4)),
                                kerb_large_density=float(j.uniform(0.4, 0.9)))
    elif spec.traffic:                       # its own stream: the draws above and below are those of any town
        t = np.random.default_rng([spec.seed, 131])
        kerb = float(np.random.default_rng([spec.seed, 132]).uniform(0.3, 0.8)) if spec.kerb_trucks else 0.0
        traffic = TrafficParams(adjacent_density=float(t.uniform(0.3, 0.9)),
                                ahead_spacing=float(t.uniform(35.0, 90.0)),
                                large_fraction=float(t.uniform(0.3, 0.7)), van_fraction=float(t.uniform(0.1, 0.35)),
                                kerb_large_density=kerb)
    green = (0.0, 0.0)
    if spec.greenery:                        # its own stream too: a twin keeps every other draw of its town
        g = np.random.default_rng([spec.seed, 134])
        green = (float(g.uniform(0.3, 0.8)), float(g.uniform(0.3, 0.8)))
    return Recipe(
        name=spec.name, seed=spec.seed, frames=spec.frames, trajectory=spec.trajectory,
        pose_stride=spec.pose_stride, first_pose=spec.first_pose,
        description=f"randomised training town along KITTI {spec.trajectory}",
        street=StreetParams(lane_width=u(3.0, 4.0), parking_width=u(1.8, 2.8), sidewalk_width=u(2.0, 4.5),
                            curb_height=u(0.1, 0.2)),
        buildings=BuildingParams(density=u(0.5, 1.0), height_min=h_min, height_max=h_min + u(3.0, 18.0),
                                 width_min=w_min, width_max=w_min + u(4.0, 14.0), depth_min=8.0, depth_max=14.0,
                                 setback_max=u(0.0, 5.0), glass_fraction=u(0.2, 0.9),
                                 storefront_fraction=u(0.0, 0.7), brick_fraction=u(0.0, 0.8)),
        cars=CarParams(density=u(0.2, 0.95), black_fraction=u(0.05, 0.3), van_fraction=u(0.0, 0.25),
                       detail=DETAILED_SHARE if spec.vehicle_detail else 0.0),
        trees=TreeParams(spacing=u(8.0, 30.0), density=u(0.1, 0.9), canopy=green[0]),
        props=PropParams(pole_spacing=u(15.0, 45.0), fence_fraction=u(0.0, 0.7), hedge_fraction=green[1]),
        light=LightParams(sun_azimuth_deg=u(-180.0, 180.0), sun_elevation_deg=u(12.0, 70.0),
                          haze_distance=float(np.exp(r.uniform(np.log(70.0), np.log(600.0)))), exposure=1.0),
        traffic=traffic,
    )


def randomized_appearance(spec: TownSpec) -> Appearance:
    """Sky, sun, overcast, palette and camera of a town."""
    r = np.random.default_rng([spec.seed, 202])
    overcast = float(r.uniform(0.0, 1.0)) ** 2          # most towns sunny, some grey
    zen = np.array([0.30, 0.48, 0.78]) * r.uniform(0.7, 1.25, 3)
    hor = np.array([0.78, 0.82, 0.86]) * r.uniform(0.8, 1.15, 3)
    grey = np.array([0.62, 0.64, 0.67]) * r.uniform(0.8, 1.2)
    zen = (1 - overcast) * zen + overcast * grey
    hor = (1 - overcast) * hor + overcast * grey * 1.1
    warm = r.uniform(-0.12, 0.12)                        # sun colour temperature
    sun = np.array([1.0 + warm, 0.95, 0.86 - warm]) * 0.95 * r.uniform(0.8, 1.2) * (1 - 0.8 * overcast)
    amb = np.array([0.36, 0.40, 0.47]) * r.uniform(0.75, 1.3) * (1 + 0.9 * overcast)
    gain = np.exp(r.normal(0.0, 0.18, (N_MATERIALS, 3))) * np.exp(r.normal(0.0, 0.15, (N_MATERIALS, 1)))
    gain[M.SKY] = 1.0
    wb = np.exp(r.normal(0.0, 0.06, 3))
    return Appearance(
        zenith=tuple(np.clip(zen, 0, 1).round(4)), horizon=tuple(np.clip(hor, 0, 1).round(4)),
        sun_color=tuple(sun.round(4)), ambient=tuple(amb.round(4)), albedo_gain=tuple(map(tuple, gain.round(4))),
        hue_shift=float(r.uniform(-0.6, 0.6)), saturation=float(r.uniform(0.5, 1.4)),
        exposure=float(np.exp(r.normal(0.0, 0.2))), white_balance=tuple(wb.round(4)),
        blur_sigma=float(r.uniform(0.0, 0.9)), noise=float(r.uniform(0.0, 0.02)),
        jpeg_quality=int(r.choice([0, 0, 95, 85, 70])))


def recolor_objects(colors: np.ndarray, flags: np.ndarray, app: Appearance, black_flag: int) -> np.ndarray:
    """Object albedos (N, 3) rotated in hue about the grey axis and rescaled in saturation; black paint stays."""
    c = np.asarray(colors, np.float64)
    grey = c.mean(axis=1, keepdims=True)
    d = c - grey
    axis = np.ones(3) / np.sqrt(3.0)
    cos, sin = np.cos(app.hue_shift), np.sin(app.hue_shift)
    d = d * cos + np.cross(axis, d) * sin + np.outer(d @ axis, axis) * (1 - cos)   # Rodrigues about grey
    out = np.clip(grey + app.saturation * d, 0.0, 1.0)
    black = (np.asarray(flags) & black_flag) > 0
    out[black] = c[black]
    return out.astype(np.float32)


def frame_jitter(spec: TownSpec, i: int) -> dict:
    """Small per-frame camera changes: exposure, white balance, blur, noise (auto-exposure flicker)."""
    r = np.random.default_rng([spec.seed, i, 303])
    return {"exposure": float(np.exp(r.normal(0.0, 0.08))), "white_balance": np.exp(r.normal(0.0, 0.02, 3)),
            "blur": float(r.uniform(0.0, 0.3)), "seed": int(r.integers(2**31))}


def apply_camera(rgb: np.ndarray, app: Appearance, jitter: dict) -> np.ndarray:
    """uint8 RGB -> uint8 RGB after white balance, exposure, blur, noise and JPEG round trip."""
    import cv2

    img = rgb.astype(np.float32) / 255.0
    img *= (np.asarray(app.white_balance) * jitter["white_balance"] * app.exposure * jitter["exposure"]
            ).astype(np.float32)
    sigma = app.blur_sigma + jitter["blur"]
    if sigma > 0.05:
        img = cv2.GaussianBlur(img, (0, 0), sigma)
    if app.noise > 0:
        img += np.random.default_rng(jitter["seed"]).standard_normal(img.shape, dtype=np.float32) * app.noise
    out = np.clip(img * 255.0 + 0.5, 0, 255).astype(np.uint8)
    if app.jpeg_quality:
        ok, buf = cv2.imencode(".jpg", out[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, app.jpeg_quality])
        out = cv2.imdecode(buf, cv2.IMREAD_COLOR)[..., ::-1]
    return np.ascontiguousarray(out)


def training_towns(seed: int = 2026, frames_per_town: int = 500, stride: int = 2, variants: int = 2) -> list[TownSpec]:
    """Towns along KITTI 01-10 (never 00), windows of ``frames_per_town·stride`` poses, ``variants``
    differently randomised renderings of each window (variant v starts v poses later, so poses differ too).

    The last third of trajectory 09 is left out: it is the validation town (:func:`validation_town`).
    Ordered round-robin over trajectories, first variants first, so that any prefix of the list is diverse.
    """
    from mono_map.data.synth.trajectory import trajectory_length

    per_traj = []
    for traj in ("01", "02", "03", "04", "05", "06", "07", "08", "09", "10"):
        n = trajectory_length(traj) if traj != "09" else VALIDATION_FIRST_POSE
        s = 1 if n < 2 * frames_per_town * 0.6 else stride
        towns, start, k = [], 0, 0
        while start + s * 50 < n:
            f = min(frames_per_town, (n - start - variants) // s)
            for v in range(variants):
                towns.append((traj, start + v, s, f, k, v))
            start += f * s
            k += 1
        per_traj.append(towns)
    out = []
    for v in range(variants):               # every window once before any second variant
        for j in range(max(len(t) for t in per_traj)):
            for towns in per_traj:
                for traj, first, s, f, k, vv in towns:
                    if k == j and vv == v:
                        out.append(TownSpec(name=f"t{traj}_{k}{'ab'[v] if v < 2 else v}", trajectory=traj,
                                            first_pose=first, pose_stride=s, frames=f,
                                            seed=seed * 1000 + int(traj) * 50 + k * 5 + v))
    return out


TRAFFIC_PREFIX = "h"
KERB_PREFIX = "k"
DETAIL_PREFIXES = {"t": "p", TRAFFIC_PREFIX: "d", KERB_PREFIX: "v"}   # a family -> its twins with painted vehicles
DETAILED_SHARE = 0.9    # share of a detailed twin's (p, d, v) vehicles with painted details


def traffic_towns(n: int = 4, frames: int = 250, seed: int = 2026, kerb_trucks: bool = False) -> list[TownSpec]:
    """The first ``n`` windows of :func:`training_towns` as towns with lane traffic and large vehicles (issue
    31): named ``h…`` (``t01_0a`` → ``h01_0a``), ``frames`` poses each, other seeds (other towns, light and
    camera); the frames whose camera would be inside a vehicle are not rendered (traffic.clear_frames).
    ``kerb_trucks``: the ``k…`` family, the same with large vehicles parked at both kerbs too (other seeds)."""
    prefix, offset = (KERB_PREFIX, 600_000) if kerb_trucks else (TRAFFIC_PREFIX, 500_000)
    out = []
    for s in training_towns(seed)[:n]:
        out.append(replace(s, name=prefix + s.name[1:], frames=min(frames, s.frames), seed=s.seed + offset,
                           traffic=True, kerb_trucks=kerb_trucks))
    return out


JAM_PREFIX = "j"


def jam_towns(n: int = 6, frames: int = 250, seed: int = 2026) -> list[TownSpec]:
    """The first ``n`` windows of :func:`training_towns` as traffic jams (issue 31: real01's 1-5 m band holds 24 %
    of its LiDAR pixels, the training towns' 1-15 %): the adjacent lane nearly full, half or more of the lane
    vehicles large, a vehicle 12-25 m apart in the camera's own lane, large vehicles at the kerbs; painted vehicle
    details as the p, d, v families. Named ``j…`` (``t01_0a`` → ``j01_0a``), other seeds; the frames whose camera
    would be inside a vehicle are not rendered."""
    return [replace(s, name=JAM_PREFIX + s.name[1:], frames=min(frames, s.frames), seed=s.seed + 700_000,
                    traffic=True, kerb_trucks=True, vehicle_detail=True, jam=True) for s in training_towns(seed)[:n]]


def detailed_towns(specs: list[TownSpec]) -> list[TownSpec]:
    """Twins of the towns ``specs`` (same windows, seeds, layout, traffic, light and camera) with painted details on
    their vehicles, renamed by family: ``t…`` → ``p…``, ``h…`` → ``d…``, ``k…`` → ``v…`` (``k01_0a`` →
    ``v01_0a``). Only the vehicles' paint differs, so a model trained on them instead of their flat-painted twins
    measures that one lever (issue 31)."""
    return twins(specs, DETAIL_PREFIXES, "detailed", vehicle_detail=True)


def twins(specs: list[TownSpec], prefixes: dict, kind: str, **flags) -> list[TownSpec]:
    """The towns ``specs`` renamed by family (``prefixes``: first letter → the twins' first letter) with ``flags``
    set; a town of a family without ``kind`` twins is refused (ValueError)."""
    out = []
    for s in specs:
        if s.name[0] not in prefixes:
            raise ValueError(f"{s.name}: no {kind} family for it (families: {', '.join(prefixes)})")
        out.append(replace(s, name=prefixes[s.name[0]] + s.name[1:], **flags))
    return out


GREENERY_PREFIXES = {"p": "q", "d": "g", "v": "e"}   # a painted family -> its twins with greenery


def greenery_towns(specs: list[TownSpec]) -> list[TownSpec]:
    """Twins of the painted towns ``specs`` (p, d, v families: same windows, seeds, layout, vehicles, light and camera)
    with greenery added (issue 31: real KITTI's residential streets): hedges along 30-80 % of the frontages still
    free and large canopy trees at 30-80 % of the tree slots, crowns over the road. Renamed ``p…`` → ``q…``,
    ``d…`` → ``g…``, ``v…`` → ``e…``; only the greenery differs, so a model trained on them instead of their
    twins measures that one lever."""
    return twins(specs, GREENERY_PREFIXES, "greenery", greenery=True)


VALIDATION_FIRST_POSE = 1060   # trajectory 09: poses 1060.. are the held-out validation town


def validation_town(seed: int = 2026, frames: int = 250) -> TownSpec:
    """A held-out town of the training distribution (the end of trajectory 09), for learning curves."""
    return TownSpec(name="val09", trajectory="09", first_pose=VALIDATION_FIRST_POSE, pose_stride=2, frames=frames,
                    seed=seed * 1000 + 999)
