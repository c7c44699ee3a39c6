"""The right colour camera (image_3) as a source: the reader, adapt --stereo, the multi-view posterior's stereo view
(a stopped car and a scene moving with the car still get depth), bad inputs."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
import torch

from mono_map.cli import main as cli_main
from mono_map.depth import photometric as ph
from mono_map.depth.adapt import AdaptConfig, adapt, with_stereo_sources
from mono_map.depth.inference import load_checkpoint
from mono_map.depth.multiview import MultiviewConfig, MultiviewPosterior
from mono_map.errors import MonoMapError
from test_multiview import BINS, WALL, K, WallSeq, flat_prediction, texture
from tiny_net import write_tiny_checkpoint

BASELINE = 0.53      # metres between KITTI's colour cameras


class StereoWallSeq(WallSeq):
    """WallSeq with a right camera BASELINE metres to the right of each left one (same instant, same K)."""

    right_dir = "image_3"

    def T_world_cam3(self, i):
        T = self.T_world_cam2(i).copy()
        T[0, 3] += BASELINE
        return T

    def has_right(self, indices):
        return True

    def require_right(self, indices, option):
        pass

    def image_right(self, i):
        v, u = np.mgrid[0:64, 0:160].astype(np.float64)
        cx = (0.0 if self.moving else self.step * i) + BASELINE
        g = np.clip(texture(cx + (u - K[0, 2]) / K[0, 0] * WALL, (v - K[1, 2]) / K[1, 1] * WALL), 0, 1)
        return (np.repeat(g[..., None], 3, -1) * 255).round().astype(np.uint8)


def posterior_modes(seq, stereo):
    r = MultiviewPosterior(MultiviewConfig(scale=1, stereo=stereo), BINS)
    pred = flat_prediction()
    q = r.refine(seq, 2, pred)
    return np.asarray(q.probs).argmax(0), r, q, pred


@pytest.mark.parametrize("kind", ["stopped car", "wall moving with the car"])
def test_the_right_camera_gives_depth_where_the_neighbours_cannot(kind):
    seq = StereoWallSeq(step=0.0) if kind == "stopped car" else StereoWallSeq(moving=True)
    _, r, q, pred = posterior_modes(seq, stereo=False)
    assert r.last_informative < 0.05                       # left images alone: nothing (no baseline / auto-masked)
    mode, r, q, _ = posterior_modes(seq, stereo=True)
    true_bin = int(np.searchsorted(BINS.edges, WALL) - 1)
    assert r.last_informative > 0.8
    assert np.mean(np.abs(mode[8:-8, 30:-30] - true_bin) <= 1) > 0.9


def test_adapt_stereo_sources_are_the_frames_own_right_images():
    temporal = {0: [1], 1: [0, 2], 3: [2]}
    s = with_stereo_sources(temporal, 4)
    assert s == {0: [1, 4], 1: [0, 2, 5], 2: [6], 3: [2, 7]}     # frame 2 had no neighbour: now a target too


@pytest.fixture(scope="module")
def stereo_root(tiny_root, tmp_path_factory):
    """A copy of tiny with image_3 rendered (mono-map synth --stereo)."""
    from mono_map.data.synth import generate_sequence, load_recipe

    root = tmp_path_factory.mktemp("kitti_tiny_stereo")
    shutil.copytree(tiny_root, root, dirs_exist_ok=True)
    generate_sequence(load_recipe("tiny"), root, workers=1, quiet=True, stereo=True)
    return root


def test_the_reader_finds_image_3_and_its_pose(tiny_root, stereo_root):
    from mono_map.data.kitti import open_sequence

    mono, st = open_sequence(tiny_root, "tiny"), open_sequence(stereo_root, "tiny")
    assert not mono.has_right(range(len(mono))) and st.has_right(range(len(st)))
    assert st.image_right(1).shape == st.image(1).shape
    d = np.linalg.inv(st.T_world_cam2(1)) @ st.T_world_cam3(1)     # cam3 in cam2's frame
    assert np.allclose(d[:3, :3], np.eye(3)) and 0.5 < d[0, 3] < 0.6 and abs(d[1, 3]) < 0.01 and abs(d[2, 3]) < 0.01


def test_image_3_warped_through_the_true_depth_reconstructs_image_2(stereo_root):
    """The stereo pair is the photometric loss's ideal source: true depth reconstructs, wrong depth (×0.5, ×2)
    does not, and the baseline is fixed (no scale freedom)."""
    import cv2

    from mono_map.data.kitti import open_sequence

    seq = open_sequence(stereo_root, "tiny")
    h, w = seq.image_size
    size = (w // 4, h // 4)

    def img(a):
        return torch.from_numpy(cv2.resize(a, size, interpolation=cv2.INTER_AREA)).permute(2, 0, 1)[None].float() / 255

    d = cv2.resize(seq.depth(1), size, interpolation=cv2.INTER_NEAREST)
    d = torch.from_numpy(np.where(d > 0, d, 1000.0))[None, None].float()
    Ks = seq.calib.K2.copy()
    Ks[0] *= size[0] / w
    Ks[1] *= size[1] / h
    Kt = torch.as_tensor(Ks)[None].float()
    T = torch.as_tensor(np.linalg.inv(seq.T_world_cam3(1)) @ seq.T_world_cam2(1))[None].float()
    tgt, right = img(seq.image(1)), img(seq.image_right(1))

    def loss(depth):
        return float(ph.reprojection_loss(tgt, [right], depth, Kt, [T], automask=False)[0])

    true = loss(d)
    assert true < 0.6 * float(ph.photometric_error(right, tgt).mean())
    assert loss(d * 0.5) > 1.15 * true and loss(d * 2.0) > 1.15 * true


def run(root, ckpt, tmp_path, name, **kw):
    cfg = AdaptConfig(steps=2, batch_size=2, eval_every=1, **kw)
    return adapt(str(ckpt), root, "tiny", None, cfg, out_dir=tmp_path / name, state_dir=tmp_path / f"s{name}",
                 log=lambda m: None)


def test_adapt_uses_image_3_when_there_and_names_it(tiny_root, stereo_root, tmp_path):
    ckpt = write_tiny_checkpoint(tmp_path / "tinynet.pt", beyond=True)
    default = run(stereo_root, ckpt, tmp_path, "default")
    assert default.metadata["adapted"]["stereo"] is False          # off unless asked for (measured: docs/real_kitti.md)
    a = run(stereo_root, ckpt, tmp_path, "auto", stereo="auto")
    again = run(stereo_root, ckpt, tmp_path, "again", stereo="auto")      # deterministic with image_3 too
    ma, mb = load_checkpoint(a.checkpoint)[0], load_checkpoint(again.checkpoint)[0]
    assert a.checkpoint.name == again.checkpoint.name
    assert all(torch.equal(x, y) for x, y in zip(ma.state_dict().values(), mb.state_dict().values()))
    off = run(stereo_root, ckpt, tmp_path, "off", stereo="off")
    assert a.metadata["adapted"]["stereo"] is True and off.metadata["adapted"]["stereo"] is False
    assert a.checkpoint.name != off.checkpoint.name and off.checkpoint.name == default.checkpoint.name
    # without image_3, auto is the run it always was: the same name as stereo off
    plain = run(tiny_root, ckpt, tmp_path, "plain", stereo="auto")
    plain_off = run(tiny_root, ckpt, tmp_path, "plain_off", stereo="off")
    assert plain.checkpoint.name == plain_off.checkpoint.name and plain.metadata["adapted"]["stereo"] is False
    # a car too slow for a temporal source: the right images alone still adapt
    slow = run(stereo_root, ckpt, tmp_path, "slow", min_baseline=3.9, stereo="auto")
    assert slow.metadata["adapted"]["targets"] == 6
    with pytest.raises(MonoMapError, match="too little motion"):
        run(stereo_root, ckpt, tmp_path, "slow_off", min_baseline=3.9, stereo="off")


def test_stereo_on_renders_a_synthetic_sequences_image_3(tiny_root, tmp_path):
    ckpt = write_tiny_checkpoint(tmp_path / "tinynet.pt", beyond=True)
    root = tmp_path / "copy"
    shutil.copytree(tiny_root, root)
    res = run(root, ckpt, tmp_path, "on", stereo="on")
    assert res.metadata["adapted"]["stereo"] is True
    assert len(list((root / "sequences" / "tiny" / "image_3").glob("*.png"))) == 6


def test_stereo_bad_inputs_are_one_line(tiny_root, tmp_path, capsys):
    """A sequence without image_3 that is not ours to render (no synthetic marker: as a real download)."""
    ckpt = write_tiny_checkpoint(tmp_path / "tinynet.pt", beyond=True)
    real = tmp_path / "real"
    shutil.copytree(tiny_root, real)
    (real / "sequences" / "tiny" / "synth.json").unlink()
    adapt_base = ["adapt", "--seq", "tiny", "--data-root", str(real), "--out", str(tmp_path / "o"),
                  "--steps", "1", "--model", str(ckpt)]
    build_base = ["build", "--seq", "tiny", "--data-root", str(real), "--out", str(tmp_path / "m"),
                  "--model", str(ckpt), "--integrate", "fused"]
    cases = [(adapt_base + ["--stereo", "on"], "--stereo on"),
             (build_base + ["--fused-stereo", "1"], "--fused-stereo 1"),
             (build_base + ["--fused-stereo", "1", "--fused-multiview", "0"], "--fused-stereo"),
             (build_base + ["--fused-stereo", "2"], "--fused-stereo")]
    for argv, words in cases:
        capsys.readouterr()
        assert cli_main(argv) == 2, argv
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and words in err[0], (argv, err)
    assert not (tmp_path / "o").exists() or not list((tmp_path / "o").glob("*.pt"))
    assert not (tmp_path / "m").exists() or not list((tmp_path / "m").rglob("*.bt"))
    assert not (real / "sequences" / "tiny" / "image_3").exists()


def test_adapt_auto_masks_the_neighbours_and_the_right_image_apart():
    """A wall moving with the car: the unwarped neighbour matches (monodepth2's auto-mask drops every pixel when
    the right image is one more source of the same minimum); masked per group the right image still counts."""
    seq = StereoWallSeq(moving=True)

    def t(a):
        return torch.from_numpy(a).permute(2, 0, 1)[None].float() / 255

    tgt, near, right = t(seq.image(2)), t(seq.image(1)), t(seq.image_right(2))
    Kt = torch.as_tensor(K)[None].float()
    T_near = torch.as_tensor(np.linalg.inv(seq.T_world_cam2(1)) @ seq.T_world_cam2(2))[None].float()
    T_right = torch.as_tensor(np.linalg.inv(seq.T_world_cam3(2)) @ seq.T_world_cam2(2))[None].float()
    depth = torch.full((1, 1, 64, 160), WALL)
    _, used_one = ph.reprojection_loss(tgt, [near, right], depth, Kt, [T_near, T_right])
    err, used = ph.grouped_reprojection(tgt, [([near], [T_near]), ([right], [T_right])], depth, Kt)
    assert used_one.float().mean() < 0.05 and used.float().mean() > 0.7
    assert float(err[used].mean()) < 0.05
    # a static scene seen by both: the same pixels count as with one minimum, at the same or lower error
    _, used_plain = ph.reprojection_loss(tgt, [right], depth, Kt, [T_right])
    err_r, used_r = ph.grouped_reprojection(tgt, [([right], [T_right])], depth, Kt)
    assert torch.equal(used_r, used_plain)


def test_a_fused_build_takes_the_right_images_and_keys_them(stereo_root, tmp_path):
    import json

    ckpt = write_tiny_checkpoint(tmp_path / "tinynet.pt", beyond=True)
    keys = {}
    for stereo in ("0", "1"):
        out = tmp_path / f"m{stereo}"
        assert cli_main(["build", "--seq", "tiny", "--data-root", str(stereo_root), "--out", str(out), "--frames", "0:3",
                         "--model", str(ckpt), "--integrate", "fused", "--fused-stereo", stereo]) == 0
        side = list(out.rglob("mono-fused*.json"))
        assert len(side) == 1
        keys[stereo] = json.loads(side[0].read_text())["job"]["integration"]["fused"]
    assert "stereo" not in keys["0"] and keys["1"]["stereo"] == 1    # maps made before stereo keep their keys
