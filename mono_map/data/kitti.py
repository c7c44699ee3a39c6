"""Opening a KITTI sequence by name (real or synthetic): :func:`open_sequence`, a pure validating reader (it
never renders or writes). A raw drive name (``2011_09_26_drive_0013_sync``) opens a
:class:`~mono_map.data.kitti_raw_reader.KittiRawSequence`, any other name an odometry
:class:`~mono_map.data.kitti_odometry.KittiSequence`; both have the same interface.
"""

from __future__ import annotations

import os

from mono_map.data import kitti_raw
from mono_map.data.kitti_odometry import KittiSequence
from mono_map.data.kitti_raw_reader import KittiRawSequence
from mono_map.errors import MonoMapError
from mono_map.paths import data_root


def open_sequence(root: str | os.PathLike | None, name: str) -> KittiSequence:
    """Open and validate sequence ``name`` under ``root`` (``None`` → :func:`mono_map.paths.data_root`):
    a raw drive name (``2011_09_26_drive_0013_sync``) opens a :class:`KittiRawSequence`, any other an
    odometry :class:`KittiSequence`; both read alike downstream.

    Only reads; a command that may render a missing synthetic sequence calls
    :func:`mono_map.data.prepare.prepare_sequence` instead.
    """
    if kitti_raw.drive_date(name) is not None:
        return KittiRawSequence(data_root(root), name)
    if name.endswith("_extract") and kitti_raw.drive_date(name.removesuffix("_extract") + "_sync") is not None:
        raise MonoMapError(f"--seq: {name}: an unsynced, unrectified raw drive; mono-map reads the synced and "
                           f"rectified download ({name.removesuffix('_extract')}_sync)")
    return KittiSequence(data_root(root), name)
