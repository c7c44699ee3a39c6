"""Every matplotlib figure of mono-map, written atomically as PNG (dicts and trees in, files out).

* :func:`render_topdown` — top-down, height-coloured pictures of OctoMaps (the paper's Fig. 2 style).
  World = first cam0 frame: x right, y DOWN, z forward. The picture looks down on the x–z plane;
  colour encodes height = -y, normalised over the shown maps (shared range), taken per pixel from
  the highest occupied cell.
* :func:`plot_table` — every picture of ``eval --table`` (the next three and the top-down maps).
* :func:`plot_sweep` — map accuracy and memory against ``keep`` (``eval --table``).
* :func:`plot_accuracy_memory` — accuracy against memory: keep sweep a curve, distribution map a point.
* :func:`plot_reliability` — reliability diagrams of maps' occupancy probabilities (``eval --table``).
* :func:`plot_sparsification` — sparsification and oracle curves per head (``mono-map eval-depth``).
* :func:`plot_hypotheses` — oracle multi-hypothesis errors against M (``mono-map eval-depth``).
"""

from __future__ import annotations

import contextlib
from pathlib import Path
from typing import Iterator

import numpy as np

from mono_map.viz.codec import occupied_cells


@contextlib.contextmanager
def figure(path: str | Path, dpi: int, **savefig) -> Iterator:
    """``with figure(path, dpi) as plt:`` draw with pyplot; on exit the current figure is saved
    atomically to ``path`` (PNG) and closed."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from mono_map.io import atomic_path

    try:
        yield plt
        with atomic_path(path, suffix=".png") as tmp:
            plt.gcf().savefig(tmp, dpi=dpi, **savefig)
    finally:
        plt.close(plt.gcf())


def error_image(depth: np.ndarray, lidar: np.ndarray) -> np.ndarray:
    """log2(depth / lidar) at the LiDAR pixels (each spread to its 3×3 neighbourhood, the nearer point winning),
    NaN elsewhere; both (H,W) metres, 0 = no LiDAR point."""
    H, W = lidar.shape
    pad = np.pad(np.where(lidar > 0, lidar, np.inf), 1, constant_values=np.inf)
    near = np.min([pad[dy:dy + H, dx:dx + W] for dy in range(3) for dx in range(3)], axis=0)   # 3×3 minimum
    ok = np.isfinite(near) & (depth > 0)
    out = np.full(depth.shape, np.nan, np.float32)
    out[ok] = np.log2(depth[ok] / near[ok])
    return out


def write_picture(path: str | Path, rgb: np.ndarray) -> None:
    """Write an H×W×3 uint8 RGB picture to ``path`` atomically: JPEG (quality 85) for .jpg/.jpeg, else PNG."""
    import cv2

    from mono_map.io import atomic_path

    jpeg = Path(path).suffix.lower() in (".jpg", ".jpeg")
    ok, buf = cv2.imencode(".jpg" if jpeg else ".png", cv2.cvtColor(np.ascontiguousarray(rgb), cv2.COLOR_RGB2BGR),
                           [cv2.IMWRITE_JPEG_QUALITY, 85] if jpeg else [cv2.IMWRITE_PNG_COMPRESSION, 9])
    if not ok:  # pragma: no cover - cv2 failure
        raise OSError(f"{path}: could not encode the picture")
    with atomic_path(path) as tmp:
        tmp.write_bytes(buf.tobytes())


# --------------------------------------------------------------------------- top-down maps


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
    """Side-by-side top-down pictures of (title, octomap.OcTree or its Leaves) pairs, written atomically as PNG."""
    cells = [(title, occupied_cells(tree)) for title, tree in maps]
    clouds = [(title, c) for title, (c, _) in cells]
    allp = np.concatenate([c for _, c in clouds if len(c)]) if any(len(c) for _, c in clouds) else np.zeros((1, 3))
    cell = float(cells[0][1][1])
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
    with figure(path, dpi, bbox_inches="tight") as plt:
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
    return Path(path)


# --------------------------------------------------------------------------- map table


def plot_table(table, folder: Path | None = None) -> list[str]:
    """The pictures of a :class:`mono_map.eval.table.Table` beside its Markdown (in ``folder``, default its
    ``out_dir``): the keep sweep and, for the extended table, accuracy vs memory and the reliability
    diagram, then the top-down maps; their file names."""
    ref_label = "LiDAR-FOV" if table.reference == "lidar-fov" else "LiDAR"
    out, stem = Path(folder or table.out_dir), table.stem
    plot_sweep(table.rows, out / f"{stem}_sweep.png", ref_label)
    pngs = [f"{stem}_sweep.png"]
    if table.extended:
        plot_accuracy_memory(table.rows, out / f"{stem}_acc_memory.png", ref_label)
        plot_reliability(table.reliability, out / f"{stem}_reliability.png", ref_label)
        pngs += [f"{stem}_acc_memory.png", f"{stem}_reliability.png"]
    render_topdown(table.topdown, out / f"{stem}_topdown.png")
    return pngs + [f"{stem}_topdown.png"]


def plot_sweep(rows: list[dict], path: Path, reference_label: str = "LiDAR-FOV") -> None:
    """Accuracy (left axis) and memory (right axis) of the mono rows against keep; the LiDAR-FOV row's
    memory as a dotted line. ``rows``: ``eval --table`` rows (source, keep, accuracy, accuracy_covered,
    memory_mb)."""
    mono = sorted((r for r in rows if r["source"] == "mono"), key=lambda r: r["keep"])
    ref = next(r for r in rows if r["source"] == "lidar-fov")
    keeps = [r["keep"] for r in mono]
    with figure(path, 130) as plt:
        fig, ax1 = plt.subplots(figsize=(6, 4.6))
        ax1.plot(keeps, [100 * r["accuracy"] for r in mono], "o-", color="tab:blue", label="accuracy")
        ax1.plot(keeps, [100 * r["accuracy_covered"] for r in mono], "s--", color="tab:cyan",
                 label="accuracy (covered cells)")
        ax1.set_xlabel("keep (fraction of lowest-entropy pixels)")
        ax1.set_ylabel(f"accuracy vs {reference_label} map (%)", color="tab:blue")
        ax2 = ax1.twinx()
        ax2.plot(keeps, [r["memory_mb"] for r in mono], "^-", color="tab:red", label="memory")
        ax2.axhline(ref["memory_mb"], color="tab:red", ls=":", lw=1, label="LiDAR-FOV memory")
        ax2.set_ylabel("memory (MB, OctoMap memoryUsage)", color="tab:red")
        h1, l1 = ax1.get_legend_handles_labels()
        h2, l2 = ax2.get_legend_handles_labels()
        ax1.legend(h1 + h2, l1 + l2, fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.16), ncol=2,
                   frameon=False)  # below the axes: the curves use the whole plot
        ax1.grid(alpha=0.3)
        fig.tight_layout()


def plot_accuracy_memory(rows: list[dict], path: Path, reference_label: str = "LiDAR-FOV") -> None:
    """Accuracy (and accuracy on covered cells) against memory: the keep sweep (source "mono") a
    curve, the distribution map (source "mono-distribution") a point."""
    sweep = sorted((r for r in rows if r["source"] == "mono"), key=lambda r: r["memory_mb"])
    dist = [r for r in rows if r["source"] == "mono-distribution"]
    with figure(path, 130) as plt:
        fig, ax = plt.subplots(figsize=(6.4, 4.6))
        for key, style, name in (("accuracy", "o-", "accuracy"), ("accuracy_covered", "s--", "acc. on covered cells")):
            ax.plot([r["memory_mb"] for r in sweep], [100 * r[key] for r in sweep], style, color="tab:blue",
                    label=f"keep sweep: {name}", alpha=1.0 if key == "accuracy" else 0.6)
            for r in dist:
                ax.plot(r["memory_mb"], 100 * r[key], "*" if key == "accuracy" else "P", color="tab:red", ms=14,
                        label=f"distribution: {name}", alpha=1.0 if key == "accuracy" else 0.6)
        for r in sweep:
            ax.annotate(f"{r['keep']:g}", (r["memory_mb"], 100 * r["accuracy"]), textcoords="offset points",
                        xytext=(4, -10), fontsize=7, color="tab:blue")
        ax.set_xlabel("memory (MB, OctoMap memoryUsage)")
        ax.set_ylabel(f"accuracy vs {reference_label} map (%)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.16), ncol=2, frameon=False)
        fig.tight_layout()


def plot_reliability(reliability: dict, path: Path, reference_label: str = "LiDAR-FOV") -> None:
    """Reliability diagram: per map (label -> :func:`mono_map.eval.map_metrics.calibration` result), the
    share of cells the reference has occupied against the map's occupancy probability (binned), with
    the bins' weights below."""
    with figure(path, 130) as plt:
        fig, (ax, axw) = plt.subplots(2, 1, figsize=(5.6, 6.2), sharex=True, gridspec_kw={"height_ratios": [3, 1]})
        ax.plot([0, 1], [0, 1], ":", color="grey", lw=1, label="perfectly calibrated")
        n = max(len(reliability), 1)
        for j, (label, cal) in enumerate(reliability.items()):
            conf, freq, w = (np.asarray(cal[k], dtype=float) for k in ("confidence", "frequency", "weight"))
            ok = w > 0
            ax.plot(conf[ok], freq[ok], "o-", label=f"{label} (ECE {cal['ece']:.3f})")
            edges = np.asarray(cal["bin_edges"])
            width = (edges[1] - edges[0]) / (n + 1)
            axw.bar(edges[:-1] + (j + 0.5) * width, w, width=width, align="edge", label=label)
        ax.set_ylabel(f"share occupied in the {reference_label} map")
        ax.set_xlim(0, 1)
        ax.set_ylim(0, 1)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
        axw.set_xlabel("map's occupancy probability (cells both maps know)")
        axw.set_ylabel("share of cells")
        axw.set_yscale("log")
        fig.tight_layout()


