"""The procedural town around a trajectory: ground, curbs and buildings here; parked cars, trees, poles and
fences in :mod:`mono_map.data.synth.props`, placed with :mod:`mono_map.data.synth.placement`.

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
from mono_map.data.synth.meshes import MeshBuilder, box
from mono_map.data.synth.placement import (BRICK, STOREFRONT, ObjectTable, Occupancy, box_axes, clear_of_road,
                                           footprint_samples, frame_at)
from mono_map.data.synth.props import add_canopy_trees, add_cars, add_fences, add_hedges, add_trees_and_poles
from mono_map.data.synth.traffic import add_traffic
from mono_map.data.synth.trajectory import PathIndex, RoadPath, build_road_path, town_poses

GROUND_RADIUS = 60.0      # metres of ground kept around the road path
GROUND_RES = 1.0          # ground grid spacing, metres


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
    obj_flags: np.ndarray       # (N,) int32 BLACK | BRICK | STOREFRONT | VAN | LARGE
    obj_origin: np.ndarray      # (N, 3) float64 facade texture origin (a footprint corner at ground level); vehicle: ground centre
    obj_params: np.ndarray      # (N, 4) float32 facade: window spacing, floor height, window width, window height;
    #                             vehicle: forward direction (x, z), length, width (m)
    street: object              # recipe StreetParams
    seed: int
    glass_fraction: float = 0.6 # share of facade windows that are reflective glass (others curtained)
    stats: dict = field(default_factory=dict)
    lane_vehicles: np.ndarray = field(default_factory=lambda: np.zeros((0, 4, 2)))  # (N, 4, 2) x-z footprint
    # corners (world, m) of the vehicles standing in the driving lanes (recipe [traffic]); see traffic.clear_frames
    lane_vehicle_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int32))  # (N,) their object ids
    vehicle_detail: float = 0.0 # share of vehicles with painted details (recipe [cars] detail)

    @property
    def road_edges(self) -> tuple[float, float]:
        """Lateral offsets (m, + = right of the driven lane centre) of the left and right road edges."""
        s = self.street
        return -(1.5 * s.lane_width + s.parking_width), 0.5 * s.lane_width + s.parking_width


def build_town(recipe) -> Town:
    """Deterministic town for a recipe (depends on nothing else)."""
    rng = np.random.default_rng([recipe.seed, 7])
    _, poses = town_poses(recipe)
    path = build_road_path(poses)
    index = PathIndex(path, margin=GROUND_RADIUS + 5.0)
    occ = Occupancy(index)
    mb = MeshBuilder()
    objs = ObjectTable()
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
        add_cars(mb, objs, occ, path, index, rng, recipe, side, counts)
        add_trees_and_poles(mb, objs, occ, path, index, rng, recipe, side, edges[side], counts)
        add_fences(mb, objs, occ, path, index, rng, recipe, side, edges[side], counts)
    for side in (+1, -1):                         # greenery: each from its own random stream, so that a town
        if recipe.trees.canopy > 0:               # without it draws exactly what it drew before
            add_canopy_trees(mb, objs, occ, path, index, np.random.default_rng([recipe.seed, 8, side + 1]), recipe,
                             side, edges[side], counts)
        if recipe.props.hedge_fraction > 0:
            add_hedges(mb, objs, occ, path, index, np.random.default_rng([recipe.seed, 9, side + 1]), recipe, side,
                       edges[side], counts)
    lane_vehicles, lane_ids = np.zeros((0, 4, 2)), np.zeros(0, np.int32)
    if recipe.traffic.enabled():                  # after everything else, from its own random stream
        lane_vehicles, lane_ids = add_traffic(mb, objs, occ, path, index, recipe, counts)

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
        lane_vehicles=lane_vehicles, lane_vehicle_ids=lane_ids, vehicle_detail=recipe.cars.detail,
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


def _add_curbs(mb, path, index, edges, st) -> int:
    """Curb stones along both road edges, 2 m pieces, removed where they would cross another pass's road.
    The pieces' end and mid points are looked up in the path index in one batch (the same per-point results
    as one query per piece, at a fraction of the cost)."""
    step = 2.0
    pieces = []                      # (s0, a, b, mid, unit direction, length) of pieces of a plausible length
    for side, edge in edges.items():
        for s0 in np.arange(0.0, path.s[-1] - step, step):
            k0, p0, f0, r0 = frame_at(path, s0)
            k1, p1, f1, r1 = frame_at(path, s0 + step)
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
        V, F = box(center, box_axes(f, r), [length / 2 + 0.01, (h + 0.1) / 2, 0.125])
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
    k, p, f, r = frame_at(path, s_c)
    center = p + side * r * (near + depth / 2)
    pts = footprint_samples(center, f, r, w / 2, depth / 2)
    if not clear_of_road(index, pts, clearance) or not occ.free(pts):
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
    V, F = box(c, box_axes(f, r), [w / 2, (bottom - top) / 2, depth / 2])
    mb.add(V, F, M.FACADE, oid)
    return True
