"""mono_map/cli/options.py (the shared options, declared once), the one model-name → checkpoint resolution
(depth/inference.py) and the map specification passed whole (MapJob → make_builder → MapBuilder)."""

import argparse
import hashlib

import pytest

from mono_map.cli import options
from mono_map.depth.inference import checkpoint_path, default_checkpoint, model_digest, resolve_checkpoint
from mono_map.errors import MonoMapError


def parser(**frames) -> argparse.ArgumentParser:
    p = argparse.ArgumentParser()
    options.add_seq(p)
    options.add_frames(p, **frames)
    options.add_data_root(p)
    options.add_model(p, oracle=True)
    options.add_out(p, default="outputs/x")
    options.add_threads(p, default=2)
    options.add_precision(p)
    options.add_octomap(p)
    return p


def test_shared_options_defaults_and_help():
    a = parser().parse_args([])
    assert (a.seq, a.frames, a.data_root, a.model, a.out, a.threads, a.precision) == \
        ("00", None, None, None, "outputs/x", 2, None)
    assert parser(default="0:20").parse_args([]).frames == "0:20"          # a script's own default
    text = parser(says="the first 500 frames").format_help()
    assert options.FRAMES_GRAMMAR.split(" ")[0] in text and "the first 500 frames" in text and "'oracle'" in text
    p = argparse.ArgumentParser()
    options.add_seq(p, required=True)
    options.add_model(p, repeat=True)
    a = p.parse_args(["--seq", "tiny", "--model", "a.pt", "--model", "v2/softmax"])
    assert a.seq == "tiny" and a.model == ["a.pt", "v2/softmax"]
    with pytest.raises(SystemExit):
        p.parse_args([])                                                   # --seq is required there


def test_octomap_options_are_checked_naming_the_option():
    cfg = options.octomap_config(parser().parse_args(["--res", "0.4", "--max-range", "30"]))
    assert cfg.resolution == 0.4 and cfg.max_range == 30.0
    assert options.octomap_config(parser().parse_args([])).max_range == -1.0
    for argv, name in ((["--max-range", "-1"], "--max-range"), (["--res", "50"], "--res")):
        with pytest.raises(MonoMapError, match=name):
            options.octomap_config(parser().parse_args(argv))
    options.check_threads(None)
    with pytest.raises(MonoMapError, match="--threads"):
        options.check_threads(0)


def test_a_model_name_becomes_a_checkpoint_in_one_place(tmp_path):
    assert resolve_checkpoint(None) == default_checkpoint("binary")
    assert resolve_checkpoint("v2/softmax") == default_checkpoint("v2/softmax")   # a bare name: shipped
    own = tmp_path / "mine.pt"
    own.write_bytes(b"not a network")
    assert resolve_checkpoint(str(own)) == own and checkpoint_path(str(own)) == own
    assert checkpoint_path("oracle") is None and model_digest("oracle") == "oracle"
    assert model_digest(str(own)) == hashlib.sha256(b"not a network").hexdigest()[:16]
    with pytest.raises(MonoMapError, match="--model: nothing-here: checkpoint not found"):
        checkpoint_path("nothing-here")


def test_the_builder_takes_the_job_whole(tiny_root):
    from mono_map.config import OctoMapConfig
    from mono_map.data.kitti import open_sequence
    from mono_map.mapping.build import make_builder
    from mono_map.mapping.jobs import MapJob
    from mono_map.mapping.oracle import NoisyGroundTruthPredictor

    seq = open_sequence(tiny_root, "tiny")
    spec = MapJob.spec("mono", range(2), keep=0.6, stride=3, octomap=OctoMapConfig(resolution=0.4))
    full = MapJob.of(seq, "mono", range(2), keep=0.6, stride=3, octomap=OctoMapConfig(resolution=0.4),
                     digest="x" * 16)
    # the same map: a spec differs from the job of the open sequence only in the data's identity
    differs = {k for k, v in spec.key().items() if full.key()[k] != v}
    assert differs == {"data_root", "sequence", "synthetic", "data", "model", "precision"}
    b = make_builder(seq, spec, NoisyGroundTruthPredictor())
    assert b.job is spec and (b.keep, b.stride, b.n_frames) == (0.6, 3, 2)
    assert b.integrator.cfg.resolution == 0.4 and b.kind.predicted and b.integration.end_points
    with pytest.raises(MonoMapError, match="--stride"):
        make_builder(seq, MapJob.spec("lidar", range(2), stride=0))
    with pytest.raises(MonoMapError, match="--keep"):
        make_builder(seq, MapJob.spec("mono", range(2), keep=1.5), NoisyGroundTruthPredictor())
