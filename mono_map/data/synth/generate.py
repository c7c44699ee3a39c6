"""Render a synthetic sequence from its recipe, frames in parallel, into the KITTI odometry layout.

Frame i depends only on (recipe, i): the town is built from the whole recipe and every
frame has its own random streams seeded by (seed, i), so a prefix can be extended later
and two generations of the same recipe are byte-identical. The right colour camera (image_3,
opt-in: ``stereo``) has a stream of its own, so asking for it changes no other file.
"""

from __future__ import annotations

import contextlib
import itertools
import multiprocessing as mp
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from mono_map.config import KITTI_IMAGE_HEIGHT, KITTI_IMAGE_WIDTH
from mono_map.data.synth import writer
from mono_map.data.synth.recipe import Recipe, load_recipe, recipe_path
from mono_map.data.synth.trajectory import frame_pose_indices, frame_pose_lines, frame_poses
from mono_map.errors import MonoMapError
from mono_map.temps import clean_stale_temps, pid_alive

GENERATOR_VERSION = "3"
FRAME_PERIOD = 0.1          # seconds between consecutive real poses (KITTI records at 10 Hz)


class FrameRenderer:
    """Holds the ray-casting scene of one town; renders (image, depth, scan) of frame i, and on request the
    right colour camera's image (KITTI's image_3, projection P3)."""

    def __init__(self, recipe: Recipe, town, nthreads: int = 0, poses: np.ndarray | None = None):
        import open3d as o3d

        from mono_map.data.synth.camera import Lighting, PinholeCamera
        from mono_map.data.synth.lidar import ray_directions
        from mono_map.geometry import T_cam_cam0_from_projection, pose_inverse

        self.recipe = recipe
        self.town = town
        self.nthreads = nthreads
        self.scene = o3d.t.geometry.RaycastingScene()
        self.scene.add_triangles(o3d.core.Tensor(town.vertices), o3d.core.Tensor(town.triangles.astype(np.uint32)))
        calib = writer.read_calib()
        self.K2 = calib["P2"][:, :3].copy()
        self.T_cam0_cam2 = pose_inverse(T_cam_cam0_from_projection(calib["P2"]))
        self.T_cam0_velo = calib["Tr"]
        self.camera = PinholeCamera(self.K2, KITTI_IMAGE_HEIGHT, KITTI_IMAGE_WIDTH)
        self.K3 = calib["P3"][:, :3].copy()
        self.T_cam0_cam3 = pose_inverse(T_cam_cam0_from_projection(calib["P3"]))
        self.camera3 = self.camera if np.array_equal(self.K3, self.K2) else \
            PinholeCamera(self.K3, KITTI_IMAGE_HEIGHT, KITTI_IMAGE_WIDTH)
        self.light = Lighting.from_recipe(recipe.light)
        self.lidar_dirs = ray_directions()
        self.poses = frame_poses(recipe) if poses is None else poses   # (n, 4, 4) T_world_cam0 per frame

    def render(self, i: int):
        """(rgb H×W×3 uint8, depth H×W float32 metres, velodyne (M, 4) float32) of frame i."""
        from mono_map.data.synth.camera import render
        from mono_map.data.synth.lidar import scan

        T_world_cam0 = self.poses[i]
        rng = np.random.default_rng([self.recipe.seed, i, 1])
        rgb, depth = render(self.scene, self.town, self.light, self.camera, T_world_cam0 @ self.T_cam0_cam2, rng,
                            self.nthreads)
        rng = np.random.default_rng([self.recipe.seed, i, 2])
        pts = scan(self.scene, self.town, T_world_cam0 @ self.T_cam0_velo, self.lidar_dirs, rng, self.nthreads)
        return rgb, depth, pts

    def render_right(self, i: int) -> np.ndarray:
        """rgb H×W×3 uint8 of frame i seen by the right colour camera (image_3), from its own random stream
        (seed, i, 3): rendering it leaves image_2, depth_2 and the scan as they were."""
        from mono_map.data.synth.camera import render

        rng = np.random.default_rng([self.recipe.seed, i, 3])
        rgb, _ = render(self.scene, self.town, self.light, self.camera3, self.poses[i] @ self.T_cam0_cam3, rng,
                        self.nthreads)
        return rgb


