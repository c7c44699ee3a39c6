"""Top-down, height-coloured pictures of OctoMaps (the paper's Fig. 2 style).

World = first cam0 frame: x right, y DOWN, z forward. The picture looks down on the x–z plane;
colour encodes height = -y, normalised over the shown maps (shared range), taken per pixel from
the highest occupied cell.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np


def occupied_centres(tree) -> np.ndarray:
    """(N, 3) world centres of occupied finest-resolution cells (pruned occupied leaves expanded)."""
    res = float(tree.getResolution())
    pts = []
    for it in tree.begin_leafs():
        if not tree.isNodeOccupied(it):
            continue
        c = np.array([it.getX(), it.getY(), it.getZ()])
        n = int(round(it.getSize() / res))
        if n == 1:
            pts.append(c[None, :])
        else:
            g = c - it.getSize() / 2 + res / 2 + res * np.stack(np.meshgrid(*[np.arange(n)] * 3, indexing="ij"), -1).reshape(-1, 3)
            pts.append(g)
    return np.concatenate(pts) if pts else np.zeros((0, 3))


def picture_extent(points: np.ndarray, res: float, pad: float = 2.0) -> tuple[float, float, float, float]:
    """(xmin, xmax, zmin, zmax) around ``points`` (metres, world), padded, with edges on multiples of
    ``res``: OctoMap cell centres ((k + 0.5) · cell) then never fall on a pixel border."""
    x0, x1 = points[:, 0].min() - pad, points[:, 0].max() + pad
    z0, z1 = points[:, 2].min() - pad, points[:, 2].max() + pad
    return (float(np.floor(x0 / res) * res), float(np.ceil(x1 / res) * res),
            float(np.floor(z0 / res) * res), float(np.ceil(z1 / res) * res))


def height_image(points: np.ndarray, extent: tuple[float, float, float, float], res: float) -> np.ndarray:
    """H×W float image of max height (-y) per (x, z) pixel; NaN where empty. extent = (xmin, xmax, zmin, zmax)."""
    xmin, xmax, zmin, zmax = extent
    w = max(1, int(np.ceil((xmax - xmin) / res)))
    h = max(1, int(np.ceil((zmax - zmin) / res)))
    img = np.full(h * w, -np.inf)
    if len(points):
        col = np.clip(((points[:, 0] - xmin) / res).astype(np.int64), 0, w - 1)
        row = np.clip(((zmax - points[:, 2]) / res).astype(np.int64), 0, h - 1)   # forward = up in the picture
        np.maximum.at(img, row * w + col, -points[:, 1])
    img[~np.isfinite(img)] = np.nan
    return img.reshape(h, w)


def render_topdown(maps: list[tuple[str, object]], path: str | Path, res: float | None = None,
                   height_range: tuple[float, float] | None = None, dpi: int = 150) -> Path:
    """Side-by-side top-down pictures of (title, octomap.OcTree) pairs, written atomically as PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from mono_map.io import atomic_path

    clouds = [(title, occupied_centres(tree)) for title, tree in maps]
    allp = np.concatenate([c for _, c in clouds if len(c)]) if any(len(c) for _, c in clouds) else np.zeros((1, 3))
    cell = float(maps[0][1].getResolution())
    # one picture pixel per screen pixel (max height over the cells it covers), never finer than a cell:
    # finer pixels leave empty rows/columns between cells (moire), coarser screen sampling drops cells
    x0, x1 = picture_extent(allp, cell)[:2]
    res = res or max(cell, (x1 - x0) / (4.5 * dpi * 0.8))
    extent = picture_extent(allp, res)
    if height_range is None:
        hgt = -allp[:, 1]
        height_range = (float(np.percentile(hgt, 1)), float(np.percentile(hgt, 99)))
    lo, hi = height_range
    aspect = (extent[3] - extent[2]) / max(extent[1] - extent[0], 1e-6)
    width_in = 4.5 * len(clouds)
    fig, axes = plt.subplots(1, len(clouds), figsize=(width_in, min(4.5 * aspect, 14) + 0.8), squeeze=False)
    for ax, (title, pts) in zip(axes[0], clouds):
        img = height_image(pts, extent, res)
        norm = (img - lo) / max(hi - lo, 1e-6)
        im = ax.imshow(np.clip(norm, 0, 1), cmap="turbo", vmin=0, vmax=1, interpolation="nearest",
                       extent=extent, origin="upper")
        ax.set_facecolor("black")
        ax.set_title(f"{title}\n{len(pts):,} occupied cells", fontsize=9)
        ax.set_xlabel("x (m, right)")
        ax.set_ylabel("z (m, forward)")
    cb = fig.colorbar(im, ax=axes[0].tolist(), fraction=0.02, pad=0.01)
    cb.set_label(f"normalised height (-y), {lo:.1f}…{hi:.1f} m")
    with atomic_path(path, suffix=".png") as tmp:
        fig.savefig(tmp, dpi=dpi, bbox_inches="tight")
    plt.close(fig)
    return Path(path)
