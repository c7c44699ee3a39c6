"""Fused integration (``--integrate fused``): the frames' depth distributions fused across views before OctoMap.

A map gets two halves:

* **free space** — the distribution integration's calibrated expected free-space update
  (:mod:`mono_map.mapping.distribution`; only its negative, free-space updates are applied);
* **surface** — an uncertainty-weighted truncated signed-distance field (TSDF) in open3d's tensor
  ``VoxelBlockGrid`` (sparse 8³ blocks around the observed surfaces: memory grows with the surface, not
  the volume), fused from every frame's per-pixel expected depth μ and the distribution's spread. Each
  pixel's log-depth spread σ_log (bin probabilities over the log bin centres) sets its weight
  w = 1 / (1 + (σ_log / ``spread_ref``)²) (a confident pixel counts ~1, a two-mode or smeared one ~0)
  and its truncation band τ = clip(``trunc_sigma`` · μ · σ_log, ``trunc_min`` · res, ``trunc_max``)
  (metres). Every voxel of the blocks near the frame's surface (its cell centre) is projected into the
  ray grid; where the signed distance along the optical axis sdf = μ − z ≥ −``trunc_behind`` · τ, the
  voxel's weighted mean of clip(sdf, −τ, τ) / ``trunc_max`` and its summed weight are updated.

``lag`` frames after a frame was fused (the views after it are in the TSDF by then; the last frame
snaps the rest), each of its pixels looks along its own ray, within ``snap_window`` of μ, for the TSDF's
zero crossing whose two sides have summed weight ≥ ``min_weight`` (:meth:`SurfaceFusion.snap_depths`);
the cell at the crossing gets OctoMap's hit update, once per frame (the builder applies it). Pixels with
no fused surface near them give no hit. Cells are then occupied by OctoMap's own log-odds: hits from
the views that agree on a surface against the free half's misses; a frame's rays never free the cells
they end on (the free half has no update there).
Voxel (i, j, k) of the grid is OctoMap key (i, j, k) + 32768: the signed distance is evaluated at the
cell's centre. Settings chosen on training town 06 (``tools/tune_fused.py``), never on 00. A frame's
prediction goes in and its hits come out through :mod:`mono_map.mapping.fused_frames`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from mono_map.errors import MonoMapError
from mono_map.geometry import backproject_pixels
from mono_map.mapping import fused_c


@dataclass(frozen=True)
class FusedConfig:
    """Settings of the fused surface (``--integrate fused``; the free half uses DistributionConfig).

    spread_ref: log-depth spread at which a pixel's weight halves; min_weight: summed weight a voxel needs
    on both sides of a zero crossing; trunc_sigma, trunc_min (cells), trunc_max (metres): the truncation
    band; trunc_behind: voxels up to this many bands behind a pixel's depth are updated (with −τ: at
    grazing angles, e.g. the road far ahead, the cells just under the surface lie metres behind it along the
    optical axis); max_depth: pixels whose expected depth is farther (metres) are not fused (free space unaffected);
    max_spread: pixels whose log-depth spread is larger are not fused; lag: a frame's pixels are snapped to the
    fused surface this many frames after it was fused (the views that follow it are in the surface; the
    end of the build snaps the rest); snap_window: how far (metres) from a pixel's expected depth the
    surface is looked for along its ray; euclid: 1 = the signed distance a pixel gives a voxel is its distance to the
    plane through the pixel's surface point along its depth image's normal (:func:`mono_map.geometry.depth_normals`:
    cos · (μ − z)), the same from every view, and the snap reads a cell's value moved to the sample along the
    pixel's own normal; 0 = the distance along the optical axis (μ − z) and the value moved along the axis;
    snap_step: every snap_step-th pixel row and column of the ray grid is
    snapped (each still hits a cell of its own at 0.2 m cells beyond a few metres); multiview: neighbouring frames
    (0 = off, 1 or 2) whose images sharpen each frame's distribution before both halves use it (the plane-sweep
    posterior of :mod:`mono_map.depth.multiview`) and multiview_temperature its likelihood's τ; subpixel: 1 = each
    voxel reads the depth bilinearly at its projection into the full-resolution expected depth (nearest pixel
    across a depth edge), 0 = the nearest pixel of the ray grid; mode: 1 = each pixel's surface depth (fused and
    snapped) is moved from its expected depth by its distribution's step from mean to mode (:func:`mode_shift`;
    the posterior's where multiview is on), 0 = the expected depth (the free half always uses the whole
    distribution)."""

    # chosen on training town 06 frames 0-199 (docs/fused.md), never on 00
    spread_ref: float = 0.15
    min_weight: float = 1.0
    trunc_sigma: float = 1.0
    trunc_min: float = 3.0
    trunc_max: float = 1.0
    trunc_behind: float = 3.0
    max_depth: float = 40.0
    max_spread: float = 0.3            # chosen on towns 06 and 07 with the model shipped since 2026-12-05 (docs/fused.md)
    lag: int = 10
    snap_window: float = 1.0
    snap_step: int = 1
    multiview: int = 2
    multiview_temperature: float = 0.02
    subpixel: int = 0
    mode: int = 1
    stereo: int = 0                    # 1: image_3 is one more source of the posterior (needs multiview on)
    gate: float = 0.0                  # > 0: a pixel's hit stays at its own surface depth where the fused surface is
                                       # within this many cells of it, none elsewhere; 0: the hit on the fused surface
    euclid: int = 0                    # 1: distances along the surface normal (the same from every view), 0: along
                                       # the optical axis (projective)

    def multiview_config(self):
        """The multi-view posterior's settings (:mod:`mono_map.depth.multiview`), None when it is off."""
        from mono_map.depth.multiview import MultiviewConfig

        return MultiviewConfig(sources=int(self.multiview), temperature=self.multiview_temperature,
                               stereo=bool(self.stereo)) if self.multiview else None


