"""Checks a map job passes before it is built: its camera stays inside what an OctoMap of its resolution
can address (:func:`check_reach`), and its first frame fits in memory (:func:`check_memory`)."""

from __future__ import annotations

from mono_map.mapping.strategies import source_of


def memory_limit() -> tuple[float, str]:
    """Bytes a build may use, and where the figure comes from: ``$MONO_MAP_MEMORY_GB``, else the
    smaller of the available RAM (/proc/meminfo) and the address-space limit (ulimit -v)."""
    import resource

    from mono_map.schema import env_value

    gb = env_value("MONO_MAP_MEMORY_GB")  # checked: a positive, finite number of GB or refused naming it
    if gb is not None:
        return gb * 2**30, "$MONO_MAP_MEMORY_GB"
    limit, where = float("inf"), "no limit known"
    try:
        for line in open("/proc/meminfo"):
            if line.startswith("MemAvailable:"):
                limit, where = float(line.split()[1]) * 1024, "available RAM"
    except OSError:
        pass
    soft = resource.getrlimit(resource.RLIMIT_AS)[0]
    if soft != resource.RLIM_INFINITY and soft < limit:
        limit, where = float(soft), "ulimit -v"
    return limit, where


# Peak memory of one frame's integration, measured on tiny frame 0 (peak RSS above the start-up):
# LiDAR ≈ 90 B per ray-cell visit (0.05 m: 22 M visits, 1.9 GB); mono (shipped model, keep 0.8,
# 1241×376) ≈ 150 MB at 0.2 m, growing as (0.2 / res)^2.5 (0.1 m: 0.58 GB, 0.05 m: 3.3 GB).
BYTES_PER_VISIT = 90
MONO_BYTES_AT_02 = 150e6


def estimate_frame_bytes(seq, i: int, source: str, cfg, stride: int, keep: float) -> float:
    """Peak bytes to integrate frame ``i`` alone (see the constants above; an estimate, not a bound).
    Camera sources (mono, depth-gt) are estimated from their pixel count."""
    import numpy as np

    if source_of(source).camera:
        h, w = seq.image_size
        pixels = (-(-h // stride)) * (-(-w // stride)) * keep
        return MONO_BYTES_AT_02 * (0.2 / cfg.resolution) ** 2.5 * pixels / (376 * 1241 * 0.8)
    from mono_map.mapping.reference import lidar_measurement

    pts, origin = lidar_measurement(seq, i, source)
    lengths = np.linalg.norm(pts - origin, axis=1)
    if cfg.max_range > 0:
        lengths = np.minimum(lengths, cfg.max_range)
    return float(np.sum(lengths / cfg.resolution + 1)) * BYTES_PER_VISIT


def check_reach(seq, job) -> None:
    """Refuse, before building, a job whose camera leaves the region an OctoMap of its resolution can
    address (16-bit keys: ±32767 cells around the world origin), naming the pose file and line."""
    import numpy as np

    from mono_map.errors import MonoMapError

    poses = getattr(seq, "poses_cam0", None)
    if poses is None:
        return
    frames = np.asarray(job.frames, dtype=np.int64)
    reach = 32767 * job.octomap.resolution
    far = np.abs(poses[frames, :3, 3]).max(axis=1)
    if far.max() >= reach:
        k = int(frames[int(far.argmax())])
        raise MonoMapError(f"{seq.pose_path}:{k + 1}: frame {k}'s pose is {far.max():.0f} m from the first camera, "
                           f"beyond what a {job.octomap.resolution:g} m OctoMap can address (±{reach:.0f} m); "
                           "is the pose right? (a coarser --res reaches further)")


def check_memory(seq, job) -> None:
    """Refuse, before building, a job whose first frame alone would not fit in memory (a distribution
    build: one ray every ``ray_step``-th pixel of every valid one; depth-gt: every pixel)."""
    from mono_map.errors import MonoMapError

    keep, stride, cfg = job.keep, job.stride, job.octomap
    if job.kind.ground_truth:
        keep = 1.0
    elif job.distributional:
        keep, stride = 1.0, stride * job.distribution.ray_step
    need = estimate_frame_bytes(seq, job.frames[0], job.source, cfg, stride, keep)
    limit, where = memory_limit()
    if need > limit:
        raise MonoMapError(f"--res: {cfg.resolution:g} m cells: integrating frame {job.frames[0]} alone would need "
                           f"about {need / 2**30:.1f} GB, more than the {limit / 2**30:.1f} GB allowed ({where}); "
                           "use a coarser --res, a --max-range or a larger --stride")
