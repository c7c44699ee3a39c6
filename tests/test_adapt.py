"""mono-map adapt: the photometric warp, its scale, auto-masking, sources by baseline, determinism, resume,
bad inputs."""

import json
import shutil

import numpy as np
import pytest
import torch

from mono_map.cli import main as cli_main
from mono_map.depth import photometric as ph
from mono_map.depth.adapt import AdaptConfig, adapt, held_out
from mono_map.depth.inference import load_checkpoint
from mono_map.errors import MonoMapError
from mono_map.depth.sources import choose_sources
from mono_map.frames import parse_frames
from tiny_net import write_tiny_checkpoint



@pytest.fixture
def tiny_ckpt(tmp_path):
    return write_tiny_checkpoint(tmp_path / "tinynet.pt", beyond=True)


@pytest.fixture(scope="module")
def pair(tiny_root):
    """Frames 1 (target) and 2 (source) of tiny at 1/4 resolution: images, true depth, K, T_src_tgt."""
    import cv2

    from mono_map.data.kitti import open_sequence

    seq = open_sequence(tiny_root, "tiny")
    h, w = seq.image_size
    s = 4
    size = (w // s, h // s)

    def img(i):
        return torch.from_numpy(cv2.resize(seq.image(i), size, interpolation=cv2.INTER_AREA)).permute(2, 0, 1)[None].float() / 255

    d = cv2.resize(seq.depth(1), size, interpolation=cv2.INTER_NEAREST)
    d = np.where(d > 0, d, 1000.0)   # sky: far away
    K = seq.calib.K2.copy()
    K[0] *= size[0] / w
    K[1] *= size[1] / h
    T = np.linalg.inv(seq.T_world_cam2(2)) @ seq.T_world_cam2(1)
    return (img(1), img(2), torch.from_numpy(d)[None, None].float(), torch.as_tensor(K)[None].float(),
            torch.as_tensor(T)[None].float())


def loss_of(target, source, depth, K, T, automask=False):
    return float(ph.reprojection_loss(target, [source], depth, K, [T], automask=automask)[0])


def test_true_depth_and_pose_reconstruct_the_target(pair):
    tgt, src, depth, K, T = pair
    true = loss_of(tgt, src, depth, K, T)
    unwarped = float(ph.photometric_error(src, tgt).mean())
    assert true < 0.75 * unwarped     # the warp explains most of the change between the frames
    for wrong in (depth * 0.5, depth * 2.0, torch.full_like(depth, 10.0)):
        assert loss_of(tgt, src, wrong, K, T) > true * 1.15


def test_scale_comes_from_the_poses(pair):
    tgt, src, depth, K, T = pair
    T2 = T.clone()
    T2[:, :3, 3] *= 2
    base = loss_of(tgt, src, depth, K, T)
    assert abs(loss_of(tgt, src, depth * 2, K, T2) - base) < 1e-4     # depth ×2 with translation ×2: same
    assert loss_of(tgt, src, depth * 2, K, T) > base * 1.15           # depth ×2 alone: worse


def test_identity_pose_reproduces_the_image_and_automask_masks_a_static_camera(pair):
    tgt, _, depth, K, _ = pair
    warped, valid = ph.warp(tgt, depth, K, torch.eye(4)[None])
    assert valid.all() and (warped - tgt).abs().max() < 1e-4
    loss, used = ph.reprojection_loss(tgt, [tgt.clone()], depth, K, [torch.eye(4)[None]])
    assert used.sum() == 0 and float(loss) == 0.0


def test_a_mirrored_sample_is_the_same_geometry(pair):
    """Images, depth, intrinsics and pose all mirrored: the same loss; the images alone mirrored: a worse one."""
    from mono_map.depth.adapter import mirror_images, mirror_intrinsics, mirror_poses

    tgt, src, depth, K, T = pair
    yes, no = torch.tensor([True]), torch.tensor([False])
    assert torch.equal(mirror_images(tgt, no), tgt) and torch.equal(mirror_intrinsics(K, 9, no), K)
    assert torch.equal(mirror_poses(T, no), T)
    Km = mirror_intrinsics(K, tgt.shape[-1], yes)
    assert float(Km[0, 0, 2]) == pytest.approx(tgt.shape[-1] - 1 - float(K[0, 0, 2]))
    Tm = mirror_poses(T, yes)
    assert float(Tm[0, 0, 3]) == pytest.approx(-float(T[0, 0, 3])) and float(Tm[0, 2, 3]) == pytest.approx(float(T[0, 2, 3]))
    base = loss_of(tgt, src, depth, K, T)
    mirrored = loss_of(mirror_images(tgt, yes), mirror_images(src, yes), mirror_images(depth, yes), Km, Tm)
    assert mirrored == pytest.approx(base, rel=1e-4)
    images_only = loss_of(mirror_images(tgt, yes), mirror_images(src, yes), mirror_images(depth, yes), K, T)
    assert images_only > base * 1.15


def test_trim_leaves_out_the_worst_pixels(pair):
    tgt, src, depth, K, T = pair
    full, used = ph.reprojection_loss(tgt, [src], depth, K, [T], automask=False)
    half, used_half = ph.reprojection_loss(tgt, [src], depth, K, [T], automask=False, trim=0.5)
    assert abs(int(used_half.sum()) - int(used.sum()) / 2) <= 0.01 * int(used.sum())
    assert (used_half <= used).all() and float(half) < float(full)



def test_sources_by_baseline_not_offset():
    # a car that stops for frames 2-5: 1 m steps, then 0.01 m steps, then 1 m steps
    x = np.concatenate([[0, 1, 2], 2 + 0.01 * np.arange(1, 4), [3.03, 4.03]])
    pos = np.stack([x, 0 * x, 0 * x], 1)
    src = choose_sources(pos, 0.3, 4.0, 10)
    assert src[0] == [1] and src[1] == [0, 2]
    assert src[3] == [1, 6]           # the stopped frames look past the stop
    assert all(abs(x[i] - x[j]) >= 0.3 for j, s in src.items() for i in s)
    assert 0 not in choose_sources(pos, 0.3, 0.5, 10)     # no neighbour within 0.3-0.5 m
    two = choose_sources(pos, 0.3, 4.0, 10, per_side=2)   # a second source per side at >= 2x the baseline
    assert two[0] == [1, 2] and two[6] == [1, 5, 7] and two[3] == [1, 6]
    for j, s in two.items():
        for side in ([i for i in s if i < j][::-1], [i for i in s if i > j]):
            b = [abs(x[i] - x[j]) for i in side]
            assert len(b) <= 2 and all(b1 >= 2 * b0 - 1e-9 for b0, b1 in zip(b, b[1:]))
    assert all(choose_sources(pos, 0.3, 4.0, 10, per_side=1)[j] == s for j, s in src.items())
    assert held_out(list(range(20))) == [5, 15] and held_out([1, 2]) == []


def run(tiny_root, ckpt, tmp_path, steps, state, out, **kw):
    cfg = AdaptConfig(steps=steps, batch_size=2, eval_every=1, seed=kw.pop("seed", 0), **kw)
    return adapt(str(ckpt), tiny_root, "tiny", None, cfg, out_dir=tmp_path / out, state_dir=tmp_path / state,
                 log=lambda m: None)


def last_weights(state_dir):
    st = torch.load(next(state_dir.glob("*/state.pt")), weights_only=False)
    return st["step"], st["model"]


def test_adapt_is_deterministic_resumes_and_names_its_settings(tiny_root, tiny_ckpt, tmp_path):
    a = run(tiny_root, tiny_ckpt, tmp_path, 3, "sa", "oa")
    b = run(tiny_root, tiny_ckpt, tmp_path, 3, "sb", "ob")
    assert a.checkpoint.name == b.checkpoint.name and a.checkpoint.name.startswith("tinynet-adapted-tiny-")
    ma, _ = load_checkpoint(a.checkpoint)
    mb, _ = load_checkpoint(b.checkpoint)
    assert all(torch.equal(x, y) for x, y in zip(ma.state_dict().values(), mb.state_dict().values()))
    base, _ = load_checkpoint(tiny_ckpt)
    step_a, wa = last_weights(tmp_path / "sa")
    assert step_a == 3 and not all(torch.equal(wa[k], v) for k, v in base.state_dict().items())
    # 2 steps, then the same run asked for 3 resumes at 2: the same weights as 3 in one go
    run(tiny_root, tiny_ckpt, tmp_path, 2, "sc", "oc")
    c = run(tiny_root, tiny_ckpt, tmp_path, 3, "sc", "oc")
    step_c, wc = last_weights(tmp_path / "sc")
    assert step_c == 3 and all(torch.equal(wa[k], wc[k]) for k in wa)
    assert c.checkpoint.name == a.checkpoint.name
    meta = json.loads(c.checkpoint.with_suffix(".json").read_text())
    assert meta["adapted"]["sequence"] == "tiny" and meta["steps"] == 3 and len(meta["adapted"]["curve"]) == 4
    # other settings, another seed or other frames: another name
    d = run(tiny_root, tiny_ckpt, tmp_path, 3, "sd", "od", lr=3e-4)
    e = run(tiny_root, tiny_ckpt, tmp_path, 3, "se", "oe", seed=1)
    assert len({a.checkpoint.name, d.checkpoint.name, e.checkpoint.name}) == 3
    # mirrored samples: deterministic, other weights, another name; off is the key of a run without the option
    f = run(tiny_root, tiny_ckpt, tmp_path, 3, "sf", "of", mirror=0.5)
    g = run(tiny_root, tiny_ckpt, tmp_path, 3, "sg", "og", mirror=0.5)
    assert f.checkpoint.name == g.checkpoint.name and f.checkpoint.name != a.checkpoint.name
    _, wf = last_weights(tmp_path / "sf")
    _, wg = last_weights(tmp_path / "sg")
    assert all(torch.equal(wf[k], wg[k]) for k in wf) and not all(torch.equal(wa[k], wf[k]) for k in wa)
    assert "mirror" not in AdaptConfig().run_settings() and AdaptConfig(mirror=0.5).run_settings()["mirror"] == 0.5


def test_the_adapted_checkpoint_predicts(tiny_root, tiny_ckpt, tmp_path):
    res = run(tiny_root, tiny_ckpt, tmp_path, 1, "s", "o")
    out = tmp_path / "pred"
    assert cli_main(["predict", "--seq", "tiny", "--data-root", str(tiny_root), "--frames", "0:2",
                     "--model", str(res.checkpoint), "--out", str(out)]) == 0
    assert len(list((out / "depth").glob("*.png"))) == 2


def test_bad_inputs_one_line(tiny_root, tiny_ckpt, tmp_path, capsys):
    base = ["adapt", "--seq", "tiny", "--data-root", str(tiny_root), "--out", str(tmp_path / "o"), "--steps", "1"]
    torch.manual_seed(0)
    gauss = tmp_path / "gauss.pt"
    write_tiny_checkpoint(gauss, {}, beyond=True, head="gaussian")
    no_poses = tmp_path / "noposes"
    shutil.copytree(tiny_root, no_poses)
    (no_poses / "poses" / "tiny.txt").unlink()
    cases = [(["--model", str(tiny_ckpt), "--frames", "1"], "at least 2 frames"),
             (["--model", str(gauss)], "gaussian"),
             (["--model", str(tiny_ckpt), "--min-baseline", "3.9"], "too little motion"),
             (["--model", str(tiny_ckpt), "--steps", "0"], "--steps"),
             (["--model", str(tiny_ckpt), "--replay", "0.5"], "--replay-seq"),
             (["--model", str(tiny_ckpt), "--max-baseline", "0.1"], "--max-baseline"),
             (["--model", str(tiny_ckpt), "--data-root", str(no_poses)], "no poses"),
             (["--model", str(tiny_ckpt), "--hints", "-1"], "--hints"),
             (["--model", str(tiny_ckpt), "--hints", "nan"], "--hints"),
             (["--model", str(tiny_ckpt), "--mirror", "1.5"], "--mirror"),
             (["--model", str(tiny_ckpt), "--smoothness", "-1"], "--smoothness"),
             (["--model", str(tiny_ckpt), "--entropy-hold", "-1"], "--entropy-hold"),
             (["--model", str(tiny_ckpt), "--mirror", "0.5", "--hints", "0.1"], "--mirror")]
    for extra, words in cases:
        capsys.readouterr()
        assert cli_main(base + extra) == 2, extra
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and words in err[0], (extra, err)
    assert not (tmp_path / "o").exists() or not list((tmp_path / "o").glob("*.pt"))
    # a replay sequence is only read, never rendered (the data root may be shared)
    with pytest.raises(MonoMapError, match="not found"):
        run(tiny_root, tiny_ckpt, tmp_path, 1, "sr", "or", replay=0.5, replay_seq="05")
    assert not (tiny_root / "sequences" / "05").exists()
    with pytest.raises(MonoMapError, match="00 is the held-out"):
        AdaptConfig(replay=1.0, replay_seq="00").validate()


def test_replay_mixes_supervised_batches(tiny_root, tiny_ckpt, tmp_path):
    """Replay on a synthetic sequence (here tiny itself, with its LiDAR) changes the weights the run reaches."""
    run(tiny_root, tiny_ckpt, tmp_path, 2, "s0", "o0")
    r = run(tiny_root, tiny_ckpt, tmp_path, 2, "s1", "o1", replay=0.5, replay_seq="tiny", replay_frames=3)
    assert r.metadata["adapted"]["settings"]["replay"] == 0.5
    st = torch.load(next((tmp_path / "s1").glob("*/state.pt")), weights_only=False)
    assert st["replay_scale"] is not None and st["replay_scale"] > 0
    _, w0 = last_weights(tmp_path / "s0")
    assert not all(torch.equal(w0[k], v) for k, v in st["model"].items())



def test_decoder_only_keeps_the_encoder_and_more_sources_run(tiny_root, tiny_ckpt, tmp_path):
    base, _ = load_checkpoint(tiny_ckpt)
    assert AdaptConfig().train_encoder is False                    # the default: the decoder and head adapt
    run(tiny_root, tiny_ckpt, tmp_path, 2, "s", "o", per_side=2)
    _, w = last_weights(tmp_path / "s")
    b = base.state_dict()
    enc = [k for k in w if k.startswith("encoder.") and w[k].is_floating_point()]
    assert enc and all(torch.equal(w[k], b[k]) for k in enc)
    assert not all(torch.equal(w[k], b[k]) for k in w if not k.startswith("encoder."))
    run(tiny_root, tiny_ckpt, tmp_path, 2, "s2", "o2", train_encoder=True)   # --no-decoder-only: the whole network
    _, w2 = last_weights(tmp_path / "s2")
    assert not all(torch.equal(w2[k], b[k]) for k in enc)


def test_adapt_cli_decoder_only_is_the_default_and_can_be_turned_off():
    import argparse

    from mono_map.cli import adapt as cli_adapt

    root = argparse.ArgumentParser()
    sub = root.add_subparsers(dest="cmd")
    cli_adapt.register(sub)
    assert root.parse_args(["adapt", "--seq", "s"]).decoder_only is True
    assert root.parse_args(["adapt", "--seq", "s", "--no-decoder-only"]).decoder_only is False


def test_a_corrupt_saved_state_starts_the_run_again(tiny_root, tiny_ckpt, tmp_path):
    run(tiny_root, tiny_ckpt, tmp_path, 1, "s", "o")
    state = next((tmp_path / "s").glob("*/state.pt"))
    state.write_bytes(b"not a torch file")
    messages = []
    cfg = AdaptConfig(steps=2, batch_size=2, eval_every=1)
    res = adapt(str(tiny_ckpt), tiny_root, "tiny", None, cfg, out_dir=tmp_path / "o", state_dir=tmp_path / "s",
                log=messages.append)
    assert any("unreadable saved state" in m for m in messages)
    assert last_weights(tmp_path / "s")[0] == 2 and res.checkpoint.is_file()


def test_adapt_with_hints_is_deterministic_and_named_by_them(tiny_root, tiny_ckpt, tmp_path):
    a = run(tiny_root, tiny_ckpt, tmp_path, 2, "sa", "oa", hints=1.0)
    b = run(tiny_root, tiny_ckpt, tmp_path, 2, "sb", "ob", hints=1.0)
    ma, _ = load_checkpoint(a.checkpoint)
    mb, _ = load_checkpoint(b.checkpoint)
    assert a.checkpoint.name == b.checkpoint.name
    assert all(torch.equal(x, y) for x, y in zip(ma.state_dict().values(), mb.state_dict().values()))
    curve = a.metadata["adapted"]["curve"]
    assert a.metadata["adapted"]["settings"]["hints"] == 1.0 and 0 < curve[-1]["hinted_pixels"] <= 1
    # the hints change the run, and the name; another hint loss too
    off = run(tiny_root, tiny_ckpt, tmp_path, 2, "sc", "oc")
    head = run(tiny_root, tiny_ckpt, tmp_path, 2, "sd", "od", hints=1.0, hint_loss="head")
    assert len({a.checkpoint.name, off.checkpoint.name, head.checkpoint.name}) == 3
    _, w_off = last_weights(tmp_path / "sc")
    _, w_a = last_weights(tmp_path / "sa")
    assert not all(torch.equal(w_off[k], w_a[k]) for k in w_a)
    # hints off: the run's key is the one from before hints existed (old checkpoints keep their names)
    assert "hints" not in AdaptConfig().run_settings() and AdaptConfig(hints=0.5).run_settings()["hints"] == 0.5
    with pytest.raises(MonoMapError, match="--hint-loss"):
        AdaptConfig(hints=1.0, hint_loss="l2").validate()


def test_the_entropy_hold_is_zero_at_the_base_and_pulls_back_a_drifted_entropy(tiny_root, tmp_path):
    """(H − H_base)² over the content pixels: 0 for the base model itself, > 0 once its weights move, a gradient
    that lowers it, and no sky pixel counted."""
    from mono_map.data.kitti import open_sequence
    from mono_map.depth.adapt import load_frames
    from mono_map.depth.adapter import Adapter, base_statistics

    model, _ = load_checkpoint(write_tiny_checkpoint(tmp_path / "t.pt", beyond=True))
    seq = open_sequence(tiny_root, "tiny")
    data = load_frames(seq, list(range(len(seq))), model.cfg.input_height, model.cfg.input_width)
    beyond, entropy = base_statistics(model, data.images, "fp32")
    assert beyond is not None and entropy.shape == beyond.shape and float(entropy.min()) >= 0
    ad = Adapter(model, beyond, data, choose_sources(data.poses[:, :3, 3], 0.3, 4.0, 10),
                 AdaptConfig(entropy_hold=1.0))
    ad.base_entropy = entropy
    model.eval()
    x = ph.to_tensor(data.images[[1, 2]])
    assert float(ad.entropy_hold_loss(ad.forward(x), [1, 2]).detach()) < 1e-8
    with torch.no_grad():                                  # a ramp on the head's bias: the entropy drifts
        head = [m for m in model.modules() if isinstance(m, torch.nn.Conv2d)][-1]
        head.bias.add_(torch.linspace(0.0, 4.0, head.bias.numel()))
    held = ad.entropy_hold_loss(ad.forward(x), [1, 2])
    assert float(held.detach()) > 1e-3
    held.backward()
    with torch.no_grad():
        for p in model.parameters():
            if p.grad is not None:
                p.sub_(0.05 * p.grad)
    assert float(ad.entropy_hold_loss(ad.forward(x), [1, 2])) < float(held)
    # every pixel sky: nothing is counted
    ad.base_beyond = torch.ones_like(beyond)
    assert float(ad.entropy_hold_loss(ad.forward(x), [1, 2])) == 0


def test_adapt_with_the_entropy_hold_keeps_the_base_entropy_and_is_named_by_it(tiny_root, tiny_ckpt, tmp_path):
    from mono_map.data.kitti import open_sequence
    from mono_map.depth.adapt import load_frames
    from mono_map.depth.adapter import base_statistics

    kw = dict(lr=2e-3, train_encoder=True)
    free = run(tiny_root, tiny_ckpt, tmp_path, 6, "sa", "oa", **kw)
    held = run(tiny_root, tiny_ckpt, tmp_path, 6, "sb", "ob", entropy_hold=1000.0, **kw)
    again = run(tiny_root, tiny_ckpt, tmp_path, 6, "sc", "oc", entropy_hold=1000.0, **kw)
    assert held.checkpoint.name == again.checkpoint.name != free.checkpoint.name
    curve = held.metadata["adapted"]["curve"]
    assert curve[-1]["entropy_hold"] >= 0 and "entropy_hold" not in free.metadata["adapted"]["curve"][-1]
    assert "entropy_hold" not in AdaptConfig().run_settings()
    assert AdaptConfig(entropy_hold=0.5).run_settings()["entropy_hold"] == 0.5
    base, _ = load_checkpoint(tiny_ckpt)
    seq = open_sequence(tiny_root, "tiny")
    data = load_frames(seq, list(range(len(seq))), base.cfg.input_height, base.cfg.input_width)
    sky, h0 = base_statistics(base, data.images, "fp32")
    counted = sky <= AdaptConfig().sky_threshold
    drift = {}
    for name, res in (("free", free), ("held", held)):
        m, _ = load_checkpoint(res.checkpoint)
        _, h = base_statistics(m, data.images, "fp32")
        drift[name] = float((h - h0).abs()[counted].mean())
    assert drift["held"] < 0.5 * drift["free"], drift
