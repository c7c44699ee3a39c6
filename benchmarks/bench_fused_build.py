"""Wall time of whole fused builds (``mono-map build --integrate fused``, the shipped model, default settings) of
two checkouts of the project, alternating: a baseline (e.g. a ``git worktree`` of an older commit) and a
candidate (e.g. this one).

    .venv/bin/python benchmarks/bench_fused_build.py --baseline ../wt-base --candidate . --data-root DATA \\
        [--seq 06] [--frames 40:70] [--rounds 3]

After ``--warmup`` untimed builds of each, each round runs the baseline, then the candidate, each in its own process (``python -m mono_map build`` with
``PYTHONPATH`` at the checkout; a fresh output directory, so no map is reused): the wall time of the whole
command (model load included) and the frames/s the build reports for its frames. Prints min / median / max of
each and of the per-round ratios (baseline time / candidate time), and each build's leaf count (the two maps
should agree up to float rounding). Run it on an idle machine (stop background jobs with ``kill -STOP``).
"""

from __future__ import annotations

import argparse
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from mono_map.cli import options
from mono_map.errors import MonoMapError
from mono_map.frames import parse_frames


def run_build(root: Path, args) -> tuple[float, float, int]:
    """(wall seconds, the build's frames/s, leaves) of one fused build from the checkout at ``root``."""
    with tempfile.TemporaryDirectory(prefix="bench-fused-") as out:
        env = dict(os.environ, PYTHONPATH=str(root))
        cmd = [sys.executable, "-m", "mono_map", "build", "--seq", args.seq, "--integrate", "fused", "--frames",
               args.frames, "--data-root", str(Path(args.data_root).resolve()), "--out", out]
        t = time.perf_counter()
        res = subprocess.run(cmd, cwd=root, env=env, capture_output=True, text=True)
        wall = time.perf_counter() - t
    if res.returncode != 0:
        sys.exit(f"bench_fused_build: the build in {root} failed:\n{res.stderr.strip()[-2000:]}")
    fps = re.search(r"= ([0-9.]+) frames/s", res.stdout + res.stderr)
    leaves = re.search(r"leaves ([0-9,]+)", res.stdout + res.stderr)
    if not fps or not leaves:
        sys.exit(f"bench_fused_build: no frames/s in the output of the build in {root}")
    return wall, float(fps.group(1)), int(leaves.group(1).replace(",", ""))


def spread(xs: list[float]) -> str:
    return f"{min(xs):.2f} / {statistics.median(xs):.2f} / {max(xs):.2f}"


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--baseline", required=True, help="checkout of the baseline (its mono_map/ is imported)")
    ap.add_argument("--candidate", default=".", help="checkout of the candidate (default: .)")
    options.add_data_root(ap, required=True)
    options.add_seq(ap, default="06")
    options.add_frames(ap, default="40:70")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--warmup", type=int, default=1, help="untimed builds of each first (kernels compiled, files cached)")
    args = ap.parse_args(argv)
    roots = {name: Path(getattr(args, name)).resolve() for name in ("baseline", "candidate")}
    for name, root in roots.items():
        if not (root / "mono_map" / "__init__.py").is_file():
            sys.exit(f"bench_fused_build: --{name} {root}: not a checkout of mono-map (no mono_map/__init__.py)")
    if not Path(args.data_root).is_dir():
        sys.exit(f"bench_fused_build: --data-root {args.data_root}: no such directory")
    if args.rounds < 1:
        sys.exit("bench_fused_build: --rounds must be at least 1")
    try:
        sel = parse_frames(args.frames)
    except MonoMapError as exc:
        sys.exit(f"bench_fused_build: {exc}")
    needed = sel.needed()
    n = "all" if needed is None else needed
    for _ in range(args.warmup):
        for root in roots.values():
            run_build(root, args)
    runs = {name: [] for name in roots}
    for r in range(args.rounds):
        for name, root in roots.items():
            runs[name].append(run_build(root, args))
            wall, fps, leaves = runs[name][-1]
            print(f"round {r + 1} {name:9s}: {wall:6.1f} s wall, {fps:.2f} frames/s (build), {leaves:,} leaves",
                  flush=True)
    print(f"\nseq {args.seq} frames {args.frames} (up to frame {n}), {args.rounds} rounds; min / median / max")
    for name in roots:
        print(f"  {name:9s}: wall {spread([w for w, _, _ in runs[name]])} s, "
              f"build {spread([f for _, f, _ in runs[name]])} frames/s")
    ratios = [b[0] / c[0] for b, c in zip(runs["baseline"], runs["candidate"])]
    fratios = [c[1] / b[1] for b, c in zip(runs["baseline"], runs["candidate"])]
    print(f"  speed-up (baseline wall / candidate wall): {spread(ratios)}×; "
          f"of the build's frames/s: {spread(fratios)}×")


if __name__ == "__main__":
    main()