_WORKER: dict = {}

# Each render process runs on one core: numpy's BLAS (OpenBLAS) otherwise starts a thread per core in every
# worker, whose spinning costs the other worker CPU. It reads these at import, so they are set in the
# environment the spawned workers start with (the results are the same: a BLAS thread splits rows, not sums).
# glibc's malloc keeps the freed per-frame arrays (up to 32 MB each) for the next frame instead of returning
# them to the kernel and faulting fresh zeroed pages in again (~5,800 page faults and ~10 of ~260 CPU-ms a
# frame of 00, measured; allocation does not change any value).
WORKER_ENV = {"OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1",
              "MALLOC_MMAP_THRESHOLD_": str(32 << 20), "MALLOC_TRIM_THRESHOLD_": str(1 << 30)}


@contextlib.contextmanager
def environment(values: dict):
    """``os.environ`` updated with ``values`` inside the block (for processes started there), restored after."""
    saved = {k: os.environ.get(k) for k in values}
    os.environ.update(values)
    try:
        yield
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


@contextlib.contextmanager
def worker_pool(n: int, what: str, where, initializer=None, initargs: tuple = ()):
    """``n`` spawned render processes (``ProcessPoolExecutor``), all started here with ``WORKER_ENV``; on leaving,
    tasks not started are dropped and the workers finish theirs. A worker that dies (killed, out of memory) ends
    the block with one MonoMapError naming ``what`` and ``where`` (the frames written there are kept), instead of
    the wait forever of ``multiprocessing.Pool``."""
    from concurrent.futures import ProcessPoolExecutor
    from concurrent.futures.process import BrokenProcessPool

    with environment(WORKER_ENV):    # the pool starts a process per task asked for: start them all here
        pool = ProcessPoolExecutor(n, mp_context=mp.get_context("spawn"), initializer=initializer,
                                   initargs=initargs)
        for _ in range(n):
            pool.submit(os.getpid)
    try:
        yield pool
    except BrokenProcessPool:
        raise MonoMapError(f"{what}: a render worker died (killed, or out of memory?); the frames written so far "
                           f"are kept under {where} and a new run renders the rest") from None
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


def _init_worker(recipe, town_file, seq_dir, nthreads, stereo=False):
    """A render process starts while the parent still builds the town: it imports open3d and computes the
    frame poses now, and reads the town from ``town_file`` (written before any frame is asked for) with its
    first frame."""
    import open3d  # noqa: F401  (~1.6 s, overlapping the town build)

    _WORKER.update(recipe=recipe, town_file=town_file, seq_dir=Path(seq_dir), nthreads=nthreads,
                   poses=frame_poses(recipe), stereo=stereo)


def _renderer() -> "FrameRenderer":
    if "renderer" not in _WORKER:
        import pickle

        with open(_WORKER["town_file"], "rb") as f:
            town = pickle.load(f)
        _WORKER["renderer"] = FrameRenderer(_WORKER["recipe"], town, _WORKER["nthreads"], poses=_WORKER["poses"])
    return _WORKER["renderer"]


def render_and_write(i: int) -> int:
    """A render worker's task: frame ``i`` of the worker's sequence (with ``stereo`` its image_3 too), rendered
    and written; returns ``i``."""
    rgb, depth, pts = _renderer().render(i)
    writer.write_frame(_WORKER["seq_dir"], i, rgb, depth, pts)
    if _WORKER.get("stereo"):
        render_right_and_write(i)
    return i


