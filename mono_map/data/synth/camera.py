"""Camera rendering by ray casting: image_2 colour + dense z-depth.

Primary rays from the cam2 centre through every pixel centre; Lambertian shading
with a sun (shadow rays) and a sky ambient term; mirror reflections on glass and
car paint (one bounce, Fresnel-weighted); distance haze; mild blur and sensor noise.
The depth image is the z-depth (metres, cam2 frame) of the primary hit — for glass
that is the glass surface itself (the LiDAR, by contrast, mostly passes through).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mono_map.data.synth import kernels
from mono_map.data.synth import materials as M

FAR = 250.0            # metres; beyond = sky, depth 0
MAX_DEPTH = 255.0      # KITTI depth PNG limit (65535 / 256)


@dataclass
class Lighting:
    sun: np.ndarray            # (3,) unit vector towards the sun, world
    sun_color: np.ndarray
    ambient: np.ndarray
    zenith: np.ndarray
    horizon: np.ndarray
    haze_distance: float
    exposure: float
    albedo_gain: np.ndarray | None = None   # (materials, 3) albedo multipliers (domain randomisation); None = 1

    @classmethod
    def from_recipe(cls, lp) -> "Lighting":
        az, el = np.radians(lp.sun_azimuth_deg), np.radians(lp.sun_elevation_deg)
        sun = np.array([np.sin(az) * np.cos(el), -np.sin(el), np.cos(az) * np.cos(el)])
        return cls(sun=sun, sun_color=np.array([1.00, 0.95, 0.86], np.float32) * 0.95,
                   ambient=np.array([0.36, 0.40, 0.47], np.float32),
                   zenith=np.array([0.30, 0.48, 0.78], np.float32), horizon=np.array([0.78, 0.82, 0.86], np.float32),
                   haze_distance=lp.haze_distance, exposure=lp.exposure)

    def sky(self, d: np.ndarray) -> np.ndarray:
        up = np.clip(-d[:, 1], 0, 1).astype(np.float32)
        w = np.exp(-up * 5.0)[:, None]
        col = self.zenith * (1 - w) + self.horizon * w
        glow = np.clip(d @ self.sun.astype(np.float32), 0, 1) ** 48
        return col + 0.35 * glow[:, None] * np.array([1.0, 0.9, 0.7], np.float32)


@dataclass
class PinholeCamera:
    K: np.ndarray              # 3×3
    height: int
    width: int

    def __post_init__(self):
        u, v = np.meshgrid(np.arange(self.width, dtype=np.float64), np.arange(self.height, dtype=np.float64))
        Kinv = np.linalg.inv(self.K)
        d = np.stack([u.ravel(), v.ravel(), np.ones(u.size)], 1) @ Kinv.T
        self.dirs = (d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32)   # cam frame, unit
        self.zfac = self.dirs[:, 2].copy()                                            # depth = t * zfac
        yy, xx = np.mgrid[0:self.height, 0:self.width].astype(np.float32)
        r2 = ((xx - self.width / 2) / (self.width / 2)) ** 2 + ((yy - self.height / 2) / (self.width / 2)) ** 2
        self.vignette = (1 - 0.18 * r2)[..., None].astype(np.float32)


def ray_buffer(origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """(N, 6) float32 rays [origin | direction] as open3d's ``RaycastingScene`` takes them (origins may broadcast)."""
    rays = np.empty((len(dirs), 6), np.float32)
    rays[:, :3] = origins
    rays[:, 3:] = dirs
    return rays


def cast_rays(scene, origins: np.ndarray, dirs: np.ndarray, nthreads: int) -> dict:
    """Closest hits of rays from ``origins`` along unit ``dirs`` ((N, 3), world frame, metres; cast in float32).

    Returns numpy arrays: ``t_hit`` (N,) distance (inf = no hit), ``primitive_ids`` (N,) triangle index,
    ``primitive_uvs`` (N, 2) barycentric coordinates, ``primitive_normals`` (N, 3) unit geometric normals.
    """
    return cast_buffer(scene, ray_buffer(origins, dirs), nthreads)


def cast_buffer(scene, rays: np.ndarray, nthreads: int) -> dict:
    """:func:`cast_rays` of a ready (N, 6) float32 C-contiguous ray buffer (:func:`ray_buffer`'s layout)."""
    import open3d as o3d

    ans = scene.cast_rays(o3d.core.Tensor.from_numpy(rays), nthreads=nthreads)
    return {k: ans[k].numpy() for k in ("t_hit", "primitive_ids", "primitive_uvs", "primitive_normals")}


