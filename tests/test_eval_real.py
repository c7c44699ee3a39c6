"""tools/eval_real.py: every real source its own row, numbers from eval-depth's own code path."""

import json

import numpy as np

from mono_map.cli import main as cli_main
from tool_loader import load_tool
from tiny_net import write_tiny_checkpoint



def test_object_rows_equal_eval_depth_and_pool(tmp_path, kitti_real):
    ckpt = write_tiny_checkpoint(tmp_path / "tiny.pt", beyond=True)
    tool = load_tool("eval_real")
    out = tmp_path / "real"
    assert tool.main(["--model", str(ckpt), "--real-root", str(kitti_real), "--only", "object/training",
                      "--only", "object/extra", "--only", "object", "--out", str(out)]) == 0
    rows = {r["source"]: r for r in json.loads((out / "eval_real.json").read_text())["rows"]}
    assert [rows[k]["n_frames"] for k in ("object/training", "object/extra", "object (all 10)")] == [3, 7, 10]
    # the same numbers as `mono-map eval-depth --kitti-object` on the same frames
    ev = tmp_path / "ev"
    assert cli_main(["eval-depth", "--kitti-object", str(kitti_real / "object" / "training"), "--model", str(ckpt),
                     "--out", str(ev), "--threads", "1"]) == 0
    ref = next(iter(json.loads((ev / "depth_object.json").read_text())["results"].values()))
    assert np.isclose(rows["object/training"]["abs_rel"], ref["metrics"]["abs_rel"])
    assert np.isclose(rows["object/training"]["auc_are"], ref["sparsification"]["auc"]["are"])
    # pooling: the mean over ten frames is the frame-weighted mean of the two folders
    pooled = (3 * rows["object/training"]["abs_rel"] + 7 * rows["object/extra"]["abs_rel"]) / 10
    assert np.isclose(rows["object (all 10)"]["abs_rel"], pooled)
    r = rows["object (all 10)"]
    assert r["auc_are_oracle"] <= r["auc_are"] and r["abs_rel_median_scaled"] > 0
    md = (out / "eval_real.md").read_text()
    assert md.count("\n| object") == 8            # the main table and the table by LiDAR distance
    bands = rows["object/training"]["by_distance"]
    assert [b["lo"] for b in bands] == [0, 5, 10, 20, 40] and "40–80 m" in md
    assert sum(b["n_pixels"] for b in bands) == rows["object/training"]["n_pixels"]
    # three of object/extra's files have scrambled colour channels: named, and left out of one pool
    assert [n for n, _ in json.loads((out / "eval_real.json").read_text())["scrambled_colour"]] == \
        ["k000000", "k000001", "k000002"]
    assert rows["object (colour agrees)"]["n_frames"] == 7 and "k000001 (" in md


def test_colour_agreement_tells_a_camera_image_from_scrambled_channels(tmp_path, kitti_real, capsys):
    from mono_map.data.kitti_files import COLOUR_AGREEMENT_MIN, colour_agreement
    from mono_map.eval.depth_evaluation import scrambled_colour

    rng = np.random.default_rng(0)
    scene = rng.random((60, 80)).astype(np.float32)                       # one scene, three channels of it
    camera = np.stack([scene * 200, scene * 180 + 20 * rng.random((60, 80)), scene * 150 + 30], -1).astype(np.uint8)
    scrambled = camera.copy()
    scrambled[..., 1] = rng.permutation(camera[..., 1].ravel()).reshape(60, 80)   # one channel of another image
    assert colour_agreement(camera) > 0.9 > COLOUR_AGREEMENT_MIN > colour_agreement(scrambled)
    grey = np.repeat(camera[..., :1], 3, -1)
    assert colour_agreement(grey) > 0.99
    assert colour_agreement(np.full((4, 4, 3), 7, np.uint8)) == 1.0              # flat: nothing disagrees
    assert scrambled_colour([("a", camera, None), ("b", scrambled, None)]) == [("b", colour_agreement(scrambled))]
    # eval-depth names each such file in one warning line and scores it anyway
    ckpt = write_tiny_checkpoint(tmp_path / "tiny.pt", beyond=True)
    assert cli_main(["eval-depth", "--kitti-object", str(kitti_real / "object" / "extra"), "--model", str(ckpt),
                     "--out", str(tmp_path / "ev"), "--threads", "1"]) == 0
    err = [line for line in capsys.readouterr().err.splitlines() if "colour channels do not agree" in line]
    assert len(err) == 3 and all("k00000" in line and "scored anyway" in line for line in err)
    ev = next(iter(json.loads((tmp_path / "ev" / "depth_object.json").read_text())["results"].values()))
    assert ev["n_frames"] == 7


def test_bad_inputs_one_line(tmp_path, capsys, kitti_real):
    tool = load_tool("eval_real")
    assert tool.main(["--real-root", str(tmp_path), "--out", str(tmp_path / "o")]) == 2
    assert tool.main(["--real-root", str(kitti_real), "--seq", "nocolon", "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and "--real-root" in err[0] and "--seq" in err[1]
