"""A KITTI raw drive (``YYYY_MM_DD_drive_NNNN_sync``, real or synthetic) read as an odometry sequence:
:class:`KittiRawSequence`, validated when opened (the raw layout's formats and maths:
:mod:`mono_map.data.kitti_raw`).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from mono_map.data import kitti_raw
from mono_map.data.kitti_files import check_images, listing, parse_calib_text, read_text
from mono_map.data.kitti_odometry import Calibration, KittiSequence
from mono_map.errors import MonoMapError


def read_raw_calibration(date_dir: str | os.PathLike) -> kitti_raw.RawCalibration:
    """The three calibration files of a raw date folder, parsed and checked (:func:`kitti_raw.raw_calibration`)."""
    paths = tuple(Path(date_dir) / f for f in kitti_raw.CALIB_FILES)
    parsed = [parse_calib_text(kitti_raw.blank_calib_time(read_text(p, "raw calibration file")), p) for p in paths]
    return kitti_raw.raw_calibration(*parsed, paths=paths)


class KittiRawSequence(KittiSequence):
    """A validated KITTI raw drive (``YYYY_MM_DD_drive_NNNN_sync``) with the odometry sequence's interface.

    ``root`` is a raw root (holding ``YYYY_MM_DD/``) or the date folder itself. Calibration from the
    date folder (``calib.P2`` = P_rect_02, ``calib.T_cam0_velo`` = R_rect_00 · [R|T]); poses from OXTS as
    rectified cam0 in the first frame's cam0 (:mod:`mono_map.data.kitti_raw`); ``times`` from
    ``image_02/timestamps.txt`` in seconds since the first frame. ``raw_calib`` keeps the whole chain.
    """

    def __init__(self, root: str | os.PathLike, name: str):
        self.root = Path(root)
        self.name = name
        date = kitti_raw.drive_date(name)
        if date is None:
            raise MonoMapError(f"'{name}' is not a raw drive name (YYYY_MM_DD_drive_NNNN_sync)")
        candidates = (self.root / date / name, self.root / name)
        self.path = next((p for p in candidates if p.is_dir()), candidates[0])
        if not self.path.is_dir():
            raise MonoMapError(
                f"{self.path}: raw drive '{name}' not found (expected the KITTI raw layout "
                f"{date}/{name}/{{image_02,velodyne_points,oxts}} and {date}/calib_*.txt under {self.root})")
        self.raw_calib = read_raw_calibration(self.path.parent)
        rc = self.raw_calib
        self.calib = Calibration(P2=rc.P_rect_02, T_cam0_velo=rc.T_cam0_velo, P3=rc.P_rect_03)
        self.image_files = listing(self.path / "image_02" / "data", ".png")
        self.velodyne_files = listing(self.path / "velodyne_points" / "data", ".bin")
        oxts_files = listing(self.path / "oxts" / "data", ".txt")
        n = len(self.image_files)
        if n == 0:
            raise MonoMapError(f"{self.path / 'image_02' / 'data'}: no PNG images")
        stamp_path = self.path / "image_02" / "timestamps.txt"
        times = kitti_raw.parse_timestamps(read_text(stamp_path, "timestamps file"), stamp_path)
        if len(times) != n:
            raise MonoMapError(f"{stamp_path}: {len(times)} timestamps for {n} images in image_02/data")
        for folder, files, what in ((self.path / "oxts" / "data", oxts_files, "OXTS packets"),
                                    (self.path / "velodyne_points" / "data", self.velodyne_files, "scans")):
            if files or what != "scans":   # OXTS is required, scans are optional
                if len(files) != n:
                    raise MonoMapError(f"{folder}: {len(files)} {what} for {n} images in image_02/data")
                bad = next((f for f, g in zip(files, self.image_files) if f.stem != g.stem), None)
                if bad is not None:
                    raise MonoMapError(f"{bad}: no image of that frame in image_02/data (frames must match by name)")
        calib_path = self.path.parent / kitti_raw.CALIB_FILES[0]
        self.image_size = check_images(self.image_files, rc.P_rect_02, calib_path)
        if self.image_size != rc.image_size:
            raise MonoMapError(f"{self.image_files[0]}: image is {self.image_size[1]}×{self.image_size[0]}, but "
                               f"{calib_path}'s S_rect_02 says {rc.image_size[1]}×{rc.image_size[0]}")
        oxts = np.stack([kitti_raw.parse_oxts_text(read_text(f, "OXTS file"), f) for f in oxts_files])
        self.times = times
        self.poses_cam0 = kitti_raw.poses_cam0(kitti_raw.oxts_poses(oxts), rc.T_cam0_imu)
        self.pose_path = self.path / "oxts"

    def __repr__(self) -> str:
        return f"KittiRawSequence({str(self.root)!r}, {self.name!r}, frames={len(self)})"

    @property
    def right_dir(self) -> Path:
        """The right colour camera's images: ``image_03/data/``."""
        return self.path / "image_03" / "data"

    @property
    def depth_dir(self) -> Path:
        """Dense ground-truth depth of image_02 (mono-map's synthetic drives only): ``depth_02/data/``."""
        return self.path / "depth_02" / "data"
