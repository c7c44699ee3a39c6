"""Stream a growing OctoMap build to rerun: live viewer (``spawn``) and/or a recording (``.rrd``).

``RerunMapLogger`` is a ``build_map`` observer: call it with each ``FrameUpdate`` (see
``mono_map.mapping.build``), then ``close()``. It only reads the update's attributes, so any
object with the same fields works. ``log_bt_map`` (``mono_map.viz.rerun_cells``) logs a finished
``.bt``. The parts: the options (``mono_map.viz.stream_options``), the occupied cells per block
(``mono_map.viz.block_map``), drawing cells (``mono_map.viz.rerun_cells``), the viewer process
(``mono_map.viz.rerun_viewer``); the array work (cell keys, colours, image encoding) is in
``mono_map.viz.codec``; the layout in ``mono_map.viz.blueprint``.

What is logged (entity paths; all temporal data on the ``frame`` sequence timeline and on a
``time`` duration timeline taken from the sequence timestamps, seconds):

==============================  ============================================================
``world``                       static ``ViewCoordinates.RDF`` (KITTI cam0 world: x right,
                                y DOWN, z forward; height = -y)
``world/camera``                ``Transform3D`` T_world_cam2 + ``Pinhole`` (image_2's K, W×H)
``world/camera/image``          image_2, JPEG (shown in the 3-D frustum and in 2-D)
``frame/depth``                 predicted expected depth, ``EncodedDepthImage`` (16-bit PNG,
                                millimetres, ``aux_scale`` of full size), colour-mapped by the
                                viewer (Turbo, 1-80 m)
``frame/entropy``               per-pixel entropy (nats), colour-mapped (magma) over
                                [0, ``entropy_max``], JPEG
``frame/kept_mask``             kept pixels (white) vs dropped (black), PNG
``world/points``                this frame's inserted end points (subsampled to ``max_points``)
``world/trajectory/seg_NNNN``   camera path so far, in segments of ``trajectory_block`` frames
``world/map/occupied/bX_Y_Z``   occupied cells of spatial block (X, Y, Z), see below
``world/reference_map``         static: occupied cells of ``reference_map`` (.bt), if given
``stats/<name>``                ``Scalars``: frames_per_s, memory_mb, leaf_count,
                                mean_entropy, kept_fraction, n_points, map_cells
==============================  ============================================================

The map is sent incrementally, per spatial block
-----------------------------------------------
Space is cut into cubic blocks of ``block_cells`` cells per side (64 × 0.2 m = 12.8 m by
default). The logger keeps, for every block, the sorted set of its occupied cells (8 bytes per
cell). A frame's ``occupied_keys_changed`` are added to their blocks and its
``freed_keys_changed`` removed; only the blocks this touched are re-logged, each as one entity
``world/map/occupied/b<X>_<Y>_<Z>`` holding exactly that block's current occupied cells
(an emptied block gets a ``Clear``). Why this shape:

* **Viewer correctness**: rerun shows the latest value of each entity at the selected time, so
  at any frame, also when scrubbing back, the union of the blocks is exactly the map after that
  frame (including cells that were freed again): no tombstones, no drift.
* **Memory / size**: nothing is re-sent for blocks the frame did not touch, so the recording
  grows with the area the camera currently sees, not with the whole map; entity count grows with
  the mapped area (not with the number of frames, unlike per-frame addition chunks, which would
  also need a re-log of every older chunk that lost a cell). ``map_every=N`` batches the dirty
  blocks of N frames into one re-log to shrink long recordings further (``close()`` flushes).

Cells are drawn as ``VoxelGridMap`` voxels (``cells="voxels"``: int32 grid indices + one value
per cell, colour-mapped by the viewer), or as ``Points3D``/``Boxes3D`` with colours computed
here. ``colour="height"`` (default): Turbo over ``height_range``, the paper's "colour encodes
normalised height". ``colour="probability"``: viridis over occupancy probability 0.5-1
(``codec.probability_colours``); the updates must then also carry ``updated_cells`` (M,3 centres
of the cells whose occupancy probability changed this frame) and ``updated_probability`` (M,
that probability after the frame); a block whose occupied cells changed probability is re-logged.
"""

from __future__ import annotations

import contextlib
import math
import os
import sys
from pathlib import Path
from typing import Any

import numpy as np

from mono_map.errors import MonoMapError
from mono_map.io import atomic_path
from mono_map.viz.block_map import BlockMap
from mono_map.viz.codec import (DEFAULT_HEIGHT_RANGE, cell_indices, colormap_lut, encode_jpeg_bgr, encode_jpeg_rgb,
                                encode_png, height_range_of, map_bounds, occupied_cells_from_bt, pack, unpack)
