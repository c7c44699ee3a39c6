"""Randomised training towns and the memory-mapped training cache."""

import json
import math
from dataclasses import replace

import numpy as np
import pytest

from mono_map.data.synth.randomize import (TownSpec, apply_camera, frame_jitter, randomized_appearance,
                                           randomized_recipe, training_towns, validation_town)
from mono_map.data.synth.trainset import (NO_SURFACE, TownCache, decode_depth, encode_depth, open_trainset,
                                          render_town)
from mono_map.depth.train_config import DataConfig
from mono_map.geometry import scaled_intrinsics
from mono_map.depth.train_data import TrainsetSampler, frame_target, subsample_targets

SPEC = TownSpec(name="t04_test", trajectory="04", first_pose=100, pose_stride=3, frames=3, seed=12345)


def test_randomisation_is_deterministic_from_the_seed():
    assert randomized_recipe(SPEC) == randomized_recipe(SPEC)
    assert randomized_appearance(SPEC) == randomized_appearance(SPEC)
    other = replace(SPEC, seed=SPEC.seed + 1)
    assert randomized_recipe(other).content_hash() != randomized_recipe(SPEC).content_hash()
    assert randomized_appearance(other) != randomized_appearance(SPEC)
    img = np.full((8, 8, 3), 120, np.uint8)
    a = apply_camera(img, randomized_appearance(SPEC), frame_jitter(SPEC, 2))
    b = apply_camera(img, randomized_appearance(SPEC), frame_jitter(SPEC, 2))
    assert np.array_equal(a, b)


def test_training_towns_never_use_sequence_00_nor_the_validation_stretch():
    towns = training_towns()
    assert len(towns) >= 10 and sum(t.frames for t in towns) >= 10000
    assert len({t.name for t in towns}) == len(towns) and len({t.seed for t in towns}) == len(towns)
    assert all(t.trajectory != "00" for t in towns)
    assert len({t.trajectory for t in towns}) == 10
    val = validation_town()
    for t in towns:
        if t.trajectory == val.trajectory:
            assert t.first_pose + (t.frames - 1) * t.pose_stride < val.first_pose
    for t in towns + [val]:
        randomized_recipe(t)   # validates the pose range against the trajectory length


def test_depth_codes_round_trip():
    d = np.array([[0.0, 1.5, 80.25, 250.0]], np.float32)
    code = encode_depth(d, np.array([[False, False, False, True]]))
    assert code[0, 3] == NO_SURFACE and code[0, 0] == 0
    m, none = decode_depth(code)
    assert np.allclose(m[0, :3], d[0, :3], atol=1 / 256) and none.tolist() == [[False, False, False, True]]


def test_scaled_intrinsics_keep_pixel_centres():
    K = np.array([[700.0, 0, 600.0], [0, 700.0, 180.0], [0, 0, 1]])
    K2 = scaled_intrinsics(K, 0.5, 0.5)
    # the full-resolution pixel centre u = 599.5 .. 600.5 block maps to low-res centre (600 + 0.5)·0.5 - 0.5
    assert K2[0, 2] == pytest.approx(299.75) and K2[0, 0] == 350.0


@pytest.fixture(scope="module")
def tiny_cache(tmp_path_factory):
    root = tmp_path_factory.mktemp("trainset")
    assert render_town(root, SPEC) == SPEC.frames
    return root


def test_cache_renders_resumes_and_is_deterministic(tiny_cache):
    tc = TownCache(tiny_cache / "towns" / SPEC.name)
    assert tc.done.tolist() == [1, 1, 1]
    img1, lid1 = np.array(tc.image[1]), np.array(tc.lidar[1])
    assert render_town(tiny_cache, SPEC) == 0                       # complete: nothing to do
    w = TownCache(tiny_cache / "towns" / SPEC.name, "r+")
    w.done[1] = 0                                                   # as if killed before frame 1 was flushed
    w.image[1] = 0
    w.done.flush(), w.image.flush()
    assert render_town(tiny_cache, SPEC) == 1                       # resumes only the missing frame
    tc = TownCache(tiny_cache / "towns" / SPEC.name)
    assert np.array_equal(tc.image[1], img1) and np.array_equal(tc.lidar[1], lid1)
    dense, sky = decode_depth(tc.dense[1])
    assert sky.any() and (dense[~sky] > 0).all()                   # every camera pixel: a depth or sky
    assert 0.02 < (np.asarray(tc.lidar[1]) > 0).mean() < 0.4        # sparse LiDAR returns in view


def test_cache_refuses_a_changed_town(tiny_cache):
    from mono_map.errors import MonoMapError

    with pytest.raises(MonoMapError, match="different town"):
        render_town(tiny_cache, replace(SPEC, seed=SPEC.seed + 7))


def test_sampler_targets_mark_sky_as_beyond(tiny_cache):
    tc = open_trainset(tiny_cache)[0]
    img, dense = frame_target(tc, 0, "dense")
    _, lidar = frame_target(tc, 0, "lidar", sky_stride=3)
    assert np.isinf(dense).any() and (dense != 0).all()
    sky_l = np.argwhere(np.isinf(lidar))
    assert len(sky_l) and (sky_l % 3 == 0).all()                    # sky labels only on the 3-pixel grid
    assert np.isinf(dense[np.isinf(lidar)]).all()
    s = TrainsetSampler(DataConfig(trainset=str(tiny_cache), target="dense", validation_town="", max_targets=500))
    x, y = s.batch(2, (64, 96), np.random.default_rng(0), augment=True)
    assert x.shape == (2, 3, 64, 96) and y.shape == (2, 64, 96)
    assert ((y > 0).reshape(2, -1).sum(1) <= 500).all() and 0 <= x.min() and x.max() <= 1


