"""The procedural town around a trajectory: ground, curbs, buildings, parked cars, trees, poles, fences.

Everything is a triangle mesh in the world frame (first cam0 frame: x right, y down,
z forward; metres) with a material id and an object id per triangle; textures are
computed later from the hit point (mono_map.data.synth.materials).  The road corridor
of the whole trajectory (every pass, including loop closures) is kept clear: every
object is tested against the distance to the nearest road-path sample.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from mono_map.data.synth import materials as M
from mono_map.data.synth.meshes import MeshBuilder, blob, box, cylinder
from mono_map.data.synth.trajectory import PathIndex, RoadPath, build_road_path, town_poses

GROUND_RADIUS = 60.0      # metres of ground kept around the road path
GROUND_RES = 1.0          # ground grid spacing, metres

# object flags
BLACK = 1
BRICK = 2
STOREFRONT = 4
VAN = 8


@dataclass
class Town:
    """Triangle soup + per-triangle material/object ids + per-object parameters."""

    vertices: np.ndarray        # (V, 3) float32 world
    triangles: np.ndarray       # (T, 3) int32
    tri_material: np.ndarray    # (T,) uint8, mono_map.data.synth.materials ids
    tri_object: np.ndarray      # (T,) int32, -1 = none
    tri_junction: np.ndarray    # (T,) bool, ground triangles where two road passes meet (no markings)
    vert_ls: np.ndarray         # (V, 2) float32 ground attributes: lateral offset l (m, + = right), arc length s
    obj_color: np.ndarray       # (N, 3) float32 base albedo
    obj_flags: np.ndarray       # (N,) int32 BLACK | BRICK | STOREFRONT | VAN
    obj_origin: np.ndarray      # (N, 3) float64 facade texture origin (a footprint corner at ground level)
    obj_params: np.ndarray      # (N, 4) float32 facade: window spacing, floor height, window width, window height
    street: object              # recipe StreetParams
    seed: int
    glass_fraction: float = 0.6 # share of facade windows that are reflective glass (others curtained)
    stats: dict = field(default_factory=dict)

    @property
    def road_edges(self) -> tuple[float, float]:
        """Lateral offsets (m, + = right of the driven lane centre) of the left and right road edges."""
        s = self.street
        return -(1.5 * s.lane_width + s.parking_width), 0.5 * s.lane_width + s.parking_width


class _Objects:
    def __init__(self):
        self.color, self.flags, self.origin, self.params = [], [], [], []

    def add(self, color, flags=0, origin=(0, 0, 0), params=(0, 0, 0, 0)) -> int:
        self.color.append(color)
        self.flags.append(flags)
        self.origin.append(origin)
        self.params.append(params)
        return len(self.color) - 1


class _Occupancy:
    """Coarse raster (0.5 m) of footprints already used, so revisited streets are not built twice."""

    def __init__(self, index: PathIndex, res: float = 0.5):
        self.origin = index.origin
        self.res = res
        rows = int(index.shape[0] * index.res / res) + 2
        cols = int(index.shape[1] * index.res / res) + 2
        self.grid = np.zeros((rows, cols), bool)

    def _ij(self, xz):
        ij = np.floor((xz - self.origin) / self.res).astype(np.int64)
        return np.clip(ij, 0, [self.grid.shape[1] - 1, self.grid.shape[0] - 1])

    def free(self, xz) -> bool:
        ij = self._ij(xz)
        return not self.grid[ij[:, 1], ij[:, 0]].any()

    def mark(self, xz) -> None:
        ij = self._ij(xz)
        self.grid[ij[:, 1], ij[:, 0]] = True


def _footprint_samples(center, f, r, half_len, half_wid, step=0.5):
    a = np.arange(-half_len, half_len + 1e-9, step)
    b = np.arange(-half_wid, half_wid + 1e-9, step)
    a = np.unique(np.concatenate([a, [half_len]]))
    b = np.unique(np.concatenate([b, [half_wid]]))
    A, B = np.meshgrid(a, b)
    pts = center[None, :] + A.reshape(-1, 1) * f[None, :] + B.reshape(-1, 1) * r[None, :]
    return pts[:, [0, 2]]


def build_town(recipe) -> Town:
    """Deterministic town for a recipe (depends on nothing else)."""
    rng = np.random.default_rng([recipe.seed, 7])
    _, poses = town_poses(recipe)
    path = build_road_path(poses)
    index = PathIndex(path, margin=GROUND_RADIUS + 5.0)
    occ = _Occupancy(index)
    mb = MeshBuilder()
    objs = _Objects()
    st = recipe.street
    left_edge = 1.5 * st.lane_width + st.parking_width
    right_edge = 0.5 * st.lane_width + st.parking_width
    edges = {+1: right_edge, -1: left_edge}

    vert_ls = _add_ground(mb, path, index)
    ground_tris = mb.arrays()[1].shape[0]
    n_curb = _add_curbs(mb, path, index, edges, st)
    counts = {"buildings": 0, "cars": 0, "black_cars": 0, "trees": 0, "poles": 0, "fences": 0}
    for side in (+1, -1):
        _add_buildings(mb, objs, occ, path, index, rng, recipe, side, edges[side], counts)
    for side in (+1, -1):
        _add_cars(mb, objs, occ, path, index, rng, recipe, side, counts)
        _add_trees_and_poles(mb, objs, occ, path, index, rng, recipe, side, edges[side], counts)
        _add_fences(mb, objs, occ, path, index, rng, recipe, side, edges[side], counts)

    V, F, mat, obj = mb.arrays()
    ls = np.zeros((len(V), 2), np.float32)
    ls[: len(vert_ls)] = vert_ls
    s_tri = ls[F[:ground_tris], 1]
    junction = np.zeros(len(F), bool)
    junction[:ground_tris] = (s_tri.max(axis=1) - s_tri.min(axis=1)) > 3.0
    n = len(objs.color)
    counts.update(triangles=int(len(F)), curbs=n_curb, path_length_m=float(path.s[-1]))
    return Town(
        vertices=V, triangles=F, tri_material=mat, tri_object=obj, tri_junction=junction, vert_ls=ls,
        obj_color=np.array(objs.color, np.float32).reshape(n, 3),
        obj_flags=np.array(objs.flags, np.int32).reshape(n),
        obj_origin=np.array(objs.origin, np.float64).reshape(n, 3),
        obj_params=np.array(objs.params, np.float32).reshape(n, 4),
        street=st, seed=recipe.seed, glass_fraction=recipe.buildings.glass_fraction, stats=counts,
    )


# ----------------------------------------------------------------------------- ground

def _add_ground(mb: MeshBuilder, path: RoadPath, index: PathIndex) -> np.ndarray:
    """Height-field grid (GROUND_RES) within GROUND_RADIUS of the path; heights from the nearest path sample."""
    lo = index.origin
    hi = index.origin + index.res * np.array([index.shape[1], index.shape[0]])
    xs = np.arange(lo[0], hi[0] + GROUND_RES, GROUND_RES)
    zs = np.arange(lo[1], hi[1] + GROUND_RES, GROUND_RES)
    X, Z = np.meshgrid(xs, zs)                      # (nz, nx)
    nz, nx = X.shape
    xz = np.stack([X.ravel(), Z.ravel()], 1)
    k, d = index.query(xz)
    # keep cells whose 4 corners are all within the radius (+ a cell)
    near = (d < GROUND_RADIUS + GROUND_RES).reshape(nz, nx)
    cell = near[:-1, :-1] & near[1:, :-1] & near[:-1, 1:] & near[1:, 1:]
    ci, cj = np.nonzero(cell)
    v00 = ci * nx + cj
    v01 = v00 + 1
    v10 = v00 + nx
    v11 = v10 + 1
    F = np.concatenate([np.stack([v00, v10, v11], 1), np.stack([v00, v11, v01], 1)])
    used = np.unique(F)
    remap = np.full(nz * nx, -1, np.int64)
    remap[used] = np.arange(len(used))
    F = remap[F]
    xz_u, k_u = xz[used], k[used]
    P = path.points[k_u]
    V = np.stack([xz_u[:, 0], P[:, 1], xz_u[:, 1]], 1)
    dvec = V - P
    l = np.einsum("ij,ij->i", dvec, path.right[k_u])
    s = path.s[k_u] + np.einsum("ij,ij->i", dvec, path.forward[k_u])
    mb.add(V, F, M.GROUND)
    return np.stack([l, s], 1).astype(np.float32)


def _clear(index: PathIndex, xz: np.ndarray, clearance: float) -> bool:
    return index.min_distance(xz) >= clearance


def _frame_at(path: RoadPath, s: float):
    k = int(np.clip(np.searchsorted(path.s, s), 0, len(path.s) - 1))
    return k, path.points[k], path.forward[k], path.right[k]


def _axes(f, r):
    return np.stack([f, np.array([0.0, 1.0, 0.0]), r], 1)


def _add_curbs(mb, path, index, edges, st) -> int:
    """Curb stones along both road edges, 2 m pieces, removed where they would cross another pass's road.
    The pieces' end and mid points are looked up in the path index in one batch (the same per-point results
    as one query per piece, at a fraction of the cost)."""
    step = 2.0
    pieces = []                      # (s0, a, b, mid, unit direction, length) of pieces of a plausible length
    for side, edge in edges.items():
        for s0 in np.arange(0.0, path.s[-1] - step, step):
            k0, p0, f0, r0 = _frame_at(path, s0)
            k1, p1, f1, r1 = _frame_at(path, s0 + step)
            a = p0 + side * r0 * (edge + 0.125)
            b = p1 + side * r1 * (edge + 0.125)
            mid = (a + b) / 2
            f = b - a
            length = np.linalg.norm(f)
            if length < 0.5 or length > 3.5:
                continue
            f /= length
            pieces.append((s0, a, b, mid, f, length))
    if not pieces:
        return 0
    ends = np.array([(a, b, mid) for _, a, b, mid, _, _ in pieces])          # (pieces, 3 points, x y z)
    kk, dd = index.query(ends[:, :, [0, 2]].reshape(-1, 2))
    kk, dd = kk.reshape(-1, 3), dd.reshape(-1, 3)
    n = 0
    for (s0, a, b, mid, f, length), k3, d3 in zip(pieces, kk, dd):
        own = np.abs(path.s[k3] - (s0 + step / 2)) < 15.0
        if (d3 < np.where(own, min(edges.values()) - 0.1, edges[-1] + 0.3)).any():
            continue
        r = np.cross([0.0, 1.0, 0.0], f)
        h = st.curb_height
        center = mid + np.array([0.0, -(h - 0.1) / 2, 0.0])
        V, F = box(center, _axes(f, r), [length / 2 + 0.01, (h + 0.1) / 2, 0.125])
        mb.add(V, F, M.CURB)
        n += 1
    return n


# ----------------------------------------------------------------------------- buildings

_PLASTER = [(0.78, 0.74, 0.66), (0.85, 0.82, 0.74), (0.70, 0.70, 0.68), (0.80, 0.68, 0.55),
            (0.62, 0.66, 0.70), (0.88, 0.86, 0.80), (0.72, 0.60, 0.50), (0.60, 0.62, 0.58)]
_BRICK = [(0.55, 0.27, 0.20), (0.62, 0.36, 0.26), (0.48, 0.30, 0.24), (0.66, 0.50, 0.38)]


def _add_buildings(mb, objs, occ, path, index, rng, recipe, side, edge, counts):
    bp = recipe.buildings
    st = recipe.street
    s = float(rng.uniform(0, 5))
    while s < path.s[-1]:
        w = float(rng.uniform(bp.width_min, bp.width_max))
        gap = float(rng.uniform(1.0, 6.0))
        place = rng.random() < bp.density
        depth = float(rng.uniform(bp.depth_min, bp.depth_max))
        height = float(rng.uniform(bp.height_min, bp.height_max))
        setback = float(rng.uniform(0.3, max(bp.setback_max, 0.3)))
        brick = rng.random() < bp.brick_fraction
        store = rng.random() < bp.storefront_fraction
        cidx = int(rng.integers(0, 1 << 30))
        back = rng.random() < 0.5
        back_h = float(rng.uniform(bp.height_max, bp.height_max * 1.8))
        back_off = float(rng.uniform(4.0, 15.0))
        if place:
            near = edge + st.sidewalk_width + setback
            if _place_building(mb, objs, occ, path, index, s + w / 2, side, near, w, depth, height,
                               brick, store, cidx, bp.glass_fraction, min(path_edge(st)) + st.sidewalk_width - 0.5):
                counts["buildings"] += 1
            if back:
                near2 = near + depth + back_off
                if _place_building(mb, objs, occ, path, index, s + w / 2, side, near2, w * 1.3, depth, back_h,
                                   False, False, cidx + 1, bp.glass_fraction, 12.0):
                    counts["buildings"] += 1
        s += w + gap


def path_edge(st):
    return (1.5 * st.lane_width + st.parking_width, 0.5 * st.lane_width + st.parking_width)


def _place_building(mb, objs, occ, path, index, s_c, side, near, w, depth, height, brick, store, cidx,
                    glass_fraction, clearance) -> bool:
    k, p, f, r = _frame_at(path, s_c)
    center = p + side * r * (near + depth / 2)
    pts = _footprint_samples(center, f, r, w / 2, depth / 2)
    if not _clear(index, pts, clearance) or not occ.free(pts):
        return False
    occ.mark(pts)
    palette = _BRICK if brick else _PLASTER
    base = np.array(palette[cidx % len(palette)], np.float32) * np.float32(0.9 + 0.2 * ((cidx >> 8) % 97) / 96)
    floor_h = 3.0 + 0.4 * ((cidx >> 4) % 3) / 2
    n_win = max(1, int(round(w / (2.6 + 0.8 * ((cidx >> 12) % 5) / 4))))
    spacing = w / n_win
    win_w = min(spacing * 0.55, 1.6)
    win_h = 1.3 + 0.4 * ((cidx >> 16) % 3) / 2
    # windows are glass with probability glass_fraction: encoded per building in the colour hash
    flags = (BRICK if brick else 0) | (STOREFRONT if store else 0)
    origin = center - f * w / 2 - side * r * depth / 2
    origin = np.array([origin[0], p[1], origin[2]])
    oid = objs.add(tuple(base), flags, tuple(origin), (spacing, floor_h, win_w, win_h))
    bottom = p[1] + 0.6                      # sink 0.6 m into the ground (slopes)
    top = p[1] - height
    c = np.array([center[0], (bottom + top) / 2, center[2]])
    V, F = box(c, _axes(f, r), [w / 2, (bottom - top) / 2, depth / 2])
    mb.add(V, F, M.FACADE, oid)
    return True


# ----------------------------------------------------------------------------- cars

_CAR_COLORS = [(0.85, 0.85, 0.85), (0.62, 0.63, 0.65), (0.35, 0.36, 0.38), (0.12, 0.18, 0.38),
               (0.55, 0.08, 0.07), (0.10, 0.26, 0.16), (0.72, 0.66, 0.52), (0.90, 0.90, 0.88),
               (0.25, 0.25, 0.27), (0.45, 0.50, 0.60)]
_BLACK_PAINT = (0.025, 0.025, 0.03)


def _add_cars(mb, objs, occ, path, index, rng, recipe, side, counts):
    cp = recipe.cars
    st = recipe.street
    lat = 0.5 * st.lane_width + st.parking_width / 2 + 0.1 if side > 0 else \
        1.5 * st.lane_width + st.parking_width / 2 + 0.1
    s = float(rng.uniform(0, 4))
    while s < path.s[-1]:
        van = rng.random() < cp.van_fraction
        L = float(rng.uniform(5.0, 6.8) if van else rng.uniform(3.9, 4.8))
        W = float(rng.uniform(1.95, 2.2) if van else rng.uniform(1.72, 1.86))
        H = float(rng.uniform(2.2, 2.9) if van else rng.uniform(1.38, 1.55))
        black = rng.random() < cp.black_fraction
        color = _BLACK_PAINT if black else _CAR_COLORS[int(rng.integers(len(_CAR_COLORS)))]
        place = rng.random() < cp.density
        jitter = float(rng.normal(0, 0.12))
        yaw = float(rng.normal(0, 0.03))
        gap = float(rng.uniform(0.8, 3.0))
        if place:
            k, p, f, r = _frame_at(path, s + L / 2)
            c, sn = np.cos(yaw), np.sin(yaw)
            f2 = c * f + sn * r
            r2 = np.cross([0.0, 1.0, 0.0], f2)
            center = p + side * r * (lat + jitter)
            pts = _footprint_samples(center, f2, r2, L / 2, W / 2, step=0.4)
            if _clear(index, pts, 1.8) and occ.free(pts):
                occ.mark(pts)
                flags = (BLACK if black else 0) | (VAN if van else 0)
                oid = objs.add(color, flags)
                _car_mesh(mb, oid, center, f2, r2, L, W, H, van)
                counts["cars"] += 1
                counts["black_cars"] += int(black)
        s += L + gap if place else float(rng.uniform(4.0, 9.0))


def _car_mesh(mb, oid, ground_center, f, r, L, W, H, van):
    axes = _axes(f, r)
    up = np.array([0.0, -1.0, 0.0])
    clearance = 0.28
    if van:
        body_h = H - clearance
        c = ground_center + up * (clearance + body_h / 2) + f * 0.0
        V, F = box(c, axes, [L / 2 - 0.9, body_h / 2, W / 2])          # cargo box (rear)
        V[:, :] += f * (-0.9)
        mb.add(V, F, M.CAR_PAINT, oid)
        cab_h = body_h * 0.8
        c2 = ground_center + up * (clearance + cab_h / 2) + f * (L / 2 - 0.9)
        V, F = box(c2, axes, [0.9, cab_h / 2, W / 2 - 0.03])
        mat = np.full(12, M.CAR_PAINT, np.uint8)
        mat[[8, 9]] = M.CAR_GLASS                    # +f face: windscreen
        mb.add_tagged(V, F, mat, oid)
    else:
        body_h = 0.55 + 0.25 * (H - 1.38) / 0.17 * 0.5
        c = ground_center + up * (clearance + body_h / 2)
        V, F = box(c, axes, [L / 2, body_h / 2, W / 2])
        mb.add(V, F, M.CAR_PAINT, oid)
        cab_h = H - clearance - body_h
        c2 = ground_center + up * (clearance + body_h + cab_h / 2) - f * (L * 0.06)
        V, F = box(c2, axes, [L * 0.27, cab_h / 2, W / 2 - 0.08])
        # slant the windscreen / rear window: pull the top corners inwards along f
        top = (V - c2) @ up > 0
        V[top] -= np.outer(np.sign((V[top] - c2) @ f), f) * 0.35
        mat = np.full(12, M.CAR_GLASS, np.uint8)
        mat[[4, 5]] = M.CAR_PAINT                    # roof
        mb.add_tagged(V, F, mat, oid)
    for a in (-1, 1):
        for b in (-1, 1):
            wc = ground_center + f * a * (L / 2 - 0.8) + r * b * (W / 2 - 0.12) + up * 0.33 - r * b * 0.11
            V, F = cylinder(wc, r * b, 0.33, 0.22, segments=10)
            mb.add(V, F, M.TYRE, oid)


# ----------------------------------------------------------------------------- trees, poles, fences

def _add_trees_and_poles(mb, objs, occ, path, index, rng, recipe, side, edge, counts):
    tp = recipe.trees
    pp = recipe.props
    up = np.array([0.0, -1.0, 0.0])
    s = float(rng.uniform(0, tp.spacing))
    while s < path.s[-1]:
        crown = float(rng.uniform(1.4, 2.8))
        trunk_h = float(rng.uniform(2.6, 4.0)) + 0.3 * crown
        trunk_r = float(rng.uniform(0.1, 0.2))
        lat = edge + float(rng.uniform(0.7, 1.4))
        tree_rng = np.random.default_rng(int(rng.integers(1 << 31)))
        tint = float(rng.uniform(0.75, 1.2))
        if rng.random() < tp.density:
            k, p, f, r = _frame_at(path, s)
            base = p + side * r * lat
            c = base + up * (trunk_h + 0.6 * crown)
            ring = c[None] + crown * np.array([f, -f, r, -r, 0.7 * (f + r), 0.7 * (f - r), -0.7 * (f + r), -0.7 * (f - r)])
            if _clear(index, base[None, [0, 2]], edge - 0.2) and _clear(index, ring[:, [0, 2]], 2.2) \
                    and occ.free(base[None, [0, 2]]):
                occ.mark(base[None, [0, 2]])
                oid = objs.add((0.20 * tint, 0.30 * tint, 0.10 * tint))
                V, F = cylinder(base + up * -0.2, up, trunk_r, trunk_h + 0.2 + 0.3 * crown, segments=7)
                mb.add(V, F, M.TRUNK, oid)
                V, F = blob(c, [crown, crown * 0.85, crown], tree_rng)
                mb.add(V, F, M.FOLIAGE, oid)
                counts["trees"] += 1
        s += tp.spacing * float(rng.uniform(0.7, 1.3))
    s = float(rng.uniform(0, pp.pole_spacing))
    while s < path.s[-1]:
        k, p, f, r = _frame_at(path, s)
        height = float(rng.uniform(6.5, 8.5))
        base = p + side * r * (edge + 0.45)
        if _clear(index, base[None, [0, 2]], edge - 0.1) and occ.free(base[None, [0, 2]]):
            occ.mark(base[None, [0, 2]])
            oid = objs.add((0.38, 0.39, 0.40))
            V, F = cylinder(base + up * -0.2, up, 0.09, height + 0.2, segments=8)
            mb.add(V, F, M.METAL, oid)
            arm_c = base + up * (height - 0.1) - side * r * 0.9
            V, F = box(arm_c, _axes(f, r), [0.05, 0.05, 0.95])
            mb.add(V, F, M.METAL, oid)
            V, F = box(arm_c - side * r * 0.8 + up * -0.1, _axes(f, r), [0.18, 0.07, 0.3])
            mb.add(V, F, M.LAMP, oid)
            counts["poles"] += 1
        s += pp.pole_spacing * float(rng.uniform(0.8, 1.2))


_FENCE_COLORS = [(0.45, 0.32, 0.20), (0.55, 0.45, 0.32), (0.30, 0.32, 0.30), (0.62, 0.60, 0.55)]


def _add_fences(mb, objs, occ, path, index, rng, recipe, side, edge, counts):
    """Fence panels along the back of the sidewalk where no building stands."""
    pp = recipe.props
    st = recipe.street
    lat = edge + st.sidewalk_width + 0.15
    step = 2.5
    s = 0.0
    while s < path.s[-1]:
        block = 25.0
        on = rng.random() < pp.fence_fraction
        height = float(rng.uniform(1.0, 1.8))
        color = _FENCE_COLORS[int(rng.integers(len(_FENCE_COLORS)))]
        oid = None
        if on:
            for s0 in np.arange(s, min(s + block, path.s[-1] - step), step):
                k0, p0, f0, r0 = _frame_at(path, s0)
                k1, p1, f1, r1 = _frame_at(path, s0 + step)
                a = p0 + side * r0 * lat
                b = p1 + side * r1 * lat
                f = b - a
                length = np.linalg.norm(f)
                if length < 1.0 or length > 4.0:
                    continue
                f /= length
                r = np.cross([0.0, 1.0, 0.0], f)
                mid = (a + b) / 2
                pts = np.stack([a, mid, b])[:, [0, 2]]
                inner = np.stack([0.75 * a + 0.25 * b, mid, 0.25 * a + 0.75 * b])[:, [0, 2]]
                if not _clear(index, pts, edge + st.sidewalk_width - 0.3) or not occ.free(inner):
                    continue
                occ.mark(inner)
                if oid is None:
                    oid = objs.add(color)
                    counts["fences"] += 1
                c = mid + np.array([0.0, -(height - 0.2) / 2, 0.0])
                V, F = box(c, _axes(f, r), [length / 2, (height + 0.2) / 2, 0.03])
                mb.add(V, F, M.FENCE, oid)
        s += block
