"""Traffic in the driving lanes and large vehicles (issue 31): what real KITTI drives beside and behind.

Vehicles stand (they do not move: the town is static) in the adjacent, left lane beside and ahead of the
camera, in the camera's own lane ahead of it, and (``kerb_large_density``) large ones parked at both kerbs
where the parked cars left room. Among them are large vehicles: box trucks, buses, tankers
and semi-trailers (L 7-13 m, W 2.4-2.6 m, H 3.0-4.0 m), a cab + body mesh each.

The trajectory is fixed, so the two lanes are kept clear of the camera differently:

- adjacent lane and kerb: every vehicle's footprint stays :data:`LANE_CLEARANCE` metres from every road-path point
  (every pass of the trajectory, the 120 m lead-in and run-out included): the camera never reaches one;
- own lane: the vehicles stand on the path, so the frames whose camera would be inside one or less than
  :data:`EGO_AHEAD` metres behind it are not rendered (:func:`clear_frames`; training towns only).

World frame: the first cam0 frame (x right, y down, z forward); metres. Everything is drawn from its own
random stream ``(recipe.seed, 31)``, after every other object, so a town without traffic is the town built
before this module existed.
"""

from __future__ import annotations

import numpy as np

from mono_map.data.synth import materials as M
from mono_map.data.synth.meshes import box, cylinder
from mono_map.data.synth.placement import BLACK, LARGE, VAN, box_axes, clear_of_road, footprint_samples, frame_at
from mono_map.data.synth.props import CAR_COLORS, BLACK_PAINT, car_mesh, vehicle_frame
from mono_map.data.synth.recipe import TrafficParams

LANE_CLEARANCE = 1.5     # metres from any road-path point to an adjacent-lane vehicle's footprint
EGO_AHEAD = 3.0          # metres: a rendered frame has no own-lane vehicle closer ahead of the camera than this
EGO_BEHIND = 4.5         # metres of the camera's own car behind the camera
EGO_HALF_WIDTH = 1.2     # metres: half the camera car's width plus a margin

LARGE_KINDS = ("box truck", "bus", "tanker", "semi-trailer")
_LARGE_COLORS = [(0.90, 0.90, 0.88), (0.86, 0.86, 0.84), (0.80, 0.81, 0.83), (0.70, 0.71, 0.72),
                 (0.75, 0.12, 0.10), (0.15, 0.30, 0.60), (0.90, 0.72, 0.15), (0.20, 0.45, 0.25),
                 (0.55, 0.56, 0.58), (0.35, 0.36, 0.40)]
_LARGE_BLACK = 0.03      # black large vehicles are rare


