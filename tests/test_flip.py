"""--flip: each image predicted mirrored too, the two outputs combined as samples (the mixture of two distributions)."""

from __future__ import annotations

import numpy as np
import pytest

from mono_map.depth.inference import DepthPredictor
from tiny_net import write_tiny_checkpoint


@pytest.fixture(scope="module")
def image():
    rng = np.random.default_rng(0)
    return (rng.uniform(0, 255, (64, 192, 3))).astype(np.uint8)     # the tiny network's input size: no padding


@pytest.mark.parametrize("head, fast", [("binary", False), ("binary", True), ("softmax", False)])
def test_flip_is_the_mixture_of_the_image_and_its_mirror(tmp_path, image, head, fast):
    ckpt = write_tiny_checkpoint(tmp_path / f"{head}.pt", head=head, beyond=True)
    plain = DepthPredictor.load(ckpt, fast=fast)
    flip = DepthPredictor.load(ckpt, fast=fast, flip=True)
    a = plain.predict(image, with_probs=True)
    b = plain.predict(np.ascontiguousarray(image[:, ::-1]), with_probs=True)
    f = flip.predict(image, with_probs=True)
    mix = 0.5 * (a.probs + b.probs[:, :, ::-1])
    assert np.allclose(f.probs, mix, atol=1e-5)
    log_centres = np.log(plain.bins.centres)[:, None, None]
    expected = np.exp((mix * log_centres).sum(0) / mix.sum(0))
    assert np.allclose(f.depth, expected, rtol=1e-4)
    assert not np.allclose(f.depth, a.depth, rtol=1e-3)        # the mirror changed something
    # the combined prediction is mirror-symmetric: the mirrored image's is its mirror image
    g = flip.predict(np.ascontiguousarray(image[:, ::-1]), with_probs=True)
    assert np.allclose(g.depth[:, ::-1], f.depth, rtol=1e-4) and np.allclose(g.probs[:, :, ::-1], f.probs, atol=1e-5)
    # the mixture is at least as uncertain as the mean of its parts (entropy is concave)
    assert np.all(f.entropy >= 0.5 * (a.entropy + b.entropy[:, ::-1]) - 1e-4)


def test_flip_with_a_gaussian_head_and_padding_runs(tmp_path):
    ckpt = write_tiny_checkpoint(tmp_path / "g.pt", head="gaussian", beyond=True)
    img = np.random.default_rng(1).uniform(0, 255, (50, 190, 3)).astype(np.uint8)   # padded to 64×192
    p = DepthPredictor.load(ckpt, flip=True).predict(img)
    assert p.depth.shape == (50, 190) and np.isfinite(p.depth).all() and np.isfinite(p.entropy).all()


def test_build_and_eval_take_flip_and_key_it(tiny_root, tmp_path, capsys):
    import json

    from mono_map.cli import main as cli_main

    ckpt = write_tiny_checkpoint(tmp_path / "tinynet.pt", beyond=True)
    common = ["--seq", "tiny", "--data-root", str(tiny_root), "--out", str(tmp_path / "m"), "--frames", "0:3",
              "--model", str(ckpt), "--keep", "0.8"]
    for extra in ([], ["--flip"]):
        assert cli_main(["build", *common, *extra]) == 0
    maps = sorted((tmp_path / "m").rglob("mono-keep0.8*.bt"), key=lambda p: "flip" in p.stem)
    assert len(maps) == 2 and [("flip" in p.stem) for p in maps] == [False, True]
    keys = [json.loads(p.with_suffix(".json").read_text())["job"] for p in maps]
    assert [k.get("flip") for k in keys] == [None, True]      # maps made before --flip keep their keys
    assert cli_main(["eval", *common, "--flip", "--json", str(tmp_path / "e.json")]) == 0
    assert "_flip_" in json.loads((tmp_path / "e.json").read_text())["map_path"]
    for bad in (["--model", "oracle"], ["--source", "lidar"]):
        capsys.readouterr()
        argv = ["build", "--seq", "tiny", "--data-root", str(tiny_root), "--out", str(tmp_path / "b"), "--flip", *bad]
        assert cli_main(argv) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "--flip" in err[0], err


def test_eval_depth_names_flipped_rows_and_they_differ(tmp_path, tiny_root):
    import json

    from mono_map.cli import main as cli_main

    ckpt = write_tiny_checkpoint(tmp_path / "tinynet.pt", {"name": "tiny-run"}, beyond=True)
    res = {}
    for extra in ([], ["--flip"]):
        out = tmp_path / f"ev{len(extra)}"
        assert cli_main(["eval-depth", "--seq", "tiny", "--data-root", str(tiny_root), "--frames", "0:2",
                         "--model", str(ckpt), "--out", str(out), "--threads", "1", *extra]) == 0
        res.update(json.loads((out / "depth_seqtiny.json").read_text())["results"])
    assert set(res) == {"tiny-run", "tiny-run --flip"}
    assert res["tiny-run"]["metrics"]["abs_rel"] != res["tiny-run --flip"]["metrics"]["abs_rel"]
