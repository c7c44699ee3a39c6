#!/usr/bin/env python3
"""Scaling study of ``mono-map build``: wall time, frames/s, peak RSS and map memory against the number
of frames (issue 14).

    python benchmarks/bench_scaling.py --data-root ~/.cache/mono-map/data/kitti_full \
        --sizes 500,1000,2000,4541 --sources lidar-fov,mono --out outputs/scaling

Each (source, size) is one ``mono-map build --frames 0:N`` child process; its peak RSS and CPU time come
from ``os.wait4`` (the child's own rusage), its build time, frames/s and map memory (OctoMap's
``memoryUsage``) from the stats JSON the build writes. Results go to ``<out>/scaling.json`` after every
run, so an interrupted study resumes where it stopped (finished runs are skipped; ``--redo`` repeats
them); ``<out>/scaling.md`` (table) and ``<out>/scaling.png`` (log-log plot) are rewritten from it.
``--report`` only rewrites the table and plot. With ``--wait`` a run waits until the data root's
sequence has N frames (a render still extending it). A 1-frame build per source (``--baseline``,
on by default) gives the fixed RSS of the interpreter, libraries and model, to read the peak RSS against.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np


def frames_available(data_root: Path, seq: str) -> int:
    """Frames of ``seq`` a build can read now: the synthetic marker's n_frames (the poses file is
    written with it), else the number of lines of poses/SEQ.txt; 0 if neither exists."""
    marker = data_root / "sequences" / seq / "synth.json"
    if marker.is_file():
        try:
            return int(json.loads(marker.read_text()).get("n_frames", 0))
        except (ValueError, OSError):
            return 0
    poses = data_root / "poses" / f"{seq}.txt"
    return sum(1 for _ in poses.open()) if poses.is_file() else 0


def run_key(source: str, n: int) -> str:
    return f"{source}:{n}"


def build_command(args, source: str, n: int, name: str) -> list[str]:
    cmd = [sys.executable, "-m", "mono_map", "build", "--seq", args.seq, "--source", source,
           "--frames", f"0:{n}", "--data-root", str(args.data_root), "--out", str(args.out / "maps"), "--name", name]
    if source == "mono":
        cmd += ["--keep", str(args.keep)]
    return cmd


def run_one(args, source: str, n: int) -> dict:
    """One build child: its rusage (wait4) and the stats it wrote."""
    name = f"scale_{source}_{n}"
    log = args.out / "logs" / f"{name}.log"
    log.parent.mkdir(parents=True, exist_ok=True)
    cmd = build_command(args, source, n, name)
    load0 = os.getloadavg()[0]
    t0 = time.perf_counter()
    with log.open("w") as fh:
        proc = subprocess.Popen(cmd, stdout=fh, stderr=subprocess.STDOUT,
                                preexec_fn=(lambda: os.nice(args.nice)) if args.nice else None)
        _, status, ru = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode != 0:
        raise SystemExit(f"bench_scaling: build {source} 0:{n} failed (exit {proc.returncode}); see {log}")
    info = json.loads((args.out / "maps" / f"{name}.json").read_text())
    stats, per_frame = info["stats"], info.get("per_frame", [])
    return {"source": source, "n_frames": n, "process_wall_s": wall, "build_s": stats["wall_s"],
            "frames_per_s": stats["frames_per_s"], "cpu_s": ru.ru_utime + ru.ru_stime,
            "peak_rss_mb": ru.ru_maxrss / 1024.0, "map_mb": stats["memory_mb"], "leaves": stats["leaf_count"],
            "load_start": load0, "load_end": os.getloadavg()[0],
            "frame_s": [round(f["frame_s"], 4) for f in per_frame],
            "memory_curve": [(f["index"], f["memory_mb"]) for f in per_frame[::100]],
            "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())}


def load_results(path: Path) -> dict:
    return json.loads(path.read_text()) if path.is_file() else {}


def save_result(path: Path, key: str, entry: dict) -> dict:
    """Add one run to the results file, re-read first (two studies may share it); returns all results."""
    from mono_map.io import write_json_atomic

    results = load_results(path)
    results[key] = entry
    write_json_atomic(path, results)
    return results


def loglog_slope(n: np.ndarray, t: np.ndarray) -> float:
    """Least-squares exponent b of t ∝ n^b."""
    return float(np.polyfit(np.log(n), np.log(t), 1)[0]) if len(n) >= 2 else float("nan")


def tail_ratio(frame_s: list[float]) -> float:
    """Median per-frame time of the last 10 % of frames over that of frames 10-20 % (past the warm-up):
    ~1 when a frame's cost does not grow with the map."""
    f = np.asarray(frame_s, float)
    k = len(f) // 10
    return float(np.median(f[-k:]) / np.median(f[k:2 * k])) if k >= 5 else float("nan")


