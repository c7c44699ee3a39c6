"""Occupied cells in rerun: one archetype per set of cells (voxels, points or boxes, coloured by height or
occupancy probability), one entity per spatial block, and a finished ``.bt`` logged whole (:func:`log_bt_map`).
"""

from __future__ import annotations

import contextlib
from pathlib import Path

import numpy as np

from mono_map.errors import MonoMapError
from mono_map.io import atomic_path
from mono_map.viz.codec import (DEFAULT_HEIGHT_RANGE, PROBABILITY_RANGE, cell_indices, colourise, group_by_block,
                                height_range_of, heights, map_bounds, occupied_cells_from_bt, unpack)
from mono_map.viz.rerun_viewer import APP_ID, spawn_viewer

CELL_STYLES = ("voxels", "points", "boxes")


def cells_archetype(idx: np.ndarray, resolution: float, style: str = "voxels",
                    height_range: tuple[float, float] = DEFAULT_HEIGHT_RANGE, origin: np.ndarray | None = None,
                    probability: np.ndarray | None = None):
    """rerun archetype drawing cells (integer indices (N,3)).

    Colour: height = -y (metres) over ``height_range`` with Turbo, or, if ``probability`` (N,) is
    given, occupancy probability over ``PROBABILITY_RANGE`` with viridis.
    "voxels": ``VoxelGridMap`` (values colour-mapped by the viewer); voxel indices are stored
    relative to ``origin`` (a block corner, cells) with the grid translated by origin·res, so they
    are small numbers that the recording's LZ4 compresses well.
    "points": ``Points3D`` of radius res/2; "boxes": solid ``Boxes3D`` (colours computed here).
    """
    import rerun as rr

    if probability is None:
        values, (lo, hi), cmap = heights(idx, resolution), height_range, "turbo"
    else:
        values, (lo, hi), cmap = np.asarray(probability, np.float32), PROBABILITY_RANGE, "viridis"
    if style == "voxels":
        o = np.zeros(3, np.int64) if origin is None else np.asarray(origin, np.int64)
        return rr.VoxelGridMap(
            (idx - o).astype(np.int32), voxel_size=[resolution] * 3,
            values=np.clip(values, lo, hi),  # the viewer greys out-of-range values
            value_range=[lo, hi], colormap=getattr(rr.components.Colormap, cmap.capitalize()),
            translation=(o * resolution).astype(np.float64))
    centres = ((idx.astype(np.float64) + 0.5) * resolution).astype(np.float32)
    colours = colourise(values, lo, hi, cmap)
    if style == "points":
        return rr.Points3D(centres, colors=colours, radii=resolution / 2)
    return rr.Boxes3D(centers=centres, half_sizes=[resolution / 2] * 3, colors=colours,
                      fill_mode=rr.components.FillMode.Solid)


def block_path(block_key: int) -> str:
    """Entity path of the map block with packed block index ``block_key``."""
    bx, by, bz = unpack(np.array([block_key]))[0].tolist()
    return f"world/map/occupied/b{bx}_{by}_{bz}"


def log_bt_map(bt_path: str | Path, rrd: str | Path | None = None, spawn: bool = False,
               cells: str = "voxels", block_cells: int = 64) -> dict:
    """Log a finished OctoMap ``.bt``: occupied cells (finest resolution) coloured by height.

    Static data, one entity per spatial block ``world/map/occupied/b<X>_<Y>_<Z>`` (as in the
    stream), height range = the map's own 2-98th percentile. The ``.rrd`` is written atomically.
    Returns counts for the caller.
    """
    import rerun as rr

    from mono_map.viz.blueprint import default_blueprint, eye_for_bounds

    if cells not in CELL_STYLES:
        raise MonoMapError(f"--cells: {cells!r} is not one of {', '.join(CELL_STYLES)}")
    if rrd is None and not spawn:
        raise MonoMapError("view: nothing to do (no --save and no viewer)")
    centres, res = occupied_cells_from_bt(bt_path)
    idx = cell_indices(centres, res)
    hrange = height_range_of(idx, res)
    rec = rr.RecordingStream(APP_ID, recording_id=None)
    rec.send_recording_name(Path(bt_path).name)
    eye = eye_for_bounds(*map_bounds(centres)) if len(centres) else None
    with contextlib.ExitStack() as files:
        sinks = [rr.FileSink(str(files.enter_context(atomic_path(rrd))))] if rrd is not None else []
        if spawn:
            sinks.append(spawn_viewer(rec))
        rec.set_sinks(*sinks, default_blueprint=default_blueprint(reference=False, frames=False, eye=eye))
        rec.log("world", rr.ViewCoordinates.RDF, static=True)
        blocks = group_by_block(idx, block_cells)
        for bk, pos in blocks:
            origin = unpack(np.array([bk]))[0] * block_cells
            rec.log(block_path(bk), cells_archetype(idx[pos], res, cells, hrange, origin), static=True)
        rec.flush(timeout_sec=60.0)
        rec.disconnect()
    return {"cells": int(len(idx)), "blocks": len(blocks), "resolution": res, "height_range": hrange}

