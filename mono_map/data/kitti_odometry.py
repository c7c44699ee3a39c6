"""A KITTI odometry sequence (real or synthetic): :class:`KittiSequence`, validated when opened, and the
:class:`Calibration` of image_2 and the velodyne (also of the object benchmark's frames).

Layout under a data root (the standard KITTI odometry download)::

    sequences/XX/image_2/NNNNNN.png   colour left camera (RGB)
    sequences/XX/velodyne/NNNNNN.bin  float32 x y z reflectance, velodyne frame
    sequences/XX/calib.txt            P0..P3 (3×4 rectified projections), Tr (velodyne → cam0)
    sequences/XX/times.txt            seconds
    sequences/XX/depth_2/NNNNNN.png   optional dense depth of image_2 (synthetic sequences only)
    poses/XX.txt                      T_world_cam0, 3×4 per line; world = first cam0 frame

Every file is validated before use (:mod:`mono_map.data.kitti_files`); bad input raises
:class:`MonoMapError` naming the file. Opening a sequence checks the listing, calibration, poses, times and
every image's PNG header (size, colour) against the calibration. Real and synthetic sequences read alike;
a synthetic one's ``synth.json`` only says how many frames are complete (rendering a missing synthetic
sequence is the commands' job: :mod:`mono_map.data.prepare`).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mono_map import geometry
from mono_map.data.kitti_files import (check_images, listing, parse_calib_text, read_calib_file, read_image_rgb,
                                       read_poses_file, read_text, read_times_file, read_velodyne_bin)
from mono_map.errors import MonoMapError


@dataclass(frozen=True)
class Calibration:
    """Calibration of image_2 and the velodyne, from an odometry ``calib.txt``.

    P2: 3×4 rectified projection of image_2 (P2 = K2·[I | t2]).
    K2: 3×3 intrinsics of image_2 (pixels).
    T_cam0_velo: Tr, velodyne → cam0.  T_cam2_cam0: [I | t2] with t2 = K2⁻¹·P2[:, 3]
    (≈ +0.06 m along x).  T_cam2_velo = T_cam2_cam0 · T_cam0_velo.
    P3: 3×4 rectified projection of image_3, the right colour camera (t3 = K⁻¹·P3[:, 3] ≈ −0.47 m along x: its
    centre 0.47 m right of cam0's, 0.53 m right of image_2's), or None.
    """

    P2: np.ndarray
    T_cam0_velo: np.ndarray
    P3: np.ndarray | None = None

    @classmethod
    def from_file(cls, path: str | os.PathLike) -> "Calibration":
        data = read_calib_file(path)
        P3 = data.get("P3")
        return cls(P2=data["P2"].reshape(3, 4), T_cam0_velo=geometry.make_pose(
            data["Tr"].reshape(3, 4)[:, :3], data["Tr"].reshape(3, 4)[:, 3]),
            P3=P3.reshape(3, 4) if P3 is not None and P3.size == 12 else None)

    @property
    def K2(self) -> np.ndarray:
        return geometry.intrinsics_from_projection(self.P2)

    @property
    def T_cam2_cam0(self) -> np.ndarray:
        return geometry.T_cam_cam0_from_projection(self.P2)

    @property
    def T_cam2_velo(self) -> np.ndarray:
        return self.T_cam2_cam0 @ self.T_cam0_velo

    @property
    def T_cam3_cam0(self) -> np.ndarray | None:
        """[I | t3] of the right colour camera (t3 = K3⁻¹·P3[:, 3]), None without P3."""
        return None if self.P3 is None else geometry.T_cam_cam0_from_projection(self.P3)


def read_object_calibration(path: str | os.PathLike) -> Calibration:
    """Calibration of a KITTI *object*-benchmark frame (P2, R0_rect, Tr_velo_to_cam) as a :class:`Calibration`.

    The object format keeps the rectifying rotation apart: velodyne → rectified cam0 is
    R0_rect · Tr_velo_to_cam, which is what the odometry ``Tr`` already is.
    """
    path = Path(path)
    data = parse_calib_text(read_text(path, "calibration file"), path)
    sizes = {"P2": 12, "R0_rect": 9, "Tr_velo_to_cam": 12}
    for key, size in sizes.items():
        if key not in data or data[key].size != size:
            raise MonoMapError(f"{path}: object calibration entry '{key}' missing or not {size} numbers")
    R0 = geometry.make_pose(data["R0_rect"].reshape(3, 3))
    Tr = data["Tr_velo_to_cam"].reshape(3, 4)
    return Calibration(P2=data["P2"].reshape(3, 4), T_cam0_velo=R0 @ geometry.make_pose(Tr[:, :3], Tr[:, 3]))


class KittiSequence:
    """A validated KITTI odometry sequence under ``root`` (real or synthetic)."""

    def __init__(self, root: str | os.PathLike, name: str):
        self.root = Path(root)
        self.name = name
        self.path = self.root / "sequences" / name
        if not self.path.is_dir():
            raise MonoMapError(
                f"{self.path}: sequence '{name}' not found (expected KITTI odometry layout "
                f"sequences/{name}/{{image_2,velodyne,calib.txt,times.txt}} under {self.root})")
        self.calib = Calibration.from_file(self.path / "calib.txt")
        times = read_times_file(self.path / "times.txt")
        pose_path = self.root / "poses" / f"{name}.txt"
        poses = read_poses_file(pose_path) if pose_path.is_file() else None
        self.image_files = listing(self.path / "image_2", ".png")
        self.velodyne_files = listing(self.path / "velodyne", ".bin")
        # A synthetic prefix being extended in place briefly holds more frames than its
        # marker, poses and times: read only the frames the marker vouches for.
        n_marked = self._synthetic_frame_count()
        if n_marked is not None:
            self.image_files = self.image_files[:n_marked]
            self.velodyne_files = self.velodyne_files[:n_marked]
        n = len(self.image_files)
        if n == 0:
            raise MonoMapError(f"{self.path / 'image_2'}: no PNG images")
        if len(times) != n:
            raise MonoMapError(f"{self.path / 'times.txt'}: {len(times)} timestamps for {n} images in image_2/")
        if poses is not None and len(poses) != n:
            raise MonoMapError(f"{pose_path}: {len(poses)} poses for {n} images in {self.path / 'image_2'}")
        if self.velodyne_files and len(self.velodyne_files) != n:
            raise MonoMapError(
                f"{self.path / 'velodyne'}: {len(self.velodyne_files)} scans for {n} images in image_2/")
        self.image_size = check_images(self.image_files, self.calib.P2, self.path / "calib.txt")
        self.times = times
        self.poses_cam0 = poses
        self.pose_path = pose_path

    def _synthetic_frame_count(self) -> int | None:
        """Frame count recorded in ``synth.json`` (synthetic sequences), else None."""
        import json

        marker = self.path / "synth.json"
        if not marker.is_file():
            return None
        try:
            text = marker.read_text()
        except OSError as exc:  # unreadable, not malformed: re-rendering would not be the fix
            raise MonoMapError(f"{marker}: cannot read the synthetic-sequence marker ({exc.strerror}); "
                               "check its permissions") from None
        try:
            n = json.loads(text)["n_frames"]
        except (ValueError, KeyError, TypeError, IndexError, UnicodeDecodeError):
            n = None
        if not isinstance(n, int) or isinstance(n, bool) or n < 1:
            raise MonoMapError(f"{marker}: malformed synthetic-sequence marker (no positive integer n_frames; "
                               f"re-render with mono-map synth --seq {self.name} --force)")
        return n

    def __len__(self) -> int:
        return len(self.image_files)

    def __repr__(self) -> str:
        return f"KittiSequence({str(self.root)!r}, {self.name!r}, frames={len(self)})"

    def _check_index(self, i: int) -> int:
        if not -len(self) <= i < len(self):
            raise MonoMapError(f"{self.path}: frame {i} out of range (sequence has {len(self)} frames)")
        return i % len(self)

    @property
    def is_synthetic(self) -> bool:
        """True for sequences written by mono-map's generator (they carry ``synth.json``)."""
        return (self.path / "synth.json").is_file()

    def T_world_cam0(self, i: int) -> np.ndarray:
        if self.poses_cam0 is None:
            raise MonoMapError(f"{self.pose_path}: poses not available for sequence '{self.name}'")
        return self.poses_cam0[self._check_index(i)]

    def T_world_cam2(self, i: int) -> np.ndarray:
        """Pose of image_2 in the world (first cam0 frame): T_world_cam0 · inv(T_cam2_cam0)."""
        return self.T_world_cam0(i) @ geometry.pose_inverse(self.calib.T_cam2_cam0)

    def T_world_cam3(self, i: int) -> np.ndarray:
        """Pose of image_3 (the right colour camera) in the world: T_world_cam0 · inv(T_cam3_cam0)."""
        if self.calib.T_cam3_cam0 is None:
            raise MonoMapError(f"{self.path}: the calibration has no P3 (right colour camera)")
        return self.T_world_cam0(i) @ geometry.pose_inverse(self.calib.T_cam3_cam0)

    @property
    def right_dir(self) -> Path:
        """Where the right colour camera's images are (odometry layout: ``image_3/``)."""
        return self.path / "image_3"

    def has_right(self, indices) -> bool:
        """True if frames ``indices`` all have a right image (and the calibration its P3 with image_2's K)."""
        return self._missing_right(indices) is None

    def require_right(self, indices, option: str) -> None:
        """MonoMapError (one line, led by ``option``) saying why frames ``indices`` have no usable right image."""
        why = self._missing_right(indices)
        if why is not None:
            hint = f"; render them with mono-map synth --seq {self.name} --stereo" if self.is_synthetic else ""
            raise MonoMapError(f"{option}: {self.path}: no right colour camera to use, {why}{hint}")

    def _missing_right(self, indices) -> str | None:
        P2, P3 = self.calib.P2, self.calib.P3
        if P3 is None or not np.allclose(P3[:, :3], P2[:, :3], rtol=1e-6, atol=1e-6):
            return "its calibration has no P3 with image_2's intrinsics"
        if not all((self.right_dir / self.image_files[self._check_index(i)].name).is_file() for i in indices):
            return f"{self.right_dir} lacks the image_3 of some of the frames"
        return None

    def image_right(self, i: int) -> np.ndarray:
        """The right colour camera's image of frame i (image_3; same size and K as image_2): H×W×3 uint8 RGB."""
        return self._read_image(self.right_dir / self.image_files[self._check_index(i)].name)

    def image(self, i: int) -> np.ndarray:
        """image_2 of frame i: H×W×3 uint8 RGB."""
        return self._read_image(self.image_files[self._check_index(i)])

    def _read_image(self, path: Path) -> np.ndarray:
        img = read_image_rgb(path)
        if img.shape[:2] != self.image_size:
            raise MonoMapError(f"{path}: image is {img.shape[1]}×{img.shape[0]}, "
                               f"expected {self.image_size[1]}×{self.image_size[0]} like the sequence's other images")
        return img

    def velodyne(self, i: int) -> np.ndarray:
        """Velodyne scan of frame i: (N, 4) float32 x y z reflectance (velodyne frame, metres)."""
        if not self.velodyne_files:
            raise MonoMapError(f"{self.path / 'velodyne'}: no velodyne scans for sequence '{self.name}'")
        return read_velodyne_bin(self.velodyne_files[self._check_index(i)])

    @property
    def depth_dir(self) -> Path:
        """Where dense ground-truth depth of image_2 would be (synthetic sequences: ``depth_2/``)."""
        return self.path / "depth_2"

    def depth(self, i: int) -> np.ndarray | None:
        """Dense ground-truth depth of image_2 (metres, 0 = none) if :attr:`depth_dir` has it, else None."""
        from mono_map.data.depth_png import read_depth_png

        path = self.depth_dir / self.image_files[self._check_index(i)].name
        if not path.is_file():
            return None
        depth = read_depth_png(path)
        if depth.shape != self.image_size:
            raise MonoMapError(f"{path}: depth is {depth.shape[1]}×{depth.shape[0]}, "
                               f"expected {self.image_size[1]}×{self.image_size[0]}")
        return depth

    def lidar_depth(self, i: int) -> np.ndarray:
        """Sparse depth of image_2 from the velodyne scan (metres, 0 = no value), KITTI's practice."""
        scan = self.velodyne(i)
        pts_cam2 = geometry.transform_points(self.calib.T_cam2_velo, scan[:, :3])
        return geometry.lidar_depth_image(pts_cam2, self.calib.K2, *self.image_size)