def sizes_of(results: dict, source: str) -> list[dict]:
    return sorted((r for r in results.values() if r["source"] == source and r["n_frames"] > 1),
                  key=lambda r: r["n_frames"])


def table(results: dict) -> str:
    lines = ["| source | frames | build (s) | frames/s | CPU (s) | peak RSS (MB) | map (MB) | RSS / map | "
             "RSS − 1-frame RSS (MB) | leaves | load avg |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    notes = []
    for source in sorted({r["source"] for r in results.values()}):
        base = results.get(run_key(source, 1))
        for r in sizes_of(results, source):
            extra = f"{r['peak_rss_mb'] - base['peak_rss_mb']:,.0f}" if base else "–"
            lines.append(f"| {source} | {r['n_frames']:,} | {r['build_s']:,.0f} | {r['frames_per_s']:.2f} | "
                         f"{r['cpu_s']:,.0f} | {r['peak_rss_mb']:,.0f} | {r['map_mb']:,.1f} | "
                         f"{r['peak_rss_mb'] / r['map_mb']:.2f} | {extra} | {r['leaves']:,} | "
                         f"{r['load_start']:.1f}–{r['load_end']:.1f} |")
        rs = sizes_of(results, source)
        if rs:
            n = np.array([r["n_frames"] for r in rs], float)
            growth = (f"time ∝ frames^{loglog_slope(n, np.array([r['build_s'] for r in rs])):.2f} (wall), "
                      f"^{loglog_slope(n, np.array([r['cpu_s'] for r in rs])):.2f} (CPU); "
                      f"map ∝ frames^{loglog_slope(n, np.array([r['map_mb'] for r in rs])):.2f}; "
                      if len(rs) >= 2 else "one size only; ")
            notes.append(f"- {source}: {growth}per-frame time, last 10 % / frames 10–20 % of the "
                         f"{rs[-1]['n_frames']}-frame build: {tail_ratio(rs[-1]['frame_s']):.2f}"
                         + (f"; 1-frame build peak RSS {base['peak_rss_mb']:,.0f} MB" if base else ""))
    return "\n".join(lines + [""] + notes) + "\n"


def plot(results: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax_t, ax_m) = plt.subplots(1, 2, figsize=(11, 5.6))
    colours = {"lidar-fov": "tab:blue", "mono": "tab:orange", "lidar": "tab:green", "depth-gt": "tab:purple"}
    for source in sorted({r["source"] for r in results.values()}):
        rs = sizes_of(results, source)
        if not rs:
            continue
        c = colours.get(source, "k")
        n = np.array([r["n_frames"] for r in rs], float)
        t = np.array([r["build_s"] for r in rs])
        ax_t.loglog(n, t, "o-", color=c, label=f"{source}: build wall")
        ax_t.loglog(n, [r["cpu_s"] for r in rs], "s:", color=c, alpha=0.7, label=f"{source}: CPU (all threads)")
        ax_t.loglog(n, t[0] * n / n[0], "--", color="grey", lw=0.8)
        ax_m.loglog(n, [r["peak_rss_mb"] for r in rs], "o-", color=c, label=f"{source}: peak RSS")
        ax_m.loglog(n, [r["map_mb"] for r in rs], "s--", color=c, label=f"{source}: map memoryUsage")
        ax_m.loglog(n, [2 * r["map_mb"] for r in rs], ":", color=c, lw=0.8, label=f"{source}: 2 × map")
        base = results.get(run_key(source, 1))
        if base:
            ax_m.axhline(base["peak_rss_mb"], color=c, lw=0.6, ls="-.", label=f"{source}: peak RSS of a 1-frame build")
    ax_t.plot([], [], "--", color="grey", lw=0.8, label="∝ frames (from the smallest run)")
    sizes = sorted({r["n_frames"] for r in results.values() if r["n_frames"] > 1})
    for ax, ylabel in ((ax_t, "seconds"), (ax_m, "MB")):
        ax.set_xticks(sizes, [str(v) for v in sizes])
        ax.minorticks_off()
        ax.set_xlabel("frames of sequence 00 (first N)")
        ax.set_ylabel(ylabel)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.14), ncol=2)
    ax_t.set_title("build time")
    ax_m.set_title("memory")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write_report(out: Path, results: dict) -> None:
    (out / "scaling.md").write_text(table(results))
    if any(r["n_frames"] > 1 for r in results.values()):
        plot(results, out / "scaling.png")


