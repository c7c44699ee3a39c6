"""Arrays in, arrays out, for the viewer and the pictures: cell keys, colours, image encoding.

Nothing here imports rerun. World = first cam0 frame (x right, y DOWN, z forward), metres; a map
cell with integer index i has its centre at (i + 0.5)·resolution.
"""

from __future__ import annotations

import functools

import numpy as np

from mono_map.errors import MonoMapError

# Bits per axis when packing integer cell indices into one int64 (indices within ±2^20 cells).
KEY_BITS = 21
KEY_OFFSET = 1 << (KEY_BITS - 1)
KEY_MASK = (1 << KEY_BITS) - 1
DEFAULT_HEIGHT_RANGE = (-2.5, 4.0)   # metres above cam0 (KITTI: ground ≈ -1.65 m, shown blue)
PROBABILITY_RANGE = (0.5, 1.0)       # occupancy probability of occupied cells (OctoMap's threshold 0.5)


# --------------------------------------------------------------------------- cell keys


def cell_indices(centres: np.ndarray, resolution: float) -> np.ndarray:
    """World cell centres (N,3) metres → integer cell indices (N,3) int64, centre = (i+0.5)·res."""
    c = np.asarray(centres, dtype=np.float64).reshape(-1, 3)
    return np.floor(c / resolution).astype(np.int64)


def pack(idx: np.ndarray) -> np.ndarray:
    """Integer cell indices (N,3) → one sortable int64 key each."""
    i = np.asarray(idx, dtype=np.int64) + KEY_OFFSET
    if i.size and (i.min() < 0 or i.max() > KEY_MASK):
        raise MonoMapError("map cells: index outside the ±2^20 cell range the viewer supports")
    return (i[:, 0] << (2 * KEY_BITS)) | (i[:, 1] << KEY_BITS) | i[:, 2]


def unpack(keys: np.ndarray) -> np.ndarray:
    """Inverse of :func:`pack`: int64 keys (N,) → integer indices (N,3) int64."""
    k = np.asarray(keys, dtype=np.int64)
    return np.stack([(k >> (2 * KEY_BITS)) & KEY_MASK, (k >> KEY_BITS) & KEY_MASK, k & KEY_MASK], axis=1) - KEY_OFFSET