def render_right_and_write(i: int) -> int:
    """A render worker's task: only the right camera's image_3 of frame ``i`` (its other files are there)."""
    writer.write_right(_WORKER["seq_dir"], i, _renderer().render_right(i))
    return i


def marker_info(recipe: Recipe, n_frames: int) -> dict:
    return {"generator": "mono-map synth", "generator_version": GENERATOR_VERSION, "recipe": recipe.name,
            "recipe_file": Path(recipe.path).name, "recipe_hash": recipe.content_hash(),
            "trajectory": recipe.trajectory, "first_pose": recipe.first_pose, "pose_stride": recipe.pose_stride,
            "n_frames": int(n_frames), "recipe_frames": recipe.frames,
            "depth_2": "z-depth (m, cam2) of the first surface hit by each pixel's ray; glass = the glass pane"}


def process_start(pid: int) -> str | None:
    """An identity of process ``pid`` that survives PID reuse: its start time (Linux /proc), else None."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    return stat.rsplit(")", 1)[1].split()[19]  # field 22, after the command name


def owner_alive(partial: dict) -> int | None:
    """PID of the live process a partial marker names as its writer, else None (finished, killed, or
    the PID now belongs to another process: the recorded start time differs)."""
    import socket

    pid = partial.get("pid")
    if not isinstance(pid, int) or isinstance(pid, bool) or pid == os.getpid():
        return None
    if partial.get("host") != socket.gethostname() or not pid_alive(pid):
        return None
    started = partial.get("pid_start")
    if started is not None and process_start(pid) not in (None, started):
        return None  # PID reused by an unrelated process
    return pid


def _check_not_busy(seq_dir: Path, partial: dict | None, force: bool = False) -> None:
    """Refuse to work on a sequence another live process is generating (its partial marker names it)."""
    pid = owner_alive(partial) if partial else None
    if pid is not None and not force:
        raise MonoMapError(f"{seq_dir / writer.PARTIAL_MARKER}: process {pid} is generating this sequence right "
                           "now; wait for it to finish, stop it, or pass --force if that process is not mono-map")


def _is_current(info: dict | None, recipe: Recipe) -> bool:
    return bool(info) and info.get("recipe_hash") == recipe.content_hash() \
        and info.get("generator_version") == GENERATOR_VERSION


def generate_sequence(recipe: Recipe, root, frames: int | None = None, workers: int = 2, force: bool = False,
                      quiet: bool = False, stereo: bool = False) -> Path:
    """Write the first ``frames`` frames (None = all) of ``recipe`` under ``root``; returns the sequence dir.

    Existing complete frames of the same recipe and generator version are kept (a prefix is
    extended); ``force`` re-renders everything.  Refuses to touch a directory that holds a
    sequence not written by this generator (no marker: e.g. a real KITTI sequence).  ``stereo`` also
    renders the right colour camera (image_3) of those frames; of a frame already there, only that.
    """
    root = Path(root)
    n = recipe.frames if frames is None else int(frames)
    if not 1 <= n <= recipe.frames:
        raise MonoMapError(f"--frames: recipe {recipe.name} has {recipe.frames} frames, asked for {n}")
    if workers < 1:
        raise MonoMapError(f"--workers: must be >= 1, got {workers}")
    if recipe.traffic.ahead_spacing > 0:
        raise MonoMapError(f"{recipe.path or recipe.name}: [traffic] ahead_spacing skips the frames that would drive "
                           "into a vehicle; a KITTI-layout sequence needs every frame (only training towns, "
                           "mono-map render-trainset, support it)")
    seq_dir = root / "sequences" / recipe.name
    partial_path = seq_dir / writer.PARTIAL_MARKER
    partial = writer.read_marker(seq_dir, partial=True)
    try:
        marker = writer.read_marker(seq_dir)
    except MonoMapError:
        if not force:
            raise
        marker = None
    if seq_dir.is_dir() and marker is None and partial is None and not force and any(seq_dir.iterdir()):
        raise MonoMapError(f"{seq_dir}: exists but was not written by mono-map synth (no {writer.MARKER}, "
                           "e.g. a real KITTI sequence); refusing to overwrite it")
    _check_not_busy(seq_dir, partial, force)
    current = _is_current(marker, recipe)
    if not force and current and marker.get("n_frames", 0) >= n and partial is None \
            and (not stereo or writer.leading_right_frames(seq_dir, n) >= n):
        return seq_dir
    fresh = force or (marker is not None and not current) or (partial is not None and not _is_current(partial, recipe))
    if fresh:
        (seq_dir / writer.MARKER).unlink(missing_ok=True)
    seq_dir.mkdir(parents=True, exist_ok=True)
    import socket

    writer.write_marker(seq_dir, {**marker_info(recipe, n), "pid": os.getpid(), "host": socket.gethostname(),
                                  "pid_start": process_start(os.getpid())}, partial=True)
    todo = list(range(n)) if fresh else [i for i in range(n) if not writer.frame_complete(seq_dir, i)]
    right = [i for i in sorted(set(range(n)) - set(todo)) if stereo and not writer.right_complete(seq_dir, i)]
    tasks = sorted([(i, False) for i in todo] + [(i, True) for i in right])   # (frame, image_3 only)
    what = [f"{len(todo)} frames" + " with their image_3" * stereo] if todo else []
    what += [f"the image_3 of {len(right)} frames already there"] if right else []
    t0 = time.perf_counter()
    if tasks:
        def town_built(town) -> None:
            if not quiet:
                print(f"synth {recipe.name}: town of {town.stats['triangles']:,} triangles "
                      f"({town.stats['buildings']} buildings, {town.stats['cars']} cars of which "
                      f"{town.stats['black_cars']} black, {town.stats['trees']} trees) built in "
                      f"{time.perf_counter() - t0:.1f} s; rendering {' and '.join(what)} with {workers} worker(s)",
                      file=sys.stderr)
        try:
            _render_frames(recipe, seq_dir, tasks, workers, quiet, town_built, stereo)
        finally:  # interrupted or failed: the workers are gone, so are their half-written frame files
            for sub in ("image_2", "depth_2", "velodyne", "image_3"):
                clean_stale_temps(seq_dir / sub)
    if fresh:   # a re-render without --stereo leaves no image_3 of the old one
        writer.remove_frames_from(seq_dir, n, image_3_from=None if stereo else 0)
    n_keep = max(n, marker.get("n_frames", 0) if (marker and current and not fresh) else n)
    idx = frame_pose_indices(recipe)[:n_keep]
    times = (idx - recipe.first_pose) * FRAME_PERIOD
    writer.write_sequence_files(root, recipe.name, frame_pose_lines(recipe, n_keep), times)
    info = marker_info(recipe, n_keep)
    if stereo or (marker and current and not fresh and "image_3" in marker):
        info["image_3"] = writer.leading_right_frames(seq_dir, n_keep)
    info["seconds"] = round(time.perf_counter() - t0, 2)
    writer.write_marker(seq_dir, info)
    partial_path.unlink(missing_ok=True)
    return seq_dir


def _render_frames(recipe, seq_dir: Path, tasks: list[tuple[int, bool]], workers: int, quiet: bool, town_built,
                   stereo: bool = False) -> None:
    """Build the town and render the ``tasks`` (frame, only its image_3?) into ``seq_dir`` (``stereo``: a whole
    frame with its image_3): in this process with one worker, else
    in ``workers`` spawned processes started before the town is built (their imports and poses overlap it);
    the town reaches them through a temporary pickle in the system's temporary directory. A worker that dies
    stops the run with a MonoMapError (:func:`worker_pool`); the frames written are kept."""
    import pickle

    from mono_map.data.synth import kernels
    from mono_map.data.synth.town import build_town
    from mono_map.progress import progress

    desc = f"synth {recipe.name}"

    def shown(frames):
        return frames if quiet else progress(frames, total=len(tasks), desc=desc, unit="frame")

    town_file = Path(tempfile.gettempdir()) / f"mono-map-town-{recipe.name}-{os.getpid()}.pkl"
    if workers == 1 or len(tasks) == 1:
        town = build_town(recipe)
        town_built(town)
        _WORKER.update(seq_dir=seq_dir, renderer=FrameRenderer(recipe, town, 0), stereo=stereo)
        try:
            for i, right_only in shown(tasks):
                (render_right_and_write if right_only else render_and_write)(i)
        finally:
            _WORKER.clear()
        return
    kernels.library()           # compile the renderer's kernels once, here, before the workers load them
    nproc = min(workers, len(tasks))
    try:
        with worker_pool(nproc, desc, seq_dir, _init_worker, (recipe, str(town_file), str(seq_dir), 1, stereo)) \
                as pool:
            town = build_town(recipe)
            town_built(town)
            tmp = town_file.with_suffix(".tmp")
            with open(tmp, "wb") as f:
                pickle.dump(town, f, protocol=pickle.HIGHEST_PROTOCOL)
            os.replace(tmp, town_file)
            del town
            for _ in shown(_completed(pool, tasks, 2 * nproc)):
                pass
    finally:
        town_file.unlink(missing_ok=True)
        town_file.with_suffix(".tmp").unlink(missing_ok=True)


def _completed(pool, tasks: list[tuple[int, bool]], in_flight: int):
    """Render ``tasks`` on ``pool``, ``in_flight`` submitted at a time; yields each frame as it is written."""
    from concurrent.futures import FIRST_COMPLETED, wait

    def submit(task):
        return pool.submit(render_right_and_write if task[1] else render_and_write, task[0])

    queue = iter(tasks)
    pending = {submit(t) for t in itertools.islice(queue, in_flight)}
    while pending:
        done, pending = wait(pending, return_when=FIRST_COMPLETED)
        for f in done:
            yield f.result()
            nxt = next(queue, None)
            if nxt is not None:
                pending.add(submit(nxt))


def ensure_sequence(root, name: str, frames: int | None = None, stereo: bool = False) -> bool:
    """Generate ``root/sequences/name`` from ``sequences/name.toml`` if missing or shorter than asked (``stereo``:
    or without the right camera's image_3 of those frames). Returns True if it generated.  Never touches a
    directory without our marker (a real KITTI sequence) and returns False for a name without a recipe."""
    root = Path(root)
    path = recipe_path(name)
    if not path.is_file():
        return False
    seq_dir = root / "sequences" / str(name)
    partial_info = writer.read_marker(seq_dir, partial=True)
    partial = partial_info is not None
    marker = writer.read_marker(seq_dir)
    if seq_dir.is_dir() and marker is None and not partial and any(seq_dir.iterdir()):
        return False
    _check_not_busy(seq_dir, partial_info)
    recipe = load_recipe(path)
    want = recipe.frames if frames is None else min(int(frames), recipe.frames)
    have = int(marker.get("n_frames", 0)) if marker is not None and not partial else 0
    if have >= want and (not stereo or writer.leading_right_frames(seq_dir, want) >= want):
        return False
    if marker is None:
        print(f"sequence {name} not found under {root}: generating it from {_short(path)} ({want} frames)",
              file=sys.stderr)
    else:
        print(f"sequence {name} under {root} has {marker.get('n_frames', 0)} frames" + (
            f": rendering the right camera's image_3 of its first {want}" if have >= want else
            f": extending it to {want}") + f" from {_short(path)}", file=sys.stderr)
    generate_sequence(recipe, root, frames=want, stereo=stereo)
    return True


def _short(path: Path) -> str:
    try:
        return str(Path(path).resolve().relative_to(Path.cwd()))
    except ValueError:
        return f"sequences/{Path(path).name}" if Path(path).parent.name == "sequences" else str(path)