def test_subsample_targets_keeps_values():
    dep = np.where(np.arange(100).reshape(10, 10) % 2 == 0, 5.0, 0.0).astype(np.float32)
    dep[0, 0] = math.inf
    out = subsample_targets(dep, 20, np.random.default_rng(0))
    assert (out > 0).sum() == 20 and set(np.unique(out[out > 0])) <= {5.0, math.inf}


def test_training_validates_logs_the_curve_and_keeps_the_best(tiny_cache, tmp_path):
    from functools import partial

    from mono_map.depth.inference import load_checkpoint
    from mono_map.depth.train import train
    from mono_map.depth.train_config import RunConfig, TrainConfig
    from mono_map.eval.validation import validate

    tc = open_trainset(tiny_cache)[0]
    model = dict(arch="small", head="binary", widths=[8, 8, 8, 8], stem_width=8, spp_width=4,
                 decoder_widths=[8, 8, 8], num_bins=16, beyond=True)
    t = TrainConfig(steps=4, batch_size=2, crop=(64, 96), lr=1e-3, threads=1, checkpoint_every=2, log_every=2,
                    validate_every=2, schedule="cosine", work_dir=str(tmp_path / "w"), output=str(tmp_path / "o.pt"))
    cfg = RunConfig(name="val", model=model, train=t, source="test")
    m = cfg.model_config()
    frames = [frame_target(tc, 0, "lidar", 1)]
    images = np.stack([np.asarray(tc.image[i]) for i in range(3)])
    depths = np.stack([frame_target(tc, i, "dense")[1] for i in range(3)]).astype(np.float32)
    train(cfg, resume=False, data=(images, depths),
          validator=partial(validate, frames=frames, head=m.head, bins=m.bins, beyond=True))
    rows = [json.loads(x) for x in (tmp_path / "w" / "val" / "curve.jsonl").read_text().splitlines()]
    assert [r["step"] for r in rows] == [2, 4]
    assert all(0 < r["abs_rel"] < 10 and 0 <= r["sky_beyond_acc"] <= 1 and r["cpu_hours"] > 0 for r in rows), rows
    _, payload = load_checkpoint(tmp_path / "w" / "val" / "best.pt")
    assert payload["training"]["validation"]["abs_rel"] == min(r["abs_rel"] for r in rows)


def test_sampler_picks_up_towns_rendered_after_it_started(tiny_cache, tmp_path):
    import shutil

    root = tmp_path / "cache"
    shutil.copytree(tiny_cache, root)
    s = TrainsetSampler(DataConfig(trainset=str(root), target="dense", validation_town=""))
    n = len(s)
    shutil.copytree(root / "towns" / SPEC.name, root / "towns" / "t04_copy")   # a town that appears later
    assert s.refresh() == 2 * n and len(s.towns) == 2


def _dying_town_worker(args):
    import os

    os._exit(3)                          # as the OOM killer would end a render worker, mid-town


def test_render_trainset_renders_through_workers_and_a_dead_worker_stops_it(tiny_cache, tmp_path, monkeypatch):
    """The worker pool renders the same cache as render_town in this process; a worker that dies stops the run
    with one line (multiprocessing.Pool waited forever)."""
    import multiprocessing as mp

    from mono_map.data.synth import generate, trainset
    from mono_map.errors import MonoMapError

    logged = []
    out = trainset.render_trainset(tmp_path / "pool", [SPEC], workers=2, log=logged.append)
    assert out["frames_rendered"] == SPEC.frames and len(logged) == 1 and SPEC.name in logged[0]
    a, b = TownCache(tmp_path / "pool" / "towns" / SPEC.name), TownCache(tiny_cache / "towns" / SPEC.name)
    for name in ("image", "dense", "lidar"):
        assert np.array_equal(np.asarray(getattr(a, name)), np.asarray(getattr(b, name))), name
    fork = mp.get_context("fork")        # forked workers inherit the patched task (spawned ones would not)
    monkeypatch.setattr(generate.mp, "get_context", lambda method=None: fork)
    monkeypatch.setattr(trainset, "town_worker", _dying_town_worker)
    with pytest.raises(MonoMapError, match="render_trainset: a render worker died") as e:
        trainset.render_trainset(tmp_path / "dead", [SPEC, replace(SPEC, name="t04_test2", seed=7)], workers=2,
                                 log=logged.append)
    assert "\n" not in str(e.value)


def test_render_trainset_command_refuses_bad_input_in_one_line(tmp_path, capsys):
    """mono-map render-trainset: bad --workers, --towns or --root -> exit 2, one line naming the option, nothing
    written (the checks come before any town is built)."""
    from mono_map.cli import main
    from mono_map.data.synth.randomize import training_towns

    afile = tmp_path / "afile"
    afile.write_text("x")
    n = len(training_towns())
    for argv, word in ((["--workers", "0"], "--workers"), (["--towns", "-1"], "--towns"),
                       (["--towns", str(n + 1)], "--towns"), (["--root", str(afile)], "--root")):
        assert main(["render-trainset", "--root", str(tmp_path / "cache"), *argv]) == 2, argv
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and word in err and "Traceback" not in err, err
    assert not (tmp_path / "cache").exists()
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    r = subprocess.run([sys.executable, str(root / "tools" / "render_trainset.py"), "--workers", "0"],
                       capture_output=True, text=True, cwd=tmp_path)
    assert r.returncode == 2 and "--workers" in r.stderr and len(r.stderr.strip().splitlines()) == 1
