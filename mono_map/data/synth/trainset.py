"""The training cache: randomised towns rendered straight to training resolution, memory-mapped.

Layout under ``root`` (default ``~/.cache/mono-map/trainset``; ``$MONO_MAP_TRAINSET`` overrides)::

    towns/<name>/meta.json    TownSpec, recipe hash, appearance, size, intrinsics K (pixels)
    towns/<name>/image.u8     (F, H, W, 3) uint8 RGB
    towns/<name>/dense.u16    (F, H, W) dense z-depth of the camera (cam2), metres × 256
    towns/<name>/lidar.u16    (F, H, W) HDL-64E returns projected into the camera, metres × 256 (nearest wins)
    towns/<name>/done.u8      (F,) 1 once frame i is written and flushed

Depth codes: 0 = no value (no LiDAR return), ``NO_SURFACE`` = the camera ray meets nothing within
255 m (sky). The camera is KITTI's image_2 (real calibration) scaled to the inference size the
model sees (376×1241 → 192×634, pixel centres preserved). Frames are written in place and marked
done after a flush, so rendering is incremental and resumable, and training can read the frames
that exist while the rest render. Everything scales past RAM (memory maps, one town at a time).
"""

from __future__ import annotations

import json
import os
import sys
import time
from concurrent.futures import as_completed
from pathlib import Path

import numpy as np

from mono_map.data.synth.randomize import TownSpec
from mono_map.errors import MonoMapError
from mono_map.geometry import scaled_intrinsics

NO_SURFACE = 65535
DEPTH_SCALE = 256.0
HEIGHT, WIDTH = 192, 634
VERSION = 1


def default_root() -> Path:
    env = os.environ.get("MONO_MAP_TRAINSET")
    return Path(env).expanduser() if env else Path("~/.cache/mono-map/trainset").expanduser()



def encode_depth(depth_m: np.ndarray, no_surface: np.ndarray | None = None) -> np.ndarray:
    """Metres -> uint16 (× 256, 0 = none, NO_SURFACE where ``no_surface``)."""
    d = np.clip(np.round(np.asarray(depth_m, np.float64) * DEPTH_SCALE), 0, NO_SURFACE - 1).astype(np.uint16)
    if no_surface is not None:
        d[no_surface] = NO_SURFACE
    return d


