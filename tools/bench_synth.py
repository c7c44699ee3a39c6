"""Benchmark synthetic sequence generation (frames/s) and optionally save a preview picture.

    python tools/bench_synth.py --seq 00 --frames 40 --workers 2
    python tools/bench_synth.py --seq tiny --preview docs/images/synth_frame.png --frame 3

Generates into a temporary root (never touches ./data), reports end-to-end frames/s
(town build + worker start-up included, and the steady rate without them) and the
per-stage time split of a single frame rendered in-process.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def stage_split(recipe, town, frames=3) -> dict:
    """Seconds per frame spent in camera, LiDAR and PNG/bin writing (single process, 1 thread)."""
    from mono_map.data.synth import FrameRenderer, writer
    from mono_map.data.synth.camera import render
    from mono_map.data.synth.lidar import scan

    fr = FrameRenderer(recipe, town, nthreads=1)
    tmp = Path(tempfile.mkdtemp())
    out = {"camera": 0.0, "lidar": 0.0, "write": 0.0}
    fr.render(0)
    for i in range(frames):
        T = fr.poses[i]
        t0 = time.perf_counter()
        rgb, depth = render(fr.scene, town, fr.light, fr.camera, T @ fr.T_cam0_cam2, np.random.default_rng(i), 1)
        t1 = time.perf_counter()
        pts = scan(fr.scene, town, T @ fr.T_cam0_velo, fr.lidar_dirs, np.random.default_rng(i), 1)
        t2 = time.perf_counter()
        writer.write_frame(tmp, i, rgb, depth, pts)
        t3 = time.perf_counter()
        out["camera"] += t1 - t0
        out["lidar"] += t2 - t1
        out["write"] += t3 - t2
    shutil.rmtree(tmp)
    return {k: v / frames for k, v in out.items()}


def preview(seq_dir: Path, index: int, out: Path) -> None:
    """One PNG: image_2 | colourised dense depth | LiDAR points projected on the image."""
    import cv2
    import pykitti

    root, name = seq_dir.parent.parent, seq_dir.name
    ds = pykitti.odometry(str(root), name)
    img = np.array(ds.get_cam2(index))
    from mono_map.data.depth_png import read_depth_png
    from mono_map.geometry import lidar_depth_image, transform_points

    depth = read_depth_png(seq_dir / "depth_2" / f"{index:06d}.png")
    velo = ds.get_velo(index)
    K = ds.calib.K_cam2
    pts_cam = transform_points(ds.calib.T_cam2_velo, velo[:, :3])
    ldepth = lidar_depth_image(pts_cam, K, img.shape[0], img.shape[1])

    from mono_map.viz.codec import colourise

    def colorise(d):
        # log depth, 2 m (red) ... 80 m (blue)
        c = colourise(1 - np.log(np.maximum(d, 1e-3) / 2.0) / np.log(40.0), 0.0, 1.0, "turbo")
        c[d <= 0] = 0
        return c

    dcol = colorise(depth)
    over = (img * 0.55).astype(np.uint8)
    lcol = colorise(ldepth)
    m = ldepth > 0
    m = cv2.dilate(m.astype(np.uint8), np.ones((2, 2), np.uint8)) > 0
    ld = cv2.dilate(ldepth, np.ones((2, 2), np.float32))
    lcol = colorise(ld)
    over[m] = lcol[m]
    panel = np.concatenate([img, dcol, over], axis=0)
    panel = cv2.resize(panel, (panel.shape[1] // 2, panel.shape[0] // 2), interpolation=cv2.INTER_AREA)
    out.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(out), panel[..., ::-1], [cv2.IMWRITE_PNG_COMPRESSION, 9])
    print(f"wrote {out} ({out.stat().st_size / 1024:.0f} KB): image_2 / dense depth_2 / LiDAR in image_2")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seq", default="00")
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--preview", default=None, help="write a preview PNG of frame --frame")
    ap.add_argument("--frame", type=int, default=0)
    ap.add_argument("--keep", default=None, help="generate into this root instead of a temporary one")
    args = ap.parse_args()

    from mono_map.data.synth import generate_sequence, load_recipe
    from mono_map.data.synth.town import build_town

    recipe = load_recipe(args.seq)
    t0 = time.perf_counter()
    town = build_town(recipe)
    t_town = time.perf_counter() - t0
    print(f"town {recipe.name}: {town.stats['triangles']:,} triangles, built in {t_town:.1f} s; {town.stats}")
    split = stage_split(recipe, town)
    print("single frame, 1 thread: " + ", ".join(f"{k} {v * 1000:.0f} ms" for k, v in split.items())
          + f" (total {sum(split.values()) * 1000:.0f} ms)")
    root = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="bench_synth_"))
    n = min(args.frames, recipe.frames)
    t0 = time.perf_counter()
    seq_dir = generate_sequence(recipe, root, frames=n, workers=args.workers, force=True)
    dt = time.perf_counter() - t0
    size = sum(p.stat().st_size for p in seq_dir.rglob("*") if p.is_file())
    print(f"generated {n} frames with {args.workers} workers in {dt:.1f} s: {n / dt:.2f} frames/s end to end "
          f"(incl. town build {t_town:.1f} s and worker start-up); "
          f"{size / n / 1e6:.2f} MB/frame → {size / n * 100 / 1e6:.0f} MB per 100 frames")
    if args.preview:
        preview(seq_dir, args.frame, Path(args.preview))
    if not args.keep:
        shutil.rmtree(root)
    return 0


if __name__ == "__main__":
    sys.exit(main())
