"""Read rerun recordings back with rerun's own reader (``rerun.chunk.RrdReader``), for the viewer tests."""

from __future__ import annotations

from collections import defaultdict
from pathlib import Path

import numpy as np


def read_recording(path: str | Path) -> dict[str, list[tuple[int | None, dict]]]:
    """Rows of an ``.rrd``: {entity path: [(frame or None if static, {column: value})]}."""
    from rerun.chunk import RrdReader

    rows: dict[str, list] = defaultdict(list)
    for chunk in RrdReader(path).stream():
        rb = chunk.to_record_batch()
        cols = {n: rb.column(n).to_pylist() for n in rb.schema.names if n != "rerun.controls.RowId"}
        for i in range(rb.num_rows):
            frame = cols["frame"][i] if "frame" in cols else None
            rows[chunk.entity_path].append((frame, {k: v[i] for k, v in cols.items()}))
    return dict(rows)


def voxel_cells(row: dict, resolution: float) -> set[tuple[int, int, int]]:
    """Absolute cell indices of one ``VoxelGridMap`` row (its indices are relative to its translation)."""
    idx = np.asarray(row["VoxelGridMap:voxel_indices"], dtype=np.int64).reshape(-1, 3)
    t = row.get("VoxelGridMap:translation")
    if t is not None:
        idx = idx + np.round(np.asarray(t[0]) / resolution).astype(np.int64)
    return {tuple(v) for v in idx.tolist()}


def latest_map_rows(rows: dict, frame: int) -> dict[str, dict]:
    """The latest-at row (at ``frame``) of every map block entity that holds cells there."""
    out = {}
    for path, entries in rows.items():
        if not path.startswith("/world/map/occupied/"):
            continue
        past = [e for f, e in sorted((r for r in entries if r[0] is not None), key=lambda r: r[0]) if f <= frame]
        if past and past[-1].get("VoxelGridMap:voxel_indices") is not None:
            out[path] = past[-1]
    return out


def map_cells_at(rows: dict, frame: int, resolution: float) -> set[tuple[int, int, int]]:
    """Occupied cells a viewer shows at ``frame``: the latest-at value of every map block entity."""
    cells: set = set()
    for row in latest_map_rows(rows, frame).values():
        cells |= voxel_cells(row, resolution)
    return cells
