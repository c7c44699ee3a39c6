"""Small configuration dataclasses shared across the pipeline (no global state).

One config per domain, each defined once: depth bins are ``mono_map.depth.bins.DepthBins``, the
network ``mono_map.depth.networks.ModelConfig``, training ``mono_map.depth.train_config``'s dataclasses,
OctoMap ``OctoMapConfig`` here.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class OctoMapConfig:
    """OctoMap parameters; the defaults are OctoMap 1.10's own."""

    resolution: float = 0.2          # metres
    prob_hit: float = 0.7
    prob_miss: float = 0.4
    clamp_min: float = 0.1192
    clamp_max: float = 0.971
    occupancy_threshold: float = 0.5
    max_range: float = -1.0          # metres; < 0 = unlimited (OctoMap's convention)


# Image size of KITTI odometry sequences 00-02 (image_2), pixels.
KITTI_IMAGE_WIDTH = 1241
KITTI_IMAGE_HEIGHT = 376
