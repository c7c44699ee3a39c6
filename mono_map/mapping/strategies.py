"""A map's source and integration, each resolved once from its name into a small strategy object.

The source (``--source``: mono, depth-gt, lidar, lidar-fov) and the integration (``--integrate``: keep,
distribution, fused) are named by strings on the command line, in a job's key and in a map's ``.json``;
this module is the one place those names are compared. The rest of the package asks the objects:
:func:`source_of` gives a :class:`Source` (does it look through image_2? need a depth network? keep
only LiDAR points in the camera's view?), :func:`integration_of` the :class:`Integration` a map of that
source uses (end points, or whole distributions; with the fused surface or not).
"""

from __future__ import annotations

from dataclasses import dataclass

from mono_map.errors import MonoMapError

CAMERA_SOURCES = ("mono", "depth-gt")
LIDAR_SOURCES = ("lidar", "lidar-fov")
SOURCES = CAMERA_SOURCES + LIDAR_SOURCES
INTEGRATIONS = ("keep", "distribution", "fused")


@dataclass(frozen=True)
class Source:
    """Where a map's end points come from (one per ``--source`` name)."""

    name: str
    camera: bool        # image_2's pixels back-projected (mono, depth-gt): stride and depth range apply
    predicted: bool     # depth from the network (mono): keep, integration, model and precision apply
    ground_truth: bool  # the synthetic ground-truth depth_2 (depth-gt)
    fov_only: bool      # LiDAR points inside image_2's view only (lidar-fov)

    @property
    def lidar(self) -> bool:
        """The velodyne scan, with the velodyne centre as sensor origin."""
        return not self.camera


@dataclass(frozen=True)
class Integration:
    """How a map's measurements update the OctoMap (one per ``--integrate`` name, as a source uses it)."""

    name: str
    distributional: bool  # each ray's whole depth distribution sets its updates (keep fraction ignored)
    fused: bool           # the distribution's free space + hits on the TSDF fused across views

    @property
    def end_points(self) -> bool:
        """Free cells along each kept ray, occupied at its end point (the paper's integration)."""
        return not self.distributional


def source_of(name: str) -> Source:
    """The :class:`Source` named ``name``; MonoMapError naming ``--source`` if there is none."""
    if name not in SOURCES:
        raise MonoMapError(f"--source: unknown source {name!r} (choose from {', '.join(SOURCES)})")
    return Source(name, camera=name in CAMERA_SOURCES, predicted=name == "mono", ground_truth=name == "depth-gt",
                  fov_only=name == "lidar-fov")


def integration_of(name: str, source: Source | str = "mono") -> Integration:
    """The :class:`Integration` named ``name`` as a map of ``source`` uses it: only a predicted source
    integrates distributions; the others integrate their end points whatever ``name`` says.
    MonoMapError naming ``--integrate`` if there is no such integration."""
    if name not in INTEGRATIONS:
        raise MonoMapError(f"--integrate: unknown integration {name!r} (choose from {', '.join(INTEGRATIONS)})")
    predicted = (source_of(source) if isinstance(source, str) else source).predicted
    distributional = predicted and name in ("distribution", "fused")
    return Integration(name, distributional=distributional, fused=predicted and name == "fused")
