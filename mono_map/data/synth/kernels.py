"""Compiled float32 kernels of the renderer: the same bits as the numpy code they replace, several times faster.

Each kernel fuses a chain of numpy's elementwise float32 operations (materials.surface's textures, the
camera's hit gathering and lighting, the image's sensor model) into one pass over the rays, in numpy's
operation order and types (python float constants rounded to float32 as numpy does; float64 where numpy
promotes). The C is ``mono_map/csrc/synth.c``, with ``synth_materials.h`` holding materials.py's ids and LiDAR
reflectances (the tests check they agree). Built by :mod:`mono_map.ckernel` without fused multiply-adds, so the results are bit for bit
numpy's (tests/test_synth.py checks each against its numpy reference). What numpy computes with its own
vector code (exp, power, matrix products) stays in numpy between the kernels. Without a C compiler (or
with ``MONO_MAP_NO_C=1``) :func:`library` is None and the renderer takes its numpy path.
"""

from __future__ import annotations

import ctypes

import numpy as np

from mono_map import ckernel
from mono_map.data.synth import materials as M

_P = ctypes.c_void_p
_I64 = ctypes.c_int64


class TownArrays(ctypes.Structure):
    """C view (``town_t``) of a town's arrays; ``keep`` holds the arrays it points into."""

    _fields_ = [("tris", _P), ("tri_mat", _P), ("tri_obj", _P), ("tri_junc", _P), ("vert_ls", _P), ("n_obj", _I64),
                ("obj_color", _P), ("obj_flags", _P), ("obj_origin", _P), ("obj_params", _P), ("seed", _I64),
                ("glass_fraction", ctypes.c_double), ("left", ctypes.c_double), ("right", ctypes.c_double),
                ("lane", ctypes.c_double), ("sidewalk", ctypes.c_double), ("vehicle_detail", ctypes.c_double)]


# the town's float arrays must have these types for the kernels to compute what numpy computes (integer arrays
# are converted: their values do not change)
TOWN_FLOATS = {"vert_ls": np.float32, "obj_color": np.float32, "obj_origin": np.float64, "obj_params": np.float32}


def town_fits(town) -> bool:
    """Whether ``town``'s float arrays have the types the kernels assume (else the renderer uses numpy)."""
    return all(getattr(town, name).dtype == dt for name, dt in TOWN_FLOATS.items())


def town_arrays(town) -> TownArrays:
    """The C view of ``town`` (arrays converted to the kernel's types only where they differ)."""
    arrays = {"tris": (town.triangles, np.int32), "tri_mat": (town.tri_material, np.uint8),
              "tri_obj": (town.tri_object, np.int32), "tri_junc": (town.tri_junction, np.bool_),
              "vert_ls": (town.vert_ls, np.float32), "obj_color": (town.obj_color, np.float32),
              "obj_flags": (town.obj_flags, np.int32), "obj_origin": (town.obj_origin, np.float64),
              "obj_params": (town.obj_params, np.float32)}
    keep = {k: np.ascontiguousarray(a, dt) for k, (a, dt) in arrays.items()}
    left, right = town.road_edges
    t = TownArrays(n_obj=len(keep["obj_color"]), seed=town.seed, glass_fraction=town.glass_fraction, left=left,
                   right=right, lane=town.street.lane_width, sidewalk=town.street.sidewalk_width,
                   vehicle_detail=float(town.vehicle_detail),
                   **{k: a.ctypes.data for k, a in keep.items()})
    t.keep = keep
    return t


_D = ctypes.c_double
_INT = ctypes.c_int
_SIGNATURES = {
    "syn_road_l": ([_P, _I64, _P, _P, _P], _I64),
    "syn_surface": ([_P, _I64, _P, _P, _P, _P, _INT, _P, _P, _P, _P, _P, _P], None),
    "syn_cam_rays": ([_I64, _P, _P, _P, _P, _P], None),
    "syn_hits": ([_P, _I64, _P, _P, _P, _P, _P, _P, _I64, _D, _INT] + [_P] * 11, _I64),
    "syn_lidar_returns": ([_I64, _P, _P, _P, _P, _P, _P, _D, _P, _P, _P, _P], _I64),
    "syn_lidar_p_ret": ([_I64, _P, _P, _P, _D, _P], None),
    "syn_lidar_points": ([_I64, _P, _P, _P, _P, _P, _P, _P, _P, _P], _I64),
    "syn_bump": ([_P, _I64, _P, _P, _P], None),
    "syn_shadow_rays": ([_I64, _P, _P, _P, _P, _P, _P], _I64),
    "syn_light": ([_P, _I64] + [_P] * 11 + [_INT] + [_P] * 8, _I64),
    "syn_final": ([_I64, _P, _I64] + [_P] * 10, None),
    "syn_depth": ([_I64, _P, _P, _D, _P], None),
    "syn_sensor": ([_I64, _P, _P, _P, _P], None),
}
library = ckernel.loader("synth", _SIGNATURES, "The compiled kernels of the renderer")


