"""What a command does to get its sequence: check the request, render a synthetic prefix if needed, open it.

The reader (:mod:`mono_map.data.kitti`) never renders; the commands call :func:`prepare_sequence`,
which refuses a bad request (a data root that is a file, more frames than the recipe has) before
anything is rendered or written.
"""

from __future__ import annotations

import os
from pathlib import Path

from mono_map.data.kitti import open_sequence
from mono_map.data.kitti_odometry import KittiSequence
from mono_map.errors import MonoMapError
from mono_map.frames import FrameSelection
from mono_map.paths import data_root


def check_data_root(root: str | os.PathLike | None) -> Path:
    """The data root (``--data-root`` > ``$MONO_MAP_DATA`` > ./data/kitti), refused if it is not a directory."""
    path = data_root(root)
    if path.exists() and not path.is_dir():
        given = "--data-root" if root else ("$MONO_MAP_DATA" if os.environ.get("MONO_MAP_DATA") else "data root")
        raise MonoMapError(f"{given}: {path} is a file, not a directory")
    return path


def prepare_sequence(root: str | os.PathLike | None, name: str, frames: FrameSelection | None = None,
                     render: bool = True, stereo: bool = False) -> KittiSequence:
    """Open sequence ``name``; with ``render``, first render the synthetic frames ``frames`` needs (``stereo``:
    with the right camera's image_3, as a real KITTI download has it).

    A synthetic sequence (recipe ``sequences/<name>.toml``, no real KITTI sequence of that name
    under the root) missing or shorter than the selection is rendered from its recipe, saying so;
    a selection beyond the recipe's frame count is refused first. Real sequences are only read.
    """
    path = check_data_root(root)
    if render:
        from mono_map.data.synth import ensure_sequence, load_recipe
        from mono_map.data.synth.recipe import recipe_path

        if recipe_path(name).is_file() and not _is_real(path / "sequences" / name):
            recipe = load_recipe(name)
            need = frames.needed() if frames is not None else None
            if need is not None and need > recipe.frames and not frames.up_to:
                raise MonoMapError(f"{frames.option}: {frames.text!r} needs {need} frames; sequence {name} "
                                   f"(recipe {recipe_path(name).name}) has {recipe.frames}")
            want = recipe.frames if need is None else min(need, recipe.frames)
            ensure_sequence(path, name, frames=want, stereo=stereo)
    seq = open_sequence(path, name)
    if frames is not None:
        frames.resolve(len(seq))  # refused here, before the command does any work
    return seq


def _is_real(seq_dir: Path) -> bool:
    """A sequence directory with data but no synthetic markers (a real KITTI download)."""
    from mono_map.data.synth.writer import MARKER, PARTIAL_MARKER

    return (seq_dir.is_dir() and not (seq_dir / MARKER).exists() and not (seq_dir / PARTIAL_MARKER).exists()
            and any(seq_dir.iterdir()))
