"""Options of the streaming map logger (:class:`~mono_map.viz.rerun_stream.RerunMapLogger`), checked once."""

from __future__ import annotations

import math
from dataclasses import dataclass

from mono_map.errors import MonoMapError
from mono_map.viz.rerun_cells import CELL_STYLES

COLOURS = ("height", "probability")


@dataclass(frozen=True)
class StreamOptions:
    """How a build is drawn (units: metres, seconds).

    resolution: map cell size (must match the build); block_cells: spatial block edge in cells;
    map_every: re-log dirty blocks every N frames; cells: "voxels" | "points" | "boxes"; colour:
    "height" | "probability" (of the map cells; the reference map is always coloured by height);
    height_range: (lo, hi) heights for the colour scale (None: from the reference map if given, else
    DEFAULT_HEIGHT_RANGE); max_points: cap on a frame's logged end points; trajectory_block: frames per
    trajectory segment entity; entropy_max: top of the entropy colour scale (nats; default ln 64, the
    64-bin maximum); jpeg_quality: of image_2 and the entropy picture; aux_scale: size of the depth,
    entropy and mask pictures relative to image_2 (they fill quarter-width panels; 0.5 quarters their
    cost); flush_s: seconds of rows batched per chunk; image_size: (H, W) of image_2 for the camera
    frustum when updates carry no image (LiDAR sources; default: twice the principal point);
    recording_name: shown by the viewer; blueprint: send the viewer layout.
    """

    resolution: float = 0.2
    block_cells: int = 64
    map_every: int = 1
    cells: str = "voxels"
    colour: str = "height"
    height_range: tuple[float, float] | None = None
    max_points: int = 8000
    trajectory_block: int = 100
    entropy_max: float = math.log(64)
    jpeg_quality: int = 85
    aux_scale: float = 0.5
    flush_s: float = 2.0
    image_size: tuple[int, int] | None = None
    recording_name: str | None = None
    blueprint: bool = True


def check_stream_options(o: StreamOptions) -> StreamOptions:
    """``o`` if valid, else one MonoMapError naming the option."""
    if o.cells not in CELL_STYLES:
        raise MonoMapError(f"cells: {o.cells!r} is not one of {', '.join(CELL_STYLES)}")
    if o.colour not in COLOURS:
        raise MonoMapError(f"colour: {o.colour!r} is not one of {', '.join(COLOURS)}")
    if not o.resolution > 0:
        raise MonoMapError(f"resolution: must be > 0 (got {o.resolution})")
    if o.block_cells < 1 or o.map_every < 1 or o.trajectory_block < 2:
        raise MonoMapError("viewer: block_cells and map_every must be ≥ 1, trajectory_block ≥ 2")
    if not 0 < o.aux_scale <= 1:
        raise MonoMapError(f"aux_scale: must be in (0, 1] (got {o.aux_scale})")
    return o