# --------------------------------------------------------------------------- depth evaluation


def plot_sparsification(results: dict[str, dict], path: Path) -> None:
    """Sparsification curves (entropy-ranked) and oracle curves (error-ranked) of ARE, RMSE and 1 − δ1,
    one colour per head. ``results``: head → ``evaluate_model`` result (its "sparsification" entry)."""
    with figure(path, 110) as plt:
        fig, axes = plt.subplots(1, 3, figsize=(15, 4.2))
        names = {"are": "ARE", "rmse": "RMSE (m)", "1-d1": "1 − δ1"}
        for ax, key in zip(axes, ("are", "rmse", "1-d1")):
            for i, (h, r) in enumerate(results.items()):
                s = r["sparsification"]
                x = 100 * np.asarray(s["fractions"])
                c = f"C{i}"
                if r["has_uncertainty"]:       # a constant uncertainty ranks nothing: no model curve
                    ax.plot(x, s["model"][key], color=c, label=f"{h} (AUC {s['auc'][key]:.3g})")
                ax.plot(x, s["oracle"][key], color=c, ls="--", lw=0.8, label=f"{h} oracle")
            ax.set_xlabel("% most confident pixels kept")
            ax.set_ylabel(names[key])
            ax.grid(alpha=0.3)
            ax.legend(fontsize=7)
        fig.suptitle("Sparsification curves (entropy-ranked) and oracle curves (error-ranked)")
        fig.tight_layout()


