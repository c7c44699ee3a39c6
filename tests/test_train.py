"""Training loop: config validation, resume, distributed data parallel with 2 CPU processes."""

import socket
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.multiprocessing as mp

from mono_map.depth.inference import DepthPredictor, load_checkpoint
from mono_map.depth.train import init_distributed, train
from mono_map.depth.train_config import DataConfig, RunConfig, TrainConfig, load_run_config
from mono_map.depth.train_data import downsample_depth, sample_batch
from mono_map.errors import MonoMapError


TINY = dict(arch="small", head="binary", widths=[8, 8, 8, 8], stem_width=8, spp_width=4,
            decoder_widths=[8, 8, 8], num_bins=16, input_height=64, input_width=128)


def _data(n=4, h=64, w=128):
    rng = np.random.default_rng(0)
    images = rng.integers(0, 255, (n, h, w, 3), dtype=np.uint8)
    depths = np.where(rng.random((n, h, w)) < 0.3, rng.uniform(2, 60, (n, h, w)), 0).astype(np.float16)
    return images, depths


def _cfg(tmp_path, steps=4, **train_kw):
    train_kw = {"lr": 1e-3, **train_kw}
    t = TrainConfig(steps=steps, batch_size=2, crop=(32, 64), threads=1, checkpoint_every=2,
                    log_every=2, work_dir=str(tmp_path / "work"), output=str(tmp_path / "out.pt"), **train_kw)
    return RunConfig(name="tiny", model=dict(TINY), data=DataConfig(), train=t, source="test")


def test_shipped_configs_parse_and_exclude_sequence_00():
    root = Path(__file__).resolve().parents[1] / "mono_map" / "depth" / "configs"
    files = sorted(root.rglob("*.toml"))
    assert {"binary.toml", "softmax.toml", "gaussian.toml"} <= {f.name for f in files}
    for f in files:
        cfg = load_run_config(f)
        assert "00" not in cfg.data.sequences
        assert cfg.model_config().head == cfg.model["head"]


