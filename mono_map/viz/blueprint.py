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


def default_blueprint(reference: bool = False, frames: bool = True):
    """Build the blueprint.

    reference: add a second 3-D view of ``world/reference_map`` (the LiDAR-FOV map) beside the
    growing map, with the same trajectory for orientation. frames: include the image row and the
    time series (False for a finished map opened with ``mono-map view map.bt``).
    """
    import rerun.blueprint as rrb

    # World y points down (KITTI cam0): look from behind and above the start, y-up = -y.
    eye = rrb.EyeControls3D(kind=rrb.Eye3DKind.Orbital, position=[0.0, -60.0, -50.0],
                            look_target=[0.0, 0.0, 30.0], eye_up=[0.0, -1.0, 0.0])
    map_view = rrb.Spatial3DView(
        origin="world", name="map (occupied cells, colour = height)",
        contents=["+ $origin/**", "- world/reference_map/**"], eye_controls=eye)
    top = [map_view]
    if reference:
        top.append(rrb.Spatial3DView(
            origin="world", name="LiDAR-FOV reference map",
            contents=["+ world/reference_map/**", "+ world/trajectory/**", "+ world/camera"],
            eye_controls=eye))
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
        rrb.TimePanel(state="collapsed", timeline="frame"),
    )