def check_fused_config(cfg: FusedConfig) -> FusedConfig:
    """``cfg`` if every setting is usable, else MonoMapError naming the option (one line)."""
    def positive(name, v):
        if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
            raise MonoMapError(f"--{name}: must be a positive number, got {v}")

    positive("fused-spread-ref", cfg.spread_ref)
    positive("fused-min-weight", cfg.min_weight)
    positive("fused-trunc-sigma", cfg.trunc_sigma)
    positive("fused-trunc-min", cfg.trunc_min)
    positive("fused-trunc-max", cfg.trunc_max)
    if not (math.isfinite(cfg.trunc_behind) and cfg.trunc_behind >= 1):
        raise MonoMapError(f"--fused-trunc-behind: must be a number >= 1 (bands), got {cfg.trunc_behind}")
    positive("fused-max-depth", cfg.max_depth)
    positive("fused-max-spread", cfg.max_spread)
    positive("fused-snap-window", cfg.snap_window)
    if int(cfg.snap_step) != cfg.snap_step or cfg.snap_step < 1:
        raise MonoMapError(f"--fused-snap-step: must be a positive integer, got {cfg.snap_step}")
    if int(cfg.lag) != cfg.lag or cfg.lag < 0:
        raise MonoMapError(f"--fused-lag: must be a non-negative integer (frames), got {cfg.lag}")
    if int(cfg.multiview) != cfg.multiview or cfg.multiview not in (0, 1, 2):
        raise MonoMapError(f"--fused-multiview: neighbours per frame must be 0 (off), 1 or 2, got {cfg.multiview}")
    positive("fused-multiview-temperature", cfg.multiview_temperature)
    if cfg.subpixel not in (0, 1):
        raise MonoMapError(f"--fused-subpixel: must be 0 or 1, got {cfg.subpixel}")
    if cfg.stereo not in (0, 1):
        raise MonoMapError(f"--fused-stereo: must be 0 or 1, got {cfg.stereo}")
    if cfg.stereo and not cfg.multiview:
        raise MonoMapError("--fused-stereo: the right image is a source of the multi-view posterior; it needs "
                           "--fused-multiview 1 or 2")
    if not (isinstance(cfg.gate, (int, float)) and math.isfinite(cfg.gate) and cfg.gate >= 0):
        raise MonoMapError(f"--fused-gate: must be a number of cells >= 0 (0 = off), got {cfg.gate}")
    if cfg.euclid not in (0, 1):
        raise MonoMapError(f"--fused-euclid: must be 0 (along the optical axis) or 1 (along the normal), got {cfg.euclid}")
    if cfg.mode not in (0, 1):
        raise MonoMapError(f"--fused-mode: must be 0 (the expected depth) or 1 (the mode), got {cfg.mode}")
    return cfg


