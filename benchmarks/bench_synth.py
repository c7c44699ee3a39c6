"""Benchmark synthetic sequence generation (frames/s) and optionally save a preview picture.

    python benchmarks/bench_synth.py --seq 00 --frames 40 --workers 2
    python benchmarks/bench_synth.py --seq tiny --preview docs/images/synth_frame.png --frame 3
    python benchmarks/bench_synth.py --seq 00 --frames 20 --compare ~/.cache/mono-map/data/kitti   # same frames?

Generates into a temporary root (never touches ./data), reports end-to-end frames/s
(town build + worker start-up included), the CPU seconds per frame of the process and its workers
(less sensitive to other jobs than wall time), the per-stage split (wall and CPU) of single frames
rendered in-process, and with --compare whether the frames are identical to another root's (decoded
PNG pixels, scan bytes).
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

# The in-process stage split runs as a render worker does: one BLAS thread (OpenBLAS reads this when numpy is
# imported; otherwise its threads' spinning inflates the LiDAR's CPU time). The workers get generate.WORKER_ENV.
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import numpy as np


def stage_split(recipe, town, frames=3) -> dict:
    """Seconds per frame spent in camera, LiDAR and PNG/bin writing (single process, 1 thread)."""
    from mono_map.data.synth import FrameRenderer, writer
    from mono_map.data.synth.camera import render
    from mono_map.data.synth.lidar import scan

    fr = FrameRenderer(recipe, town, nthreads=1)
    tmp = Path(tempfile.mkdtemp())
    out = {"camera": 0.0, "lidar": 0.0, "write": 0.0, "camera CPU": 0.0, "lidar CPU": 0.0, "write CPU": 0.0}
    fr.render(0)

    def clock():
        return np.array([time.perf_counter(), time.process_time()])
    for i in range(frames):
        T = fr.poses[i]
        t0 = clock()
        rgb, depth = render(fr.scene, town, fr.light, fr.camera, T @ fr.T_cam0_cam2, np.random.default_rng(i), 1)
        t1 = clock()
        pts = scan(fr.scene, town, T @ fr.T_cam0_velo, fr.lidar_dirs, np.random.default_rng(i), 1)
        t2 = clock()
        writer.write_frame(tmp, i, rgb, depth, pts)
        t3 = clock()
        for stage, (a, b) in (("camera", (t0, t1)), ("lidar", (t1, t2)), ("write", (t2, t3))):
            out[stage] += b[0] - a[0]
            out[f"{stage} CPU"] += b[1] - a[1]
    shutil.rmtree(tmp)
    return {k: v / frames for k, v in out.items()}


def cpu_seconds() -> float:
    """User + system CPU seconds of this process and its waited-for children (the render workers)."""
    import resource

    return sum(r.ru_utime + r.ru_stime for r in (resource.getrusage(resource.RUSAGE_SELF),
                                                  resource.getrusage(resource.RUSAGE_CHILDREN)))


def compare_frames(seq_a: Path, seq_b: Path, n: int) -> tuple[int, list[str]]:
    """Compare image_2 / depth_2 (decoded pixels: PNG settings may differ) and velodyne (bytes) of frames
    0..n-1 of two sequence dirs: (#files, differing)."""
    import cv2

    from mono_map.data.synth import writer

    def same(a: Path, b: Path) -> bool:
        if not b.is_file():
            return False
        if a.suffix != ".png":
            return a.read_bytes() == b.read_bytes()
        ia, ib = (cv2.imread(str(p), cv2.IMREAD_UNCHANGED) for p in (a, b))
        return ia is not None and ib is not None and ia.dtype == ib.dtype and np.array_equal(ia, ib)

    differ, n_files = [], 0
    for i in range(n):
        pa, pb = writer.frame_paths(seq_a, i), writer.frame_paths(seq_b, i)
        for kind in pa:
            n_files += 1
            if not same(pa[kind], pb[kind]):
                differ.append(f"{pa[kind].parent.name}/{pa[kind].name}")
    return n_files, differ


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
    from mono_map.cli.options import add_frames, add_seq
    from mono_map.frames import parse_frames

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_seq(ap, help="recipe name (sequences/NAME.toml) or path to a .toml")
    add_frames(ap, default="40", what="frames to render (the prefix up to the last one)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--preview", default=None, help="write a preview PNG of frame --frame")
    ap.add_argument("--frame", type=int, default=0)
    ap.add_argument("--keep", default=None, help="generate into this root instead of a temporary one")
    ap.add_argument("--compare", default=None,
                    help="compare the generated frames (decoded PNG pixels, scan bytes) with the same frames "
                         "under this data root")
    args = ap.parse_args()

    from mono_map.data.synth import generate_sequence, load_recipe
    from mono_map.data.synth.town import build_town

    recipe = load_recipe(args.seq)
    t0 = time.perf_counter()
    town = build_town(recipe)
    t_town = time.perf_counter() - t0
    print(f"town {recipe.name}: {town.stats['triangles']:,} triangles, built in {t_town:.1f} s; {town.stats}")
    split = stage_split(recipe, town)
    wall = {k: v for k, v in split.items() if not k.endswith("CPU")}
    print("single frame, 1 thread: " + ", ".join(f"{k} {v * 1000:.0f} ms" for k, v in split.items())
          + f" (total {sum(wall.values()) * 1000:.0f} ms wall, {(sum(split.values()) - sum(wall.values())) * 1000:.0f} ms CPU)")
    root = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="bench_synth_"))
    n = min(parse_frames(args.frames).needed() or recipe.frames, recipe.frames)
    if args.compare and not (Path(args.compare) / "sequences" / recipe.name).is_dir():
        ap.error(f"--compare: {Path(args.compare) / 'sequences' / recipe.name}: no such sequence directory")
    t0 = time.perf_counter()
    cpu0 = cpu_seconds()
    seq_dir = generate_sequence(recipe, root, frames=n, workers=args.workers, force=True)
    dt = time.perf_counter() - t0
    cpu = cpu_seconds() - cpu0
    print(f"CPU of this process and its workers: {cpu:.1f} s = {cpu / n:.3f} CPU-s per frame "
          f"(load average {os.getloadavg()[0]:.1f})")
    size = sum(p.stat().st_size for p in seq_dir.rglob("*") if p.is_file())
    print(f"generated {n} frames with {args.workers} workers in {dt:.1f} s: {n / dt:.2f} frames/s end to end "
          f"(incl. town build {t_town:.1f} s and worker start-up); "
          f"{size / n / 1e6:.2f} MB/frame → {size / n * 100 / 1e6:.0f} MB per 100 frames")
    if args.preview:
        preview(seq_dir, args.frame, Path(args.preview))
    if args.compare:
        n_files, differ = compare_frames(seq_dir, Path(args.compare) / "sequences" / recipe.name, n)
        print(f"compared {n_files} frame files with {args.compare}: {len(differ)} differ"
              + (": " + ", ".join(differ[:10]) if differ else " (same pixels and scans)"))
    if not args.keep:
        shutil.rmtree(root)
    return 0


if __name__ == "__main__":
    sys.exit(main())
