"""The untrained tiny depth network the command tests run (fast; enough to exercise every code path)."""

from __future__ import annotations

from pathlib import Path

# named_config("small", **TINY_NET): 16 bins at 64×192
TINY_NET = dict(widths=(8, 8, 8, 8), stem_width=8, spp_width=4, decoder_widths=(8, 8, 8),
                num_bins=16, input_height=64, input_width=192)


def write_tiny_checkpoint(path: Path, meta: dict | None = None, **overrides) -> Path:
    """Save a freshly initialised tiny network (torch seed 0; ``overrides`` change TINY_NET's fields) at ``path``."""
    import torch

    from mono_map.depth.inference import save_checkpoint
    from mono_map.depth.networks import DepthNet, named_config

    torch.manual_seed(0)
    save_checkpoint(path, DepthNet(named_config("small", **{**TINY_NET, **overrides})),
                    {"step": 0} if meta is None else meta)
    return path
