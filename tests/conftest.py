"""Shared fixtures: the tiny synthetic sequence (generated once per session), one torch thread."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

# ../shared/kitti_real (real KITTI poses, calibration, object frames): beside the repo as CI has it,
# or where $MONO_MAP_SHARED points
SHARED_DIR = Path(os.environ.get("MONO_MAP_SHARED") or Path(__file__).resolve().parents[2] / "shared")


@pytest.fixture(scope="session")
def tiny_root(tmp_path_factory):
    """A KITTI odometry root holding the synthetic sequence ``tiny`` (6 frames, sequences/tiny.toml)."""
    from mono_map.data.synth import generate_sequence, load_recipe

    root = tmp_path_factory.mktemp("kitti_tiny")
    generate_sequence(load_recipe("tiny"), root, workers=2, quiet=True)
    return root


@pytest.fixture(autouse=True)
def _one_torch_thread():
    """One intra-op thread: on the shared 2-core machine two threads spin-wait and run ~10x slower."""
    import torch

    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture(scope="session")
def kitti_real() -> Path:
    """The real KITTI files. Missing: a failure under CI (``MONO_MAP_REQUIRE_SHARED=1``, set by
    .ci/run), a skip naming the path in a clone that has no ``../shared`` beside it."""
    path = SHARED_DIR / "kitti_real"
    if not path.is_dir():
        message = f"{path}: real KITTI files missing (set MONO_MAP_SHARED to the folder holding kitti_real/)"
        if os.environ.get("MONO_MAP_REQUIRE_SHARED") == "1":
            pytest.fail(message)
        pytest.skip(message)
    return path
