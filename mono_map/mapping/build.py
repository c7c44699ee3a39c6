"""Build an OctoMap from a sequence: monocular depth (uncertainty-selected) or LiDAR.

Per frame (paper, Sec. "Mapping"): predict the depth distribution of image_2, take its expected
depth and entropy, keep the ``keep`` fraction of valid pixels with the lowest entropy, back-project
them with K2 and the pose ``T_world_cam2``, and integrate them into the OctoMap with the camera
centre as sensor origin (free cells along the rays, occupied at the end points). LiDAR sources use
the velodyne scans (``lidar-fov``: only points inside image_2's view) with the velodyne centre as
origin; ``depth-gt`` back-projects the synthetic ground-truth ``depth_2`` through the camera path
(every pixel within the bin range, as keep 1.0: the camera's upper bound). Integration is the exact
batched path of :mod:`mono_map.mapping.integrate`; with ``integrate="distribution"`` every valid
pixel's whole depth distribution sets the updates along its ray instead
(:mod:`mono_map.mapping.distribution`, one frame: :mod:`mono_map.mapping.distribution_frame`).

Here one map's :class:`MapBuilder`, made from the map's specification (a
:class:`~mono_map.mapping.jobs.MapJob`) by :func:`make_builder`; a frame's shared image and predictions are
:mod:`mono_map.mapping.inputs`, several maps in one pass :mod:`mono_map.mapping.pipeline`.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np

from mono_map.depth.bins import DepthBins
from mono_map.depth.multiview import MultiviewPosterior, check_multiview_config
from mono_map.errors import MonoMapError
from mono_map.mapping.distribution import CellUpdates, check_distribution_config
from mono_map.mapping.distribution_frame import distribution_frame
from mono_map.mapping.fused import SurfaceFusion, check_fused_config
from mono_map.mapping.fused_frames import due_surface_points, fuse_prediction
from mono_map.mapping.inputs import FrameInputs, bin_edges, bins_of, load_predictor, probs_steps
from mono_map.mapping.integrate import MapIntegrator
from mono_map.mapping.nested import KeepGroup, nested_frame
from mono_map.mapping.octree import coord_to_key, key_to_coord, pack_keys, sorted_unique, unpack_keys
from mono_map.mapping.points import camera_origin, pixels_to_world
from mono_map.mapping.reference import lidar_measurement
from mono_map.mapping.select import check_keep, check_rank, confidence_score, select_pixels, valid_pixels


@dataclass
class FrameUpdate:
    """Emitted once per integrated frame (world = first cam0 frame, metres)."""

    index: int
    time: float
    image: np.ndarray | None          # H×W×3 uint8 RGB (image_2)
    depth: np.ndarray | None          # H×W float32 metres (predicted expected depth; None for LiDAR)
    entropy: np.ndarray | None        # H×W float32 nats
    keep_mask: np.ndarray | None      # H×W bool, pixels kept
    K: np.ndarray                     # 3×3
    T_world_cam2: np.ndarray          # 4×4
    points_world: np.ndarray          # (N, 3) float64 end points inserted this frame
    origin: np.ndarray                # (3,) sensor origin
    occupied_keys_changed: np.ndarray  # (M, 3) centres of cells that became occupied this frame
    freed_keys_changed: np.ndarray     # (F, 3) centres of cells that stopped being occupied this frame
    stats: dict = field(default_factory=dict)
    # only when an observer colours by probability (``colour == "probability"``): centres of the cells
    # this frame updated that are occupied after it (M, 3) and their occupancy probability (M,) float32
    updated_cells: np.ndarray | None = None
    updated_probability: np.ndarray | None = None


def updated_cell_probabilities(integrator: MapIntegrator, res) -> tuple[np.ndarray, np.ndarray]:
    """(centres (M, 3) metres, occupancy probabilities (M,) float32) of the cells a frame updated
    (``res``: its FrameIntegration) that are occupied after it, read from the integrator's log-odds
    mirror (cells that stopped being occupied are ``freed_keys_changed``)."""
    keys = np.concatenate([res.keys.free, res.keys.occupied]).astype(np.int64)
    logodds = integrator.mirror.get(keys)
    occ = logodds > integrator.occ_thres
    prob = 1.0 / (1.0 + np.exp(-logodds[occ].astype(np.float64)))
    return key_to_coord(keys[occ], integrator.cfg.resolution), prob.astype(np.float32)


@dataclass
class BuildResult:
    tree: object                      # octomap.OcTree (probabilistic, before any .bt write)
    stats: dict
    per_frame: list[dict]
    integrator: MapIntegrator


@dataclass
class Measurement:
    """One frame's input to the map (world = first cam0 frame, metres), with the camera images behind it."""

    points: np.ndarray                # (N, 3) float64 end points (distribution: the kept pixels, display only)
    origin: np.ndarray                # (3,) sensor origin
    n_valid: int                      # valid pixels (camera) or scan points (LiDAR)
    kept_fraction: float = 1.0
    mean_entropy: float = float("nan")
    image: np.ndarray | None = None   # H×W×3 uint8 RGB
    depth: np.ndarray | None = None   # H×W float32 metres
    entropy: np.ndarray | None = None  # H×W float32 nats
    mask: np.ndarray | None = None    # H×W bool, pixels kept
    prediction: object = None         # mono: the DepthPrediction (distribution mode needs its probs)
    valid: np.ndarray | None = None   # mono: H×W bool, valid pixels
    key_sets: object = None           # keep maps sharing a ray cast: this map's KeySets (points then display only)


