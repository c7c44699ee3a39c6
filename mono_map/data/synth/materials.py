"""Materials: procedural albedo (camera) and reflectance / pass-through (LiDAR) at ray hits.

Textures are computed from the hit point (metres, world frame) so they have a fixed
world scale: asphalt grain, paving slabs, bricks and windows shrink with distance,
a real monocular depth cue.  Glass reflects (camera) and lets the LiDAR through.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mono_map.data.synth.noise import cell_noise, fbm, hash01, value_noise

SKY = 0
GROUND = 1
CURB = 2
FACADE = 3
CAR_PAINT = 4
CAR_GLASS = 5
TYRE = 6
TRUNK = 7
FOLIAGE = 8
METAL = 9
FENCE = 10
LAMP = 11

NAMES = {SKY: "sky", GROUND: "ground", CURB: "curb", FACADE: "facade", CAR_PAINT: "car paint",
         CAR_GLASS: "car glass", TYRE: "tyre", TRUNK: "trunk", FOLIAGE: "foliage", METAL: "metal",
         FENCE: "fence", LAMP: "lamp"}


@dataclass
class Surface:
    """Per-hit surface properties (N hits)."""

    albedo: np.ndarray       # (N, 3) float32 in [0, 1]
    mirror: np.ndarray       # (N,) float32 weight of the mirror reflection at normal incidence (glass, paint)
    lidar_refl: np.ndarray   # (N,) float32 LiDAR reflectance in [0, 1] (drives return probability + intensity)
    glass: np.ndarray        # (N,) bool: transparent for the LiDAR (it passes through or drops)
    region: np.ndarray       # (N,) uint8 ground region 0 road, 1 marking, 2 sidewalk, 3 grass; 255 not ground


def barycentric_attr(town, prim: np.ndarray, uvs: np.ndarray) -> np.ndarray:
    """Interpolate the per-vertex ground attributes (l, s) at hits (RaycastingScene uv convention)."""
    F = town.triangles[prim]
    u = uvs[:, 0:1]
    v = uvs[:, 1:2]
    A = town.vert_ls
    return (1 - u - v) * A[F[:, 0]] + u * A[F[:, 1]] + v * A[F[:, 2]]


def surface(town, p: np.ndarray, n: np.ndarray, prim: np.ndarray, uvs: np.ndarray, lidar: bool = False) -> Surface:
    """Surface properties at hit points ``p`` (N, 3) with normals ``n`` facing the ray.

    ``lidar=True`` skips the colour textures (albedo stays 0): only what the LiDAR needs.
    """
    N = len(p)
    alb = np.zeros((N, 3), np.float32)
    mirror = np.zeros(N, np.float32)
    refl = np.full(N, 0.3, np.float32)
    glass = np.zeros(N, bool)
    region = np.full(N, 255, np.uint8)
    mat = town.tri_material[prim]
    seed = town.seed
    for m in np.unique(mat):
        idx = np.nonzero(mat == m)[0]
        P = p[idx]
        x, y, z = P[:, 0], P[:, 1], P[:, 2]
        if m == GROUND:
            a, r, reg = _ground(town, P, prim[idx], uvs[idx], lidar)
            alb[idx], refl[idx], region[idx] = a, r, reg
        elif lidar and m != FACADE:
            refl[idx] = LIDAR_REFL.get(int(m), 0.3)
            if m == CAR_PAINT:
                oid = town.tri_object[prim[idx]]
                black = (town.obj_flags[oid] & 1) > 0
                refl[idx] = np.where(black, 0.012, 0.18 + 0.45 * town.obj_color[oid].mean(axis=1))
            elif m == CAR_GLASS:
                glass[idx] = True
        elif m == CURB:
            g = 0.52 + 0.10 * fbm(seed + 11, x + z, y, 0.4) + 0.05 * (cell_noise(seed + 12, x + z, y, 0.03) - 0.5)
            alb[idx] = g[:, None] * np.array([1.0, 0.99, 0.96], np.float32)
            refl[idx] = 0.35
        elif m == FACADE:
            a, mi, r, gl = _facade(town, P, n[idx], town.tri_object[prim[idx]], lidar)
            alb[idx], mirror[idx], refl[idx], glass[idx] = a, mi, r, gl
        elif m == CAR_PAINT:
            oid = town.tri_object[prim[idx]]
            black = (town.obj_flags[oid] & 1) > 0
            c = town.obj_color[oid] * (0.97 + 0.06 * cell_noise(seed + 21, x + y, z, 0.5))[:, None]
            alb[idx] = _vehicle_detail(town, P, n[idx], oid, c) if town.vehicle_detail > 0 else c
            mirror[idx] = np.where(black, 0.10, 0.07)
            lum = c.mean(axis=1)
            refl[idx] = np.where(black, 0.012, 0.18 + 0.45 * lum)
        elif m == CAR_GLASS:
            alb[idx] = (0.03, 0.035, 0.04)
            mirror[idx] = 0.55
            refl[idx] = 0.05
            glass[idx] = True
        elif m == TYRE:
            alb[idx] = 0.05
            refl[idx] = 0.10
        elif m == TRUNK:
            b = 0.8 + 0.4 * value_noise(seed + 31, x + z, y, 0.15)
            alb[idx] = b[:, None] * np.array([0.26, 0.19, 0.13], np.float32)
            refl[idx] = 0.30
        elif m == FOLIAGE:
            oid = town.tri_object[prim[idx]]
            leaf = hash01(seed + 41, np.floor(x / 0.25), np.floor(y / 0.25), np.floor(z / 0.25))
            blotch = value_noise(seed + 42, x + 0.7 * y, z - 0.5 * y, 0.8)
            alb[idx] = town.obj_color[oid] * (0.55 + 0.6 * leaf + 0.3 * blotch)[:, None]
            refl[idx] = 0.40
        elif m == METAL:
            alb[idx] = town.obj_color[town.tri_object[prim[idx]]]
            mirror[idx] = 0.05
            refl[idx] = 0.45
        elif m == FENCE:
            oid = town.tri_object[prim[idx]]
            t = _face_tangent(n[idx])
            u = np.einsum("ij,ij->i", P, t)
            plank = np.floor(u / 0.16)
            gap = (u - plank * 0.16) < 0.02
            c = town.obj_color[oid] * (0.85 + 0.3 * hash01(seed + 51, plank, oid))[:, None]
            c = c * (1 - 0.1 * value_noise(seed + 52, u, y, 0.3))[:, None]
            alb[idx] = np.where(gap[:, None], c * 0.35, c)
            refl[idx] = 0.30
        elif m == LAMP:
            alb[idx] = (0.85, 0.85, 0.80)
            refl[idx] = 0.60
    return Surface(albedo=np.clip(alb, 0, 1), mirror=mirror, lidar_refl=refl, glass=glass, region=region)


LIDAR_REFL = {CURB: 0.35, CAR_GLASS: 0.05, TYRE: 0.10, TRUNK: 0.30, FOLIAGE: 0.40, METAL: 0.45, FENCE: 0.30,
              LAMP: 0.60}


def road_track(l: np.ndarray, lane: float) -> np.ndarray:
    """Darkening weight (0..2) of the two tyre tracks of a lane at lateral offsets ``l`` (m) of road hits."""
    a = np.abs(l + lane / 2)
    return np.exp(-(((a - lane / 2 + 0.8) / 0.35) ** 2)) + np.exp(-(((a - lane / 2 - 0.8) / 0.35) ** 2))


# painted details of vehicles (recipe [cars] detail): side stripe colours, tail light, head light
STRIPE_COLORS = np.array([[0.85, 0.85, 0.82], [0.80, 0.65, 0.10], [0.60, 0.08, 0.06], [0.05, 0.05, 0.05]], np.float32)
TAIL_LIGHT = np.array([0.55, 0.06, 0.05], np.float32)
HEAD_LIGHT = np.array([0.80, 0.80, 0.78], np.float32)
PLATE = np.array([0.85, 0.85, 0.80], np.float32)


def _vehicle_detail(town, P, n, oid, c):
    """The camera albedo ``c`` (N,3) of vehicle paint with painted details on a share ``town.vehicle_detail`` of
    the vehicles: grime towards the ground and fine noise everywhere; on the sides a stripe, panel seams (vans,
    large vehicles) and lettering (large vehicles); at both ends a dark bumper, a number plate with characters
    and lights (red at the rear). In the vehicle's frame: obj_origin its ground centre, obj_params (forward x,
    forward z, length, width); the compiled kernel (csrc/synth.c: vehicle_detail) computes the same bits."""
    seed = town.seed
    on = hash01(seed + 71, oid, 0) < town.vehicle_detail
    o = town.obj_origin[oid]
    prm = town.obj_params[oid]
    fx, fz, W = prm[:, 0], prm[:, 1], prm[:, 3]
    q0 = P[:, 0].astype(np.float64) - o[:, 0]
    q2 = P[:, 2].astype(np.float64) - o[:, 2]
    al = (q0 * fx + q2 * fz).astype(np.float32)   # along, + = front (float64 like the kernel's, then float32)
    ac = (q0 * fz - q2 * fx).astype(np.float32)   # across
    h = (o[:, 1] - P[:, 1].astype(np.float64)).astype(np.float32)                       # above the ground
    nf = n[:, 0] * fx + n[:, 2] * fz
    end = on & (np.abs(nf) > 0.7)
    side = on & (np.abs(nf) < 0.3) & (np.abs(n[:, 1]) < 0.5)
    flags = town.obj_flags[oid]
    g = h / 0.7
    g = np.where(g < 1, g, np.float32(1))
    k = (0.72 + 0.28 * g) * (0.9 + 0.2 * value_noise(seed + 72, al + ac, h, 0.3))
    k = k + 0.08 * (cell_noise(seed + 73, al + ac, h, 0.04) - 0.5)
    out = np.where(on[:, None], c * k[:, None], c)
    h0 = 0.5 + 1.5 * hash01(seed + 75, oid, 0)
    stripe = side & (hash01(seed + 74, oid, 0) < 0.5) & (h > h0) & (h < h0 + (0.08 + 0.25 * hash01(seed + 76, oid, 0)))
    pal = np.floor(4 * hash01(seed + 77, oid, 0)).astype(np.int64)
    out = np.where(stripe[:, None], STRIPE_COLORS[pal], out)
    seam = side & ((flags & (8 | 16)) > 0) & (np.mod(al, 1.0 + 1.5 * hash01(seed + 78, oid, 0)) < 0.03)
    out = np.where(seam[:, None], out * 0.4, out)
    glyph = (cell_noise(seed + 80, al, h, 0.09) > 0.55) & (cell_noise(seed + 81, al, h, 0.27) > 0.3)
    letters = side & ((flags & 16) > 0) & (hash01(seed + 79, oid, 0) < 0.6) & (h > 1.4) & (h < 2.4) \
        & (al > -0.5 * prm[:, 2] + 1.0) & (al < 0) & glyph
    ink = np.where(c.mean(axis=1) > 0.4, np.float32(0.08), np.float32(0.85))
    out = np.where(letters[:, None], ink[:, None], out)
    out = np.where((end & (h > 0.25) & (h < 0.42))[:, None], out * 0.35, out)
    aac = np.abs(ac)
    out = np.where((end & (aac < 0.26) & (h > 0.42) & (h < 0.54))[:, None], PLATE, out)
    chars = end & (aac < 0.22) & (h > 0.45) & (h < 0.51) & (cell_noise(seed + 82, ac, h, 0.04) > 0.5)
    out = np.where(chars[:, None], np.float32(0.08), out)
    light = end & (aac > 0.5 * W - 0.32) & (h > 0.75) & (h < 0.98)
    out = np.where(light[:, None], np.where((nf < 0)[:, None], TAIL_LIGHT, HEAD_LIGHT), out)
    return out.astype(np.float32)


def _face_tangent(n: np.ndarray) -> np.ndarray:
    t = np.stack([n[:, 2], np.zeros(len(n)), -n[:, 0]], 1)
    return t / np.maximum(np.linalg.norm(t, axis=1, keepdims=True), 1e-6)


def _ground(town, P, prim, uvs, lidar=False):
    seed = town.seed
    st = town.street
    ls = barycentric_attr(town, prim, uvs)
    l, s = ls[:, 0], ls[:, 1]
    x, z = P[:, 0], P[:, 2]
    left, right = town.road_edges
    lane = st.lane_width
    sw = st.sidewalk_width
    road = (l > left) & (l < right)
    side = ~road & (l > left - sw) & (l < right + sw)
    grass = ~road & ~side
    N = len(P)
    alb = np.zeros((N, 3), np.float32)
    refl = np.full(N, 0.35, np.float32)
    region = np.full(N, 3, np.uint8)
    if road.any():
        i = np.nonzero(road)[0]
        xi, zi, li, si = x[i], z[i], l[i], s[i]
        junc = town.tri_junction[prim[i]]
        centre = (np.abs(li + lane / 2) < 0.075) & (np.mod(si, 9.0) < 3.0)
        edge = (np.abs(li - lane / 2) < 0.065) | (np.abs(li + 1.5 * lane) < 0.065)
        mark = (centre | edge) & ~junc
        region[i] = np.where(mark, 1, 0)
        blot = value_noise(seed + 1, xi, zi, 4.0)
        refl[i] = np.where(mark, 0.78, 0.10 + 0.08 * blot)
        if not lidar:
            grain = cell_noise(seed + 2, xi, zi, 0.05)
            track = road_track(li, lane)
            g = 0.21 + 0.08 * blot + 0.07 * (grain - 0.5) - 0.025 * track
            patch = value_noise(seed + 3, xi, zi, 7.0) > 0.78
            g = np.where(patch, g * 0.8, g)
            mi = np.nonzero(mark)[0]
            if len(mi):
                g[mi] = 0.52 + 0.30 * value_noise(seed + 4, xi[mi], zi[mi], 0.5)
            alb[i] = g[:, None] * np.array([0.96, 0.98, 1.0], np.float32)
    if side.any():
        i = np.nonzero(side)[0]
        refl[i] = 0.30
        region[i] = 2
        if not lidar:
            li, si = l[i], s[i]
            fl, fs = np.floor(li * 2), np.floor(si * 2)
            joint = ((li - fl * 0.5) < 0.02) | ((si - fs * 0.5) < 0.02)
            g = 0.46 + 0.10 * (hash01(seed + 5, fl, fs) - 0.5) + 0.05 * (cell_noise(seed + 6, x[i], z[i], 0.04) - 0.5)
            g = g * (1 - 0.12 * value_noise(seed + 7, x[i], z[i], 3.0))
            g = np.where(joint, g * 0.7, g)
            alb[i] = g[:, None] * np.array([1.0, 0.97, 0.91], np.float32)
    if grass.any() and not lidar:
        i = np.nonzero(grass)[0]
        gn = value_noise(seed + 8, x[i], z[i], 2.0)
        gg = cell_noise(seed + 9, x[i], z[i], 0.05)
        c = (1 - gn)[:, None] * np.array([0.19, 0.26, 0.10], np.float32) + gn[:, None] * np.array([0.33, 0.29, 0.18], np.float32)
        alb[i] = c * (0.8 + 0.4 * gg)[:, None]
    return alb, refl, region


def _facade(town, P, n, oid, lidar=False):
    seed = town.seed
    N = len(P)
    flags = town.obj_flags[oid]
    origin = town.obj_origin[oid]
    prm = town.obj_params[oid]
    su, fh, ww, wh = prm[:, 0], prm[:, 1], prm[:, 2], prm[:, 3]
    roof = np.abs(n[:, 1]) > 0.7
    t = _face_tangent(n)
    u = np.einsum("ij,ij->i", P - origin, t).astype(np.float32)
    h = (origin[:, 1] - P[:, 1]).astype(np.float32)
    col = np.floor(u / su)
    fu = u - col * su
    floor = np.floor(h / fh)
    fv = h - floor * fh
    dx = np.abs(fu - su / 2)
    upper = (floor >= 1) & ~roof
    inwin = (dx < ww / 2) & (fv > 0.9) & (fv < 0.9 + wh) & upper
    shop = ((flags & 4) > 0) & ~roof
    um = np.mod(u, 2.5)
    store = shop & (h > 0.45) & (h < 3.1) & (um > 0.12) & (um < 2.38)
    wi = np.nonzero(inwin)[0]
    is_glass = np.zeros(N, bool)
    is_glass[wi] = hash01(seed + 61, oid[wi], col[wi], floor[wi]) < town.glass_fraction
    glass = is_glass | store
    curtain = inwin & ~is_glass
    brick = (flags & 2) > 0
    refl = np.where(glass, 0.05, np.where(brick, 0.28, 0.40)).astype(np.float32)
    refl = np.where(curtain, 0.15, refl)
    mirror = np.where(glass, 0.9, np.where(curtain, 0.25, 0.0)).astype(np.float32)
    alb = np.zeros((N, 3), np.float32)
    if lidar:
        return alb, mirror, refl, glass
    color = town.obj_color[oid]
    wall = ~roof & ~inwin & ~glass
    bi = np.nonzero(wall & brick)[0]
    if len(bi):
        hb, ub = h[bi], u[bi]
        row = np.floor(hb / 0.075)
        off = np.mod(row, 2) * 0.125
        bcol = np.floor((ub + off) / 0.25)
        mortar = ((hb - row * 0.075) < 0.012) | ((ub + off - bcol * 0.25) < 0.015)
        bvar = 0.8 + 0.4 * hash01(seed + 62, row, bcol, oid[bi])
        alb[bi] = np.where(mortar[:, None], np.array([0.62, 0.60, 0.56], np.float32), color[bi] * bvar[:, None])
    pi = np.nonzero(wall & ~brick)[0]
    if len(pi):
        pl = 0.92 + 0.14 * value_noise(seed + 63, u[pi], h[pi], 1.2) - 0.10 * value_noise(seed + 64, u[pi], h[pi] * 0.15, 1.5)
        alb[pi] = color[pi] * pl[:, None]
    inframe = (dx < ww / 2 + 0.09) & (fv > 0.81) & (fv < 0.99 + wh) & upper & ~inwin
    store_frame = shop & (h > 0.35) & (h < 3.2) & ~store
    plinth = wall & (h < 0.6)
    alb[plinth] = color[plinth] * 0.55
    ci = np.nonzero(curtain)[0]
    if len(ci):
        alb[ci] = (0.35 + 0.3 * hash01(seed + 65, oid[ci], col[ci], floor[ci]))[:, None] * np.array([0.9, 0.85, 0.75], np.float32)
    alb[glass] = (0.04, 0.05, 0.055)
    alb[(inframe | store_frame) & ~roof] = (0.80, 0.80, 0.78)
    ri = np.nonzero(roof)[0]
    if len(ri):
        alb[ri] = (0.25 + 0.1 * value_noise(seed + 66, P[ri, 0], P[ri, 2], 2.0))[:, None] * np.array([1.0, 0.95, 0.92], np.float32)
    return alb, mirror, refl, glass