def add_traffic(mb, objs, occ, path, index, recipe, counts) -> tuple[np.ndarray, np.ndarray]:
    """Standing vehicles in the adjacent lane and the camera's own lane (recipe ``[traffic]``).

    Returns the footprints of every lane vehicle, (N, 4, 2) x-z corners (world, metres; corners 0, 1 at its
    front, 2, 3 at its back), for :func:`clear_frames`, and their object ids (N,); updates ``counts``
    (lane_vehicles, large_vehicles).
    """
    tp = recipe.traffic
    st = recipe.street
    rng = np.random.default_rng([recipe.seed, 31])
    feet: list[np.ndarray] = []
    ids: list[int] = []
    counts.setdefault("lane_vehicles", 0)
    counts.setdefault("large_vehicles", 0)
    if tp.adjacent_density > 0:
        s = float(rng.uniform(0, 6))
        while s < path.s[-1]:
            v = _draw_vehicle(rng, tp)
            place = rng.random() < tp.adjacent_density
            oncoming = rng.random() < 0.5
            jitter = float(rng.normal(0, 0.15))
            yaw = float(rng.normal(0, 0.02))
            gap = float(rng.uniform(1.5, 8.0))
            if place:
                lat = max(st.lane_width, LANE_CLEARANCE + v["W"] / 2 + 0.15) + jitter
                foot = _place(mb, objs, occ, path, index, s + v["L"] / 2, -lat, yaw, oncoming, v, LANE_CLEARANCE)
                if foot is not None:
                    feet.append(foot[0])
                    ids.append(foot[1])
                    counts["lane_vehicles"] += 1
                    counts["large_vehicles"] += int(v["kind"] in LARGE_KINDS)
            s += v["L"] + gap if place else float(rng.uniform(5.0, 25.0))
    if tp.ahead_spacing > 0:
        s = float(rng.uniform(0.3, 1.0)) * tp.ahead_spacing
        while s < path.s[-1]:
            v = _draw_vehicle(rng, tp)
            jitter = float(rng.normal(0, 0.1))
            yaw = float(rng.normal(0, 0.015))
            foot = _place(mb, objs, occ, path, index, s + v["L"] / 2, jitter, yaw, False, v, None)
            if foot is not None:
                feet.append(foot[0])
                ids.append(foot[1])
                counts["lane_vehicles"] += 1
                counts["large_vehicles"] += int(v["kind"] in LARGE_KINDS)
            s += v["L"] + tp.ahead_spacing * float(rng.uniform(0.6, 1.4))
    if tp.kerb_large_density > 0:
        large = TrafficParams(large_fraction=1.0)
        for side in (+1, -1):
            centre = 0.5 * st.lane_width + st.parking_width / 2 + 0.1 if side > 0 else \
                1.5 * st.lane_width + st.parking_width / 2 + 0.1
            s = float(rng.uniform(0, 10))
            while s < path.s[-1]:
                v = _draw_vehicle(rng, large)
                place = rng.random() < tp.kerb_large_density
                jitter = float(rng.normal(0, 0.1))
                yaw = float(rng.normal(0, 0.02))
                if place:
                    lat = max(centre, LANE_CLEARANCE + v["W"] / 2 + 0.15) + jitter
                    foot = _place(mb, objs, occ, path, index, s + v["L"] / 2, side * lat, yaw, side < 0, v,
                                  LANE_CLEARANCE)
                    if foot is not None:
                        feet.append(foot[0])
                        ids.append(foot[1])
                        counts["lane_vehicles"] += 1
                        counts["large_vehicles"] += 1
                s += v["L"] + float(rng.uniform(2.0, 12.0))
    return np.array(feet, np.float64).reshape(-1, 4, 2), np.array(ids, np.int32)


def _draw_vehicle(rng, tp) -> dict:
    """Kind, size (m) and colour of one lane vehicle (the same draws whatever the kind)."""
    u = rng.random()
    k = int(rng.integers(len(LARGE_KINDS)))
    dims = rng.random(3)
    black = rng.random()
    cidx = int(rng.integers(1 << 16))
    if u < tp.large_fraction:
        kind = LARGE_KINDS[k]
        lo, hi = {"box truck": (7.0, 10.0), "bus": (10.0, 13.0), "tanker": (9.0, 12.0),
                  "semi-trailer": (11.0, 13.0)}[kind]
        hlo, hhi = {"box truck": (3.2, 4.0), "bus": (3.0, 3.4), "tanker": (3.0, 3.6),
                    "semi-trailer": (3.6, 4.0)}[kind]
        L, W, H = lo + (hi - lo) * dims[0], 2.4 + 0.2 * dims[1], hlo + (hhi - hlo) * dims[2]
        is_black = black < _LARGE_BLACK
        color = BLACK_PAINT if is_black else _LARGE_COLORS[cidx % len(_LARGE_COLORS)]
    else:
        kind = "van" if u < tp.large_fraction + (1 - tp.large_fraction) * tp.van_fraction else "car"
        if kind == "van":
            L, W, H = 5.0 + 1.8 * dims[0], 1.95 + 0.25 * dims[1], 2.2 + 0.7 * dims[2]
        else:
            L, W, H = 3.9 + 0.9 * dims[0], 1.72 + 0.14 * dims[1], 1.38 + 0.17 * dims[2]
        is_black = black < 0.1
        color = BLACK_PAINT if is_black else CAR_COLORS[cidx % len(CAR_COLORS)]
    return {"kind": kind, "L": float(L), "W": float(W), "H": float(H), "black": bool(is_black), "color": color}


