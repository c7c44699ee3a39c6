"""Shared fixtures: the tiny synthetic sequence (generated once per session), one torch thread."""

from __future__ import annotations

import pytest


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
