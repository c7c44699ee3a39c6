"""OctoMap scan-graph files (``.graph``), for OctoMap's own tools (graph2tree, eval_octree_accuracy).

Binary layout (OctoMap ``ScanGraph::writeBinary``, little-endian as on x86):
``uint32 n_nodes``; per node: point cloud ``uint32 n`` + n × (``int32 3`` + 3 × float64),
pose = translation (``int32 3`` + 3 × float64) + rotation quaternion (``int32 4`` + 4 × float64,
w x y z), ``uint32 id``; then ``uint32 n_edges`` (0 here). OctoMap reads the float64s back into
float32 points.
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np

from mono_map.io import atomic_path


def _vec_records(values: np.ndarray, count: int) -> bytes:
    """Records of (int32 count, count × float64), packed."""
    dt = np.dtype([("n", "<i4"), ("v", "<f8", (count,))], align=False)
    rec = np.empty(len(values), dtype=dt)
    rec["n"] = count
    rec["v"] = values
    return rec.tobytes()


def write_scan_graph(path: str | Path, scans: list[tuple[np.ndarray, np.ndarray]], local: bool = False) -> Path:
    """Write scans [(points (N, 3), origin (3,)), ...] as a ``.graph`` file (atomically).

    local=False: points are stored as given (world frame); use ``graph2tree -g``.
    local=True: points are stored relative to the origin (pose = translation only), as
    ``eval_octree_accuracy`` (which always transforms by the pose) expects; OctoMap then adds the
    origin back in float32.
    """
    with atomic_path(path, suffix=".graph") as tmp, open(tmp, "wb") as fh:
        fh.write(struct.pack("<I", len(scans)))
        for i, (pts, origin) in enumerate(scans):
            pts = np.asarray(pts, dtype=np.float64).reshape(-1, 3)
            origin = np.asarray(origin, dtype=np.float64).reshape(3)
            if local:
                pts = pts.astype(np.float32) - origin.astype(np.float32)
            fh.write(struct.pack("<I", len(pts)))
            fh.write(_vec_records(pts.astype(np.float64), 3))
            fh.write(_vec_records(origin[None, :], 3))
            fh.write(_vec_records(np.array([[1.0, 0.0, 0.0, 0.0]]), 4))
            fh.write(struct.pack("<I", i))
        fh.write(struct.pack("<I", 0))
    return Path(path)
