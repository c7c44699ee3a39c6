"""The options several commands and scripts share, declared once: sequence, frames, data root, model (and the
oracle's noise), output, torch threads and precision, the OctoMap settings.

Each ``add_*`` adds one option to an argparse parser (or argument group) with its one meaning and help;
a command passes only what differs (``default``, ``required``, a sentence on what the option selects in
that command). The parsed values are checked where they are used (:func:`mono_map.frames.parse_frames`,
:func:`mono_map.data.prepare.check_data_root`, :func:`octomap_config`, ...), always naming the option.
Benchmarks and tools (``benchmarks/*.py``, ``tools/*.py``) declare theirs with these helpers too.
"""

from __future__ import annotations

import argparse
import dataclasses

FRAMES_GRAMMAR = "N (the first N), A:B[:S], I,J,... or 'all'"
DATA_ROOT_HELP = "KITTI root: odometry layout, or raw (then --seq YYYY_MM_DD_drive_NNNN_sync) " \
                 "(default $MONO_MAP_DATA or ./data/kitti)"
MODEL_HELP = "depth checkpoint: a path or a shipped name, binary (the mapping model, default), v2/<head> " \
             "(e.g. v2/softmax) or v1/<head>"
ORACLE_HELP = "; 'oracle' = noisy ground truth (synthetic sequences only, for development)"
DEFAULT_SEQ = "00"   # the held-out evaluation town


def add_seq(p, *, default: str | None = DEFAULT_SEQ, required: bool = False, help: str | None = None) -> None:
    """``--seq``: a sequence name under the data root (odometry ``NN`` or a raw drive's name)."""
    what = help or "sequence name under the data root, e.g. 00"
    if not required and default is not None:
        what += f" (default {default})"
    p.add_argument("--seq", default=None if required else default, required=required, help=what)


def add_frames(p, *, default: str | None = None, says: str | None = None, what: str = "frames") -> None:
    """``--frames`` in the one grammar (:func:`mono_map.frames.parse_frames`). ``default``: the value when
    not given (a script's "0:20"); None lets a command apply its own selection through
    ``parse_frames(args.frames, default=...)``, which ``says`` describes in the help (default: all)."""
    p.add_argument("--frames", default=default,
                   help=f"{what}: {FRAMES_GRAMMAR} (default {says or default or 'all'})")


def add_data_root(p, *, required: bool = False, help: str = DATA_ROOT_HELP) -> None:
    """``--data-root``: where the sequences are (None: ``$MONO_MAP_DATA`` or ./data/kitti)."""
    p.add_argument("--data-root", default=None, required=required, help=help)


def add_model(p, *, oracle: bool = False, repeat: bool = False, help: str | None = None) -> None:
    """``--model``: a checkpoint path or shipped name, resolved by
    :func:`mono_map.depth.inference.resolve_checkpoint`; None (the default) is the shipped binary model.
    ``oracle``: 'oracle' (noisy ground truth) is accepted too; ``repeat``: a list, one per ``--model``."""
    what = (help or MODEL_HELP) + (ORACLE_HELP if oracle else "") + ("; repeat for several" if repeat else "")
    p.add_argument("--model", default=None, action="append" if repeat else "store", help=what)


def add_out(p, *, default: str | None = None, help: str = "output directory") -> None:
    """``--out``: where a command writes (``default`` None: the command's own, e.g. outputs/seq<SEQ>)."""
    p.add_argument("--out", default=default, help=help + (f" (default {default})" if default is not None else ""))


def add_threads(p, *, default: int | None = 1, help: str = "torch intra-op threads") -> None:
    """``--threads``: torch intra-op threads (checked with :func:`check_threads`)."""
    p.add_argument("--threads", type=int, default=default,
                   help=help + (f" (default {default})" if default is not None else ""))


def check_threads(threads: int | None) -> None:
    """MonoMapError naming ``--threads`` unless it is None or a positive number."""
    from mono_map.errors import MonoMapError

    if threads is not None and threads < 1:
        raise MonoMapError(f"--threads: must be >= 1, got {threads}")


def add_precision(p, *, help: str = "network precision (default: bf16 on CPUs with AMX / AVX-512 BF16, "
                                    "else fp32)") -> None:
    """``--precision``: fp32 or bf16 (None: :func:`mono_map.depth.inference.default_precision`)."""
    p.add_argument("--precision", choices=("fp32", "bf16"), default=None, help=help)


def add_flip(p) -> None:
    """``--flip``: each image predicted mirrored too, the two outputs combined as samples (1.7–2.4× the prediction time)."""
    p.add_argument("--flip", action="store_true",
                   help="also predict each image mirrored and combine both (bin heads: the mixture of the two "
                        "distributions; monodepth2's post-processing for distributions); 1.7-2.4x the prediction time")


