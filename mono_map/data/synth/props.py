"""The props of the procedural town (:mod:`mono_map.data.synth.town`): parked cars, trees, street lamps and
fences on both sides of the road, and greenery (hedges, canopy trees over the road), as triangle meshes with a
material and an object id per triangle. World frame: the first cam0 frame (x right, y down, z forward); metres.
"""

from __future__ import annotations

import numpy as np

from mono_map.data.synth import materials as M
from mono_map.data.synth.meshes import blob, box, cylinder
from mono_map.data.synth.placement import BLACK, VAN, box_axes, clear_of_road, footprint_samples, frame_at

CAR_COLORS = [(0.85, 0.85, 0.85), (0.62, 0.63, 0.65), (0.35, 0.36, 0.38), (0.12, 0.18, 0.38),
               (0.55, 0.08, 0.07), (0.10, 0.26, 0.16), (0.72, 0.66, 0.52), (0.90, 0.90, 0.88),
               (0.25, 0.25, 0.27), (0.45, 0.50, 0.60)]
BLACK_PAINT = (0.025, 0.025, 0.03)


def add_cars(mb, objs, occ, path, index, rng, recipe, side, counts):
    """Parked cars and vans in the parking lane on ``side`` (+1 right, -1 left), black ones among them."""
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
        color = BLACK_PAINT if black else CAR_COLORS[int(rng.integers(len(CAR_COLORS)))]
        place = rng.random() < cp.density
        jitter = float(rng.normal(0, 0.12))
        yaw = float(rng.normal(0, 0.03))
        gap = float(rng.uniform(0.8, 3.0))
        if place:
            k, p, f, r = frame_at(path, s + L / 2)
            c, sn = np.cos(yaw), np.sin(yaw)
            f2 = c * f + sn * r
            r2 = np.cross([0.0, 1.0, 0.0], f2)
            center = p + side * r * (lat + jitter)
            pts = footprint_samples(center, f2, r2, L / 2, W / 2, step=0.4)
            if clear_of_road(index, pts, 1.8) and occ.free(pts):
                occ.mark(pts)
                flags = (BLACK if black else 0) | (VAN if van else 0)
                oid = objs.add(color, flags, *vehicle_frame(center, f2, L, W))
                car_mesh(mb, oid, center, f2, r2, L, W, H, van)
                counts["cars"] += 1
                counts["black_cars"] += int(black)
        s += L + gap if place else float(rng.uniform(4.0, 9.0))


def vehicle_frame(ground_center, f, L: float, W: float) -> tuple[tuple, tuple]:
    """A vehicle's (origin, params) in the object table: its ground centre (world m) and (forward x, forward z,
    length, width) — the frame of its painted details (materials.surface)."""
    return tuple(float(v) for v in ground_center), (float(f[0]), float(f[2]), float(L), float(W))


def car_mesh(mb, oid, ground_center, f, r, L, W, H, van):
    axes = box_axes(f, r)
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


def add_trees_and_poles(mb, objs, occ, path, index, rng, recipe, side, edge, counts):
    """Trees and street lamps on the sidewalk beyond the road edge ``edge`` (metres) on ``side``."""
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
            k, p, f, r = frame_at(path, s)
            base = p + side * r * lat
            c = base + up * (trunk_h + 0.6 * crown)
            ring = c[None] + crown * np.array([f, -f, r, -r, 0.7 * (f + r), 0.7 * (f - r), -0.7 * (f + r), -0.7 * (f - r)])
            if clear_of_road(index, base[None, [0, 2]], edge - 0.2) and clear_of_road(index, ring[:, [0, 2]], 2.2) \
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
        k, p, f, r = frame_at(path, s)
        height = float(rng.uniform(6.5, 8.5))
        base = p + side * r * (edge + 0.45)
        if clear_of_road(index, base[None, [0, 2]], edge - 0.1) and occ.free(base[None, [0, 2]]):
            occ.mark(base[None, [0, 2]])
            oid = objs.add((0.38, 0.39, 0.40))
            V, F = cylinder(base + up * -0.2, up, 0.09, height + 0.2, segments=8)
            mb.add(V, F, M.METAL, oid)
            arm_c = base + up * (height - 0.1) - side * r * 0.9
            V, F = box(arm_c, box_axes(f, r), [0.05, 0.05, 0.95])
            mb.add(V, F, M.METAL, oid)
            V, F = box(arm_c - side * r * 0.8 + up * -0.1, box_axes(f, r), [0.18, 0.07, 0.3])
            mb.add(V, F, M.LAMP, oid)
            counts["poles"] += 1
        s += pp.pole_spacing * float(rng.uniform(0.8, 1.2))


def frontage_segments(path, s: float, block: float, step: float, offset: float):
    """The straight pieces of a stretch of frontage: from arc length ``s`` (m) over ``block`` m in ``step`` m pieces at
    the lateral ``offset`` (m, + right of the road path); per piece (start, end, middle, forward unit, right unit,
    length), world frame. Pieces shorter than 1 m or longer than 4 m (the path turning sharply) are skipped."""
    for s0 in np.arange(s, min(s + block, path.s[-1] - step), step):
        k0, p0, f0, r0 = frame_at(path, s0)
        k1, p1, f1, r1 = frame_at(path, s0 + step)
        a = p0 + r0 * offset
        b = p1 + r1 * offset
        f = b - a
        length = np.linalg.norm(f)
        if length < 1.0 or length > 4.0:
            continue
        f /= length
        yield a, b, (a + b) / 2, f, np.cross([0.0, 1.0, 0.0], f), length


