"""Depth distributions from a single image (Yang, Hu, Ramanan, IROS 2019): bins, heads, network, training, inference."""