def main() -> int:
    from mono_map.cli.options import add_data_root, add_out, add_seq

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_seq(ap)
    add_data_root(ap, required=True, help="KITTI root holding the sequence (its first N frames are built)")
    ap.add_argument("--sizes", default="500,1000,2000,4541", help="comma-separated frame counts (first N frames)")
    ap.add_argument("--sources", default="lidar-fov,mono", help="comma-separated build sources")
    ap.add_argument("--keep", type=float, default=0.8, help="mono keep fraction (default 0.8)")
    add_out(ap, default="outputs/scaling")
    ap.add_argument("--nice", type=int, default=0, help="niceness of the build children")
    ap.add_argument("--no-baseline", dest="baseline", action="store_false", help="skip the 1-frame builds")
    ap.add_argument("--wait", action="store_true", help="wait for the data root to hold N frames")
    ap.add_argument("--redo", action="store_true", help="repeat runs already in scaling.json")
    ap.add_argument("--report", action="store_true", help="only rewrite scaling.md / scaling.png")
    args = ap.parse_args()
    try:
        sizes = [int(s) for s in args.sizes.split(",") if s]
    except ValueError:
        ap.error(f"--sizes: not a comma-separated list of integers: {args.sizes!r}")
    if not sizes or min(sizes) < 1:
        ap.error(f"--sizes: frame counts must be positive, got {args.sizes!r}")
    sources = [s for s in args.sources.split(",") if s]
    args.data_root = Path(args.data_root).expanduser()
    args.out = Path(args.out).expanduser()
    args.out.mkdir(parents=True, exist_ok=True)
    res_path = args.out / "scaling.json"
    results = load_results(res_path)
    if args.report:
        write_report(args.out, results)
        print(table(results))
        return 0
    if not (args.data_root / "sequences" / args.seq).is_dir():
        ap.error(f"--data-root: {args.data_root / 'sequences' / args.seq}: no such sequence directory")
    plan = ([(s, 1) for s in sources] if args.baseline else []) + [(s, n) for n in sorted(sizes) for s in sources]
    for source, n in plan:
        key = run_key(source, n)
        if key in results and not args.redo:
            continue
        while frames_available(args.data_root, args.seq) < n:
            if not args.wait:
                print(f"bench_scaling: {args.data_root} holds {frames_available(args.data_root, args.seq)} frames of "
                      f"{args.seq}, {source} needs {n}; stopping (--wait waits)", file=sys.stderr)
                write_report(args.out, results)
                return 1
            time.sleep(30)
        print(f"{time.strftime('%H:%M:%S')} build {source} frames 0:{n} ...", flush=True)
        r = run_one(args, source, n)
        results = save_result(res_path, key, r)
        write_report(args.out, results)
        print(f"  build {r['build_s']:.0f} s = {r['frames_per_s']:.2f} frames/s, CPU {r['cpu_s']:.0f} s, peak RSS "
              f"{r['peak_rss_mb']:.0f} MB, map {r['map_mb']:.1f} MB, load {r['load_start']:.1f}-{r['load_end']:.1f}",
              flush=True)
    print(table(results))
    return 0


if __name__ == "__main__":
    sys.exit(main())