_FENCE_COLORS = [(0.45, 0.32, 0.20), (0.55, 0.45, 0.32), (0.30, 0.32, 0.30), (0.62, 0.60, 0.55)]


def add_fences(mb, objs, occ, path, index, rng, recipe, side, edge, counts):
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
            for a, b, mid, f, r, length in frontage_segments(path, s, block, step, side * lat):
                pts = np.stack([a, mid, b])[:, [0, 2]]
                inner = np.stack([0.75 * a + 0.25 * b, mid, 0.25 * a + 0.75 * b])[:, [0, 2]]
                if not clear_of_road(index, pts, edge + st.sidewalk_width - 0.3) or not occ.free(inner):
                    continue
                occ.mark(inner)
                if oid is None:
                    oid = objs.add(color)
                    counts["fences"] += 1
                c = mid + np.array([0.0, -(height - 0.2) / 2, 0.0])
                V, F = box(c, box_axes(f, r), [length / 2, (height + 0.2) / 2, 0.03])
                mb.add(V, F, M.FENCE, oid)
        s += block


HEDGE_COLORS = [(0.13, 0.24, 0.08), (0.17, 0.27, 0.10), (0.10, 0.19, 0.08), (0.22, 0.28, 0.12)]
CANOPY_COLORS = [(0.20, 0.30, 0.10), (0.16, 0.27, 0.09), (0.25, 0.32, 0.12)]


def add_hedges(mb, objs, occ, path, index, rng, recipe, side, edge, counts):
    """Trimmed hedges (foliage boxes 0.8-2.2 m high, 0.6-1.2 m thick, their tops uneven) along the back of the
    sidewalk on ``side`` where no building or fence stands; a 25 m stretch gets one with probability
    ``recipe.props.hedge_fraction``. ``rng``: the hedges' own stream (the town's other draws stay as they were)."""
    st = recipe.street
    step = 2.5
    s = 0.0
    while s < path.s[-1]:
        block = 25.0
        on = rng.random() < recipe.props.hedge_fraction
        height = float(rng.uniform(0.8, 2.2))
        thick = float(rng.uniform(0.6, 1.2))
        color = HEDGE_COLORS[int(rng.integers(len(HEDGE_COLORS)))]
        lat = edge + st.sidewalk_width + 0.1 + thick / 2
        oid = None
        for a, b, mid, f, r, length in frontage_segments(path, s, block, step, side * lat) if on else []:
            pts = footprint_samples(mid, f, r, length / 2 * 0.8, thick / 2, step=0.4)
            if not clear_of_road(index, pts, edge + st.sidewalk_width - 0.3) or not occ.free(pts):
                continue
            occ.mark(pts)
            if oid is None:
                oid = objs.add(color)
                counts["hedges"] = counts.get("hedges", 0) + 1
            h = height * float(rng.uniform(0.93, 1.07))
            V, F = box(mid + np.array([0.0, -(h - 0.2) / 2, 0.0]), box_axes(f, r), [length / 2 + 0.05, (h + 0.2) / 2,
                                                                                    thick / 2])
            mb.add(V, F, M.FOLIAGE, oid)
        s += block


def add_canopy_trees(mb, objs, occ, path, index, rng, recipe, side, edge, counts):
    """Large trees on the sidewalk on ``side`` whose crowns (two or three lumpy blobs, radius 3-5.5 m) reach over
    the road, the crown's bottom at least 4.5 m up (above the lane's trucks); a slot every ``trees.spacing`` metres
    gets one with probability ``recipe.trees.canopy``. ``rng``: their own stream."""
    tp = recipe.trees
    up = np.array([0.0, -1.0, 0.0])
    s = float(rng.uniform(0, tp.spacing))
    while s < path.s[-1]:
        crown = float(rng.uniform(3.0, 5.5))
        trunk_h = 4.5 + 0.3 * crown + float(rng.uniform(0.0, 1.5))
        trunk_r = float(rng.uniform(0.18, 0.35))
        lat = edge + float(rng.uniform(0.6, 1.2))
        lean = float(rng.uniform(0.2, 0.5)) * crown       # the crown's centre over the road side of the trunk
        tint = float(rng.uniform(0.75, 1.2))
        blob_rng = np.random.default_rng(int(rng.integers(1 << 31)))
        if rng.random() < tp.canopy:
            k, p, f, r = frame_at(path, s)
            base = p + side * r * lat
            if clear_of_road(index, base[None, [0, 2]], edge - 0.2) and occ.free(base[None, [0, 2]]):
                occ.mark(base[None, [0, 2]])
                col = CANOPY_COLORS[int(blob_rng.integers(len(CANOPY_COLORS)))]
                oid = objs.add(tuple(c * tint for c in col))
                V, F = cylinder(base + up * -0.2, up, trunk_r, trunk_h + 0.2 + 0.4 * crown, segments=8)
                mb.add(V, F, M.TRUNK, oid)
                c = base + up * (trunk_h + 0.85 * crown * 0.6) - side * r * lean
                for j in range(int(blob_rng.integers(2, 4))):
                    o = (blob_rng.uniform(-0.45, 0.45) * crown) * f + (blob_rng.uniform(-0.3, 0.3) * crown) * r
                    rad = crown * float(blob_rng.uniform(0.7, 1.0))
                    cj = c + o + up * float(blob_rng.uniform(-0.1, 0.25)) * crown
                    V, F = blob(cj, [rad, rad * 0.6, rad], blob_rng)
                    mb.add(V, F, M.FOLIAGE, oid)
                counts["canopy_trees"] = counts.get("canopy_trees", 0) + 1
        s += tp.spacing * float(rng.uniform(0.8, 1.4))