def check_flip(args) -> None:
    """``--flip`` needs a network: refused (one line) with ``--model oracle`` or a source that predicts nothing."""
    from mono_map.errors import MonoMapError

    if getattr(args, "flip", False) and (args.model == "oracle" or getattr(args, "source", "mono") != "mono"):
        raise MonoMapError("--flip: mirrors a depth network's input; the oracle and the LiDAR / depth-gt sources "
                           "have none")


ORACLE_NOISES = {
    "sigma": "the oracle's log-depth noise, independent per pixel (default 0.03)",
    "edge_sigma": "... and its extra noise at depth edges (default 0.5)",
    "shared_sigma": "the oracle's error shared by the views: a smooth field fixed in the world (log-depth; default 0)",
    "shared_wavelength": "... its wavelength (metres; default 10)",
}


def add_oracle_noise(p) -> None:
    """``--oracle-sigma``, ``--oracle-edge-sigma``, ``--oracle-shared-sigma``, ``--oracle-shared-wavelength``: the
    noise of ``--model oracle`` (:class:`mono_map.mapping.oracle.NoisyGroundTruthPredictor`'s settings)."""
    for name, text in ORACLE_NOISES.items():
        p.add_argument("--oracle-" + name.replace("_", "-"), type=float, default=None, help=text)


def oracle_predictor(args):
    """The NoisyGroundTruthPredictor of ``--model oracle`` with the ``--oracle-*`` options given (None for another
    model); MonoMapError (one line) for such an option without ``--model oracle`` or a bad value."""
    from mono_map.errors import MonoMapError
    from mono_map.mapping.oracle import NoisyGroundTruthPredictor

    given = {name: getattr(args, "oracle_" + name) for name in ORACLE_NOISES
             if getattr(args, "oracle_" + name, None) is not None}
    if args.model != "oracle":
        if given:
            raise MonoMapError(f"--oracle-{next(iter(given)).replace('_', '-')}: needs --model oracle")
        return None
    return NoisyGroundTruthPredictor(**given)


def add_octomap(p: argparse.ArgumentParser) -> None:
    """The OctoMap settings (``--res``, ``--max-range``, ``--prob-hit``, ``--prob-miss``, ``--clamp-*``),
    defaults from :class:`mono_map.config.OctoMapConfig`; read back with :func:`octomap_config`."""
    from mono_map.config import OctoMapConfig

    d = OctoMapConfig()
    g = p.add_argument_group("OctoMap (defaults are OctoMap's own)")
    g.add_argument("--res", type=float, default=d.resolution, help=f"cell size, metres (default {d.resolution})")
    g.add_argument("--max-range", type=float, default=None,
                   help="rays longer than this are cut and mark free space only (metres, > 0; default: unlimited)")
    g.add_argument("--prob-hit", type=float, default=d.prob_hit, help=f"default {d.prob_hit}")
    g.add_argument("--prob-miss", type=float, default=d.prob_miss, help=f"default {d.prob_miss}")
    g.add_argument("--clamp-min", type=float, default=d.clamp_min, help=f"default {d.clamp_min}")
    g.add_argument("--clamp-max", type=float, default=d.clamp_max, help=f"default {d.clamp_max}")


def octomap_config(args):
    """The OctoMap settings of :func:`add_octomap`'s options, checked (MonoMapError naming the option)."""
    import math

    from mono_map.config import OctoMapConfig
    from mono_map.errors import MonoMapError
    from mono_map.mapping.octree import validate_octomap_config

    if args.max_range is not None and not (math.isfinite(args.max_range) and args.max_range > 0):
        raise MonoMapError(f"--max-range: must be a positive number of metres, got {args.max_range} "
                           "(leave it out for unlimited rays)")
    if math.isfinite(args.res) and args.res > MAX_RESOLUTION:
        raise MonoMapError(f"--res: {args.res:g} m cells are coarser than this tool supports "
                           f"(<= {MAX_RESOLUTION:g} m; a street is about 20 m wide)")
    cfg = OctoMapConfig(resolution=args.res, prob_hit=args.prob_hit, prob_miss=args.prob_miss,
                        clamp_min=args.clamp_min, clamp_max=args.clamp_max,
                        max_range=-1.0 if args.max_range is None else float(args.max_range))
    validate_octomap_config(cfg)
    return cfg


MAX_RESOLUTION = 10.0            # metres