def _place(mb, objs, occ, path, index, s_c, lat, yaw, reverse, v, clearance):
    """One vehicle centred at arc length ``s_c``, lateral offset ``lat`` (m, + = right); (its footprint
    corners (4, 2), its object id) or None where it does not fit (another object there, or closer than ``clearance``
    metres to the road path when ``clearance`` is given)."""
    k, p, f, r = frame_at(path, s_c)
    c, sn = np.cos(yaw), np.sin(yaw)
    f2 = c * f + sn * r
    if reverse:
        f2 = -f2
    r2 = np.cross([0.0, 1.0, 0.0], f2)
    center = p + r * lat
    pts = footprint_samples(center, f2, r2, v["L"] / 2, v["W"] / 2, step=0.4)
    if clearance is not None and not clear_of_road(index, pts, clearance):
        return None
    if not occ.free(pts):
        return None
    occ.mark(pts)
    flags = (BLACK if v["black"] else 0) | (VAN if v["kind"] == "van" else 0) | (LARGE if v["kind"] in LARGE_KINDS else 0)
    oid = objs.add(v["color"], flags, *vehicle_frame(center, f2, v["L"], v["W"]))
    if v["kind"] in LARGE_KINDS:
        large_vehicle_mesh(mb, oid, center, f2, r2, v["L"], v["W"], v["H"], v["kind"])
    else:
        car_mesh(mb, oid, center, f2, r2, v["L"], v["W"], v["H"], v["kind"] == "van")
    corners = center[None, :] + np.array([[a * v["L"] / 2, b * v["W"] / 2] for a, b in
                                          ((1, 1), (1, -1), (-1, -1), (-1, 1))]) @ np.stack([f2, r2])
    return corners[:, [0, 2]], oid


def large_vehicle_mesh(mb, oid, ground_center, f, r, L, W, H, kind) -> None:
    """A box truck, bus, tanker or semi-trailer standing on the ground at ``ground_center``, facing ``f``
    (unit, world): a cab at the +f end (glass windscreen) and a body behind it; six or more wheels."""
    axes = box_axes(f, r)
    up = np.array([0.0, -1.0, 0.0])
    clearance = 0.45
    wheel_r = 0.5
    if kind == "bus":
        body_h = H - clearance
        V, F = box(ground_center + up * (clearance + body_h / 2), axes, [L / 2, body_h / 2, W / 2])
        mat = np.full(12, M.CAR_PAINT, np.uint8)
        mat[[8, 9]] = M.CAR_GLASS                                     # windscreen
        mb.add_tagged(V, F, mat, oid)
        band_lo, band_hi = 1.15, H - 0.45                             # window band along both sides
        V, F = box(ground_center + up * ((band_lo + band_hi) / 2) - f * 0.4, axes,
                   [L / 2 - 1.2, (band_hi - band_lo) / 2, W / 2 + 0.02])
        mat = np.full(12, M.CAR_PAINT, np.uint8)
        mat[[0, 1, 2, 3]] = M.CAR_GLASS
        mb.add_tagged(V, F, mat, oid)
        axles = (L / 2 - 2.4, -L / 2 + 3.0)
    else:
        cab_l = 2.3
        cab_h = min(H - 0.3, 3.0) - clearance
        cab_c = ground_center + f * (L / 2 - cab_l / 2) + up * (clearance + cab_h / 2)
        V, F = box(cab_c, axes, [cab_l / 2, cab_h / 2, W / 2 - 0.03])
        mat = np.full(12, M.CAR_PAINT, np.uint8)
        mat[[8, 9]] = M.CAR_GLASS
        mb.add_tagged(V, F, mat, oid)
        body_l = L - cab_l - 0.3
        body_c = ground_center - f * (L / 2 - body_l / 2)
        if kind == "tanker":
            chassis_h = 0.5
            V, F = box(body_c + up * (clearance + chassis_h / 2), axes, [body_l / 2, chassis_h / 2, W / 2 - 0.25])
            mb.add(V, F, M.METAL, oid)
            rad = min(W / 2, (H - clearance - chassis_h) / 2)
            base = body_c - f * (body_l / 2) + up * (H - rad)
            V, F = cylinder(base, f, rad, body_l, segments=16)
            V2, F2 = cylinder(base, -f, rad, 0.02, segments=16)          # the rear cap
            mb.add(V, F, M.METAL, oid)
            mb.add(V2, F2, M.METAL, oid)
        else:
            floor = clearance + (0.8 if kind == "semi-trailer" else 0.5)
            body_h = H - floor
            V, F = box(body_c + up * (floor + body_h / 2), axes, [body_l / 2, body_h / 2, W / 2])
            mb.add(V, F, M.CAR_PAINT, oid)
            V, F = box(body_c + up * (clearance + (floor - clearance) / 2), axes,
                       [body_l / 2, (floor - clearance) / 2, W / 2 - 0.3])
            mb.add(V, F, M.METAL, oid)                                    # chassis under the box
        axles = (L / 2 - 1.3, -L / 2 + 2.2, -L / 2 + 1.0)
    for a in axles:
        for b in (-1, 1):
            wc = ground_center + f * a + r * b * (W / 2 - 0.2) + up * wheel_r - r * b * 0.15
            V, F = cylinder(wc, r * b, wheel_r, 0.3, segments=12)
            mb.add(V, F, M.TYRE, oid)


