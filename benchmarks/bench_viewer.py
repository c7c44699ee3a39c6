#!/usr/bin/env python
"""Logging overhead of the rerun viewer stream, as a ratio measured in one run.

Runs the same short ``build_map`` twice per repeat, alternating (plain, with
``RerunMapLogger(rrd=...)``, plain, with, ...) so that load from other processes hits both
alike, and reports  ratio = time(with --rrd) / time(plain)  (target ≤ 1.20) twice: on wall time
and on this process's CPU time (all threads, rerun's encoder/writer threads included). On a
shared machine the wall ratio is noisy; the CPU ratio is the steadier, conservative figure (the
rerun threads may overlap with the build on a second core, which wall time would not charge).
Also: the recording's size per frame and what the logger sent (block re-logs, cells re-sent vs
cells changed).

    python benchmarks/bench_viewer.py --seq 00 --frames 0:20 --source lidar-fov
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path


class CountingObserver:
    """Counts the cells a build reports as changed (to compare with what the logger re-sends)."""

    def __init__(self):
        self.added = self.freed = self.frames = 0

    def __call__(self, u):
        self.frames += 1
        self.added += len(u.occupied_keys_changed)
        self.freed += len(u.freed_keys_changed)


def main(argv=None) -> int:
    from mono_map.cli.options import add_data_root, add_frames, add_model, add_seq

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_seq(ap)
    add_data_root(ap)
    add_frames(ap, default="0:20")
    ap.add_argument("--source", default="lidar-fov", help="mono | lidar | lidar-fov (default lidar-fov)")
    ap.add_argument("--keep", type=float, default=0.8)
    add_model(ap, oracle=True, help="mono only: depth checkpoint (default: the shipped binary model)")
    ap.add_argument("--repeats", type=int, default=3, help="alternating pairs (default 3)")
    ap.add_argument("--map-every", type=int, default=1)
    ap.add_argument("--json", default=None, help="also write the results here")
    args = ap.parse_args(argv)

    import torch

    torch.set_num_threads(2)
    from mono_map.data.prepare import prepare_sequence
    from mono_map.frames import parse_frames
    from mono_map.mapping.pipeline import build_map
    from mono_map.mapping.jobs import MapJob
    from mono_map.viz.rerun_stream import RerunMapLogger
    from mono_map.viz.stream_options import StreamOptions

    selection = parse_frames(args.frames)
    seq = prepare_sequence(args.data_root, args.seq, selection)
    frames = selection.resolve(len(seq))
    os.environ.setdefault("MONO_MAP_PROGRESS", "0")
    predictor = None
    if args.source == "mono":
        if args.model == "oracle":
            from mono_map.mapping.oracle import NoisyGroundTruthPredictor

            predictor = NoisyGroundTruthPredictor()
        else:
            from mono_map.depth.inference import DepthPredictor

            predictor = DepthPredictor.load(args.model)

    def run(with_rrd: bool, tmp: Path) -> tuple[float, dict]:
        obs, info = [CountingObserver()], {}
        logger = None
        if with_rrd:
            logger = RerunMapLogger(rrd=tmp / "bench.rrd",
                                    options=StreamOptions(map_every=args.map_every, image_size=seq.image_size))
            obs.append(logger)  # build_map closes its observers (the .rrd is complete on return)
        t0, c0 = time.perf_counter(), time.process_time()
        build_map(seq, MapJob.spec(args.source, frames, keep=args.keep), observers=obs, show_progress=False,
                  predictor=predictor)
        dt, dc = time.perf_counter() - t0, time.process_time() - c0
        info["cpu_s"] = dc
        info["frames"] = obs[0].frames
        info["cells_changed"] = obs[0].added + obs[0].freed
        if logger is not None:
            size = (tmp / "bench.rrd").stat().st_size
            info.update(rrd_bytes=size, rrd_kb_per_frame=size / 1024 / max(obs[0].frames, 1),
                        block_relogs=logger.blocks_logged, cells_sent=logger.cells_logged,
                        block_entities=len(logger.block_entities), map_cells=logger.map_cells)
        return dt, info

    plain, logged, plain_cpu, logged_cpu, infos = [], [], [], [], []
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        run(False, tmp)  # warm-up: imports, model load, caches
        for _ in range(args.repeats):
            t, info = run(False, tmp)
            plain.append(t)
            plain_cpu.append(info["cpu_s"])
            t, info = run(True, tmp)
            logged.append(t)
            logged_cpu.append(info["cpu_s"])
            infos.append(info)
    ratio = sum(logged) / sum(plain)
    cpu_ratio = sum(logged_cpu) / sum(plain_cpu)
    info = infos[-1]
    res = {
        "seq": args.seq, "frames": args.frames, "source": args.source, "model": args.model,
        "repeats": args.repeats,
        "plain_s": plain, "with_rrd_s": logged, "ratio": ratio,
        "plain_cpu_s": plain_cpu, "with_rrd_cpu_s": logged_cpu, "cpu_ratio": cpu_ratio,
        "plain_frames_per_s": info["frames"] / statistics.mean(plain),
        **info,
        "resend_factor": info["cells_sent"] / max(info["cells_changed"], 1),
    }
    print(f"build {args.seq} frames {args.frames} source {args.source}"
          + (f" (model {args.model or 'shipped'}, keep {args.keep:g})" if args.source == "mono" else "") + ": "
          f"plain {statistics.mean(plain):.2f} s, with --rrd {statistics.mean(logged):.2f} s "
          f"-> wall ratio {ratio:.3f}; CPU {statistics.mean(plain_cpu):.2f} s vs {statistics.mean(logged_cpu):.2f} s "
          f"-> CPU ratio {cpu_ratio:.3f} (target <= 1.20)")
    print(f"recording {info['rrd_bytes'] / 1e6:.2f} MB = {info['rrd_kb_per_frame']:.0f} KB/frame; "
          f"{info['block_relogs']} block re-logs over {info['block_entities']} block entities, "
          f"{info['cells_sent']} cells sent for {info['cells_changed']} changed "
          f"(x{res['resend_factor']:.1f}); map {info['map_cells']} occupied cells")
    if args.json:
        from mono_map.io import write_json_atomic

        write_json_atomic(args.json, res)
    return 0


if __name__ == "__main__":
    sys.exit(main())
