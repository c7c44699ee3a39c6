"""The depth evaluation behind ``mono-map eval-depth``: depth checkpoints on frames with ground truth —
standard metrics (log / linear expectation, arg-max), sparsification curves + AUC (Table II), oracle
hypotheses (Table III), ms/frame — and a Markdown report (the command writes JSON and the plots).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable

import numpy as np

from mono_map.eval.depth_metrics import LABELS, METRICS, distance_bands, image_errors, mean_errors, valid_mask
from mono_map.eval.hypotheses import oracle_errors
from mono_map.eval.sparsification import sparsification

MS = (1, 3, 5, 10)


def object_frames(root: str | Path) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """Real KITTI object-benchmark frames -> [(name, RGB image, LiDAR depth of image_2 in metres)]."""
    from mono_map.data.kitti_files import read_image_rgb, read_velodyne_bin
    from mono_map.data.kitti_odometry import read_object_calibration
    from mono_map.errors import MonoMapError
    from mono_map.geometry import lidar_depth_image, transform_points

    root = Path(root)
    images = sorted((root / "image_2").glob("*.png"))
    if not images:
        raise MonoMapError(f"{root}: no image_2/*.png (expected a KITTI object 'training' folder)")
    out = []
    for p in images:
        calib = read_object_calibration(root / "calib" / f"{p.stem}.txt")
        img = read_image_rgb(p)
        scan = read_velodyne_bin(root / "velodyne" / f"{p.stem}.bin")
        pts = transform_points(calib.T_cam2_velo, scan[:, :3])
        out.append((p.stem, img, lidar_depth_image(pts, calib.K2, *img.shape[:2])))
    return out


def scrambled_colour(frames) -> list[tuple[str, float]]:
    """(name, :func:`~mono_map.data.kitti_files.colour_agreement`) of the (name, RGB image, …) frames whose colour
    channels do not agree (below ``COLOUR_AGREEMENT_MIN``): files whose colours were scrambled somewhere between
    the camera and here. They are scored like any frame; callers say so, and report pools without them."""
    from mono_map.data.kitti_files import COLOUR_AGREEMENT_MIN, colour_agreement

    out = []
    for name, image, *_ in frames:
        a = colour_agreement(image)
        if a < COLOUR_AGREEMENT_MIN:
            out.append((name, a))
    return out


def open_town(root: str, town: str):
    """A town of the training cache (``root`` "default" = ``trainset.default_root()``) for reading."""
    from mono_map.data.synth.trainset import default_root, open_trainset
    from mono_map.errors import MonoMapError

    base = default_root() if root == "default" else Path(root).expanduser()
    towns = open_trainset(base, [town])
    if not towns:
        raise MonoMapError(f"--trainset-town: no town {town!r} under {base}/towns")
    return towns[0]


def trainset_frames(town, indices, gt: str = "lidar") -> list[tuple[str, np.ndarray, np.ndarray]]:
    """Frames of a training-cache town -> [(name, RGB 192×634, ground truth metres, 0 = none)]; sky has no value."""
    from mono_map.data.synth.trainset import decode_depth
    from mono_map.errors import MonoMapError

    done = set(town.done_frames().tolist())
    out = []
    for i in indices:
        if i not in done:
            raise MonoMapError(f"--frames: frame {i} of town {town.path.name} is not rendered yet")
        d, _ = decode_depth(town.lidar[i] if gt == "lidar" else town.dense[i])
        out.append((f"{town.path.name}_{i:04d}", np.asarray(town.image[i]), d))
    return out


@dataclass(frozen=True)
class SplitSelection:
    """The frames of a split file found under a raw root: ``frames`` [(drive, frame number, sequence, index)],
    ``n_listed`` lines, ``missing_drives`` drive folders not under the root."""

    path: Path
    frames: list
    n_listed: int
    missing_drives: list[str]


def split_path(split: str) -> Path:
    """``eigen`` → the packaged Eigen test split (``data/kitti_assets/eigen_test_files.txt``), else a file path."""
    from mono_map.errors import MonoMapError
    from mono_map.paths import KITTI_ASSETS_DIR

    path = KITTI_ASSETS_DIR / "eigen_test_files.txt" if split == "eigen" else Path(split).expanduser()
    if not path.is_file():
        raise MonoMapError(f"--split: {split}: no such split file (eigen, or a file of 'DATE/DRIVE FRAME l' lines)")
    return path


def split_frames(root: str | Path, split: str) -> SplitSelection:
    """The frames of split ``split`` (``eigen`` or a file) present under the raw root ``root``; a drive that is
    there is opened (and validated) once; a listed frame its drive lacks is left out, like a missing drive."""
    from mono_map.data.kitti import open_sequence
    from mono_map.data.kitti_raw import parse_split
    from mono_map.errors import MonoMapError

    path = split_path(split)
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise MonoMapError(f"{path}: unreadable split file ({exc.__class__.__name__})") from None
    lines = parse_split(text, path)
    root = Path(root)
    seqs, missing, frames = {}, [], []
    for line in lines:
        if line.drive not in seqs:
            there = (root / line.date / line.drive).is_dir() or (root / line.drive).is_dir()
            seqs[line.drive] = open_sequence(root, line.drive) if there else None
            if not there:
                missing.append(line.drive)
            elif not seqs[line.drive].velodyne_files:   # the ground truth is made from the scans
                raise MonoMapError(f"{seqs[line.drive].path / 'velodyne_points' / 'data'}: no velodyne scans "
                                   f"(the split's ground truth is made from them)")
        seq = seqs[line.drive]
        if seq is None:
            continue
        index = {int(f.stem): i for i, f in enumerate(seq.image_files) if f.stem.isdigit()}
        if line.frame in index:
            frames.append((line.drive, line.frame, seq, index[line.frame]))
    return SplitSelection(path, frames, len(lines), missing)


def eigen_frames(selection: SplitSelection):
    """Yield (name, image, Eigen ground truth, full-image ground truth) of a split's frames: the scan projected
    as Eigen's protocol does (:func:`mono_map.data.kitti_raw.eigen_depth_map`, raw calibration) and by
    mono-map's own projection (``seq.lidar_depth``), for :func:`evaluate_model`'s one pass."""
    from mono_map.data.kitti_raw import eigen_depth_map

    for drive, frame, seq, i in selection.frames:
        rc = seq.raw_calib
        eigen = eigen_depth_map(seq.velodyne(i), rc.P_rect_02, rc.T_cam0_velo, *seq.image_size)
        yield f"{drive}_{frame:010d}", seq.image(i), eigen, seq.lidar_depth(i)


def evaluate_model(predictor, frames: Iterable[tuple[str, np.ndarray, np.ndarray]], n_frames: int | None = None,
                   cap: float = 80.0, garg_crop: bool = False, time_frames: int = 10, desc: str = "") -> dict:
    """Run ``predictor`` over (name, image, gt depth) frames and collect every statistic.

    A frame may carry a second ground truth, (name, image, gt, gt_full): the same prediction is then also
    scored against it over the whole image (no crop), as ``metrics_full_image`` — one network pass for both."""
    import torch
    import torch.nn.functional as F

    from mono_map.depth.distribution import std_log_depth, top_bins, top_modes
    from mono_map.progress import progress

    bins = predictor.bins
    per = {"log": [], "linear": [], "argmax": [], "median": [], "full": []}
    n_full = 0
    ratios = []
    pooled = {k: [] for k in ("gt", "log", "linear", "argmax", "entropy", "std_log", "modes", "top_bins")}
    times = []
    names = []
    n_hyp, has_probs = None, False
    for j, (name, image, gt, *second) in enumerate(progress(frames, total=n_frames, desc=desc or "eval-depth",
                                                            unit="frame")):
        if j == 0:
            predictor.predict(image)  # warm-up, not timed
        if j < time_frames:
            t0 = time.perf_counter()
            predictor.predict(image)
            times.append(1000 * (time.perf_counter() - t0))
        out, geom = predictor.raw_outputs([image])
        with torch.inference_mode():
            r_log = predictor.decode(out, "log", with_probs=True)
            r_lin = predictor.decode(out, "linear")
            probs = r_log["probs"]
            if probs is not None:  # second uncertainty measure: std of log-depth under the distribution
                has_probs = True
                std_log = std_log_depth(probs, bins)
            else:
                std_log = torch.zeros_like(r_log["entropy"])
            maps = torch.stack([r_log["depth"], r_lin["depth"], r_log["argmax"], r_log["entropy"], std_log], 1)
            maps = predictor.to_image(maps, geom)[0].numpy()

            def nearest(t: torch.Tensor) -> np.ndarray:   # (1, M, h', w') hypotheses -> (M, h, w) at the pixels
                (H, W), (fh, fw), (h, w), low = geom
                if low:
                    t = F.interpolate(t, size=(H, W), mode="nearest")
                return F.interpolate(t[..., :fh, :fw], size=(h, w), mode="nearest")[0].numpy()

            if r_log["probs"] is not None:   # the paper's M most probable bins, and the M most probable modes
                top = nearest(top_bins(r_log["probs"], bins, max(MS))[0])
                modes = nearest(top_modes(r_log["probs"], bins, max(MS))[0])
            elif r_log.get("modes") is not None:   # MHL: its M hypotheses, one code path with the bin heads'
                n_hyp = int(r_log["modes"].shape[1])
                modes = nearest(r_log["modes"][:, :max(MS)])
                if len(modes) < max(MS):     # fewer hypotheses than asked: repeat the last
                    modes = np.concatenate([modes, np.repeat(modes[-1:], max(MS) - len(modes), 0)])
                top = modes
            else:
                top = modes = maps[None, 0].repeat(max(MS), 0)
        m = valid_mask(gt, cap, garg_crop=garg_crop)
        clip = lambda a: np.clip(a, 1e-3, cap)  # noqa: E731
        for key, idx in (("log", 0), ("linear", 1), ("argmax", 2)):
            per[key].append(image_errors(gt, maps[idx], cap, garg_crop=garg_crop))
            pooled[key].append(clip(maps[idx][m]))
        if m.any():   # monocular methods' convention: each image scaled by median(gt) / median(prediction)
            ratios.append(float(np.median(gt[m]) / np.median(maps[0][m])))
            per["median"].append(image_errors(gt, maps[0] * ratios[-1], cap, garg_crop=garg_crop))
        if second:
            per["full"].append(image_errors(second[0], maps[0], cap))
            n_full += int(valid_mask(second[0], cap).sum())
        pooled["gt"].append(gt[m].astype(np.float64))
        pooled["entropy"].append(maps[3][m])
        pooled["std_log"].append(maps[4][m])
        pooled["modes"].append(clip(modes[:, m]))
        pooled["top_bins"].append(clip(top[:, m]))
        names.append(name)
    if not names:
        raise ValueError("evaluate_model: no frames")
    P = {k: np.concatenate(v, axis=-1) for k, v in pooled.items()}
    spars = sparsification(P["gt"], P["log"], P["entropy"])
    spars_std = sparsification(P["gt"], P["log"], P["std_log"])
    return {
        "head": predictor.head,
        "checkpoint": str(predictor.checkpoint),
        "training": {k: predictor.training.get(k) for k in ("steps", "step", "wall_time_s", "command", "data")},
        "frames": names, "n_frames": len(names), "n_pixels": int(P["gt"].size),
        "metrics": mean_errors(per["log"]),
        "per_frame": {n: {k: float(v) for k, v in e.items()} for n, e in zip(names, per["log"])},
        "metrics_linear": mean_errors(per["linear"]),
        "metrics_argmax": mean_errors(per["argmax"]),
        "metrics_median_scaled": mean_errors(per["median"]),
        "by_distance": distance_bands(P["gt"], P["log"]),         # pooled pixels, by ground-truth distance
        "median_ratio": {"median": float(np.median(ratios)), "std": float(np.std(ratios))} if ratios else None,
        "metrics_full_image": mean_errors(per["full"]) if per["full"] else None,
        "n_pixels_full_image": n_full if per["full"] else None,
        "mean_entropy": float(P["entropy"].mean()),                    # nats, at the ground-truth pixels
        "sparsification": spars,
        "auc_std_log": spars_std["auc"],
        # an uncertainty equal at every pixel (l2, berhu, MHL with one hypothesis) ranks nothing: its AUCs are
        # those of an arbitrary order, reported as "no uncertainty"; std-log needs bin probabilities
        "has_uncertainty": bool(np.ptp(P["entropy"]) > 0) if P["entropy"].size else False,
        "has_distribution": has_probs,
        "n_hypotheses": n_hyp,       # MHL: the hypotheses it was trained with (None: modes of a distribution)
        # Table III: the paper's hypotheses are a distribution's M highest-scoring bins ("we report back M depth
        # hypotheses with the highest scores"); its M most probable local maxima (modes) are reported beside them
        "hypotheses": {str(k): v for k, v in oracle_errors(P["gt"], P["top_bins"], MS).items()},
        "hypotheses_modes": {str(k): v for k, v in oracle_errors(P["gt"], P["modes"], MS).items()},
        "ms_per_frame": float(np.median(times)) if times else None,
    }


def distance_table(label_columns: list[str], rows: list[tuple[list[str], list[dict]]]) -> list[str]:
    """Markdown lines of a table by ground-truth distance: per row its labels (``label_columns``' values) and one
    :func:`~mono_map.eval.depth_metrics.distance_bands` result, one cell per band ("share % / median ratio /
    AbsRel", "–" for an empty band); the bands' header from the first row. No rows: no lines."""
    if not rows:
        return []
    bands = rows[0][1]
    L = ["| " + " | ".join([*label_columns, *(f"{b['lo']:g}–{b['hi']:g} m" for b in bands)]) + " |",
         "|" + "---|" * len(label_columns) + "---:|" * len(bands)]
    for labels, result in rows:
        cells = [f"{100 * b['share']:.1f} % / {b['median_ratio']:.2f} / {b['abs_rel']:.3f}" if b["n_pixels"] else "–"
                 for b in result]
        L.append("| " + " | ".join([*labels, *cells]) + " |")
    return L


def markdown_report(results: dict[str, dict], title: str) -> str:
    heads = list(results)
    L = [f"# {title}", ""]
    any_r = next(iter(results.values()))
    L.append(f"{any_r['n_frames']} frames, {any_r['n_pixels']} ground-truth pixels; depth = log-space expectation "
             "exp(Σ p log d) unless noted; uncertainty = entropy (nats).")
    L += ["", "## Depth metrics", "",
          "| head | " + " | ".join(LABELS[m] for m in METRICS) + " | ms/frame |",
          "|---|" + "---|" * (len(METRICS) + 1)]
    for h in heads:
        r = results[h]
        L.append(f"| {h} | " + " | ".join(f"{r['metrics'][m]:.3f}" for m in METRICS) + f" | {r['ms_per_frame']:.0f} |")
    L += ["", "## By ground-truth distance (share of the pixels / median predicted ÷ true depth, below 1 too near / "
          "AbsRel)", ""]
    L += distance_table(["head"], [([h], results[h]["by_distance"]) for h in heads])
    if any_r["n_frames"] <= 10:   # few frames (e.g. the real KITTI ones): every frame, since three are a hint
        L += ["", "## Per frame (AbsRel / RMSE / δ<1.25)", "", "| head | " + " | ".join(any_r["per_frame"]) + " |",
              "|---|" + "---|" * len(any_r["per_frame"])]
        for h in heads:
            pf = results[h]["per_frame"]
            L.append(f"| {h} | " + " | ".join(f"{e['abs_rel']:.3f} / {e['rmse']:.2f} / {e['a1']:.3f}"
                                               for e in pf.values()) + " |")
    L += ["", "## Expectation: log space vs linear vs arg-max", "",
          "| head | AbsRel log | AbsRel linear | AbsRel arg-max | RMSE log | RMSE linear | RMSE arg-max | δ1 log | δ1 linear | δ1 arg-max |",
          "|---|---|---|---|---|---|---|---|---|---|"]
    for h in heads:
        r = results[h]
        a, b, c = r["metrics"], r["metrics_linear"], r["metrics_argmax"]
        L.append(f"| {h} | {a['abs_rel']:.4f} | {b['abs_rel']:.4f} | {c['abs_rel']:.4f} | {a['rmse']:.3f} | "
                 f"{b['rmse']:.3f} | {c['rmse']:.3f} | {a['a1']:.4f} | {b['a1']:.4f} | {c['a1']:.4f} |")
    L += ["", "## Uncertainty: sparsification AUC (lower is better; paper Table II, ARE and 1−δ1 in %)", "",
          "Model = pixels ranked by entropy; oracle = ranked by the true error; random = no ranking; "
          "std-log = ranked by the standard deviation of log-depth under the predicted distribution instead of entropy.", "",
          "| head | AUC ARE (%) | AUC RMSE (m) | AUC 1−δ1 (%) | oracle ARE | oracle RMSE | oracle 1−δ1 | random ARE | random RMSE | random 1−δ1 | std-log: ARE | std-log: RMSE | std-log: 1−δ1 |",
          "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]

    def aucs(a: dict, ok: bool, none: str) -> str:
        return f"{100*a['are']:.2f} | {a['rmse']:.3f} | {100*a['1-d1']:.2f}" if ok else " | ".join([none] * 3)

    for h in heads:
        r = results[h]
        s = r["sparsification"]
        unc = r["has_uncertainty"]
        dist_ok = r["has_distribution"]
        std_log = aucs(r["auc_std_log"], unc and dist_ok, "no distribution" if unc else "no uncertainty")
        L.append(f"| {h} | {aucs(s['auc'], unc, 'no uncertainty')} | {aucs(s['auc_oracle'], True, '')} | "
                 f"{aucs(s['auc_random'], True, '')} | {std_log} |")

    def best_of(hy: dict, m: int, n_hyp: int | None) -> str:
        if n_hyp is not None and m < n_hyp:      # MHL-M's first m < M outputs are no hypothesis set of their own
            return "– | – | –"
        return f"{hy[str(m)]['abs_rel']:.4f} | {hy[str(m)]['rmse']:.3f} | {hy[str(m)]['a1']:.4f}"

    for key, what in (("hypotheses", "the M most probable bins, the paper's protocol; paper Table III / Fig. 6"),
                      ("hypotheses_modes", "the M most probable modes, i.e. local maxima of the distribution")):
        L += ["", f"## Oracle multi-hypothesis evaluation ({what})", "",
              "| head | " + " | ".join(f"ARE M={m} | RMSE M={m} | δ1 M={m}" for m in MS) + " |",
              "|---|" + "---|---|---|" * len(MS)]
        for h in heads:
            r = results[h]
            L.append(f"| {h} | " + " | ".join(best_of(r[key], m, r["n_hypotheses"]) for m in MS) + " |")
    if any(results[h]["n_hypotheses"] for h in heads):
        L += ["", "MHL models are evaluated at M ≥ the number of hypotheses they were trained with (beyond it, "
              "their M repeat) and give the same M in both tables."]
    return "\n".join(L) + "\n"



def table_one(results: dict[str, dict], title: str, found: int, listed: int) -> str:
    """Table-I-style Markdown: per model (``results[model]``, :func:`evaluate_model` on :func:`eigen_frames`)
    the seven standard metrics under Eigen's protocol, median-scaled, and over the full image."""
    keys = ("abs_rel", "sq_rel", "rmse", "rmse_log", "a1", "a2", "a3")
    rows = (("metrics", "Eigen: raw-calibration LiDAR, Garg crop, 1e-3–80 m"),
            ("metrics_median_scaled", "Eigen, per-image median scaling"),
            ("metrics_full_image", "full image, mono-map's LiDAR projection, 1e-3–80 m"))
    L = [f"# {title}", "", f"{found} of the {listed} frames of the split found; depth = log-space expectation.", "",
         "| model | protocol | " + " | ".join(LABELS[k] for k in keys) + " |", "|---|---|" + "---|" * len(keys)]
    for model, r in results.items():
        for field, label in rows:
            m = r[field]
            L.append(f"| {model} | {label} | " + " | ".join(f"{m[k]:.3f}" for k in keys) + " |")
    return "\n".join(L) + "\n"