def decode_depth(code: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """uint16 -> (metres float32 with 0 = none or no surface, no-surface mask bool)."""
    code = np.asarray(code)
    none = code == NO_SURFACE
    return np.where(none, 0.0, code / DEPTH_SCALE).astype(np.float32), none


class TownCache:
    """The memory maps of one town (mode "r" to read, "r+" to write frames)."""

    def __init__(self, path: Path, mode: str = "r"):
        self.path = Path(path)
        self.meta = json.loads((self.path / "meta.json").read_text())
        F, H, W = self.meta["frames"], self.meta["height"], self.meta["width"]
        self.image = np.memmap(self.path / "image.u8", np.uint8, mode, shape=(F, H, W, 3))
        self.dense = np.memmap(self.path / "dense.u16", np.uint16, mode, shape=(F, H, W))
        self.lidar = np.memmap(self.path / "lidar.u16", np.uint16, mode, shape=(F, H, W))
        self.done = np.memmap(self.path / "done.u8", np.uint8, mode, shape=(F,))

    @property
    def frames(self) -> int:
        return int(self.meta["frames"])

    def done_frames(self) -> np.ndarray:
        return np.flatnonzero(np.asarray(self.done))


def create_town(root: Path, spec: TownSpec, recipe_hash: str, appearance: dict, K: np.ndarray,
                frames: int | None = None) -> Path:
    """Allocate (or find) a town's files; a town of another spec/hash under the same name is an error.
    ``frames``: how many frames it holds (default ``spec.frames``; fewer where traffic skips some)."""
    from mono_map.io import write_json_atomic

    d = Path(root) / "towns" / spec.name
    F = spec.frames if frames is None else int(frames)
    meta = {"version": VERSION, "spec": spec.to_dict(), "recipe_hash": recipe_hash, "appearance": appearance,
            "frames": F, "height": HEIGHT, "width": WIDTH, "K": np.asarray(K).tolist(),
            "depth_scale": DEPTH_SCALE, "no_surface": NO_SURFACE}
    if (d / "meta.json").is_file():
        old = json.loads((d / "meta.json").read_text())
        if old.get("spec") != meta["spec"] or old.get("recipe_hash") != recipe_hash or old.get("version") != VERSION:
            raise MonoMapError(f"{d}: holds a different town (spec or recipe changed); remove it to re-render")
        return d
    d.mkdir(parents=True, exist_ok=True)
    for name, nbytes in (("image.u8", F * HEIGHT * WIDTH * 3), ("dense.u16", F * HEIGHT * WIDTH * 2),
                         ("lidar.u16", F * HEIGHT * WIDTH * 2), ("done.u8", F)):
        with open(d / name, "wb") as fh:
            fh.truncate(nbytes)
    write_json_atomic(d / "meta.json", meta)   # last: a town without meta.json is not a town yet
    return d


class TownRenderer:
    """Renders frames of one randomised town at training resolution (camera + LiDAR projected)."""

    def __init__(self, spec: TownSpec, nthreads: int = 1):
        import open3d as o3d

        from mono_map.data.synth import writer
        from mono_map.data.synth.camera import Lighting, PinholeCamera
        from mono_map.data.synth.lidar import ray_directions
        from mono_map.data.synth.placement import BLACK
        from mono_map.data.synth.randomize import randomized_appearance, randomized_recipe, recolor_objects
        from mono_map.data.synth.town import build_town
        from mono_map.data.synth.traffic import clear_frames
        from mono_map.data.synth.trajectory import frame_poses
        from mono_map.config import KITTI_IMAGE_HEIGHT, KITTI_IMAGE_WIDTH
        from mono_map.geometry import T_cam_cam0_from_projection, pose_inverse

        self.spec = spec
        self.recipe = randomized_recipe(spec)
        self.app = randomized_appearance(spec)
        t0 = time.perf_counter()
        self.town = build_town(self.recipe)
        self.town.obj_color = recolor_objects(self.town.obj_color, self.town.obj_flags, self.app, BLACK)
        self.build_s = time.perf_counter() - t0
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(o3d.core.Tensor(self.town.vertices),
                                 o3d.core.Tensor(self.town.triangles.astype(np.uint32)))
        calib = writer.read_calib()
        self.K = scaled_intrinsics(calib["P2"][:, :3], WIDTH / KITTI_IMAGE_WIDTH, HEIGHT / KITTI_IMAGE_HEIGHT)
        self.T_cam0_cam2 = pose_inverse(T_cam_cam0_from_projection(calib["P2"]))
        self.T_cam0_velo = calib["Tr"]
        self.camera = PinholeCamera(self.K, HEIGHT, WIDTH)
        base = Lighting.from_recipe(self.recipe.light)
        a = self.app
        self.light = Lighting(sun=base.sun, sun_color=np.array(a.sun_color, np.float32),
                              ambient=np.array(a.ambient, np.float32), zenith=np.array(a.zenith, np.float32),
                              horizon=np.array(a.horizon, np.float32), haze_distance=base.haze_distance,
                              exposure=1.0, albedo_gain=np.array(a.albedo_gain, np.float32))
        self.lidar_dirs = ray_directions()
        poses = frame_poses(self.recipe)
        # the window's poses whose camera is clear of the vehicles in its lane (all of them without traffic)
        self.pose_index = np.flatnonzero(clear_frames(self.town.lane_vehicles, poses))
        self.poses = poses[self.pose_index]
        self.nthreads = nthreads

    @property
    def frames(self) -> int:
        """Frames this town renders (the window's poses less those inside or just behind a vehicle)."""
        return len(self.poses)

    def render(self, i: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(rgb (H,W,3) uint8, dense code (H,W) uint16, lidar code (H,W) uint16) of frame i."""
        from mono_map.data.synth.camera import render
        from mono_map.data.synth.lidar import scan
        from mono_map.data.synth.randomize import apply_camera, frame_jitter
        from mono_map.geometry import lidar_depth_image, pose_inverse, transform_points

        T_world_cam0 = self.poses[i]
        rng = np.random.default_rng([self.spec.seed, i, 1])
        rgb, depth = render(self.scene, self.town, self.light, self.camera, T_world_cam0 @ self.T_cam0_cam2, rng,
                            self.nthreads)
        rgb = apply_camera(rgb, self.app, frame_jitter(self.spec, i))
        rng = np.random.default_rng([self.spec.seed, i, 2])
        pts = scan(self.scene, self.town, T_world_cam0 @ self.T_cam0_velo, self.lidar_dirs, rng, self.nthreads)
        T_cam2_velo = pose_inverse(self.T_cam0_cam2) @ self.T_cam0_velo
        lid = lidar_depth_image(transform_points(T_cam2_velo, pts[:, :3]), self.K, HEIGHT, WIDTH)
        return rgb, encode_depth(depth, depth <= 0), encode_depth(lid)


def render_town(root: Path, spec: TownSpec, nthreads: int = 1, log=None) -> int:
    """Render the missing frames of one town into the cache; returns the number rendered."""
    from mono_map.data.synth.randomize import randomized_recipe

    recipe = randomized_recipe(spec)
    d = Path(root) / "towns" / spec.name
    if (d / "meta.json").is_file():
        tc = TownCache(d, "r")
        if tc.done.all() and tc.meta.get("recipe_hash") == recipe.content_hash():
            return 0
    r = TownRenderer(spec, nthreads)
    d = create_town(root, spec, recipe.content_hash(), r.app.to_dict(), r.K, r.frames)
    tc = TownCache(d, "r+")
    todo = [i for i in range(r.frames) if not tc.done[i]]
    t0 = time.perf_counter()
    for n, i in enumerate(todo):
        rgb, dense, lidar = r.render(i)
        tc.image[i], tc.dense[i], tc.lidar[i] = rgb, dense, lidar
        for m in (tc.image, tc.dense, tc.lidar):
            m.flush()
        tc.done[i] = 1
        tc.done.flush()
        if log and (n + 1) % 50 == 0:
            log(f"{spec.name}: {n + 1}/{len(todo)} frames, {(n + 1) / (time.perf_counter() - t0):.2f} frames/s")
    return len(todo)


def town_worker(args) -> tuple[str, int, float]:
    """A render worker's task: ``(root, spec)`` → the town rendered into the cache (name, frames rendered, s)."""
    root, spec = args
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    t0 = time.perf_counter()
    n = render_town(Path(root), spec, nthreads=1,
                    log=lambda m: print(f"[{time.strftime('%H:%M:%S')}] {m}", file=sys.stderr, flush=True))
    return spec.name, n, time.perf_counter() - t0


def render_trainset(root: Path, specs: list[TownSpec], workers: int = 2, log=print) -> dict:
    """Render every town (one town per worker process at a time); resumable; returns counts."""
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    total = 0
    from mono_map.data.synth import kernels
    from mono_map.data.synth.generate import worker_pool

    kernels.library()                       # compile the renderer's kernels once, before the workers load them
    with worker_pool(workers, "render_trainset", root) as pool:
        for f in as_completed([pool.submit(town_worker, (str(root), s)) for s in specs]):
            name, n, sec = f.result()
            total += n
            el = time.perf_counter() - t0
            log(f"[{time.strftime('%H:%M:%S')}] town {name}: {n} frames in {sec:.0f} s; total {total} frames, "
                f"{total / max(el, 1e-9):.2f} frames/s overall")
    return {"frames_rendered": total, "seconds": time.perf_counter() - t0}


def open_trainset(root: Path | None = None, names: list[str] | None = None) -> list[TownCache]:
    """Every town under root (or the named ones) for reading."""
    root = Path(root) if root else default_root()
    towns = sorted(p.parent for p in (root / "towns").glob("*/meta.json"))
    if names is not None:
        towns = [t for t in towns if t.name in set(names)]
    return [TownCache(t, "r") for t in towns]