def test_config_refuses_sequence_00_and_unknown_keys(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text('[model]\nhead = "binary"\n[data]\nsequences = ["05", "00"]\n')
    with pytest.raises(MonoMapError, match="held-out"):
        load_run_config(bad)
    bad.write_text('[train]\nstepz = 3\n')
    with pytest.raises(MonoMapError, match="stepz"):
        load_run_config(bad)
    bad.write_text('[model]\nhead = "nope"\n')
    with pytest.raises(MonoMapError, match="nope"):
        load_run_config(bad)


def test_sparse_downsample_keeps_nearest_point():
    d = np.zeros((4, 4), np.float32)
    d[0, 0], d[0, 1], d[3, 3] = 10.0, 7.0, 5.0
    out = downsample_depth(d, 2, 2)
    assert out[0, 0] == 7.0 and out[1, 1] == 5.0 and out[0, 1] == 0.0 and out[1, 0] == 0.0


def test_outputs_at_targets_equals_upsampling():
    from mono_map.depth.train import outputs_at_targets

    torch.manual_seed(0)
    low = torch.randn(2, 5, 8, 26)
    depth = torch.zeros(2, 32, 104)
    depth[0, 3, 7], depth[0, 31, 103], depth[1, 0, 0], depth[1, 17, 50] = 5.0, 6.0, 7.0, 8.0
    out, tgt = outputs_at_targets(low, depth)
    up = torch.nn.functional.interpolate(low, size=(32, 104), mode="bilinear", align_corners=False)
    expect = torch.stack([up[0, :, 3, 7], up[0, :, 31, 103], up[1, :, 0, 0], up[1, :, 17, 50]], -1)
    torch.testing.assert_close(out[0, :, 0], expect, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(tgt[0, 0], torch.tensor([5.0, 6.0, 7.0, 8.0]))


def test_batches_are_seeded_and_augmented_in_range():
    images, depths = _data()
    a = sample_batch(images, depths, 3, (32, 64), np.random.default_rng([0, 0, 5]), True)
    b = sample_batch(images, depths, 3, (32, 64), np.random.default_rng([0, 0, 5]), True)
    np.testing.assert_array_equal(a[0], b[0])
    assert a[0].shape == (3, 3, 32, 64) and a[0].min() >= 0 and a[0].max() <= 1


def test_train_checkpoint_and_resume(tmp_path):
    images, depths = _data()
    meta = train(_cfg(tmp_path, steps=4), resume=False, data=(images, depths), log=lambda m: None)
    assert meta["step"] == 4 and Path(meta["output"]).is_file()
    _, payload = load_checkpoint(tmp_path / "work" / "tiny" / "last.pt")
    assert payload["training"]["step"] == 4 and "optimizer" in payload
    logs = []
    meta = train(_cfg(tmp_path, steps=6), resume=True, data=(images, depths), log=logs.append)
    assert any("resuming" in m and "step 4" in m for m in logs)
    assert meta["step"] == 6
    pred = DepthPredictor.load(tmp_path / "out.pt")
    p = pred.predict(np.zeros((50, 100, 3), np.uint8))
    assert p.depth.shape == (50, 100) and p.entropy.shape == (50, 100)


def test_keep_checkpoints_keeps_every_checkpoint_step(tmp_path):
    images, depths = _data()
    train(_cfg(tmp_path, steps=4, keep_checkpoints=True, photometric="camera", scale=(1.0, 1.2)), resume=False,
          data=(images, depths), log=lambda m: None)
    kept = sorted(p.name for p in (tmp_path / "work" / "tiny").glob("step*.pt"))
    assert kept == ["step2.pt", "step4.pt"]
    _, payload = load_checkpoint(tmp_path / "work" / "tiny" / "step2.pt")
    assert payload["training"]["step"] == 2 and "optimizer" not in payload
    assert payload["training"]["train"]["photometric"] == "camera"


def test_a_run_can_start_from_another_checkpoints_weights(tmp_path):
    """train.init: the run starts from the checkpoint's weights (not a fresh draw) with step 0; another
    network or a missing file is refused, naming train.init, before any step."""
    from mono_map.depth.inference import save_checkpoint
    from mono_map.depth.networks import DepthNet, named_config

    def net(**over):
        m = {**TINY, **over}
        return DepthNet(named_config(m.pop("arch"), **m))

    def weights(path):   # the parameters (batch-norm running statistics move with any step)
        return torch.cat([v.detach().float().ravel() for v in load_checkpoint(path)[0].parameters()])

    images, depths = _data()
    torch.manual_seed(7)
    save_checkpoint(tmp_path / "src.pt", net(), {"step": 123})
    logs = []
    meta = train(_cfg(tmp_path / "a", steps=1, lr=1e-12, init=str(tmp_path / "src.pt")), resume=False,
                 data=(images, depths), log=logs.append)
    assert meta["step"] == 1 and any("starting from the weights" in m for m in logs)
    src = weights(tmp_path / "src.pt")
    assert torch.allclose(weights(tmp_path / "a" / "out.pt"), src, atol=1e-6)
    train(_cfg(tmp_path / "b", steps=1, lr=1e-12), resume=False, data=(images, depths), log=lambda m: None)
    assert not torch.allclose(weights(tmp_path / "b" / "out.pt"), src, atol=1e-3)     # without init: a fresh draw
    with pytest.raises(MonoMapError, match="train.init: .*not found"):
        train(_cfg(tmp_path / "c", steps=1, init=str(tmp_path / "nope.pt")), resume=False, data=(images, depths),
              log=lambda m: None)
    save_checkpoint(tmp_path / "k32.pt", net(num_bins=32), {"step": 1})
    with pytest.raises(MonoMapError, match="train.init: .*another network.*num_bins"):
        train(_cfg(tmp_path / "d", steps=1, init=str(tmp_path / "k32.pt")), resume=False, data=(images, depths),
              log=lambda m: None)
    assert not (tmp_path / "d" / "out.pt").exists()


def _ddp_worker(rank, world, port, tmp, q):
    import os

    os.environ["MASTER_ADDR"], os.environ["MASTER_PORT"] = "127.0.0.1", str(port)
    init_distributed(rank, world, "gloo")
    images, depths = _data()
    cfg = _cfg(Path(tmp), steps=3)
    meta = train(cfg, resume=False, rank=rank, world=world, device="cpu", data=(images, depths), log=lambda m: None)
    # ranks draw different batches; DDP averages gradients, so the replicas stay identical
    q.put((rank, meta["param_checksum"]))
    torch.distributed.destroy_process_group()


def test_ddp_two_cpu_processes(tmp_path):
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    ctx = mp.get_context("spawn")
    q = ctx.SimpleQueue()
    mp.start_processes(_ddp_worker, args=(2, port, str(tmp_path), q), nprocs=2, join=True, start_method="spawn")
    results = dict(q.get() for _ in range(2))
    assert set(results) == {0, 1}
    assert (tmp_path / "out.pt").is_file()
    assert np.isfinite(results[0])
    assert results[0] == pytest.approx(results[1], rel=1e-9, abs=1e-9)


def test_bf16_autocast_and_channels_last_train(tmp_path):
    cfg = _cfg(tmp_path, steps=3, bf16=True, channels_last=True, schedule="cosine")
    meta = train(cfg, resume=False, data=_data())
    assert meta["step"] == 3 and np.isfinite(meta["final_loss"])
    model, _ = load_checkpoint(tmp_path / "out.pt")
    assert all(p.dtype == torch.float32 for p in model.parameters())   # weights stay fp32


def test_command_line_overrides(tmp_path):
    """`mono-map train --steps/--output/--precision/--threads`: None keeps the config, a value replaces it,
    a bad value is refused naming the option."""
    from mono_map.depth.train_config import override

    cfg = _cfg(tmp_path, steps=4, bf16=True)
    assert override(cfg) == cfg
    o = override(cfg, steps=9, output="x.pt", precision="fp32", threads=2, data_root="d")
    assert (o.train.steps, o.train.output, o.train.bf16, o.train.threads, o.data.root) == (9, "x.pt", False, 2, "d")
    assert o.train.lr == cfg.train.lr and o.model == cfg.model
    assert override(_cfg(tmp_path, bf16=False), precision="bf16").train.bf16 is True
    for kw, opt in ((dict(threads=0), "--threads"), (dict(steps=0), "--steps"), (dict(precision="fp16"), "--precision")):
        with pytest.raises(MonoMapError, match=opt):
            override(cfg, **kw)
