"""Reference maps from the velodyne: full LiDAR and LiDAR-FOV (points inside image_2's view).

These are the upper bound of the paper's Table IV ("LiDAR-FOV"). They are built by the same
:func:`mono_map.mapping.pipeline.build_map` (``source="lidar"`` / ``"lidar-fov"``); this module gives
the per-frame measurement (the sources are named in :mod:`mono_map.mapping.strategies`).
"""

from __future__ import annotations

import numpy as np

from mono_map.mapping.points import lidar_to_world
from mono_map.mapping.strategies import source_of


def lidar_measurement(seq, i: int, source: str) -> tuple[np.ndarray, np.ndarray]:
    """World end points (N, 3) and velodyne origin (3,) of frame i for a LiDAR source."""
    scan = seq.velodyne(i)
    return lidar_to_world(scan, seq.T_world_cam2(i), seq.calib.T_cam2_velo,
                          fov_only=source_of(source).fov_only, K=seq.calib.K2, image_size=seq.image_size)