def sorted_union(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Sorted unique union of sorted unique ``a`` and any ``b`` (sort-based: numpy 2's hash-based
    ``union1d`` is several times slower on int64 keys)."""
    u = np.sort(np.concatenate([a, b]), kind="stable")
    return u[np.concatenate([[True], u[1:] != u[:-1]])] if len(u) else u


def sorted_difference(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Elements of sorted unique ``a`` not in ``b``."""
    if len(a) == 0 or len(b) == 0:
        return a
    bs = np.sort(b)
    pos = np.minimum(np.searchsorted(bs, a), len(bs) - 1)
    return a[bs[pos] != a]


def group_by_block(idx: np.ndarray, block_cells: int) -> list[tuple[int, np.ndarray]]:
    """Split integer cell indices (N,3) into cubic spatial blocks of ``block_cells`` cells per side.

    Returns [(packed block index, positions in ``idx`` of its cells)], blocks in packed-key order,
    cells in their input order.
    """
    if len(idx) == 0:
        return []
    bkeys = pack(np.floor_divide(idx, block_cells))
    order = np.argsort(bkeys, kind="stable")
    ub, starts = np.unique(bkeys[order], return_index=True)
    ends = np.append(starts[1:], len(order))
    return [(bk, order[s0:s1]) for bk, s0, s1 in zip(ub.tolist(), starts, ends)]


# --------------------------------------------------------------------------- finished trees


def occupied_cells(tree) -> tuple[np.ndarray, float]:
    """Occupied cells of an ``octomap.OcTree`` (or of its :class:`~mono_map.mapping.octree.Leaves`) →
    (centres (N,3) metres at finest resolution, in Morton order, resolution): pruned (merged) occupied
    nodes are expanded into their finest cells."""
    from mono_map.mapping.octree import Leaves, key_to_coord, occupied_keys, tree_leaves

    leaves = tree if isinstance(tree, Leaves) else tree_leaves(tree)
    return key_to_coord(occupied_keys(leaves), leaves.resolution), leaves.resolution


def occupied_cells_from_bt(path) -> tuple[np.ndarray, float]:
    """Read an OctoMap ``.bt`` (or ``.ot``) → :func:`occupied_cells` of it; MonoMapError naming the file."""
    from mono_map.mapping.octree import load_tree

    return occupied_cells(load_tree(path))


def map_bounds(centres: np.ndarray, q=(1.0, 99.0)) -> tuple[np.ndarray, np.ndarray]:
    """Robust bounding box (metres) of cell centres: per-axis percentiles ``q``."""
    c = np.asarray(centres, dtype=np.float64).reshape(-1, 3)
    if len(c) == 0:
        return np.zeros(3), np.zeros(3)
    return np.percentile(c, q[0], axis=0), np.percentile(c, q[1], axis=0)


# --------------------------------------------------------------------------- colours


def heights(idx: np.ndarray, resolution: float) -> np.ndarray:
    """Height above the cam0 origin (metres) of cell centres: world y points down, so height = -y."""
    return (-(np.asarray(idx)[:, 1].astype(np.float64) + 0.5) * resolution).astype(np.float32)


def height_range_of(idx: np.ndarray, resolution: float, q=(2.0, 98.0), pad_low: float = 0.12
                    ) -> tuple[float, float]:
    """Robust height range (metres) of cells for colour normalisation.

    Percentiles ``q`` of the cell heights; the low end is lowered by ``pad_low`` of the span so the
    ground maps to Turbo's blue rather than its near-black bottom.
    """
    if len(idx) == 0:
        return DEFAULT_HEIGHT_RANGE
    lo, hi = (float(v) for v in np.percentile(heights(idx, resolution), q))
    hi = max(hi, lo + resolution)
    return lo - pad_low * (hi - lo), hi


@functools.lru_cache(maxsize=None)
def colormap_lut(name: str = "turbo") -> np.ndarray:
    """256×3 uint8 RGB lookup table of a matplotlib colour map (computed once per name; read-only)."""
    from matplotlib import colormaps

    lut = (colormaps[name](np.linspace(0.0, 1.0, 256))[:, :3] * 255 + 0.5).astype(np.uint8)
    lut.flags.writeable = False
    return lut


def apply_lut(values: np.ndarray, lo: float, hi: float, lut: np.ndarray) -> np.ndarray:
    """Map values to colours: clip to [lo, hi], normalise, look up (…×3 uint8; NaN → ``lo``'s colour)."""
    t = (np.nan_to_num(np.asarray(values, dtype=np.float32), nan=lo) - lo) / max(hi - lo, 1e-9)
    return lut[np.clip((t * 255).astype(np.int32), 0, 255)]


def colourise(values: np.ndarray, lo: float, hi: float, cmap: str = "magma") -> np.ndarray:
    """Any-shape float array → same shape ×3 uint8 RGB, colour map ``cmap`` over [lo, hi]."""
    return apply_lut(values, lo, hi, colormap_lut(cmap))


def probability_colours(probability: np.ndarray, lo: float = PROBABILITY_RANGE[0], hi: float = PROBABILITY_RANGE[1],
                        cmap: str = "viridis") -> np.ndarray:
    """Occupancy probabilities (N,) in [0, 1] → (N,3) uint8 RGB (viridis over [lo, hi]: dark = barely
    occupied, yellow = certain). The logger's ``colour="probability"`` draws cells with the same scale."""
    return colourise(probability, lo, hi, cmap)


# --------------------------------------------------------------------------- image encoding


def _encode(ext: str, img: np.ndarray, params: list[int]) -> bytes:
    import cv2

    ok, buf = cv2.imencode(ext, img, params)
    if not ok:  # pragma: no cover - cv2 failure
        raise MonoMapError(f"viewer: could not encode a {ext} image")
    return buf.tobytes()


def encode_jpeg_rgb(rgb: np.ndarray, quality: int = 85) -> bytes:
    """H×W×3 uint8 RGB → JPEG bytes."""
    return encode_jpeg_bgr(np.ascontiguousarray(rgb[..., ::-1]), quality)


def encode_jpeg_bgr(bgr: np.ndarray, quality: int = 85) -> bytes:
    """H×W×3 uint8 BGR (OpenCV order) → JPEG bytes."""
    import cv2

    return _encode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, quality])


def encode_png(gray_or_u16: np.ndarray) -> bytes:
    """H×W uint8 or uint16 → PNG bytes (fast compression)."""
    import cv2

    return _encode(".png", np.ascontiguousarray(gray_or_u16), [cv2.IMWRITE_PNG_COMPRESSION, 1])