def bins_last(probs: np.ndarray) -> np.ndarray:
    """Bin probabilities (K, ...) as float32 (..., K): a view, contiguous for the predictor's probabilities
    (each pixel's K values side by side), so sums over the bins are dot products over contiguous memory."""
    return np.moveaxis(np.asarray(probs, dtype=np.float32), 0, -1)


def log_centres(edges: np.ndarray) -> np.ndarray:
    """(K,) float32 log-depth centres of bins with ``edges`` (K+1,) metres."""
    le = np.log(np.asarray(edges, dtype=np.float64))
    return (0.5 * (le[:-1] + le[1:])).astype(np.float32)


def log_spread(probs: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """Per-pixel standard deviation of log-depth (float32, shape of ``probs`` without its first axis) of bin
    probabilities ``probs`` (K, ...) over bins with ``edges`` (K+1,) metres, each bin's mass at its log
    centre (the bins' own width is not added: a point mass in one bin has spread 0). Rows summing to 0: 0."""
    p, lc = bins_last(probs), log_centres(edges)
    mass = p.sum(axis=-1)
    safe = np.where(mass > 0, mass, 1.0)
    m1 = (p @ lc) / safe
    m2 = (p @ (lc * lc)) / safe
    return np.sqrt(np.maximum(m2 - m1 * m1, 0.0)).astype(np.float32)


def pixel_weights(spread: np.ndarray, cfg: FusedConfig) -> np.ndarray:
    """Fusion weight of pixels with log-depth spread ``spread``: 1 / (1 + (spread / spread_ref)²) (float32)."""
    s = np.asarray(spread, dtype=np.float32) / np.float32(cfg.spread_ref)
    return (1.0 / (1.0 + s * s)).astype(np.float32)


def mode_shift(probs: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """Per pixel (float32; shape of ``probs`` (K, ...) without its first axis) the log-depth from the mean of
    bin probabilities ``probs`` over bins with ``edges`` (K+1,) metres to their mode: the most probable bin's
    log centre moved by a parabola through it and its two neighbours (at most half a bin;
    :func:`mono_map.depth.multiview.parabola_peak`, the sweep's best plane). 0 for a point mass
    or a mode symmetric about its bin; for two modes, the step from between them onto the larger one. Rows
    summing to 0: 0."""
    import torch

    from mono_map.depth.multiview import parabola_peak

    p, lc = bins_last(probs), log_centres(edges)
    mode = parabola_peak(torch.from_numpy(np.ascontiguousarray(p)), lc, dim=-1).numpy()
    mass = p.sum(axis=-1)
    mean = (p @ lc) / np.where(mass > 0, mass, 1.0)
    return np.where(mass > 0, mode - mean, 0.0).astype(np.float32)


class SurfaceFusion:
    """The uncertainty-weighted TSDF of a build (open3d ``VoxelBlockGrid``, CPU, voxel = OctoMap cell)."""

    BLOCK = 8

    def __init__(self, cfg: FusedConfig, resolution: float, initial_blocks: int = 4096):
        import open3d as o3d
        import open3d.core as o3c

        self.cfg, self.res = check_fused_config(cfg), float(resolution)
        self.o3d, self.o3c = o3d, o3c
        self.device = o3c.Device("CPU:0")
        self.vbg = o3d.t.geometry.VoxelBlockGrid(
            attr_names=("tsdf", "weight"), attr_dtypes=(o3c.float32, o3c.float32), attr_channels=((1), (1)),
            voxel_size=self.res, block_resolution=self.BLOCK, block_count=int(initial_blocks), device=self.device)
        self.frames = 0
        self.pending: list[tuple] = []     # frames fused, not yet snapped: (depth grid, K of the grid, pose,
                                           # its normals or None)

    def integrate(self, depth: np.ndarray, weight: np.ndarray, trunc: np.ndarray, K: np.ndarray,
                  T_world_cam: np.ndarray, fine: tuple | None = None, normals: np.ndarray | None = None) -> int:
        """Fuse one depth image: ``depth`` (H, W) float32 z-depth in metres (0 = no surface), per-pixel
        ``weight`` (H, W) and truncation ``trunc`` (H, W, metres), pinhole ``K`` (3×3) of this pixel grid and
        the camera pose ``T_world_cam`` (4×4). ``fine``: (depth (H', W') at a finer grid, its K, step: pixel
        (step·j, step·i) of it is pixel (j, i) of ``depth``) — each voxel then reads its depth bilinearly there
        (the nearest fine pixel where the four neighbours differ by more than 5 %; none where one is 0), its
        weight and truncation at the coarse pixel holding it. ``normals`` (H, W, 3): camera-frame unit normals facing the
        camera (:func:`mono_map.geometry.depth_normals`); then a voxel's signed distance is the distance of its
        centre to the plane through its pixel's surface point (the point on its own ray at the fine depth)
        along that pixel's normal, else the distance along the axis. Returns the number of voxels updated."""
        o3d, o3c = self.o3d, self.o3c
        depth = np.ascontiguousarray(depth, dtype=np.float32)
        self.frames += 1
        if not (depth > 0).any():
            return 0
        h, w = depth.shape
        T_cam_world = np.linalg.inv(np.asarray(T_world_cam, dtype=np.float64))
        intr = o3c.Tensor(np.asarray(K, dtype=np.float64))
        # blocks are activated at the voxel lattice points; the cell centres sit half a voxel further: one
        # voxel of margin on top of the widest truncation
        mult = float(math.ceil(self.cfg.trunc_behind * float(np.max(trunc[depth > 0])) / self.res) + 1)
        coords = self.vbg.compute_unique_block_coordinates(
            o3d.t.geometry.Image(o3c.Tensor(depth)), intr, o3c.Tensor(T_cam_world), 1.0,
            float(depth.max()) + 1.0, mult)
        hm = self.vbg.hashmap()
        hm.activate(coords)
        buf, _ = hm.find(coords)
        vcoords, vidx = self.vbg.voxel_coordinates_and_flattened_indices(buf.to(o3c.int32))
        # the cells' centres (world, metres) in the camera; float32 (the offset keeps them near the camera)
        R, t = T_cam_world[:3, :3].astype(np.float32), (T_cam_world[:3, 3] + 0.5 * self.res
                                                          * T_cam_world[:3, :3].sum(axis=1)).astype(np.float32)
        idx = vidx.numpy()
        lib = fused_c.library() if fine is None else None
        if lib is not None:                                 # the same in one compiled pass
            return fused_c.tsdf_update(lib, vcoords.numpy(), idx, R, t, K, depth, trunc, weight, normals,
                                       self.cfg.trunc_behind, self.cfg.trunc_max, *self.fields())
        pc = vcoords.numpy() @ R.T + t
        z = pc[:, 2]
        front = z > 1e-3
        zs = np.where(front, z, np.float32(1.0))
        if fine is None:
            u = np.rint(np.float32(K[0, 0]) * pc[:, 0] / zs + np.float32(K[0, 2])).astype(np.int64)
            v = np.rint(np.float32(K[1, 1]) * pc[:, 1] / zs + np.float32(K[1, 2])).astype(np.int64)
            ok = front & (u >= 0) & (u < w) & (v >= 0) & (v < h)
            sel = np.flatnonzero(ok)
            u, v, z = u[sel], v[sel], z[sel]
            d = depth[v, u]
        else:
            fd, Kf, step = fine
            fh, fw = fd.shape
            uf = np.float32(Kf[0, 0]) * pc[:, 0] / zs + np.float32(Kf[0, 2])
            vf = np.float32(Kf[1, 1]) * pc[:, 1] / zs + np.float32(Kf[1, 2])
            ok = front & (uf >= 0) & (uf <= fw - 1) & (vf >= 0) & (vf <= fh - 1)
            sel = np.flatnonzero(ok)
            uf, vf, z = uf[sel], vf[sel], z[sel]
            u0 = np.minimum(np.floor(uf).astype(np.int64), fw - 2)
            v0 = np.minimum(np.floor(vf).astype(np.int64), fh - 2)
            a, b = uf - u0, vf - v0
            d00, d01, d10, d11 = fd[v0, u0], fd[v0, u0 + 1], fd[v0 + 1, u0], fd[v0 + 1, u0 + 1]
            lo = np.minimum(np.minimum(d00, d01), np.minimum(d10, d11))
            hi = np.maximum(np.maximum(d00, d01), np.maximum(d10, d11))
            bil = (d00 * (1 - a) + d01 * a) * (1 - b) + (d10 * (1 - a) + d11 * a) * b
            near = fd[np.rint(vf).astype(np.int64), np.rint(uf).astype(np.int64)]
            d = np.where(lo <= 0, np.float32(0.0), np.where(hi > 1.05 * lo, near, bil)).astype(np.float32)
            u = np.minimum(np.rint(uf / step).astype(np.int64), w - 1)       # the coarse pixel: weight, band
            v = np.minimum(np.rint(vf / step).astype(np.int64), h - 1)
        tau = trunc[v, u]
        if normals is None:
            sdf = d - z
        elif fine is None:                  # to the plane through the pixel's surface point
            sdf = (normals[v, u] * (pc[sel] - backproject_pixels(K, u, v, d))).sum(axis=1)
        else:                               # the surface point on the voxel's own ray
            sdf = -(normals[v, u] * (pc[sel] / z[:, None])).sum(axis=1) * (d - z)
        keep = (d > 0) & (sdf >= -self.cfg.trunc_behind * tau)
        sel, sdf, tau = sel[keep], sdf[keep], tau[keep]
        wgt = weight[v[keep], u[keep]]
        t_new = (np.clip(sdf, -tau, tau) / self.cfg.trunc_max).astype(np.float32)
        tsdf, wsum = self.fields()
        i = idx[sel]
        w_old = wsum[i]
        w_new = w_old + wgt
        tsdf[i] = (tsdf[i] * w_old + t_new * wgt) / np.where(w_new > 0, w_new, 1.0)
        wsum[i] = w_new
        return int(len(i))

    def sample(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(tsdf, summed weight) float32 of the cells holding world ``points`` (N, 3) metres; weight 0 where the
        TSDF has no voxel. Every point's block is looked up in open3d's hash map (multi-threaded; 2.4× faster
        than finding the distinct blocks first: ``benchmarks/bench_fused_sample.py``)."""
        lat = np.floor(np.asarray(points, dtype=np.float64) / self.res).astype(np.int64)   # the cell = the voxel
        blk = lat >> 3
        loc = lat - (blk << 3)
        tsdf_out = np.zeros(len(lat), np.float32)
        w_out = np.zeros(len(lat), np.float32)
        if len(lat) == 0 or self.n_blocks == 0:
            return tsdf_out, w_out
        b = self.slots(blk)
        ok = b >= 0
        flat = b[ok] * self.BLOCK ** 3 + loc[ok, 0] + self.BLOCK * loc[ok, 1] + self.BLOCK ** 2 * loc[ok, 2]
        tsdf, wsum = self.fields()
        tsdf_out[ok] = tsdf[flat]
        w_out[ok] = wsum[flat]
        return tsdf_out, w_out

    def fields(self) -> tuple[np.ndarray, np.ndarray]:
        """(tsdf, summed weight): flat float32 views of open3d's attribute buffers (512 voxels a block, in the
        hash map's slot order; tsdf in units of ``trunc_max``), written in place by :meth:`integrate`."""
        return (self.vbg.attribute("tsdf").reshape((-1,)).numpy(),
                self.vbg.attribute("weight").reshape((-1,)).numpy())

    def slots(self, blocks: np.ndarray) -> np.ndarray:
        """The hash map's slot (int64 (N,); −1: no such block) of each block coordinate in ``blocks`` (N, 3)."""
        if len(blocks) == 0 or self.n_blocks == 0:
            return np.full(len(blocks), -1, np.int64)
        buf, found = self.vbg.hashmap().find(self.o3c.Tensor(np.ascontiguousarray(blocks, dtype=np.int32)))
        return np.where(found.numpy().astype(bool).reshape(-1), buf.numpy().astype(np.int64).reshape(-1), -1)

    def snap_depths(self, depth: np.ndarray, K: np.ndarray, T_world_cam: np.ndarray,
                    window: float, min_weight: float | None = None, normals: np.ndarray | None = None) -> np.ndarray:
        """Each pixel's depth moved to the fused surface along its ray: the TSDF's zero crossing (from + in
        front to − behind, both cells with summed weight ≥ ``min_weight``) nearest to ``depth`` (H, W, metres, 0 =
        none) within ±``window`` metres, sampled every cell size along the optical axis (each sample reads its
        cell's signed distance, moved from the cell's centre to the sample along the axis, or with ``normals``
        (H, W, 3) camera-frame unit normals facing the camera, along the pixel's normal) and interpolated
        linearly; 0 where there is none (float32 (H, W))."""
        thr = np.float32(self.cfg.min_weight if min_weight is None else min_weight)
        depth = np.asarray(depth, dtype=np.float32)
        v, u = np.nonzero(depth > 0)
        out = np.zeros(depth.shape, np.float32)
        if len(v) == 0:
            return out
        n = int(math.ceil(window / self.res))
        offs = np.arange(-n, n + 1, dtype=np.float64) * self.res
        T = np.asarray(T_world_cam, dtype=np.float64)
        nw = None if normals is None else normals[v, u].astype(np.float64) @ T[:3, :3].T    # (P, 3) world
        lib = fused_c.library()
        if lib is not None:                                   # the same in two compiled passes
            blk, loc, zs, step = fused_c.ray_samples(lib, u, v, depth[v, u].astype(np.float64), offs, K, T,
                                                     self.res, nw)
            out[v, u] = fused_c.crossings(lib, self.slots(blk), loc, zs, step, *self.fields(), self.cfg.trunc_max, thr)
            return out
        z = depth[v, u].astype(np.float64)[:, None] + offs[None, :]            # (P, S) sample depths
        x = (u[:, None] - K[0, 2]) / K[0, 0] * z
        y = (v[:, None] - K[1, 2]) / K[1, 1] * z
        pts = (np.stack([x, y, z], axis=-1) @ T[:3, :3].T + T[:3, 3]).reshape(-1, 3)
        t, w = self.sample(pts)
        # the cell's value holds at its centre: moved to the sample along this camera's axis (first order)
        centres = (np.floor(pts / self.res) + 0.5) * self.res
        if nw is None:
            zc = (centres - T[:3, 3]) @ T[:3, 2]                   # the centres' depths in this camera
            step = z - zc.reshape(z.shape)
        else:                                                      # the distance grows along the normal
            step = -np.einsum("psk,pk->ps", (pts - centres).reshape(z.shape + (3,)), nw)
        t = t.reshape(z.shape) * np.float32(self.cfg.trunc_max) - step
        w = w.reshape(z.shape)
        good = (w >= thr) & (z > 0)
        cross = good[:, :-1] & good[:, 1:] & (t[:, :-1] >= 0) & (t[:, 1:] < 0)
        # the crossing nearest the pixel's own depth (offset index n)
        dist = np.where(cross, np.abs(np.arange(2 * n)[None, :] + 0.5 - n), np.inf)
        k = dist.argmin(axis=1)
        has = np.isfinite(dist[np.arange(len(k)), k])
        r = np.flatnonzero(has)
        k = k[r]
        t0, t1 = t[r, k], t[r, k + 1]
        zc = z[r, k] + (z[r, k + 1] - z[r, k]) * (t0 / np.where(t0 - t1 > 0, t0 - t1, 1.0))
        out[v[r], u[r]] = zc.astype(np.float32)
        return out

    @property
    def n_blocks(self) -> int:
        return int(self.vbg.hashmap().size())