class MapBuilder:
    """Integrates the frames of ``job`` (a :class:`~mono_map.mapping.jobs.MapJob`: source, keep,
    integration and its settings, OctoMap settings, stride, frames) from ``seq`` into a new OctoMap, one
    :meth:`step` per frame; ``predictor`` makes a mono map's depth distributions, ``observers`` get each
    frame's :class:`FrameUpdate`. :func:`make_builder` checks the job and loads the predictor.

    depth_range: valid depths (metres); stats_every: leaf count / memory measured every N frames;
    method: the integration ("batched", or OctoMap's own "insertPointCloud"); rank: the keep maps'
    pixel ranking ("entropy", the paper's, or "metric": :func:`mono_map.mapping.select.confidence_score`)."""

    def __init__(self, job, seq, predictor, observers: Sequence[Callable] = (), *,
                 depth_range: tuple[float, float], stats_every: int = 100, method: str = "batched",
                 rank: str = "entropy", multiview=None):
        self.job, self.seq, self.predictor, self.observers = job, seq, predictor, list(observers)
        self.source, self.keep, self.stride, self.rank = job.source, job.keep, job.stride, rank
        self.kind, self.integration = job.kind, job.integration
        self.depth_range, self.stats_every, self.n_frames = depth_range, stats_every, len(job.frames)
        self.dcfg, self.fcfg = job.distribution, job.fused
        self.dist_mode = self.integration.distributional
        self.integrator = MapIntegrator(job.octomap, method=method)
        # fused: the surface's TSDF beside the free-space half
        self.fusion = SurfaceFusion(self.fcfg, job.octomap.resolution) if self.integration.fused else None
        # the multi-view posterior (depth/multiview.py): a fused map's own setting, or any mono map's if given
        mv = multiview or (self.fcfg.multiview_config() if self.fusion is not None else None)
        self.multiview = MultiviewPosterior(mv, bins_of(predictor)) if mv is not None and self.kind.predicted else None
        if self.multiview is not None and mv.stereo:
            seq.require_right(job.frames, "--fused-stereo 1")
        self.surface_points = 0                    # fused: surface hits inserted (cells, summed over frames)
        self.group: KeepGroup | None = None   # keep maps whose frames share one ray cast (share_ray_casts)
        self.edges = bin_edges(predictor) if self.dist_mode else None
        self.K = np.asarray(seq.calib.K2, dtype=np.float64)
        self.per_frame: list[dict] = []
        self.points_valid = self.points_kept = self.rays_cast = 0
        self.last = {"leaf_count": 0, "memory_mb": 0.0, "memory_bytes": 0}
        self.t_start = time.perf_counter()

    def step(self, i: int, inputs: FrameInputs | None = None) -> None:
        """Frame ``i``: measure (predict → select → back-project, or read the scan) → integrate → account →
        observers. ``inputs``: the frame's image and predictions shared with other maps built in the same pass."""
        t_frame = time.perf_counter()
        if inputs is None:
            inputs = FrameInputs(self.seq, i, probs_steps([self]))
        T_world_cam2 = self.seq.T_world_cam2(i)
        m = self.measure(i, T_world_cam2, inputs)
        res, n_used = self.integrate(i, T_world_cam2, m)
        fstats = self.account(i, m, res, n_used, t_frame)
        if self.observers:
            self.notify(i, T_world_cam2, m, res, fstats)

    def measure(self, i: int, T_world_cam2: np.ndarray, inputs: FrameInputs) -> Measurement:
        """Frame ``i``'s input to the map, from the job's source."""
        if self.kind.predicted:
            return self.mono_measurement(i, T_world_cam2, inputs)
        if self.kind.ground_truth:
            return self.depth_gt_measurement(i, T_world_cam2, inputs)
        return self.lidar_measurement(i)

    def integrate(self, i: int, T_world_cam2: np.ndarray, m: Measurement):
        """Insert a measurement with the job's integration: whole distributions (and the fused surface), the
        keep group's shared ray cast, or end points. Returns (the frame's FrameIntegration, rays used)."""
        if self.dist_mode:
            res, n_used = distribution_frame(self.integrator, m.prediction, m.valid, self.K, T_world_cam2,
                                             self.edges, self.dcfg, i, free_only=self.fusion is not None)
            if self.fusion is not None:
                fuse_prediction(self.fusion, m.prediction, m.valid, self.K, T_world_cam2, self.edges,
                                self.dcfg.ray_step)
                last = len(self.per_frame) + 1 == self.n_frames
                res = self.surface_hits(res, due_surface_points(self.fusion, flush=last))
            m.kept_fraction = n_used / m.n_valid
            return res, n_used
        if m.key_sets is not None:
            return self.integrator.insert_key_sets(m.key_sets), int(np.count_nonzero(m.mask))
        return self.integrator.insert(m.points, m.origin), len(m.points)

    def surface_hits(self, res, points: list[np.ndarray]):
        """Insert the fused surface's hits (one array of world points per snapped frame: each frame's cells
        hit once, OctoMap's hit update) and add the cells whose occupied state flipped to ``res`` (this frame's
        FrameIntegration)."""
        for pts in points:
            if not len(pts):
                continue
            keys = unpack_keys(sorted_unique(pack_keys(coord_to_key(pts, self.integrator.cfg.resolution))))
            hits = self.integrator.insert_updates(CellUpdates(keys, np.full(len(keys), self.integrator.hit,
                                                                            np.float32), n_free=0))
            self.integrator.frames -= 1              # not a frame of its own
            res.became_occupied = np.concatenate([res.became_occupied, hits.became_occupied])
            res.stopped_occupied = np.concatenate([res.stopped_occupied, hits.stopped_occupied])
            self.surface_points += len(keys)
        return res

    def prediction(self, i: int, inputs: FrameInputs):
        """Frame ``i``'s depth prediction for this map: the predictor's, refined by the multi-view posterior if
        the map has one (once per frame for the maps of a pass that share it)."""
        pred = inputs.prediction(self.predictor)
        if self.multiview is None:
            return pred
        return inputs.shared(("multiview", id(self.predictor), self.multiview.cfg),
                             lambda: self.multiview.refine(self.seq, i, pred))

    def prepare(self, i: int, inputs: FrameInputs) -> None:
        """The part of frame ``i``'s work that needs no map (its prediction and posterior), so that it can run
        ahead, beside the previous frame's integration (:func:`~mono_map.mapping.pipeline.run_builders`)."""
        if self.kind.predicted:
            self.prediction(i, inputs)

    def mono_measurement(self, i: int, T_world_cam2: np.ndarray, inputs: FrameInputs) -> Measurement:
        """Predict image_2's depth distribution, keep the lowest-entropy pixels, back-project them."""
        image = inputs.image()
        pred = self.prediction(i, inputs)
        depth = np.asarray(pred.depth, dtype=np.float32)
        entropy = np.asarray(pred.entropy, dtype=np.float32)
        if depth.shape != image.shape[:2] or entropy.shape != image.shape[:2]:
            raise MonoMapError(f"frame {i}: prediction is {depth.shape}, image is {image.shape[:2]}")
        if np.isnan(depth).any():
            raise MonoMapError(f"frame {i}: predicted depth has {int(np.isnan(depth).sum())} NaN pixels "
                               f"(model failure)")
        # distribution: every valid pixel, its p_beyond is mass beyond each cell (distribution_frame);
        # keep: pixels more likely beyond range than not (sky) are never end points
        score = entropy if self.dist_mode else confidence_score(depth, entropy, self.rank)
        key_sets = None
        if self.group is not None:                     # one selection and ray cast for the group's keep maps
            g = self.group
            nf = inputs.shared(g.key, lambda: nested_frame(depth, score, g.keeps, self.depth_range, self.stride,
                                                           getattr(pred, "p_beyond", None), self.K, T_world_cam2,
                                                           self.integrator.cfg.resolution))
            level = g.level(self.keep)
            mask, valid, key_sets = nf.masks[level], nf.valid, nf.key_sets[level]
        else:
            mask, valid = select_pixels(depth, score, 1.0 if self.dist_mode else self.keep, *self.depth_range,
                                        stride=self.stride, return_valid=True,
                                        p_beyond=None if self.dist_mode else getattr(pred, "p_beyond", None))
        if not mask.any():
            raise MonoMapError(f"frame {i}: empty frame, no valid predicted depth within "
                               f"[{self.depth_range[0]:g}, {self.depth_range[1]:g}] m")
        if key_sets is not None:                       # the points are only shown
            pts = nf.points_of(level) if self.observers else np.zeros((0, 3))
        elif not self.dist_mode or self.observers:     # distribution mode integrates rays, not these points
            pts = pixels_to_world(depth, mask, self.K, T_world_cam2)
        else:
            pts = np.zeros((0, 3))
        n_valid = int(valid.sum())
        return Measurement(pts, camera_origin(T_world_cam2), n_valid, float(mask.sum()) / n_valid,
                           float(entropy[mask].mean()), image, depth, entropy, mask, pred, valid, key_sets)

    def depth_gt_measurement(self, i: int, T_world_cam2: np.ndarray, inputs: FrameInputs) -> Measurement:
        """The synthetic ground-truth depth_2, every pixel within the bin range, back-projected."""
        image = inputs.image() if self.observers else None
        depth = self.seq.depth(i)
        if depth is None:
            raise MonoMapError(f"{self.seq.depth_dir}: no ground-truth depth for frame {i}; --source "
                               f"depth-gt needs a synthetic sequence")
        mask = valid_pixels(depth, *self.depth_range, stride=self.stride)
        if not mask.any():
            raise MonoMapError(f"frame {i}: empty frame, no ground-truth depth within "
                               f"[{self.depth_range[0]:g}, {self.depth_range[1]:g}] m")
        return Measurement(pixels_to_world(depth, mask, self.K, T_world_cam2), camera_origin(T_world_cam2),
                           int(mask.sum()), image=image, depth=depth, mask=mask)

    def lidar_measurement(self, i: int) -> Measurement:
        pts, origin = lidar_measurement(self.seq, i, self.source)
        if len(pts) == 0:
            raise MonoMapError(f"frame {i}: empty frame, the {self.source} scan has no points")
        return Measurement(pts, origin, len(pts))

    def account(self, i: int, m: Measurement, res, n_used: int, t_frame: float) -> dict:
        """Totals and this frame's statistics (leaf count / memory every ``stats_every`` frames)."""
        self.points_valid += m.n_valid
        self.points_kept += n_used
        self.rays_cast += res.keys.n_rays
        n = len(self.per_frame) + 1
        measured = n == 1 or n % self.stats_every == 0 or n == self.n_frames  # first frame too: no zeros in the plots
        if measured:
            self.last = self.integrator.stats()
        elapsed = time.perf_counter() - self.t_start
        fstats = {"index": int(i), "frames_per_s": n / elapsed if elapsed > 0 else 0.0,
                  "frame_s": time.perf_counter() - t_frame,
                  "memory_mb": self.last["memory_mb"], "leaf_count": self.last["leaf_count"], "tree_measured": measured,
                  "kept_fraction": m.kept_fraction, "mean_entropy": m.mean_entropy, "n_points": int(n_used),
                  "n_rays": int(res.keys.n_rays), "free_cells": int(len(res.keys.free)),
                  "occupied_cells": int(len(res.keys.occupied))}
        self.per_frame.append(fstats)
        return fstats

    def notify(self, i: int, T_world_cam2: np.ndarray, m: Measurement, res, fstats: dict) -> None:
        upd = FrameUpdate(index=int(i), time=float(self.seq.times[i]), image=m.image, depth=m.depth,
                          entropy=m.entropy, keep_mask=m.mask, K=self.K, T_world_cam2=T_world_cam2,
                          points_world=m.points, origin=m.origin, occupied_keys_changed=res.became_occupied,
                          freed_keys_changed=res.stopped_occupied, stats=dict(fstats))
        if self.integrator.mirror is not None and any(getattr(o, "colour", None) == "probability"
                                                      for o in self.observers):
            upd.updated_cells, upd.updated_probability = updated_cell_probabilities(self.integrator, res)
        for obs in self.observers:
            obs(upd)

    def result(self, frames: Sequence[int]) -> BuildResult:
        """The tree and the build's statistics (the integrator is finished: no more steps)."""
        integrate = self.job.integrate
        cfg, dcfg, dist = self.integrator.cfg, self.dcfg, self.dist_mode
        final = self.integrator.stats()
        wall = time.perf_counter() - self.t_start
        stats = {
            "source": self.source, "keep": self.keep if self.kind.predicted and not dist else None,
            "integrate": integrate if self.kind.predicted else None,
            "eps": dcfg.eps if dist else None, "temperature": dcfg.temperature if dist else None,
            "fused": dict(self.fcfg.__dict__) if self.fusion is not None else None,
            "sequence": getattr(self.seq, "name", None),
            "frames": [int(frames[0]), int(frames[-1]) + 1], "n_frames": len(frames), "stride": self.stride,
            "resolution": cfg.resolution, "prob_hit": cfg.prob_hit, "prob_miss": cfg.prob_miss,
            "clamp_min": cfg.clamp_min, "clamp_max": cfg.clamp_max, "max_range": cfg.max_range,
            "depth_range": list(self.depth_range) if self.kind.camera else None,
            "points_valid": int(self.points_valid), "points_kept": int(self.points_kept),
            "rays_cast": int(self.rays_cast),
            "leaf_count": final["leaf_count"], "tree_nodes": final["tree_nodes"],
            "memory_bytes": final["memory_bytes"], "memory_mb": final["memory_mb"],
            "wall_s": wall, "frames_per_s": len(frames) / wall if wall > 0 else 0.0,
            "integration": self.integrator.method,
        }
        if self.fusion is not None:
            stats["surface_hits"] = int(self.surface_points)
            stats["tsdf_blocks"] = self.fusion.n_blocks
            self.fusion = None
        tree = self.integrator.finish()          # the mirror is freed before the tree is made: lower peak RSS
        stats["tree_seconds"] = self.integrator.sync_seconds
        return BuildResult(tree=tree, stats=stats, per_frame=self.per_frame, integrator=self.integrator)


