"""tools/plot_predictions.py: the error column (log2 of predicted over LiDAR depth at the LiDAR points), and a
picture with it from the tiny sequence."""

import numpy as np

from tool_loader import load_tool


def test_error_image_at_lidar_points_only():
    tool = load_tool("plot_predictions")
    lidar = np.zeros((9, 9), np.float32)
    lidar[4, 4] = 10.0
    lidar[0, 8] = 5.0
    depth = np.full((9, 9), 20.0, np.float32)
    err = tool.error_image(depth, lidar)
    assert np.allclose(err[3:6, 3:6], 1.0)               # twice too far, spread to 3×3
    assert np.allclose(err[0:2, 7:9], 2.0)               # four times too far, clipped at the border
    assert np.isnan(err).sum() == 81 - 9 - 4             # nothing else has a value
    lidar[4, 5] = 40.0                                   # a farther neighbour: the nearer point wins
    assert np.allclose(tool.error_image(depth, lidar)[4, 4], 1.0)
    assert np.allclose(tool.error_image(depth * 0.5, lidar)[4, 4], 0.0)   # right: 0


def test_picture_with_error_column(tiny_root, tmp_path):
    tool = load_tool("plot_predictions")
    out = tmp_path / "p.png"
    assert tool.main(["--seq", "tiny", "--data-root", str(tiny_root), "--frames", "0,3", "--error",
                      "--model", "binary", "--out", str(out)]) == 0
    assert out.stat().st_size > 10_000