def occluded(scene, rays: np.ndarray, nthreads: int) -> np.ndarray:
    """(N,) bool: whether each ray of a (N, 6) ray buffer hits anything within 400 m (shadow rays)."""
    import open3d as o3d

    if len(rays) == 0:
        return np.zeros(0, bool)
    return scene.test_occlusions(o3d.core.Tensor.from_numpy(np.ascontiguousarray(rays)), tnear=0.0, tfar=400.0,
                                 nthreads=nthreads).numpy().astype(bool)


def shade(scene, town, light: Lighting, origins: np.ndarray, dirs: np.ndarray, nthreads: int,
          bounce: bool = True, rays: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Colour (N, 3) float32, hit distance t (N,) (inf = sky) and material (N,) of rays.

    ``rays``: the same rays as a ready (N, 6) buffer, if the caller has one. Runs the compiled kernels when
    available (:mod:`kernels`; the same bits), else :func:`shade_numpy`.
    """
    if not kernels.fits(town, light):
        return shade_numpy(scene, town, light, origins, dirs, nthreads, bounce)
    ans = cast_buffer(scene, ray_buffer(origins, dirs) if rays is None else rays, nthreads)
    h = kernels.Hits(town, ans, dirs, origins, FAR)
    col = np.empty((len(dirs), 3), np.float32)
    col[h.miss] = light.sky(dirs[h.miss])
    if len(h.idx) == 0:
        return col, h.t, h.mat
    surf = kernels.surface(town, h.p, h.n, h.prim, h.uvs)
    if bounce:
        kernels.bump(town, h)
    sun = light.sun.astype(np.float32)
    ndl = np.clip(h.n @ sun, 0, 1)
    if bounce:
        li, srays = kernels.shadow_rays(h, ndl, sun)
        ndl[li[occluded(scene, srays, nthreads)]] = 0.0
    lit = kernels.Light(town, h, ndl, surf, light, bounce)
    spec60 = f5 = rcol = np.zeros((0, 3), np.float32)
    if bounce and len(lit.mi):
        spec60 = lit.specbase ** 60
        f5 = lit.omc ** 5
        rcol = light.sky(lit.rdir)
        rcol = np.where((lit.rdir[:, 1] > 0)[:, None], 0.35 * light.horizon[None, :], rcol)
        if len(lit.traced):
            rcol[lit.traced], _, _ = shade(scene, town, light, np.ascontiguousarray(lit.trays[:, :3]),
                                           np.ascontiguousarray(lit.trays[:, 3:]), nthreads, bounce=False,
                                           rays=lit.trays)
    tr = np.exp(-h.th / np.float32(light.haze_distance))
    kernels.final(h, lit, spec60, ndl, f5, surf.mirror, rcol, tr, light.horizon, col)
    return col, h.t, h.mat


def shade_numpy(scene, town, light: Lighting, origins: np.ndarray, dirs: np.ndarray, nthreads: int,
                bounce: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`shade` in numpy (the reference of the compiled path)."""
    ans = cast_rays(scene, origins, dirs, nthreads)
    t = ans["t_hit"]
    hit = np.isfinite(t) & (t < FAR)
    col = np.empty((len(t), 3), np.float32)
    miss = np.nonzero(~hit)[0]
    col[miss] = light.sky(dirs[miss])
    mat = np.zeros(len(t), np.uint8)
    idx = np.nonzero(hit)[0]
    t = np.where(hit, t, np.inf).astype(np.float32)
    if len(idx) == 0:
        return col, t, mat
    prim = ans["primitive_ids"][idx].astype(np.int64)
    d = dirs[idx]
    th = t[idx]
    p = origins[idx] + th[:, None] * d
    n = ans["primitive_normals"][idx]
    n *= np.where(np.einsum("ij,ij->i", n, d) > 0, -1.0, 1.0).astype(np.float32)[:, None]
    surf = M.surface(town, p, n, prim, ans["primitive_uvs"][idx])
    mat[idx] = town.tri_material[prim]
    if bounce:
        # foliage: bumpy normals; everything else flat-shaded
        fol = mat[idx] == M.FOLIAGE
        if fol.any():
            from mono_map.data.synth.noise import hash01
            q = np.floor(p[fol] / 0.2)
            jit = np.stack([hash01(town.seed + 71 + k, q[:, 0], q[:, 1], q[:, 2]) - 0.5 for k in range(3)], 1)
            nf = n[fol] + 1.2 * jit
            n[fol] = nf / np.linalg.norm(nf, axis=1, keepdims=True)
    sun = light.sun.astype(np.float32)
    ndl = np.clip(n @ sun, 0, 1)
    lit = ndl > 0
    if bounce and lit.any():
        li = np.nonzero(lit)[0]
        occ = occluded(scene, ray_buffer(p[li] + n[li] * 0.03, np.broadcast_to(sun, (len(li), 3))), nthreads)
        ndl[li[occ]] = 0.0
    up = np.clip(-n[:, 1], -1, 1)
    amb = light.ambient[None, :] * (0.65 + 0.35 * up)[:, None]
    albedo = surf.albedo if light.albedo_gain is None else surf.albedo * light.albedo_gain[mat[idx]]
    c = albedo * (amb + light.sun_color[None, :] * ndl[:, None])
    mi = np.nonzero(surf.mirror > 0)[0]
    # glossy highlight on paint / glass / metal
    if bounce and len(mi):
        h = sun - d[mi]
        h /= np.linalg.norm(h, axis=1, keepdims=True)
        spec = (np.clip(np.einsum("ij,ij->i", n[mi], h), 0, 1) ** 60) * (ndl[mi] > 0)
        c[mi] += (1.5 * spec)[:, None]
    if bounce and len(mi):
        cosi = np.abs(np.einsum("ij,ij->i", d[mi], n[mi]))
        fres = surf.mirror[mi] * (0.25 + 0.75 * (1 - cosi) ** 5)
        rdir = d[mi] - 2 * np.einsum("ij,ij->i", d[mi], n[mi])[:, None] * n[mi]
        # glass: trace the reflected ray; glossy paint / metal: reflect the sky (and a dim ground below it)
        rcol = light.sky(rdir)
        rcol = np.where((rdir[:, 1] > 0)[:, None], 0.35 * light.horizon[None, :], rcol)
        traced = np.nonzero(surf.mirror[mi] >= 0.5)[0]
        if len(traced):
            tm = mi[traced]
            rcol[traced], _, _ = shade_numpy(scene, town, light, p[tm] + n[tm] * 0.03, rdir[traced], nthreads,
                                             bounce=False)
        c[mi] = c[mi] * (1 - fres[:, None]) + rcol * fres[:, None]
    # haze
    tr = np.exp(-th / np.float32(light.haze_distance))[:, None]
    col[idx] = c * tr + light.horizon[None, :] * (1 - tr)
    return col, t, mat


def render(scene, town, light: Lighting, cam: PinholeCamera, T_world_cam: np.ndarray, rng: np.random.Generator,
           nthreads: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """RGB image (H, W, 3) uint8 and z-depth (H, W) float32 metres (0 = sky / beyond 255 m)."""
    import cv2

    R = T_world_cam[:3, :3].astype(np.float32)
    if kernels.fits(town, light):
        o = T_world_cam[:3, 3].astype(np.float32)
        dirs, rays = kernels.cam_rays(cam.dirs, R, o)
        col, t, _ = shade(scene, town, light, np.broadcast_to(o, dirs.shape), dirs, nthreads, rays=rays)
        depth = kernels.depth(t, cam.zfac, MAX_DEPTH).reshape(cam.height, cam.width)
        img = cv2.GaussianBlur((col * np.float32(light.exposure)).reshape(cam.height, cam.width, 3), (3, 3), 0.6)
        noise = rng.standard_normal(img.shape, dtype=np.float32)
        return kernels.sensor(img, cam.vignette, noise), depth
    dirs = cam.dirs[:, :1] * R[:, 0] + cam.dirs[:, 1:2] * R[:, 1] + cam.dirs[:, 2:] * R[:, 2]
    origins = np.broadcast_to(T_world_cam[:3, 3].astype(np.float32), dirs.shape)
    col, t, _ = shade_numpy(scene, town, light, origins, dirs, nthreads)
    depth = np.where(np.isfinite(t), t * cam.zfac, 0.0).astype(np.float32)
    depth[depth > MAX_DEPTH] = 0.0
    depth = depth.reshape(cam.height, cam.width)
    img = (col * np.float32(light.exposure)).reshape(cam.height, cam.width, 3)
    img = cv2.GaussianBlur(img, (3, 3), 0.6)
    # vignetting + sensor noise (shot-like + read noise)
    img *= cam.vignette
    noise = rng.standard_normal(img.shape, dtype=np.float32)
    img += noise * (0.006 + 0.012 * np.sqrt(np.clip(img, 0, 1)))
    rgb = np.clip(img * 255 + 0.5, 0, 255).astype(np.uint8)
    return rgb, depth