def _ptr(a: np.ndarray) -> int:
    assert a.flags.c_contiguous
    return a.ctypes.data


def surface(town, p: np.ndarray, n: np.ndarray, prim: np.ndarray, uvs: np.ndarray, lidar: bool = False) -> M.Surface:
    """:func:`materials.surface` (same arguments, same bits), compiled when :func:`library` is available."""
    lib = library()
    if lib is None or not town_fits(town):
        return M.surface(town, p, n, prim, uvs, lidar)
    T = town_arrays(town)
    N = len(p)
    p, n = np.ascontiguousarray(p, np.float32), np.ascontiguousarray(n, np.float32)
    prim, uvs = np.ascontiguousarray(prim, np.int64), np.ascontiguousarray(uvs, np.float32)
    track = None
    if not lidar:
        road_l = np.empty(N, np.float32)
        k = lib.syn_road_l(ctypes.byref(T), N, _ptr(prim), _ptr(uvs), _ptr(road_l))
        track = np.ascontiguousarray(M.road_track(road_l[:k], town.street.lane_width), np.float32)
    alb = np.empty((N, 3), np.float32)
    mirror, refl = np.empty(N, np.float32), np.empty(N, np.float32)
    glass, region = np.empty(N, np.bool_), np.empty(N, np.uint8)
    lib.syn_surface(ctypes.byref(T), N, _ptr(p), _ptr(n), _ptr(prim), _ptr(uvs), int(lidar),
                    None if track is None else _ptr(track), _ptr(alb), _ptr(mirror), _ptr(refl), _ptr(glass),
                    _ptr(region))
    return M.Surface(albedo=alb, mirror=mirror, lidar_refl=refl, glass=glass, region=region)


