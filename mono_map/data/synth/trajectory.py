"""Trajectories of the synthetic sequences: real KITTI cam0 poses and the road path under them.

World frame = first cam0 frame of the real trajectory (x right, y down, z forward).
The ground under each pose lies ``CAMERA_HEIGHT`` metres below cam0 along the pose's
down axis; the road path is the polyline of those ground points, resampled by arc length.
"""

from __future__ import annotations

import functools
import gzip
from dataclasses import dataclass

import numpy as np

from mono_map.paths import KITTI_ASSETS_DIR

CAMERA_HEIGHT = 1.65      # metres, cam0 above the road (KITTI)
DOWN = np.array([0.0, 1.0, 0.0])


def available_trajectories() -> set[str]:
    return {p.name.split(".")[0] for p in (KITTI_ASSETS_DIR / "poses").glob("*.txt.gz")}


@functools.lru_cache(maxsize=16)
def _pose_lines(trajectory: str) -> tuple[str, ...]:
    with gzip.open(KITTI_ASSETS_DIR / "poses" / f"{trajectory}.txt.gz", "rt") as fh:
        return tuple(line.strip() for line in fh if line.strip())


def trajectory_length(trajectory: str) -> int:
    return len(_pose_lines(trajectory))


def frame_pose_lines(recipe, n: int) -> list[str]:
    """Lines of poses/XX.txt for the first n frames (KITTI format, 12 numbers)."""
    return [format_pose_line(T) for T in frame_poses(recipe)[:n]]


@functools.lru_cache(maxsize=16)
def load_poses(trajectory: str) -> np.ndarray:
    """All real poses T_world_cam0 of a KITTI trajectory, (N, 4, 4) float64."""
    rows = np.array([[float(x) for x in line.split()] for line in _pose_lines(trajectory)])
    T = np.tile(np.eye(4), (len(rows), 1, 1))
    T[:, :3, :4] = rows.reshape(-1, 3, 4)
    T.setflags(write=False)
    return T


def frame_pose_indices(recipe) -> np.ndarray:
    """Pose index of every frame of the recipe (length recipe.frames)."""
    return recipe.first_pose + recipe.pose_stride * np.arange(recipe.frames)


def town_pose_range(recipe, margin_m: float = 120.0) -> tuple[int, int]:
    """Poses [lo, hi) the town is built around: the recipe's span plus ``margin_m`` of road
    before and after (so the camera looks down a street, not into the void)."""
    poses = load_poses(recipe.trajectory)
    idx = frame_pose_indices(recipe)
    c = poses[:, :3, 3]
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(c, axis=0), axis=1))])
    lo = int(np.searchsorted(arc, arc[idx[0]] - margin_m))
    hi = int(np.searchsorted(arc, arc[idx[-1]] + margin_m, side="right"))
    return max(lo, 0), min(max(hi, idx[-1] + 1), len(poses))


