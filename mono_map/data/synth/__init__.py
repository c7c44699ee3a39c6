"""Synthetic KITTI world: procedural towns along real KITTI trajectories, rendered by ray casting
into the KITTI odometry layout (image_2, velodyne, dense depth_2, calib, times, poses).

    from mono_map.data.synth import load_recipe, generate_sequence, ensure_sequence
    recipe = load_recipe("00")                       # sequences/00.toml
    generate_sequence(recipe, "data/kitti", frames=100)
"""

from mono_map.data.synth.generate import GENERATOR_VERSION, FrameRenderer, ensure_sequence, generate_sequence
from mono_map.data.synth.recipe import Recipe, load_recipe

__all__ = ["Recipe", "load_recipe", "generate_sequence", "ensure_sequence", "FrameRenderer", "GENERATOR_VERSION"]