def plot_hypotheses(results: dict[str, dict], path: Path) -> None:
    """Oracle ARE and RMSE against the number of hypotheses M (paper Fig. 6): one line per distribution head
    (its M most probable bins; dashed, its M most probable modes) and one line through the MHL models, each at
    the M it was trained with. ``results``:
    head → ``evaluate_model`` result (its "hypotheses" entry: str(M) → errors; "n_hypotheses" for MHL)."""
    with figure(path, 110) as plt:
        fig, axes = plt.subplots(1, 2, figsize=(11, 5.2))
        ms = sorted({int(m) for r in results.values() for m in r["hypotheses"]})
        mhl = sorted((r["n_hypotheses"], r["hypotheses"][str(r["n_hypotheses"])], h) for h, r in results.items()
                     if r["n_hypotheses"] and str(r["n_hypotheses"]) in r["hypotheses"])
        lines = [(h, ms, [r["hypotheses"][str(m)] for m in ms]) for h, r in results.items()
                 if not r["n_hypotheses"]]
        if mhl:
            lines.append((f"MHL ({', '.join(h for _, _, h in mhl)})", [m for m, _, _ in mhl], [e for _, e, _ in mhl]))
        for i, (label, x, errs) in enumerate(lines):
            axes[0].plot(x, [e["abs_rel"] for e in errs], "o-", color=f"C{i}", label=label)
            axes[1].plot(x, [e["rmse"] for e in errs], "o-", color=f"C{i}", label=label)
            r = results.get(label)              # None for the MHL line
            if r is not None and r["has_distribution"]:   # its modes beside its top bins
                em = [r["hypotheses_modes"][str(m)] for m in x]
                axes[0].plot(x, [e["abs_rel"] for e in em], "s--", color=f"C{i}", lw=0.9, ms=4, label=f"{label}, modes")
                axes[1].plot(x, [e["rmse"] for e in em], "s--", color=f"C{i}", lw=0.9, ms=4, label=f"{label}, modes")
        for ax, lab in zip(axes, ("ARE", "RMSE (m)")):
            ax.set_xlabel("number of hypotheses M (oracle picks the best)")
            ax.set_ylabel(lab)
            ax.set_xticks(ms)
            ax.grid(alpha=0.3)
        handles, labels = axes[0].get_legend_handles_labels()      # one legend below both panels
        fig.legend(handles, labels, loc="lower center", ncol=min(4, len(labels)), fontsize=8, frameon=False)
        fig.suptitle("Oracle best of M: a distribution's M most probable bins (solid), its M modes (dashed), "
                     "MHL models at their own M", fontsize=10)
        fig.tight_layout(rect=(0, 0.06 + 0.035 * ((len(labels) - 1) // 4), 1, 0.96))