# --fused-* options: FusedConfig's fields, each with what it means (the default is the dataclass's)
FUSED_OPTIONS = (
    ("spread_ref", "log-depth spread at which a pixel's fusion weight halves"),
    ("min_weight", "summed weight a cell needs to be surface (~ confident views)"),
    ("trunc_sigma", "truncation band in metric spreads"),
    ("trunc_min", "narrowest truncation band, cells"),
    ("trunc_max", "widest truncation band, metres"),
    ("max_depth", "pixels farther than this (metres) are not fused"),
    ("max_spread", "pixels with a wider log-depth spread are not fused"),
    ("trunc_behind", "cells up to this many bands behind a pixel's depth are fused"),
    ("lag", "frames after which a frame's pixels are snapped to the fused surface"),
    ("snap_window", "how far (metres) from a pixel's expected depth its ray looks for the fused surface"),
    ("snap_step", "snap every N-th ray of the --ray-step grid"),
    ("multiview", "neighbouring frames (0 = off, 1, 2) whose images sharpen each frame's depth distribution "
                  "(plane-sweep posterior, depth/multiview.py)"),
    ("multiview_temperature", "temperature of the multi-view photometric likelihood"),
    ("stereo", "1: the frame's right colour camera (image_3, KITTI's stereo partner) is one more source of the "
               "multi-view posterior (the sequence needs image_3); 0: the left images only"),
    ("subpixel", "1: voxels read the full-resolution depth bilinearly; 0: the nearest ray-grid pixel"),
    ("mode", "1: each pixel's surface moves from its expected depth to its distribution's mode; 0: it stays"),
    ("gate", "> 0: a pixel's hit stays at its own surface depth where the fused surface is within this many "
             "cells of it (none elsewhere); 0: the hit is moved onto the fused surface"),
    ("euclid", "1: a pixel's signed distances are measured along its depth image's surface normal (the same from "
               "every view; hits land in the surface's own cells at grazing angles); 0: along the optical axis"),
)


def add_integration(p: argparse.ArgumentParser) -> None:
    """How a mono map integrates (``--integrate``) and the distribution and fused settings; read back with
    :func:`distribution_config` and :func:`fused_config`."""
    from mono_map.mapping.distribution import DistributionConfig

    d = DistributionConfig()
    g = p.add_argument_group("integration of monocular depth")
    from mono_map.mapping.strategies import INTEGRATIONS

    g.add_argument("--integrate", default="keep", choices=INTEGRATIONS,
                   help="keep: the paper's cut, the --keep lowest-entropy pixels' expected depths as end points "
                        "(default); distribution: every valid pixel's whole depth distribution sets the expected "
                        "OctoMap update of each cell along its ray (--keep ignored); fused: the distribution's free "
                        "space + a thin surface fused across views (uncertainty-weighted TSDF; docs/fused.md)")
    g.add_argument("--eps", type=float, default=d.eps,
                   help=f"distribution: rays stop where P(surface beyond) < eps (default {d.eps:g})")
    g.add_argument("--temperature", type=float, default=d.temperature,
                   help=f"distribution: probabilities p^(1/T), renormalised (default {d.temperature:g}; 1 = as predicted)")
    g.add_argument("--min-update", type=float, default=d.min_update,
                   help=f"distribution: drop per-cell updates weaker than this log-odds magnitude (default {d.min_update:g})")
    g.add_argument("--bin-spread", type=float, default=d.bin_spread,
                   help=f"distribution: spread each bin's mass over this central fraction of the bin, placed at the "
                        f"pixel's local mean (default {d.bin_spread:g} = whole bins)")
    g.add_argument("--quantum", type=float, default=d.quantum,
                   help=f"distribution: round per-cell updates to multiples of this log-odds step, so free space "
                        f"prunes (default {d.quantum:g}; 0 = off)")
    g.add_argument("--snap-free", action=argparse.BooleanOptionalAction, default=d.snap_free,
                   help="distribution: snap free-space updates to the sensor model's {miss, 0} (a whole miss where "
                        "the expected update is at least half a miss), so free space prunes as in a keep map "
                        f"(default {'on' if d.snap_free else 'off'})")
    g.add_argument("--ray-step", type=int, default=d.ray_step,
                   help=f"distribution: one ray every N-th pixel row and column (default {d.ray_step})")
    from mono_map.mapping.fused import FusedConfig

    f = FusedConfig()
    g = p.add_argument_group("fused surface (--integrate fused; the free space uses the distribution options)")
    kinds = {fld.name: {"int": int, "float": float}[str(fld.type)] for fld in dataclasses.fields(FusedConfig)}
    for name, what in FUSED_OPTIONS:
        default = getattr(f, name)
        g.add_argument("--fused-" + name.replace("_", "-"), type=kinds[name], default=default,
                       help=f"{what} (default {default:g})")


def distribution_config(args):
    """The ``--integrate distribution`` settings of the options, checked (MonoMapError naming the option)."""
    from mono_map.mapping.distribution import DistributionConfig, check_distribution_config

    return check_distribution_config(DistributionConfig(eps=args.eps, temperature=args.temperature,
                                                        ray_step=args.ray_step, min_update=args.min_update,
                                                        bin_spread=args.bin_spread, quantum=args.quantum,
                                                        snap_free=args.snap_free))


def fused_config(args):
    """The ``--integrate fused`` surface settings of the options, checked (MonoMapError naming the option)."""
    from mono_map.mapping.fused import FusedConfig, check_fused_config

    return check_fused_config(FusedConfig(**{name: getattr(args, "fused_" + name) for name, _ in FUSED_OPTIONS}))