def make_builder(seq, job, predictor=None, observers: Sequence[Callable] = (), *,
                 depth_range: tuple[float, float] | None = None, stats_every: int = 100, method: str = "batched",
                 rank: str = "entropy", multiview=None) -> MapBuilder:
    """A checked :class:`MapBuilder` of ``job`` (a :class:`~mono_map.mapping.jobs.MapJob`) over ``seq``.
    predictor: anything with ``predict(image) -> DepthPrediction`` or ``predict_frame(seq, i, image)``;
    None loads ``job.model``'s (:func:`~mono_map.mapping.inputs.load_predictor`; None → the shipped
    checkpoint). depth_range: valid predicted depths (metres), default the predictor's bin range (else
    DepthBins' 1–80 m). multiview: a MultiviewConfig applied to any mono map (e.g. a keep map,
    for measuring); a fused map's is its own setting. Raises MonoMapError on bad input."""
    if job.stride < 1:
        raise MonoMapError(f"--stride: must be a positive integer, got {job.stride}")
    dist_mode = job.integration.distributional
    check_distribution_config(job.distribution)
    check_fused_config(job.fused)
    if multiview is not None:
        check_multiview_config(multiview)
    if dist_mode and method != "batched":
        raise MonoMapError(f"--integrate {job.integrate}: needs the batched integration method")
    if job.kind.predicted and not dist_mode:
        check_keep(job.keep)
    rank = check_rank(rank)
    if job.kind.predicted and predictor is None:
        predictor = load_predictor(job.model, flip=job.flip)
    if depth_range is None:
        bins = getattr(predictor, "bins", None) or DepthBins()
        depth_range = (float(bins.min_depth), float(bins.max_depth))
    return MapBuilder(job, seq, predictor, observers, depth_range=depth_range, stats_every=stats_every,
                      method=method, rank=rank, multiview=multiview)