from mono_map.viz.rerun_cells import block_path, cells_archetype
from mono_map.viz.rerun_viewer import APP_ID, spawn_viewer
from mono_map.viz.stream_options import StreamOptions, check_stream_options

STAT_NAMES = ("frames_per_s", "memory_mb", "leaf_count", "mean_entropy", "kept_fraction", "n_points")

IMAGE_VIEWS = ("world/camera/image", "frame/depth", "frame/entropy", "frame/kept_mask")


class RerunMapLogger:
    """Observer that streams each ``FrameUpdate`` of a map build to rerun (see module doc).

    rrd: write a recording to this file (atomically on ``close()``); spawn: start a viewer and stream to
    it live (both may be given); reference_map: a ``.bt`` (e.g. the LiDAR-FOV map) logged once, static,
    in its own 3-D view; options: how the build is drawn (:class:`StreamOptions`, checked here).
    """

    def __init__(self, rrd: str | Path | None = None, spawn: bool = False, reference_map: str | Path | None = None,
                 options: StreamOptions | None = None) -> None:
        import rerun as rr

        o = options or StreamOptions()
        if rrd is None and not spawn:
            raise MonoMapError("viewer: give --rrd FILE and/or --viewer")
        check_stream_options(o)
        self.options = o
        self.rr = rr
        self.resolution = float(o.resolution)
        self.block_cells = int(o.block_cells)
        self.map_every = int(o.map_every)
        self.cells = o.cells
        self.colour = o.colour
        self.max_points = int(o.max_points)
        self.trajectory_block = int(o.trajectory_block)
        self.entropy_max = float(o.entropy_max)
        self.jpeg_quality = int(o.jpeg_quality)
        self.aux_scale = float(o.aux_scale)
        self.rrd = Path(rrd) if rrd is not None else None
        self.image_size = tuple(o.image_size) if o.image_size is not None else None

        ref_idx = None
        if reference_map is not None:
            ref_centres, ref_res = occupied_cells_from_bt(reference_map)
            ref_idx = cell_indices(ref_centres, ref_res)
            self._ref_res = ref_res
        self.height_range = tuple(o.height_range) if o.height_range is not None else (
            height_range_of(ref_idx, self._ref_res) if ref_idx is not None else DEFAULT_HEIGHT_RANGE)
        self._magma_bgr = np.ascontiguousarray(colormap_lut("magma")[:, ::-1])

        # Batch rows for a few seconds before cutting chunks: every touched block is one row per frame,
        # and one chunk per row would cost more in chunk headers than the cells themselves.
        batcher = rr.ChunkBatcherConfig(flush_tick=float(os.environ.get("MONO_MAP_RR_FLUSH_S", o.flush_s)),
                                        flush_num_bytes=32 << 20)
        self.rec = rr.RecordingStream(APP_ID, recording_id=None, batcher_config=batcher)
        if o.recording_name:
            self.rec.send_recording_name(o.recording_name)
        bp = None
        self._blueprint = o.blueprint
        self._has_reference = reference_map is not None
        if o.blueprint:
            from mono_map.viz.blueprint import default_blueprint

            bp = default_blueprint(reference=self._has_reference)
        viewer = spawn_viewer(self.rec) if spawn else None
        # The recording is written to a temporary file beside the target and renamed on close():
        # the .rrd appears whole or not at all.
        self._files = contextlib.ExitStack()
        sinks = []
        if self.rrd is not None:
            sinks.append(rr.FileSink(str(self._files.enter_context(atomic_path(self.rrd)))))
        if viewer is not None:
            sinks.append(viewer)
        self.rec.set_sinks(*sinks, default_blueprint=bp)

        self.rec.log("world", rr.ViewCoordinates.RDF, static=True)
        for name in STAT_NAMES + ("map_cells",):
            self.rec.log(f"stats/{name}", rr.SeriesLines(names=name), static=True)
        if ref_idx is not None:
            self.rec.log("world/reference_map", cells_archetype(ref_idx, self._ref_res, self.cells, self.height_range),
                         static=True)
            self.reference_cells = len(ref_idx)
        else:
            self.reference_cells = 0

        self.map = BlockMap(self.block_cells, by_prob=o.colour == "probability")   # the occupied cells per block
        self.blocks_logged = 0      # block re-logs so far (size accounting for the benchmark)
        self.cells_logged = 0       # cells sent so far, re-sends included
        self.block_entities: set[int] = set()
        self._pending: list[tuple] = []   # per frame: (added keys, freed keys, (keys, probabilities) or None)
        self._traj_seg: list[np.ndarray] = []
        self._traj_n = 0
        self._pinhole_logged = None
        self.frames = 0
        self._closed = False

    # ----------------------------------------------------------------- per frame

    def __call__(self, update: Any) -> None:
        if self._closed:
            raise MonoMapError("viewer: logger already closed")
        rr, rec = self.rr, self.rec
        rec.set_time("frame", sequence=int(update.index))
        rec.set_time("time", duration=float(update.time))

        self._log_camera(update)
        self._log_images(update)
        self._log_points(update)
        self._log_trajectory(update)

        self._check_resolution(update.occupied_keys_changed)
        self._pending.append((pack(cell_indices(update.occupied_keys_changed, self.resolution)),
                              pack(cell_indices(update.freed_keys_changed, self.resolution)),
                              self._probability_update(update) if self.colour == "probability" else None))
        self.frames += 1
        if self.frames % self.map_every == 0:
            self._flush_map()

        stats = dict(getattr(update, "stats", {}) or {})
        measured = stats.get("tree_measured", True)    # leaf count / memory are measured every N frames
        for name in STAT_NAMES:
            v = stats.get(name)
            if name in ("memory_mb", "leaf_count") and not measured:
                continue                                  # carried over, not measured: not a data point
            if v is not None and np.isfinite(v):
                rec.log(f"stats/{name}", rr.Scalars(float(v)))
        rec.log("stats/map_cells", rr.Scalars(float(self.map_cells)))

    def _check_resolution(self, centres: np.ndarray) -> None:
        """Cell centres sit at (i + 0.5)·res: anything else means the build used another --res."""
        c = np.asarray(centres, dtype=np.float64).reshape(-1, 3)[:64] / self.resolution
        if len(c) and np.abs(c - np.floor(c) - 0.5).max() > 1e-3:
            raise MonoMapError(f"viewer: changed cells are not centres of {self.resolution:g} m cells "
                               f"(give RerunMapLogger the build's resolution)")

    def _probability_update(self, u: Any) -> tuple[np.ndarray, np.ndarray]:
        """(packed keys, float32 probabilities) of the cells whose occupancy probability changed."""
        cells, prob = getattr(u, "updated_cells", None), getattr(u, "updated_probability", None)
        if cells is None or prob is None:
            raise MonoMapError("viewer: colour='probability' needs updates carrying updated_cells and "
                               "updated_probability")
        cells = np.asarray(cells, dtype=np.float64).reshape(-1, 3)
        prob = np.asarray(prob, dtype=np.float32).reshape(-1)
        if len(cells) != len(prob):
            raise MonoMapError(f"viewer: {len(cells)} updated_cells but {len(prob)} updated_probability values")
        self._check_resolution(cells)
        return pack(cell_indices(cells, self.resolution)), prob

    def _log_camera(self, u: Any) -> None:
        rr = self.rr
        T = np.asarray(u.T_world_cam2, dtype=np.float64)
        self.rec.log("world/camera", rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3]))
        K = np.asarray(u.K, dtype=np.float64)
        if u.image is not None:
            hw = u.image.shape[:2]
        elif u.depth is not None:
            hw = u.depth.shape
        else:
            hw = self.image_size or (int(round(2 * K[1, 2])), int(round(2 * K[0, 2])))
        key = (K.tobytes(), tuple(hw))
        if key != self._pinhole_logged:  # intrinsics are constant: log once (re-log if they change)
            self.rec.log("world/camera", rr.Pinhole(image_from_camera=K, resolution=[hw[1], hw[0]],
                                                     camera_xyz=rr.ViewCoordinates.RDF,
                                                     image_plane_distance=2.0))
            self._pinhole_logged = key

    def _aux(self, a: np.ndarray, nearest: bool = False) -> np.ndarray:
        """Depth/entropy/mask pictures at ``aux_scale`` of the image size (they fill small panels)."""
        if self.aux_scale == 1.0:
            return a
        import cv2

        h, w = a.shape[:2]
        size = (max(1, round(w * self.aux_scale)), max(1, round(h * self.aux_scale)))
        return cv2.resize(a, size, interpolation=cv2.INTER_NEAREST if nearest else cv2.INTER_AREA)

    def _log_images(self, u: Any) -> None:
        rr, rec = self.rr, self.rec
        if u.image is not None:
            rec.log("world/camera/image", rr.EncodedImage(
                contents=encode_jpeg_rgb(np.asarray(u.image, dtype=np.uint8), self.jpeg_quality),
                media_type="image/jpeg"))
        if u.depth is not None:
            d = np.asarray(u.depth, dtype=np.float32)
            d = self._aux(np.where(np.isfinite(d), d, 0.0).astype(np.float32), nearest=True)
            mm = np.clip(d * 1000.0 + 0.5, 0, 65535).astype(np.uint16)
            rec.log("frame/depth", rr.EncodedDepthImage(
                encode_png(mm), media_type="image/png", meter=1000.0,
                colormap=rr.components.Colormap.Turbo, depth_range=[1000.0, 80000.0]))  # raw units (mm)
        if u.entropy is not None:
            e = self._aux(np.asarray(u.entropy, dtype=np.float32))
            e = np.clip(np.nan_to_num(e, nan=0.0, posinf=self.entropy_max, neginf=0.0), 0.0, self.entropy_max)
            q = (e * (255.0 / self.entropy_max)).astype(np.uint8)
            rec.log("frame/entropy", rr.EncodedImage(
                contents=encode_jpeg_bgr(self._magma_bgr[q], self.jpeg_quality), media_type="image/jpeg"))
        if u.keep_mask is not None:
            m = self._aux(np.asarray(u.keep_mask, dtype=bool).astype(np.uint8) * 255, nearest=True)
            rec.log("frame/kept_mask", rr.EncodedImage(contents=encode_png(m), media_type="image/png"))

    def _log_points(self, u: Any) -> None:
        pts = np.asarray(u.points_world, dtype=np.float32).reshape(-1, 3)
        if len(pts) > self.max_points:
            pts = pts[:: int(math.ceil(len(pts) / self.max_points))]
        self.rec.log("world/points", self.rr.Points3D(pts, colors=[80, 220, 255], radii=0.04))

    def _log_trajectory(self, u: Any) -> None:
        """Camera path: the current segment entity is re-logged each frame; full segments stay put."""
        p = np.asarray(u.T_world_cam2, dtype=np.float64)[:3, 3].astype(np.float32)
        seg = self._traj_n // self.trajectory_block
        self._traj_seg.append(p)
        self._traj_n += 1
        self.rec.log(f"world/trajectory/seg_{seg:04d}",
                     self.rr.LineStrips3D([np.stack(self._traj_seg)], colors=[255, 60, 60], radii=0.15))
        if self._traj_n % self.trajectory_block == 0:
            self._traj_seg = [p]  # the next segment starts where this one ends: no gap

    # ----------------------------------------------------------------- map

    def _flush_map(self) -> None:
        """Apply the pending per-frame changes (in frame order) and re-log every touched block."""
        pending, self._pending = self._pending, []
        touched: set[int] = set()
        by_prob = self.colour == "probability"
        for add, rem, prob in pending:
            touched |= self.map.apply(add, rem, prob)
        for bk in sorted(touched):
            path = block_path(bk)
            keys = self.map.blocks.get(bk)
            if keys is None:
                self.rec.log(path, self.rr.Clear(recursive=False))
            else:
                origin = unpack(np.array([bk]))[0] * self.block_cells
                self.rec.log(path, cells_archetype(unpack(keys), self.resolution, self.cells, self.height_range,
                                                   origin, self.map.probs.get(bk) if by_prob else None))
                self.cells_logged += len(keys)
        self.blocks_logged += len(touched)
        self.block_entities |= touched

    @property
    def map_cells(self) -> int:
        """Occupied cells the logger tracks."""
        return self.map.map_cells

    def occupied_cells(self) -> np.ndarray:
        """Current occupied cell centres (N,3) metres, as the logger tracks them (for checks)."""
        return self.map.occupied_cells(self.resolution)

    # ----------------------------------------------------------------- end

    def close(self) -> None:
        """Flush the last dirty blocks, finish the recording and move it into place.

        Called while an exception propagates (``build_map`` closes its observers in ``finally``),
        it discards the recording instead: a failed build leaves no partial ``.rrd``.
        """
        if self._closed:
            return
        if sys.exc_info()[0] is not None:
            self.abort()
            return
        self._flush_map()
        self._closed = True
        if self._blueprint and self.map.blocks:
            # Re-send the layout with the 3-D eye fitted to the finished map (the first one could not know it).
            from mono_map.viz.blueprint import default_blueprint, eye_for_bounds

            lo, hi = map_bounds(self.occupied_cells())
            self.rec.send_blueprint(default_blueprint(reference=self._has_reference, eye=eye_for_bounds(lo, hi)))
        self.rec.flush(timeout_sec=60.0)  # bounded: a closed live viewer must not hang the build
        self.rec.disconnect()
        self._files.close()  # atomic_path renames the finished recording into place

    def abort(self) -> None:
        """Stop without writing the recording (used when the build fails)."""
        if self._closed:
            return
        self._closed = True
        self.rec.disconnect()
        discarded = MonoMapError("viewer: recording discarded")
        self._files.__exit__(type(discarded), discarded, None)  # atomic_path removes the temporary file

    def __enter__(self) -> "RerunMapLogger":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()

