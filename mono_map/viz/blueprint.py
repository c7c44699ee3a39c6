"""Default rerun layout for a map build: 3-D map (+ reference map), an image row, time series.

Entity paths are those of ``mono_map.viz.rerun_stream`` (see its module doc).
"""

from __future__ import annotations

STAT_PLOTS = (
    ("frames_per_s", "frames/s"),
    ("memory_mb", "memory MB"),
    ("leaf_count", "leaf count"),
    ("mean_entropy", "mean entropy (nats)"),
    ("kept_fraction", "kept fraction"),
)


GROUND_Y = 1.65  # metres: KITTI's camera height above the road; world y points down


def eye_for_bounds(lo, hi) -> tuple[list[float], list[float]]:
    """An oblique overview eye (position, look target), world metres, for a map spanning lo..hi."""
    lo, hi = [float(v) for v in lo], [float(v) for v in hi]
    cx, cz = (lo[0] + hi[0]) / 2, (lo[2] + hi[2]) / 2
    ext = max(hi[0] - lo[0], hi[2] - lo[2], 10.0)
    return [cx, GROUND_Y - 0.45 * ext, cz - 0.55 * ext], [cx, GROUND_Y, cz]


def default_blueprint(reference: bool = False, frames: bool = True,
                      eye: tuple[list[float], list[float]] | None = None):
    """Build the blueprint.

    reference: add a second 3-D view of ``world/reference_map`` (the LiDAR-FOV map) beside the
    growing map, with the same trajectory for orientation. frames: include the image row and the
    time series (False for a finished map opened with ``mono-map view map.bt``). eye: (position,
    look target) of the 3-D views, world metres (default: behind and above the start).
    """
    import rerun as rr
    import rerun.blueprint as rrb

    # World y points down (KITTI cam0): up is -y; the grid lies on the road, not at camera height.
    position, target = eye if eye is not None else ([0.0, -25.0, -30.0], [0.0, GROUND_Y, 25.0])
    eye_ctl = rrb.EyeControls3D(kind=rrb.Eye3DKind.Orbital, position=position, look_target=target,
                                eye_up=[0.0, -1.0, 0.0])
    grid = rrb.LineGrid3D(visible=True, spacing=10.0, plane=rr.components.Plane3D([0.0, 1.0, 0.0], GROUND_Y))
    map_view = rrb.Spatial3DView(
        origin="world", name="map (occupied cells, colour = height)",
        contents=["+ $origin/**", "- world/reference_map/**"], eye_controls=eye_ctl, line_grid=grid)
    top = [map_view]
    if reference:
        top.append(rrb.Spatial3DView(
            origin="world", name="LiDAR-FOV reference map",
            contents=["+ world/reference_map/**", "+ world/trajectory/**", "+ world/camera"],
            eye_controls=eye_ctl, line_grid=grid))
    if not frames:
        return rrb.Blueprint(rrb.Horizontal(*top), collapse_panels=True)
    images = rrb.Horizontal(
        rrb.Spatial2DView(origin="world/camera/image", name="image_2"),
        rrb.Spatial2DView(origin="frame/depth", name="predicted depth"),
        rrb.Spatial2DView(origin="frame/entropy", name="entropy"),
        rrb.Spatial2DView(origin="frame/kept_mask", name="kept pixels"),
    )
    series = rrb.Horizontal(*[rrb.TimeSeriesView(origin=f"stats/{name}", name=title)
                              for name, title in STAT_PLOTS])
    return rrb.Blueprint(
        rrb.Vertical(rrb.Horizontal(*top), images, series, row_shares=[5, 2, 1.5]),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
        rrb.TimePanel(state="collapsed", timeline="frame", play_state="following"),
    )