def height_corrections(ground: np.ndarray, radius: float = 3.0, same_pass_arc: float = 30.0,
                       smooth_m: float = 8.0) -> np.ndarray:
    """Vertical offsets (N,) that make revisits of the same street agree in height.

    Real KITTI ground truth drifts in height between passes (up to ~1 m in 00, more in 08);
    a town has one road surface, so where other passes run within ``radius`` metres a ground
    point moves to the mean height of all passes there (consensus minus its own pass's
    local mean, so slopes and path ends add no bias), then offsets are smoothed along the
    path.  Poses without a revisit keep their height exactly (offset 0).
    """
    xz = ground[:, [0, 2]]
    y = ground[:, 1]
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(ground, axis=0), axis=1))])
    cells = np.floor(xz / radius).astype(np.int64)
    buckets: dict[tuple[int, int], list[int]] = {}
    for i, (a, b) in enumerate(cells):
        buckets.setdefault((int(a), int(b)), []).append(i)
    buckets_np = {k: np.array(v) for k, v in buckets.items()}
    delta = np.zeros(len(y))
    for i, (a, b) in enumerate(cells):
        cand = [buckets_np[k] for k in ((a + da, b + db) for da in (-1, 0, 1) for db in (-1, 0, 1)) if k in buckets_np]
        j = np.concatenate(cand)
        j = j[np.linalg.norm(xz[j] - xz[i], axis=1) < radius]
        own = np.abs(arc[j] - arc[i]) <= same_pass_arc
        if own.all():
            continue
        delta[i] = y[j].mean() - y[j[own]].mean() if own.any() else y[j].mean() - y[i]
    if np.any(delta):
        # Gaussian smoothing along the arc length
        step = max(np.median(np.diff(arc)), 1e-3)
        sig = smooth_m / step
        k = np.arange(-int(3 * sig), int(3 * sig) + 1)
        w = np.exp(-0.5 * (k / sig) ** 2)
        pad = np.pad(delta, len(k) // 2, mode="edge")
        delta = np.convolve(pad, w / w.sum(), mode="valid")
    return delta


def format_pose_line(T: np.ndarray) -> str:
    return " ".join(f"{v:.9e}" for v in T[:3, :4].ravel())


@functools.lru_cache(maxsize=8)
def _town_poses(trajectory: str, lo: int, hi: int) -> np.ndarray:
    P = load_poses(trajectory)[lo:hi].copy()
    for _ in range(3):                       # a few rounds: passes converge to one surface
        P[:, 1, 3] += height_corrections(ground_points(P))
    # round-trip through the text written to poses/XX.txt so rendering uses exactly the file's values
    P[:, :3, :4] = np.array([[float(v) for v in format_pose_line(T).split()] for T in P]).reshape(-1, 3, 4)
    P.setflags(write=False)
    return P


def town_poses(recipe) -> tuple[int, np.ndarray]:
    """(lo, poses) of the town's pose range, heights made consistent across revisits (T_world_cam0)."""
    lo, hi = town_pose_range(recipe)
    return lo, _town_poses(recipe.trajectory, lo, hi)


def frame_poses(recipe) -> np.ndarray:
    """T_world_cam0 of every frame of the recipe (recipe.frames, 4, 4), as written to poses/XX.txt."""
    lo, P = town_poses(recipe)
    return P[frame_pose_indices(recipe) - lo]


@dataclass
class RoadPath:
    """Ground path resampled every ``spacing`` metres (world frame)."""

    points: np.ndarray    # (M, 3) ground points
    forward: np.ndarray   # (M, 3) horizontal unit tangent
    right: np.ndarray     # (M, 3) horizontal unit normal, to the driver's right
    s: np.ndarray         # (M,) arc length, metres


def ground_points(poses: np.ndarray) -> np.ndarray:
    """Road point under each cam0 pose: centre + CAMERA_HEIGHT · down axis (N, 3)."""
    return poses[:, :3, 3] + CAMERA_HEIGHT * poses[:, :3, 1]


def build_road_path(poses: np.ndarray, spacing: float = 0.5) -> RoadPath:
    g = ground_points(poses)
    seg = np.linalg.norm(np.diff(g, axis=0), axis=1)
    keep = np.concatenate([[True], seg > 1e-3])          # drop standing-still duplicates
    g = g[keep]
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(g, axis=0), axis=1))])
    s = np.arange(0.0, arc[-1] + 1e-9, spacing) if arc[-1] > 0 else np.zeros(1)
    pts = np.stack([np.interp(s, arc, g[:, k]) for k in range(3)], axis=1)
    if len(pts) > 1:
        # tangent from a +-2 m window for smooth headings
        w = max(1, int(round(2.0 / spacing)))
        ahead = pts[np.minimum(np.arange(len(pts)) + w, len(pts) - 1)]
        behind = pts[np.maximum(np.arange(len(pts)) - w, 0)]
        fwd = ahead - behind
    else:
        fwd = (poses[:1, :3, 2]).copy()
    fwd[:, 1] = 0.0
    fwd /= np.maximum(np.linalg.norm(fwd, axis=1, keepdims=True), 1e-9)
    right = np.cross(DOWN, fwd)
    return RoadPath(points=pts, forward=fwd, right=right, s=s)


class PathIndex:
    """Nearest road-path sample of any horizontal (x, z) position, via a label raster."""

    def __init__(self, path: RoadPath, margin: float, res: float = 0.25):
        import cv2

        xz = path.points[:, [0, 2]]
        self.path = path
        self.res = res
        self.origin = xz.min(axis=0) - margin
        size = np.ceil((xz.max(axis=0) + margin - self.origin) / res).astype(int) + 1
        self.shape = (int(size[1]), int(size[0]))            # rows = z, cols = x
        ij = self._cells(xz)
        src = np.ones(self.shape, np.uint8)
        src[ij[:, 1], ij[:, 0]] = 0
        dist, labels = cv2.distanceTransformWithLabels(src, cv2.DIST_L2, cv2.DIST_MASK_5,
                                                       labelType=cv2.DIST_LABEL_PIXEL)
        lab_to_sample = np.zeros(labels.max() + 1, np.int64)
        lab_to_sample[labels[ij[:, 1], ij[:, 0]]] = np.arange(len(xz))
        self.nearest = lab_to_sample[labels]                  # (rows, cols) sample index
        self.dist_coarse = dist * res
        self.xz = xz                                          # (N, 2) the samples' x, z (a copy: fancy index)

    def _cells(self, xz: np.ndarray) -> np.ndarray:
        ij = np.round((xz - self.origin) / self.res).astype(np.int64)
        return np.clip(ij, 0, [self.shape[1] - 1, self.shape[0] - 1])

    def query(self, xz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(nearest sample index, horizontal distance in metres) for (N, 2) positions x, z."""
        xz = np.asarray(xz, dtype=np.float64).reshape(-1, 2)
        ij = self._cells(xz)
        k = self.nearest[ij[:, 1], ij[:, 0]]
        # refine among neighbours along the path (the raster label is approximate)
        best_k, best_d = k, np.full(len(k), np.inf)
        P = self.xz
        for off in (-2, -1, 0, 1, 2):
            kk = np.clip(k + off, 0, len(P) - 1)
            d = np.linalg.norm(xz - P[kk], axis=1)
            better = d < best_d
            best_k = np.where(better, kk, best_k)
            best_d = np.where(better, d, best_d)
        return best_k, best_d

    def min_distance(self, xz: np.ndarray) -> float:
        return float(self.query(xz)[1].min()) if len(xz) else np.inf
