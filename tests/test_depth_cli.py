"""CLI: predict on an image folder, eval-depth on the real KITTI object frames."""

import json

import numpy as np
import pytest
import torch

from mono_map.cli import main
from mono_map.data.depth_png import read_depth_png
from tiny_net import write_tiny_checkpoint




@pytest.fixture
def tiny_ckpt(tmp_path):
    return write_tiny_checkpoint(tmp_path / "tiny.pt")


def test_predict_image_folder(tmp_path, tiny_ckpt):
    import cv2

    imgs = tmp_path / "imgs"
    imgs.mkdir()
    cv2.imwrite(str(imgs / "a.png"), (np.random.default_rng(0).random((60, 200, 3)) * 255).astype(np.uint8))
    out = tmp_path / "out"
    assert main(["predict", "--images", str(imgs), "--model", str(tiny_ckpt), "--out", str(out), "--npz"]) == 0
    d = read_depth_png(out / "depth" / "a.png")
    assert d.shape == (60, 200) and d.min() >= 1.0 - 1 / 256 and d.max() <= 80.0
    assert (out / "vis" / "a.jpg").is_file()
    z = np.load(out / "npz" / "a.npz")
    assert z["probs"].shape[0] == 16 and z["depth"].shape == (60, 200)


def test_eval_depth_on_real_object_frames(tmp_path, tiny_ckpt, kitti_real):
    obj = kitti_real / "object" / "training"
    out = tmp_path / "ev"
    assert main(["eval-depth", "--kitti-object", str(obj), "--model", str(tiny_ckpt), "--out", str(out),
                 "--threads", "1"]) == 0
    res = json.loads((out / "depth_object.json").read_text())["results"]["binary"]
    assert res["n_frames"] == 3 and res["n_pixels"] > 10000  # HDL-64E points inside image_2
    s = res["sparsification"]
    for k in ("are", "rmse", "1-d1"):
        assert s["auc_oracle"][k] <= s["auc"][k]
    assert res["hypotheses"]["5"]["abs_rel"] <= res["hypotheses"]["1"]["abs_rel"]
    assert (out / "sparsification_object.png").stat().st_size > 1000
    assert main(["eval-depth", "--kitti-object", str(tmp_path), "--model", str(tiny_ckpt)]) == 2


def test_eval_depth_rows_are_named_by_their_training_runs(tmp_path, kitti_real):
    """Two runs of one head (e.g. the bin-count ablation) are two rows named by their runs, in one table."""
    torch.manual_seed(0)
    a, b = tmp_path / "a.pt", tmp_path / "b.pt"
    write_tiny_checkpoint(a, {"name": "v2-binary"})
    write_tiny_checkpoint(b, {"name": "v2-binary-k8"}, num_bins=8)
    out = tmp_path / "ev"
    assert main(["eval-depth", "--kitti-object", str(kitti_real / "object" / "training"), "--model", str(a),
                 "--model", str(b), "--out", str(out), "--threads", "1"]) == 0
    res = json.loads((out / "depth_object.json").read_text())["results"]
    assert set(res) == {"v2-binary", "v2-binary-k8"}
    md = (out / "depth_object.md").read_text()
    assert "v2-binary-k8" in md and "v2-binary " in md.replace("|", " ")
