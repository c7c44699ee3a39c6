"""``mono-map demo``: the README's main job, end to end on the embedded default.

Generates synthetic sequence 00 if missing (first 500 frames by default), then builds
the LiDAR-FOV, mono and mono-keep-0.8 maps, prints the paper's mapping table and
writes pictures and a rerun recording under ``outputs/``.
"""

from __future__ import annotations

import argparse
from contextlib import contextmanager

from mono_map.cli.build import DEFAULT_FRAMES
from mono_map.cli.options import add_data_root, add_frames, add_out, add_seq
from mono_map.io import prepare_output_dir
from mono_map.paths import sequence_output_dir


def register(subparsers) -> None:
    p = subparsers.add_parser("demo", help="run the main job end to end (synthetic sequence 00 + shipped model)",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_seq(p, help="sequence name (00: the held-out evaluation town)")
    add_frames(p, says=f"the first {DEFAULT_FRAMES} frames")
    add_data_root(p)
    add_out(p, help="output directory (default outputs/seq<SEQ>)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """synth (if missing) → LiDAR-FOV map → mono keep 0.8 map streamed to a rerun recording and the
    mono keep 1.0 map, in one prediction pass → the mapping table, sweep plot and top-down pictures."""
    import time

    from mono_map.config import OctoMapConfig
    from mono_map.data.prepare import check_data_root, prepare_sequence
    from mono_map.eval.table import TableJob
    from mono_map.frames import first_frames, frames_tag, parse_frames
    from mono_map.mapping.inputs import load_predictor
    from mono_map.cli.eval import run_table
    from mono_map.depth.inference import model_digest
    from mono_map.mapping.jobs import MapJob, reusable
    from mono_map.mapping.publish import MapRequest, build_and_write, build_and_write_all
    from mono_map.viz.rerun_stream import RerunMapLogger
    from mono_map.viz.stream_options import StreamOptions

    t0 = time.perf_counter()
    selection = parse_frames(args.frames, default=first_frames(DEFAULT_FRAMES))
    check_data_root(args.data_root)
    out_dir = prepare_output_dir(sequence_output_dir(args.out, args.seq))
    predictor = load_predictor(None)
    digest = model_digest(None)
    seq = prepare_sequence(args.data_root, args.seq, selection)
    phases = [("model and sequence", time.perf_counter() - t0)]    # the sequence is rendered here if missing

    @contextmanager
    def timed(name: str):
        t = time.perf_counter()
        yield
        phases.append((name, time.perf_counter() - t))
    frames = selection.resolve(len(seq))
    print(f"mono-map demo: sequence {seq.name} ({'synthetic' if seq.is_synthetic else 'real KITTI'}, "
          f"{len(seq)} frames under {seq.root}); {selection.describe(frames)}", flush=True)
    cfg = OctoMapConfig()
    tag = frames_tag(frames)

    # 1. the LiDAR-FOV reference, built first so the recording can show it beside the growing map
    ref_job = MapJob.of(seq, "lidar-fov", frames, octomap=cfg)
    ref_bt = ref_job.path(out_dir)
    if not reusable(ref_bt, ref_job)[0]:
        print("[1/3] LiDAR-FOV reference map", flush=True)
        with timed("LiDAR-FOV"):
            build_and_write(ref_job, seq, out_dir)
    # 2. the uncertainty-aware monocular map, streamed to a rerun recording while it grows, and the
    #    vanilla monocular map (keep 1.0) built in the same pass: each frame is predicted once for both
    rrd = out_dir / f"demo_mono-keep0.8_{tag}.rrd"
    keep_job = MapJob.of(seq, "mono", frames, keep=0.8, octomap=cfg, digest=digest)
    all_job = MapJob.of(seq, "mono", frames, keep=1.0, octomap=cfg, digest=digest)
    requests = []
    if not reusable(keep_job.path(out_dir), keep_job)[0] or not rrd.exists():
        def logger(path):
            # the map is re-sent every 5 frames (images and stats every frame): keeps the recording
            # near 0.56 MB/frame instead of ~1 MB/frame
            return RerunMapLogger(rrd=path, reference_map=ref_bt,
                                  options=StreamOptions(resolution=cfg.resolution, image_size=seq.image_size,
                                                        map_every=5))

        requests.append(MapRequest(keep_job, rrd=rrd, logger=logger))
    if not reusable(all_job.path(out_dir), all_job)[0]:
        requests.append(MapRequest(all_job))
    if requests:
        keeps = ", ".join(f"keep {r.job.keep:.1f}" for r in requests)
        print(f"[2/3] monocular maps ({keeps}; keep 0.8 recorded to {rrd}), one prediction per frame", flush=True)
        with timed("monocular maps"):
            build_and_write_all(requests, seq, out_dir, predictor=predictor)
    # 3. the vanilla monocular map and the table (maps built by the same job are reused)
    print("[3/3] the mapping table", flush=True)
    with timed("table"):
        run_table(TableJob(seq=args.seq, data_root=args.data_root, frames=selection, out=str(out_dir),
                           keeps=(0.8, 1.0), stride=1, model=None, octomap=cfg, paper_only=True))
    print(f"recording: {rrd}  (open it with: mono-map view {rrd})")
    print(f"demo finished in {time.perf_counter() - t0:.0f} s ("
          + ", ".join(f"{name} {sec:.0f} s" for name, sec in phases) + ")")
    return 0