def clear_frames(footprints: np.ndarray, poses: np.ndarray) -> np.ndarray:
    """(n,) bool: frames whose camera car (from :data:`EGO_BEHIND` metres behind the camera to
    :data:`EGO_AHEAD` ahead of it, :data:`EGO_HALF_WIDTH` to each side; x-z plane) overlaps no vehicle
    footprint. ``footprints`` (N, 4, 2) x-z corners (world, m); ``poses`` (n, 4, 4) T_world_cam0."""
    poses = np.asarray(poses, np.float64)
    out = np.ones(len(poses), bool)
    if len(footprints) == 0:
        return out
    fp = np.asarray(footprints, np.float64)
    for i, T in enumerate(poses):
        c = T[[0, 2], 3]
        f = T[[0, 2], 2] / np.linalg.norm(T[[0, 2], 2])
        r = np.array([f[1], -f[0]])                   # x right of z forward, seen from above (y down)
        ego = np.stack([c + f * a + r * b for a, b in ((EGO_AHEAD, EGO_HALF_WIDTH), (EGO_AHEAD, -EGO_HALF_WIDTH),
                                                         (-EGO_BEHIND, -EGO_HALF_WIDTH),
                                                         (-EGO_BEHIND, EGO_HALF_WIDTH))])
        out[i] = not rectangles_overlap(ego, fp).any()
    return out


def rectangles_overlap(rect: np.ndarray, rects: np.ndarray) -> np.ndarray:
    """(N,) bool: whether the rectangle ``rect`` (4, 2) overlaps each of ``rects`` (N, 4, 2) (corners in
    order around each; separating-axis test, touching counts as overlap)."""
    rects = np.asarray(rects, np.float64)
    a = np.broadcast_to(np.asarray(rect, np.float64), rects.shape)
    hit = np.ones(len(rects), bool)
    for poly in (a, rects):
        for e in range(2):                                    # two edge directions of each rectangle
            d = poly[:, e + 1] - poly[:, e]
            n = np.stack([-d[:, 1], d[:, 0]], 1)
            pa = np.einsum("nkj,nj->nk", a, n)
            pb = np.einsum("nkj,nj->nk", rects, n)
            hit &= (pa.max(1) >= pb.min(1)) & (pb.max(1) >= pa.min(1))
    return hit
