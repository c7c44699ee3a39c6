"""Where things live: data root, recipes, shipped checkpoints, outputs."""

from __future__ import annotations

import os
from pathlib import Path

PACKAGE_DIR = Path(__file__).resolve().parent
REPO_DIR = PACKAGE_DIR.parent
CHECKPOINT_DIR = PACKAGE_DIR / "checkpoints"
KITTI_ASSETS_DIR = PACKAGE_DIR / "data" / "kitti_assets"


def data_root(arg: str | os.PathLike | None = None) -> Path:
    """KITTI odometry root: ``--data-root`` > ``$MONO_MAP_DATA`` > ``./data/kitti``.

    The root holds the standard layout ``sequences/XX/{image_2,velodyne,calib.txt,times.txt}``
    and ``poses/XX.txt``; a real KITTI download works unchanged.
    """
    if arg:
        return Path(arg).expanduser()
    env = os.environ.get("MONO_MAP_DATA")
    if env:
        return Path(env).expanduser()
    return Path("data/kitti")


def recipes_dir() -> Path:
    """Directory of synthetic sequence recipes (``sequences/XX.toml``); ``$MONO_MAP_RECIPES`` overrides."""
    env = os.environ.get("MONO_MAP_RECIPES")
    return Path(env) if env else REPO_DIR / "sequences"


def sequence_output_dir(arg: str | os.PathLike | None, seq: str) -> Path:
    """Where a sequence's maps, tables, pictures and recordings go: ``--out`` > ``./outputs/seq<SEQ>``."""
    return Path(arg) if arg else Path("outputs") / f"seq{seq}"