def cam_rays(cam_dirs: np.ndarray, R: np.ndarray, origin: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World directions (N, 3) of camera-frame unit directions ``cam_dirs`` rotated by ``R`` (3×3 float32), and
    the (N, 6) ray buffer [origin | direction]: camera.render's ``cam.dirs[:, :1] * R[:, 0] + …``."""
    cam_dirs = np.ascontiguousarray(cam_dirs, np.float32)
    N = len(cam_dirs)
    dirs, rays = np.empty((N, 3), np.float32), np.empty((N, 6), np.float32)
    library().syn_cam_rays(N, _ptr(cam_dirs), _ptr(np.ascontiguousarray(R, np.float32)),
                           _ptr(np.ascontiguousarray(origin, np.float32)), _ptr(dirs), _ptr(rays))
    return dirs, rays


class Hits:
    """The rays that hit within ``far`` (K of N), as camera.shade gathers them.

    ``t`` (N,) float32 distance (inf = miss), ``mat`` (N,) uint8 material (0 = miss), ``miss`` (N-K,) and
    ``idx`` (K,) ray indices; per hit ``d`` direction, ``th`` distance, ``p`` point, ``n`` unit normal facing
    the ray (as cast with ``face_ray=False``), ``prim`` (int64) triangle, ``uvs`` barycentric coordinates.
    """

    def __init__(self, town, ans: dict, dirs: np.ndarray, origins: np.ndarray, far: float, face_ray: bool = True):
        N = len(dirs)
        dirs = np.ascontiguousarray(dirs, np.float32)
        if origins.ndim == 2 and origins.strides[0] == 0:
            o, stride = np.ascontiguousarray(origins[0], np.float32), 0
        else:
            o, stride = np.ascontiguousarray(origins, np.float32), 3
        src = {k: np.ascontiguousarray(ans[k])
               for k in ("t_hit", "primitive_ids", "primitive_uvs", "primitive_normals")}
        assert src["t_hit"].dtype == np.float32 and src["primitive_ids"].dtype == np.uint32
        self.t, self.mat = np.empty(N, np.float32), np.empty(N, np.uint8)
        idx, miss = np.empty(N, np.int64), np.empty(N, np.int64)
        d, p, n = (np.empty((N, 3), np.float32) for _ in range(3))
        th, prim, uvs = np.empty(N, np.float32), np.empty(N, np.int64), np.empty((N, 2), np.float32)
        n_miss = ctypes.c_int64()
        T = town_arrays(town)
        k = library().syn_hits(ctypes.byref(T), N, _ptr(src["t_hit"]), _ptr(src["primitive_ids"]),
                               _ptr(src["primitive_uvs"]), _ptr(src["primitive_normals"]), _ptr(dirs), _ptr(o),
                               stride, far, int(face_ray), _ptr(self.t), _ptr(self.mat), _ptr(idx), _ptr(d),
                               _ptr(th), _ptr(p), _ptr(n), _ptr(prim), _ptr(uvs), _ptr(miss), ctypes.byref(n_miss))
        self.idx, self.miss = idx[:k], miss[:n_miss.value]
        self.d, self.th, self.p, self.n, self.prim, self.uvs = d[:k], th[:k], p[:k], n[:k], prim[:k], uvs[:k]


def bump(town, hits: Hits) -> None:
    """Foliage hits' bumpy normals, in place in ``hits.n`` (camera.shade's, seeds town.seed + 71 …)."""
    library().syn_bump(ctypes.byref(town_arrays(town)), len(hits.idx), _ptr(hits.p), _ptr(hits.prim), _ptr(hits.n))


def shadow_rays(hits: Hits, ndl: np.ndarray, sun: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Indices (into the hits) of the lit hits (ndl > 0) and their (L, 6) shadow rays [p + 0.03 n | sun]."""
    K = len(hits.idx)
    li, rays = np.empty(K, np.int64), np.empty((K, 6), np.float32)
    m = library().syn_shadow_rays(K, _ptr(hits.p), _ptr(hits.n), _ptr(np.ascontiguousarray(ndl, np.float32)),
                                  _ptr(np.ascontiguousarray(sun, np.float32)), _ptr(li), _ptr(rays))
    return li[:m], rays[:m]


class Light:
    """Direct light of the hits (``c`` (K, 3)) and, with bounce, the mirror hits' terms: ``mi`` (M,) indices
    into the hits, ``specbase`` / ``omc`` (M,) the bases of the highlight's 60th and Fresnel's 5th power,
    ``rdir`` (M, 3) reflected directions, ``traced`` indices into ``mi`` of the rays to trace and ``trays``
    (T, 6) their ray buffer."""

    def __init__(self, town, hits: Hits, ndl: np.ndarray, surf: M.Surface, light, bounce: bool):
        K = len(hits.idx)
        gain = None if light.albedo_gain is None else np.ascontiguousarray(light.albedo_gain, np.float32)
        self.c = np.empty((K, 3), np.float32)
        mi, specbase, omc = np.empty(K, np.int64), np.empty(K, np.float32), np.empty(K, np.float32)
        rdir, traced, trays = np.empty((K, 3), np.float32), np.empty(K, np.int64), np.empty((K, 6), np.float32)
        n_traced = ctypes.c_int64()
        colours = [np.ascontiguousarray(a, np.float32) for a in (light.ambient, light.sun_color, light.sun)]
        m = library().syn_light(ctypes.byref(town_arrays(town)), K, _ptr(hits.prim), _ptr(hits.d), _ptr(hits.n),
                                _ptr(hits.p), _ptr(ndl), _ptr(surf.albedo), _ptr(surf.mirror),
                                None if gain is None else _ptr(gain), *map(_ptr, colours), int(bounce),
                                _ptr(self.c), _ptr(mi), _ptr(specbase), _ptr(omc), _ptr(rdir), _ptr(traced),
                                _ptr(trays), ctypes.byref(n_traced))
        self.mi, self.specbase, self.omc, self.rdir = mi[:m], specbase[:m], omc[:m], rdir[:m]
        self.traced, self.trays = traced[:n_traced.value], trays[:n_traced.value]


def final(hits: Hits, lit: Light, spec60: np.ndarray, ndl: np.ndarray, f5: np.ndarray, mirror: np.ndarray,
          rcol: np.ndarray, tr: np.ndarray, horizon: np.ndarray, col: np.ndarray) -> None:
    """Highlight + Fresnel reflection on the mirror hits, haze, written to ``col`` (N, 3) at the hits."""
    arrays = [np.ascontiguousarray(a, np.float32) for a in (spec60, ndl, f5, mirror, rcol, tr, horizon)]
    library().syn_final(len(hits.idx), _ptr(lit.c), len(lit.mi), _ptr(lit.mi), *map(_ptr, arrays), _ptr(hits.idx),
                        _ptr(col))


def depth(t: np.ndarray, zfac: np.ndarray, max_depth: float) -> np.ndarray:
    """z-depth (N,) float32 of hit distances ``t`` (inf = sky) along rays with cos factor ``zfac``; 0 beyond
    ``max_depth`` (metres)."""
    out = np.empty(len(t), np.float32)
    library().syn_depth(len(t), _ptr(np.ascontiguousarray(t, np.float32)), _ptr(np.ascontiguousarray(zfac, np.float32)),
                        max_depth, _ptr(out))
    return out


def sensor(img: np.ndarray, vignette: np.ndarray, noise: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8 of the blurred float image: vignetting, shot + read noise, rounding (camera.render's)."""
    img, noise = np.ascontiguousarray(img, np.float32), np.ascontiguousarray(noise, np.float32)
    vignette = np.ascontiguousarray(vignette, np.float32)
    assert img.shape == noise.shape and vignette.size * 3 == img.size
    out = np.empty(img.shape, np.uint8)
    library().syn_sensor(vignette.size, _ptr(img), _ptr(vignette), _ptr(noise), _ptr(out))
    return out


def fits(town, light=None) -> bool:
    """Whether the kernels are available and give numpy's bits for ``town`` (and ``light``), else use numpy."""
    return library() is not None and town_fits(town) and (light is None or lighting_fits(light))


def lighting_fits(light) -> bool:
    """Whether ``light``'s colours are the float32 (3,) arrays the kernels read (else camera uses numpy)."""
    ok = all(isinstance(a, np.ndarray) and a.dtype == np.float32 and a.shape == (3,)
             for a in (light.sun_color, light.ambient, light.zenith, light.horizon))
    g = light.albedo_gain
    return ok and (g is None or (isinstance(g, np.ndarray) and g.dtype == np.float32 and g.ndim == 2
                                 and g.shape[1] == 3 and len(g) > M.LAMP))


def lidar_returns(hits: Hits, lost: np.ndarray, refl: np.ndarray, max_range: float) -> tuple:
    """The hits not ``lost`` (bool, per hit): (ray index, t, reflectance, |cos incidence|, return probability)
    as lidar.scan computes them."""
    K = len(hits.idx)
    idx, t, rf, cosi, p_ret = (np.empty(K, np.int64), np.empty(K, np.float32), np.empty(K, np.float32),
                               np.empty(K, np.float32), np.empty(K, np.float32))
    lib = library()
    m = lib.syn_lidar_returns(K, _ptr(np.ascontiguousarray(lost, np.bool_)), _ptr(hits.idx), _ptr(hits.th),
                              _ptr(hits.d), _ptr(hits.n), _ptr(np.ascontiguousarray(refl, np.float32)), max_range,
                              _ptr(idx), _ptr(t), _ptr(rf), _ptr(cosi))
    lib.syn_lidar_p_ret(m, _ptr(t), _ptr(rf), _ptr(cosi), max_range, _ptr(p_ret))
    return idx[:m], t[:m], rf[:m], cosi[:m], p_ret[:m]


def lidar_points(keep: np.ndarray, idx: np.ndarray, t: np.ndarray, refl: np.ndarray, cosi: np.ndarray,
                 noise_r: np.ndarray, noise_i: np.ndarray, dirs_velo: np.ndarray) -> np.ndarray:
    """(M, 4) float32 x y z intensity of the kept returns (lidar.scan's last lines; noises float32 (M,))."""
    keep = np.ascontiguousarray(keep, np.bool_)
    M_ = int(np.count_nonzero(keep))
    assert len(noise_r) == len(noise_i) == M_
    pts = np.empty((M_, 4), np.float32)
    library().syn_lidar_points(len(keep), _ptr(keep), _ptr(idx), _ptr(t), _ptr(refl), _ptr(cosi),
                               _ptr(np.ascontiguousarray(noise_r, np.float32)),
                               _ptr(np.ascontiguousarray(noise_i, np.float32)),
                               _ptr(np.ascontiguousarray(dirs_velo, np.float32)), _ptr(pts))
    return pts
