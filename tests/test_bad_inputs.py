"""The bad-input suite: bad data, options, checkpoints, outputs and processes against ``mono-map``.

Every case of the table asserts: a non-zero exit, exactly one stderr line ``mono-map: error: ...``
naming the file or option, no traceback, and no new, changed or removed file anywhere under the
test's folder (data root, output folder and everything else). The process cases (signals during
build, synth and eval; concurrent builds; a full or read-only disk) run the CLI in a subprocess;
the rest run ``mono_map.cli.main`` in-process on a hard-linked copy of the session's ``tiny``
sequence (tests/conftest.py).
"""

from __future__ import annotations

import json
import re
import os
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import cv2
import numpy as np
import pytest

from mono_map.cli import main as cli_main

REPO = Path(__file__).resolve().parents[1]
SEQ = "sequences/tiny"


# ------------------------------------------------------------------------------------------ helpers


def link_copy(src: Path, dst: Path) -> None:
    """A copy of a data root whose files are hard links (cheap); corrupting a file replaces it."""
    shutil.copytree(src, dst, copy_function=os.link)


def replace(path: Path, data: bytes | str) -> None:
    """New contents for ``path`` in a new inode (never through a hard link into the session's data)."""
    path.unlink(missing_ok=True)
    path.write_bytes(data.encode() if isinstance(data, str) else data)


def snapshot(root: Path) -> dict:
    """Every file and folder under ``root``: size, mtime and inode (a rename or rewrite shows)."""
    out = {}
    for p in sorted(root.rglob("*")):
        st = p.lstat()
        out[str(p.relative_to(root))] = None if p.is_dir() else (st.st_size, st.st_mtime_ns, st.st_ino)
    return out


def assert_one_error_line(err: str, expect: str) -> str:
    assert "Traceback" not in err, err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1, f"expected one stderr line, got:\n{err}"
    assert lines[0].startswith("mono-map: error: "), lines[0]
    assert expect in lines[0], f"{expect!r} not named in: {lines[0]}"
    return lines[0]


def temps(root: Path) -> list[Path]:
    return [p for p in root.rglob(".*") if ".tmp" in p.name]


@dataclass
class Ctx:
    tmp: Path
    data: Path
    out: Path
    good_bt: Path
    good_rrd: Path

    def fill(self, argv: list[str]) -> list[str]:
        return [a.format(tmp=self.tmp, data=self.data, out=self.out) for a in argv]

    def fill_env(self, env: dict) -> dict:
        return {k: v.format(tmp=self.tmp, data=self.data, out=self.out) for k, v in env.items()}


@pytest.fixture(scope="session")
def good_outputs(tiny_root, tmp_path_factory):
    """One good map (+ .json) and recording of tiny, built once: material for the eval/view cases."""
    d = tmp_path_factory.mktemp("good")
    assert cli_main(["build", "--seq", "tiny", "--frames", "0:2", "--res", "0.4", "--data-root", str(tiny_root),
                     "--out", str(d), "--source", "lidar-fov", "--name", "m", "--rrd", str(d / "r.rrd")]) == 0
    return d / "m.bt", d / "r.rrd"


@pytest.fixture
def ctx(tiny_root, tmp_path, good_outputs, monkeypatch):
    monkeypatch.setenv("MONO_MAP_PROGRESS", "0")
    data = tmp_path / "data"
    link_copy(tiny_root, data)
    out = tmp_path / "out"
    out.mkdir()
    bt, rrd = good_outputs
    for f in (bt, bt.with_suffix(".json"), rrd):
        shutil.copy(f, tmp_path / f.name)
    return Ctx(tmp_path, data, out, tmp_path / bt.name, tmp_path / rrd.name)


# ------------------------------------------------------------------------------------------ the table

B = ["build", "--seq", "tiny", "--frames", "0:2", "--res", "0.4", "--data-root", "{data}", "--out", "{out}",
     "--source", "lidar"]
M = ["build", "--seq", "tiny", "--frames", "0:2", "--res", "0.4", "--data-root", "{data}", "--out", "{out}",
     "--source", "mono", "--stride", "8"]
EVAL = ["eval", "--map", "{tmp}/m.bt", "--reference", "{tmp}/m.bt"]
TABLE = ["eval", "--table", "--seq", "tiny", "--data-root", "{data}", "--out", "{out}", "--frames", "0:2",
         "--res", "0.4", "--model", "oracle", "--stride", "8"]


@dataclass
class Case:
    id: str
    argv: list[str]
    expect: str                                     # what the error line must name
    setup: Callable[[Ctx], None] | None = None      # corrupts data / prepares files before the snapshot
    env: dict = field(default_factory=dict)


def poses(c: Ctx) -> Path:
    return c.data / "poses" / "tiny.txt"


def seq_file(c: Ctx, rel: str) -> Path:
    return c.data / SEQ / rel


def pose_lines(c: Ctx) -> list[str]:
    return poses(c).read_text().splitlines()


def resize_all(c: Ctx) -> None:
    for p in sorted((c.data / SEQ / "image_2").glob("*.png")):
        img = cv2.imread(str(p))
        replace(p, cv2.imencode(".png", cv2.resize(img, (620, 188)))[1].tobytes())


def resize_first(c: Ctx) -> None:
    p = seq_file(c, "image_2/000000.png")
    replace(p, cv2.imencode(".png", cv2.resize(cv2.imread(str(p)), (620, 188)))[1].tobytes())


def grayscale(c: Ctx) -> None:
    p = seq_file(c, "image_2/000003.png")
    replace(p, cv2.imencode(".png", cv2.imread(str(p), cv2.IMREAD_GRAYSCALE))[1].tobytes())


def nan_scan(c: Ctx) -> None:
    p = seq_file(c, "velodyne/000001.bin")
    scan = np.fromfile(p, np.float32)
    scan[7] = np.nan
    replace(p, scan.tobytes())


def marker(c: Ctx, text: str) -> None:
    replace(seq_file(c, "synth.json"), text)


def locked_by_pid_1(c: Ctx) -> None:
    """A partial-synthesis marker naming a live process that is not mono-map (PID 1), as an old
    marker without the process start time would."""
    import socket

    replace(seq_file(c, ".synth_partial.json"), json.dumps({"recipe": "tiny", "pid": 1, "host": socket.gethostname()}))


def write(rel: str, data: bytes | str) -> Callable[[Ctx], None]:
    def setup(c: Ctx) -> None:
        p = c.tmp / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        replace(p, data)
    return setup


def truncated_checkpoint(c: Ctx) -> None:
    replace(c.tmp / "trunc.pt", (REPO / "mono_map/checkpoints/binary.pt").read_bytes()[:100_000])


def bt_junk(c: Ctx) -> None:
    head = c.good_bt.read_bytes()[:120]  # "# Octomap OcTree binary file" ... into the header
    replace(c.good_bt, head + np.random.default_rng(0).bytes(3000))


def bt_truncated(c: Ctx) -> None:
    replace(c.good_bt, c.good_bt.read_bytes()[:2000])


def rrd_truncated(c: Ctx) -> None:
    replace(c.good_rrd, c.good_rrd.read_bytes()[: c.good_rrd.stat().st_size // 2])


# ------------------------------------------------------------------------------------------ reliability 3 helpers

_TINY_NET = dict(widths=(8, 8, 8, 8), stem_width=8, spp_width=4, decoder_widths=(8, 8, 8), num_bins=16,
                 input_height=64, input_width=192)
_PAYLOAD: dict = {}


def tiny_payload() -> dict:
    """A small, valid checkpoint payload (made once per session) to corrupt field by field."""
    import io

    import torch

    from mono_map.depth.inference import save_checkpoint
    from mono_map.depth.networks import DepthNet, named_config

    if not _PAYLOAD:
        import tempfile

        with tempfile.TemporaryDirectory() as d:
            torch.manual_seed(0)
            save_checkpoint(Path(d) / "t.pt", DepthNet(named_config("small", **_TINY_NET)), {"step": 0})
            _PAYLOAD["bytes"] = (Path(d) / "t.pt").read_bytes()
    return torch.load(io.BytesIO(_PAYLOAD["bytes"]), weights_only=True)


def checkpoint_with(config_keys: dict | None = None, **top) -> Callable[[Ctx], None]:
    """Setup: ``{tmp}/bad.pt``, the tiny checkpoint with ``config_keys`` of its model_config (None value:
    removed) and top-level entries replaced."""
    def setup(c: Ctx) -> None:
        import torch

        payload = tiny_payload()
        for k, v in (config_keys or {}).items():
            if v is None:
                payload["model_config"].pop(k)
            else:
                payload["model_config"][k] = v
        payload.update(top)
        torch.save(payload, c.tmp / "bad.pt")
    return setup


def run_config(text: str, name: str = "run.toml") -> Callable[[Ctx], None]:
    """Setup: a training config ``{tmp}/<name>`` whose work folder is under {tmp} (``{work}`` in ``text``)."""
    def setup(c: Ctx) -> None:
        replace(c.tmp / name, text.replace("{work}", str(c.tmp / "work")).replace("{tmp}", str(c.tmp)))
    return setup


# a config that trains on 2 frames of tiny for one step: a check that failed to refuse costs seconds, not a render
GOOD_RUN = 'name = "r"\n[model]\narch = "small"\n[data]\nsequences = ["tiny"]\nframes = 2\n[train]\nwork_dir = "{work}"\n'
DATA_RUN = 'name = "r"\n[model]\narch = "small"\n[train]\nwork_dir = "{work}"\n[data]\nsequences = ["tiny"]\nframes = 2\n'
TRAIN = ["train", "--config", "{tmp}/run.toml", "--data-root", "{data}", "--steps", "1"]
TINY_DATA = '[data]\nsequences = ["tiny"]\nframes = 2\n'
CKPT = M + ["--model", "{tmp}/bad.pt"]


def pose_line(c: Ctx, lineno: int, T: np.ndarray) -> None:
    lines = pose_lines(c)
    lines[lineno - 1] = " ".join(f"{v:.9e}" for v in T[:3].reshape(-1))
    replace(poses(c), "\n".join(lines) + "\n")


def reflect_pose(c: Ctx) -> None:
    T = np.array([float(v) for v in pose_lines(c)[2].split()] + [0, 0, 0, 1]).reshape(4, 4)
    T[:3, 2] *= -1  # a mirrored z axis: orthonormal, determinant -1
    pose_line(c, 3, T)


def png_bytes(c: Ctx, i: int) -> bytes:
    return seq_file(c, f"image_2/{i:06d}.png").read_bytes()


def flip_png_byte(c: Ctx) -> None:
    data = bytearray(png_bytes(c, 1))
    data[len(data) // 2] ^= 0xFF
    replace(seq_file(c, "image_2/000001.png"), bytes(data))


def folder_at(rel: str) -> Callable[[Ctx], None]:
    def setup(c: Ctx) -> None:
        (c.tmp / rel).mkdir(parents=True)
    return setup


CASES = [
    # --frames: one grammar, refused before any data is opened or rendered
    Case("frames-letters", B + ["--frames", "a:b"], "--frames"),
    Case("frames-reversed", B + ["--frames", "10:5"], "--frames"),
    Case("frames-beyond-recipe", B + ["--frames", "0:100000"], "--frames"),
    Case("frames-beyond-empty-root", B + ["--frames", "0:100000", "--data-root", "{tmp}/empty"], "--frames"),
    Case("frames-beyond-sequence-list", B + ["--frames", "1,9"], "--frames"),
    Case("frames-letters-seq-00-empty-root", B + ["--seq", "00", "--frames", "a:b", "--data-root", "{tmp}/empty"],
         "--frames"),
    Case("frames-beyond-seq-00-empty-root", B + ["--seq", "00", "--frames", "0:100000", "--data-root",
                                                 "{tmp}/empty"], "--frames"),
    Case("predict-frames-letters", ["predict", "--seq", "tiny", "--data-root", "{data}", "--frames", "a:b",
                                    "--out", "{out}/p"], "--frames"),
    Case("predict-frames-beyond", ["predict", "--seq", "tiny", "--data-root", "{data}", "--frames", "0:50",
                                   "--out", "{out}/p"], "--frames"),
    Case("eval-depth-frames", ["eval-depth", "--seq", "tiny", "--data-root", "{data}", "--frames", "5:2",
                               "--model", "binary", "--out", "{out}/d"], "--frames"),
    Case("synth-frames-zero", ["synth", "--seq", "tiny", "--data-root", "{data}", "--frames", "0"], "--frames"),
    Case("synth-frames-beyond", ["synth", "--seq", "tiny", "--data-root", "{data}", "--frames", "7"], "--frames"),
    Case("synth-workers", ["synth", "--seq", "tiny", "--data-root", "{data}", "--workers", "0"], "--workers"),
    Case("demo-frames", ["demo", "--seq", "tiny", "--data-root", "{data}", "--out", "{out}", "--frames", "x"],
         "--frames"),
    Case("table-frames", TABLE + ["--frames", "1:1"], "--frames"),
    # OctoMap and selection options
    Case("max-range-zero", B + ["--max-range", "0"], "--max-range"),
    Case("max-range-negative", B + ["--max-range", "-5"], "--max-range"),
    Case("max-range-nan", B + ["--max-range", "nan"], "--max-range"),
    Case("res-zero", B + ["--res", "0"], "--res"),
    Case("res-nan", B + ["--res", "nan"], "--res"),
    Case("res-huge", B + ["--res", "1e9"], "--res"),
    Case("res-too-fine", B + ["--res", "0.001"], "--res"),
    Case("res-out-of-memory", B + ["--res", "0.05"], "--res", env={"MONO_MAP_MEMORY_GB": "0.5"}),
    Case("prob-hit", B + ["--prob-hit", "0.3"], "--prob-hit"),
    Case("stride-not-an-integer", M + ["--stride", "abc"], "--stride"),
    Case("required-option-missing", ["build", "--data-root", "{data}"], "--seq"),
    Case("keep-zero", M + ["--keep", "0"], "--keep"),
    Case("keep-nan", M + ["--keep", "nan"], "--keep"),
    Case("stride-zero", M + ["--stride", "0"], "--stride"),
    Case("source-unknown", B + ["--source", "radar"], "--source"),
    Case("keeps-outside", TABLE + ["--keeps", "0,2"], "--keeps"),
    # outputs
    Case("name-escapes-out", B + ["--name", "../escaped"], "--name"),
    Case("name-hidden", B + ["--name", ".m"], "--name"),
    Case("rrd-is-a-directory", B + ["--rrd", "{out}"], "--rrd"),
    Case("rrd-suffix", B + ["--rrd", "{tmp}/r.txt"], "--rrd"),
    Case("rrd-folder-is-a-file", B + ["--rrd", "{tmp}/m.bt/r.rrd"], "--rrd"),
    Case("out-is-a-file", B + ["--out", "{tmp}/m.bt"], "--out"),
    Case("json-is-a-directory", EVAL + ["--json", "{out}"], "--json"),
    Case("reference-map-missing", B + ["--reference-map", "{tmp}/nope.bt", "--rrd", "{out}/r.rrd"],
         "--reference-map"),
    # data
    Case("data-root-is-a-file", B + ["--data-root", "{tmp}/m.bt"], "--data-root"),
    Case("sequence-missing", B + ["--seq", "77"], "sequences/77"),
    Case("poses-random-bytes", B, "poses/tiny.txt",
         lambda c: replace(poses(c), np.random.default_rng(1).bytes(2000))),
    Case("poses-short-line", B, "tiny.txt:2",
         lambda c: replace(poses(c), "\n".join(pose_lines(c)[:1] + ["1 0 0"] + pose_lines(c)[2:]) + "\n")),
    Case("poses-nan", B, "tiny.txt:3",
         lambda c: replace(poses(c), "\n".join(pose_lines(c)[:2] + [" ".join(["nan"] * 12)] + pose_lines(c)[3:]))),
    Case("poses-count", B, "poses/tiny.txt", lambda c: replace(poses(c), "\n".join(pose_lines(c)[:5]) + "\n")),
    Case("times-text", B, "times.txt", lambda c: replace(seq_file(c, "times.txt"), "0 0.1 x\n")),
    Case("calib-no-P2", B, "calib.txt", lambda c: replace(seq_file(c, "calib.txt"),
                                                          "\n".join(ln for ln in seq_file(c, "calib.txt").read_text()
                                                                    .splitlines() if not ln.startswith("P2")))),
    Case("calib-missing", B, "calib.txt", lambda c: seq_file(c, "calib.txt").unlink()),
    Case("velodyne-empty", B, "000000.bin", lambda c: replace(seq_file(c, "velodyne/000000.bin"), b"")),
    Case("velodyne-odd-size", B, "000000.bin", lambda c: replace(seq_file(c, "velodyne/000000.bin"), b"\0" * 20)),
    Case("velodyne-nan-mid-build", B, "000001.bin", nan_scan),
    Case("images-resized", B, "principal point", resize_all),
    Case("image-0-resized", B, "000000.png", resize_first),
    Case("image-grayscale", B, "000003.png", grayscale),
    Case("image-not-png", B, "000002.png", lambda c: replace(seq_file(c, "image_2/000002.png"), b"not a png")),
    Case("synth-json-abc", B, "synth.json", lambda c: marker(c, '{"n_frames": "abc"}')),
    Case("synth-json-list", B, "synth.json", lambda c: marker(c, "[]")),
    Case("synth-json-binary", B, "synth.json", lambda c: marker(c, "\x00\xff garbage")),
    Case("partial-marker-locked-build", B, ".synth_partial.json", locked_by_pid_1),
    Case("partial-marker-locked-synth", ["synth", "--seq", "tiny", "--data-root", "{data}"], ".synth_partial.json",
         locked_by_pid_1),
    Case("map-sidecar-truncated", EVAL, "m.json", lambda c: replace(c.good_bt.with_suffix(".json"), '{"stats": {"n')),
    Case("map-sidecar-list", EVAL, "m.json", lambda c: replace(c.good_bt.with_suffix(".json"), "[1]")),
    Case("map-sidecar-bad-frames", ["eval", "--map", "{tmp}/m.bt", "--reference", "lidar-fov", "--seq", "tiny",
                                    "--data-root", "{data}", "--out", "{out}"], "m.json",
         lambda c: replace(c.good_bt.with_suffix(".json"), json.dumps({"stats": {"frames": ["a", "b"]}}))),
    Case("map-sidecar-frames-beyond", ["eval", "--map", "{tmp}/m.bt", "--reference", "lidar-fov", "--seq", "tiny",
                                       "--data-root", "{data}", "--out", "{out}"], "m.json",
         lambda c: replace(c.good_bt.with_suffix(".json"), json.dumps({"stats": {"frames": [0, 100000]}}))),
    Case("map-header-then-junk", EVAL, "m.bt", bt_junk),
    Case("map-truncated", EVAL, "m.bt", bt_truncated),
    Case("map-not-octomap", EVAL, "m.bt", lambda c: replace(c.good_bt, "hello")),
    Case("map-missing", ["eval", "--map", "{tmp}/nope.bt", "--reference", "{tmp}/m.bt"], "--map"),
    Case("reference-missing", ["eval", "--map", "{tmp}/m.bt", "--reference", "{tmp}/nope.bt"], "--reference"),
    Case("view-random-rrd", ["view", "{tmp}/r.rrd", "--save", "{out}/v.rrd"], "r.rrd",
         lambda c: replace(c.good_rrd, np.random.default_rng(2).bytes(5000))),
    Case("view-truncated-rrd", ["view", "{tmp}/r.rrd", "--save", "{out}/v.rrd"], "r.rrd", rrd_truncated),
    Case("view-suffix", ["view", "{tmp}/m.json"], "m.json"),
    Case("view-corrupt-map", ["view", "{tmp}/m.bt", "--save", "{out}/v.rrd"], "m.bt", bt_truncated),
    Case("reference-map-corrupt", B + ["--reference-map", "{tmp}/m.bt", "--rrd", "{out}/r.rrd"], "m.bt",
         bt_truncated),
    Case("predict-folder-with-a-bad-image", ["predict", "--images", "{tmp}/imgs", "--out", "{out}/p"], "b.png",
         lambda c: (write("imgs/a.png", seq_file(c, "image_2/000000.png").read_bytes())(c),
                    write("imgs/b.png", b"junk")(c))),
    Case("predict-image-fails-to-decode", ["predict", "--images", "{tmp}/imgs", "--out", "{out}/p", "--model",
                                           "binary"], "b.png",
         lambda c: (write("imgs/a.png", seq_file(c, "image_2/000000.png").read_bytes())(c),
                    write("imgs/b.png", seq_file(c, "image_2/000001.png").read_bytes()[:3000])(c))),
    Case("predict-folder-grayscale", ["predict", "--images", "{tmp}/imgs", "--out", "{out}/p"], "g.png",
         lambda c: write("imgs/g.png", cv2.imencode(".png", np.zeros((40, 60), np.uint8))[1].tobytes())(c)),
    Case("synth-recipe-missing", ["synth", "--seq", "no_such_recipe", "--data-root", "{data}"], "no_such_recipe"),
    Case("synth-recipe-not-toml", ["synth", "--seq", "{tmp}/bad.toml", "--data-root", "{data}"], "bad.toml",
         write("bad.toml", "x = \n")),
    # checkpoints
    Case("model-missing", M + ["--model", "{tmp}/missing.pt"], "missing.pt"),
    Case("model-random-bytes", M + ["--model", "{tmp}/rand.pt"], "rand.pt",
         write("rand.pt", np.random.default_rng(3).bytes(4000))),
    Case("model-truncated", M + ["--model", "{tmp}/trunc.pt"], "trunc.pt", truncated_checkpoint),
    Case("model-text", M + ["--model", "{tmp}/text.pt"], "text.pt", write("text.pt", "not a checkpoint\n")),
    Case("table-model-truncated", TABLE + ["--model", "{tmp}/trunc.pt"], "trunc.pt", truncated_checkpoint),
    # ---- reliability 3: checkpoint metadata typed where it enters (one line naming file and key)
    Case("ckpt-num-bins-string", CKPT, "bad.pt model_config: num_bins", checkpoint_with({"num_bins": "16"})),
    Case("ckpt-num-bins-float", CKPT, "bad.pt model_config: num_bins", checkpoint_with({"num_bins": 16.5})),
    Case("ckpt-input-height-negative", CKPT, "bad.pt model_config: input_height",
         checkpoint_with({"input_height": -192})),
    Case("ckpt-input-width-not-32", CKPT, "bad.pt model_config: input_width", checkpoint_with({"input_width": 200})),
    Case("ckpt-max-below-min", CKPT, "bad.pt model_config: max_depth",
         checkpoint_with({"min_depth": 1.0, "max_depth": 0.5})),
    Case("ckpt-min-depth-nan", CKPT, "bad.pt model_config: min_depth", checkpoint_with({"min_depth": float("nan")})),
    Case("ckpt-widths-three", CKPT, "bad.pt model_config: widths", checkpoint_with({"widths": [8, 8, 8]})),
    Case("ckpt-widths-strings", CKPT, "bad.pt model_config: widths[0]", checkpoint_with({"widths": ["8"] * 4})),
    Case("ckpt-layers-zero", CKPT, "bad.pt model_config: layers[1]", checkpoint_with({"layers": [1, 0, 1, 1]})),
    Case("ckpt-unknown-key", CKPT, "bad.pt model_config: unknown key colour", checkpoint_with({"colour": 1})),
    Case("ckpt-head-unknown", CKPT, "bad.pt model_config", checkpoint_with({"head": "mystery"})),
    Case("ckpt-head-number", CKPT, "bad.pt model_config: head", checkpoint_with({"head": 3})),
    Case("ckpt-dropout-one", CKPT, "bad.pt model_config: dropout", checkpoint_with({"dropout": 1.0})),
    Case("ckpt-beyond-string", CKPT, "bad.pt model_config: beyond", checkpoint_with({"beyond": "yes"})),
    Case("ckpt-model-config-list", CKPT, "bad.pt model_config", checkpoint_with(model_config=[1])),
    Case("ckpt-training-not-a-table", CKPT, "bad.pt: training", checkpoint_with(training="step 5")),
    Case("ckpt-bins-disagree", CKPT, "bad.pt: stored bins", checkpoint_with({"num_bins": 17})),
    Case("ckpt-state-dict-number", CKPT, "bad.pt: state_dict", checkpoint_with(state_dict=5)),
    Case("ckpt-state-dict-values", CKPT, "bad.pt: state_dict", checkpoint_with(state_dict={"stem.0.weight": 1})),
    Case("ckpt-bin-centres-text", CKPT, "bad.pt: stored bin centres", checkpoint_with(bin_centres="abc")),
    Case("ckpt-bin-centres-short", CKPT, "bad.pt: stored bin centres", checkpoint_with(bin_centres=[1.0, 2.0])),
    Case("table-ckpt-num-bins-string", TABLE + ["--model", "{tmp}/bad.pt"], "bad.pt model_config: num_bins",
         checkpoint_with({"num_bins": "16"})),
    # ---- training configs: [model]/[data]/[train] typed before any work (no work folder left)
    Case("train-steps-abc", TRAIN, "run.toml [train]: steps", run_config(GOOD_RUN + 'steps = "abc"\n')),
    Case("train-batch-float", TRAIN, "run.toml [train]: batch_size", run_config(GOOD_RUN + "batch_size = 1.5\n")),
    Case("train-batch-zero", TRAIN, "run.toml [train]: batch_size", run_config(GOOD_RUN + "batch_size = 0\n")),
    Case("train-model-int", TRAIN, "run.toml: model", run_config('name = "r"\nmodel = 3\n[data]\nsequences = ["tiny"]\nframes = 2\n')),
    Case("train-lr-negative", TRAIN, "run.toml [train]: lr", run_config(GOOD_RUN + "lr = -1e-4\n")),
    Case("train-lr-nan", TRAIN, "run.toml [train]: lr", run_config(GOOD_RUN + "lr = nan\n")),
    Case("train-crop-one-value", TRAIN, "run.toml [train]: crop", run_config(GOOD_RUN + "crop = [128]\n")),
    Case("train-schedule-unknown", TRAIN, "run.toml [train]: schedule", run_config(GOOD_RUN + 'schedule = "linear"\n')),
    Case("train-augment-string", TRAIN, "run.toml [train]: augment", run_config(GOOD_RUN + 'augment = "no"\n')),
    Case("train-threads-zero", TRAIN, "run.toml [train]: threads", run_config(GOOD_RUN + "threads = 0\n")),
    Case("train-unknown-key", TRAIN, "run.toml [train]: unknown key stepz", run_config(GOOD_RUN + "stepz = 5\n")),
    Case("train-unknown-section", TRAIN, "run.toml: unknown key optimiser", run_config(GOOD_RUN + "[optimiser]\nx = 1\n")),
    Case("train-data-frames-negative", TRAIN, "run.toml [data]: frames",
         run_config(DATA_RUN.replace("frames = 2", "frames = -3"))),
    Case("train-data-sequences-numbers", TRAIN, "run.toml [data]: sequences[0]",
         run_config(DATA_RUN.replace('["tiny"]', "[5, 6]"))),
    Case("train-data-target", TRAIN, "run.toml [data]: target", run_config(DATA_RUN + 'target = "radar"\n')),
    Case("train-model-arch-unknown", TRAIN, "run.toml [model]: arch",
         run_config('name = "r"\n[model]\narch = "resnet-9000"\n[train]\nwork_dir = "{work}"\n' + TINY_DATA)),
    Case("train-model-num-bins-string", TRAIN, "run.toml [model]: num_bins",
         run_config('name = "r"\n[model]\nnum_bins = "64"\n[train]\nwork_dir = "{work}"\n' + TINY_DATA)),
    Case("train-name-escapes", TRAIN, "run.toml: name",
         run_config('name = "../up"\n[train]\nwork_dir = "{work}"\n' + TINY_DATA)),
    Case("train-data-root-is-a-file", ["train", "--config", "{tmp}/run.toml"], "run.toml [data]: root",
         run_config(DATA_RUN + 'root = "{tmp}/m.bt"\n')),
    Case("train-output-is-a-folder", TRAIN, "run.toml [train]: output",
         run_config(GOOD_RUN + 'output = "{tmp}/out"\n')),
    Case("train-work-dir-is-a-file", TRAIN, "run.toml [train]: work_dir",
         run_config('name = "r"\n[train]\nwork_dir = "{tmp}/m.bt"\n' + TINY_DATA)),
    Case("train-output-option-is-a-folder", TRAIN + ["--output", "{out}"], "--output", run_config(GOOD_RUN)),
    Case("train-toml-syntax", TRAIN, "run.toml: cannot parse", run_config(GOOD_RUN + "steps = \n")),
    Case("train-json-steps-null", ["train", "--config", "{tmp}/run.json", "--data-root", "{data}"], "run.json [train]: steps",
         run_config('{"name": "r", "train": {"steps": null, "work_dir": "{work}"}, "data": {"sequences": ["tiny"], "frames": 2}}', "run.json")),
    Case("train-json-top-list", ["train", "--config", "{tmp}/run.json"], "run.json",
         run_config("[1, 2]", "run.json")),
    # ---- environment variables: checked once before any command, naming the variable
    Case("env-precision-garbage", M, "$MONO_MAP_PRECISION", env={"MONO_MAP_PRECISION": "garbage"}),
    Case("env-memory-nan", B, "$MONO_MAP_MEMORY_GB", env={"MONO_MAP_MEMORY_GB": "nan"}),
    Case("env-memory-negative", B, "$MONO_MAP_MEMORY_GB", env={"MONO_MAP_MEMORY_GB": "-1"}),
    Case("env-memory-inf", B, "$MONO_MAP_MEMORY_GB", env={"MONO_MAP_MEMORY_GB": "inf"}),
    Case("env-memory-words", B, "$MONO_MAP_MEMORY_GB", env={"MONO_MAP_MEMORY_GB": "lots"}),
    Case("env-data-is-a-file", B[:8] + B[10:], "$MONO_MAP_DATA", env={"MONO_MAP_DATA": "{tmp}/m.bt"}),
    Case("env-recipes-is-a-file", ["synth", "--seq", "tiny", "--data-root", "{data}"], "$MONO_MAP_RECIPES",
         env={"MONO_MAP_RECIPES": "{tmp}/m.bt"}),
    Case("env-ray-threads-abc", B, "$MONO_MAP_RAY_THREADS", env={"MONO_MAP_RAY_THREADS": "abc"}),
    Case("env-ray-threads-zero", B, "$MONO_MAP_RAY_THREADS", env={"MONO_MAP_RAY_THREADS": "0"}),
    Case("env-progress-yes", B, "$MONO_MAP_PROGRESS", env={"MONO_MAP_PROGRESS": "yes"}),
    Case("env-no-c-true", B, "$MONO_MAP_NO_C", env={"MONO_MAP_NO_C": "true"}),
    Case("env-rr-flush-negative", B, "$MONO_MAP_RR_FLUSH_S", env={"MONO_MAP_RR_FLUSH_S": "-1"}),
    Case("env-trainset-is-a-file", B, "$MONO_MAP_TRAINSET", env={"MONO_MAP_TRAINSET": "{tmp}/m.bt"}),
    # ---- data that would give a silently wrong map
    Case("pose-reflection", B, "tiny.txt:3: pose rotation is a reflection", reflect_pose),
    Case("pose-beyond-the-maps-reach", B, "tiny.txt:2: frame 1's pose is", lambda c: shift_pose(c, 2, 1e6)),
    Case("table-pose-beyond-the-maps-reach", TABLE, "tiny.txt:2: frame 1's pose is", lambda c: shift_pose(c, 2, 1e6)),
    Case("scan-point-far-away", B, "velodyne/000000.bin: 10 points lie more than",
         lambda c: replace(seq_file(c, "velodyne/000000.bin"), np.array([[1e7, 0, 0, 1]] * 10, np.float32).tobytes())),
    Case("image-name-is-a-folder", B, "image_2/000001.png: a folder",
         lambda c: (seq_file(c, "image_2/000001.png").unlink(), seq_file(c, "image_2/000001.png").mkdir())),
    Case("times-going-back", B, "times.txt:3: timestamp",
         lambda c: replace(seq_file(c, "times.txt"), "0.0\n0.3\n0.1\n0.9\n1.2\n1.5\n")),
    Case("eval-sidecar-missing", ["eval", "--map", "{tmp}/m.bt", "--reference", "lidar-fov", "--seq", "tiny",
                                  "--data-root", "{data}", "--out", "{out}"], "m.json is missing",
         lambda c: c.good_bt.with_suffix(".json").unlink()),
    Case("image-truncated-mid-build", M, "000001.png: unreadable image (truncated PNG",
         lambda c: replace(seq_file(c, "image_2/000001.png"), png_bytes(c, 1)[:len(png_bytes(c, 1)) // 2])),
    Case("image-byte-flipped", M, "000001.png: unreadable image (corrupt PNG", flip_png_byte),
    Case("depth-png-truncated", ["build", "--seq", "tiny", "--frames", "0:2", "--res", "0.4", "--data-root", "{data}",
                                 "--out", "{out}", "--source", "depth-gt", "--stride", "8"], "depth_2/000001.png",
         lambda c: replace(seq_file(c, "depth_2/000001.png"), seq_file(c, "depth_2/000001.png").read_bytes()[:5000])),
    # ---- outputs: a folder in an output's place, names too long for the file system
    Case("folder-in-place-of-bt", B + ["--name", "m"], "out/m.bt: a folder is in the way", folder_at("out/m.bt")),
    Case("folder-in-place-of-json", B + ["--name", "m"], "out/m.json: a folder is in the way",
         folder_at("out/m.json")),
    Case("folder-in-place-of-rrd", B + ["--name", "m", "--rrd", "{tmp}/elsewhere/r.rrd"], "r.rrd",
         folder_at("elsewhere/r.rrd")),
    Case("name-too-long", B + ["--name", "n" * 251], "--name: 251 bytes is too long"),
    Case("view-save-is-a-folder", ["view", "{tmp}/m.bt", "--save", "{out}"], "--save"),
    Case("synth-recipe-fraction", ["synth", "--seq", "{tmp}/r.toml", "--data-root", "{data}"],
         "r.toml [buildings]: glass_fraction", write("r.toml", 'seed = 1\nframes = 2\ntrajectory = "00"\n'
                                                          '[buildings]\nglass_fraction = 5\n')),
    Case("synth-recipe-nan", ["synth", "--seq", "{tmp}/r.toml", "--data-root", "{data}"], "r.toml [light]: exposure",
         write("r.toml", 'seed = 1\nframes = 2\ntrajectory = "00"\n[light]\nexposure = nan\n')),
    Case("synth-recipe-string-number", ["synth", "--seq", "{tmp}/r.toml", "--data-root", "{data}"],
         "r.toml [street]: lane_width", write("r.toml", 'seed = 1\nframes = 2\ntrajectory = "00"\n'
                                                        '[street]\nlane_width = "3.5"\n')),
    Case("view-frame-negative", ["view", "{tmp}/m.bt", "--screenshot", "{out}/v.png", "--frame", "-4"], "--frame"),
    Case("view-screenshot-suffix", ["view", "{tmp}/m.bt", "--screenshot", "{out}/v.jpg"], "--screenshot"),
    Case("eval-depth-threads-zero", ["eval-depth", "--seq", "tiny", "--data-root", "{data}", "--frames", "0:1",
                                     "--threads", "0", "--out", "{out}/d"], "--threads"),
    Case("view-save-under-a-file", ["view", "{tmp}/m.bt", "--save", "{tmp}/m.bt/v.rrd"], "--save"),
]


@pytest.mark.parametrize("case", CASES, ids=[c.id for c in CASES])
def test_bad_input(case: Case, ctx: Ctx, capfd, monkeypatch):
    for k, v in ctx.fill_env(case.env).items():
        monkeypatch.setenv(k, v)
    if case.setup:
        case.setup(ctx)
    before = snapshot(ctx.tmp)
    capfd.readouterr()
    try:
        rc = cli_main(ctx.fill(case.argv))
    except SystemExit as exc:  # argparse's usage errors
        rc = exc.code
    captured = capfd.readouterr()
    assert rc != 0
    assert "Traceback" not in captured.out
    line = assert_one_error_line(captured.err, case.expect)
    assert ".tmp" not in line and "tmpstage" not in line  # what the user named, never a temporary
    print(line)  # shown by pytest -rP
    assert "generating it from" not in captured.err and "extending it" not in captured.err  # nothing rendered
    assert snapshot(ctx.tmp) == before


def test_the_table_is_large_enough():
    assert len(CASES) >= 150 and len({c.id for c in CASES}) == len(CASES)


# ------------------------------------------------------------------------------------------ faults needing more


def test_partial_marker_lock_is_overridden_by_force_and_ignores_a_reused_pid(ctx, capsys):
    """A partial marker that names a live process which is not its writer (recorded start time differs)
    does not lock; one that cannot tell (old marker, live PID) locks until --force."""
    import socket

    from mono_map.data.synth.generate import owner_alive, process_start

    host = socket.gethostname()
    assert owner_alive({"pid": 1, "host": host, "pid_start": "not-its-start"}) is None
    assert owner_alive({"pid": 1, "host": host, "pid_start": process_start(1)}) == 1
    assert owner_alive({"pid": 1, "host": "elsewhere"}) is None
    locked_by_pid_1(ctx)
    assert cli_main(["synth", "--seq", "tiny", "--data-root", str(ctx.data), "--force", "--workers", "1"]) == 0
    assert not seq_file(ctx, ".synth_partial.json").exists() and seq_file(ctx, "synth.json").is_file()
    assert not temps(ctx.data)


def test_error_line_starts_its_own_line_after_a_progress_bar(ctx, capsys, monkeypatch):
    monkeypatch.setenv("MONO_MAP_PROGRESS", "1")
    nan_scan(ctx)
    capsys.readouterr()
    assert cli_main(ctx.fill(B)) == 2
    err = capsys.readouterr().err
    assert "build lidar" in err  # the bar was drawn
    assert err.rstrip("\n").split("\n")[-1].startswith("mono-map: error: ") and "000001.bin" in err
    assert not any(ctx.out.iterdir())


def test_failed_build_keeps_the_previous_outputs(ctx, capsys):
    """A build that fails mid-way (frame 1 corrupt) leaves an earlier map of the same name untouched."""
    assert cli_main(ctx.fill(B + ["--name", "m", "--rrd", "{out}/m.rrd"])) == 0
    before = snapshot(ctx.tmp)
    nan_scan(ctx)
    before_data = snapshot(ctx.tmp)
    assert cli_main(ctx.fill(B + ["--name", "m", "--rrd", "{out}/m.rrd"])) == 2
    assert_one_error_line(capsys.readouterr().err, "000001.bin")
    assert snapshot(ctx.tmp) == before_data and {k for k in before if k.startswith("out")} == \
        {k for k in before_data if k.startswith("out")}


def test_eval_reference_is_built_for_the_maps_frames(ctx, capsys):
    """eval --map M --reference lidar-fov builds the reference for M's own frames (from its .json),
    never for the default 500 frames (which would render a synthetic sequence further)."""
    before = snapshot(ctx.data)
    assert cli_main(["eval", "--map", str(ctx.good_bt), "--reference", "lidar-fov", "--seq", "tiny",
                     "--data-root", str(ctx.data), "--out", str(ctx.out)]) == 0
    assert "accuracy   100.00 %" in capsys.readouterr().out  # the map is the LiDAR-FOV map of frames 0:2
    assert [p.name for p in sorted(ctx.out.glob("*.bt"))] == ["lidar-fov_res0.4_f0-2.bt"]
    assert snapshot(ctx.data) == before


def test_stale_map_is_never_reused(ctx, capsys, tmp_path):
    """A map is keyed by data root, checkpoint digest and settings (its .json's job): eval without
    --map refuses a map built from other data or by another checkpoint; eval --table rebuilds it."""
    import torch

    from mono_map.depth.inference import save_checkpoint
    from mono_map.depth.networks import DepthNet, named_config

    tiny_net = dict(widths=(8, 8, 8, 8), stem_width=8, spp_width=4, decoder_widths=(8, 8, 8),
                    num_bins=16, input_height=64, input_width=192)
    ckpt = tmp_path / "net.pt"
    torch.manual_seed(0)
    save_checkpoint(ckpt, DepthNet(named_config("small", **tiny_net)), {"step": 0})
    opts = ["--seq", "tiny", "--frames", "0:1", "--res", "0.4", "--stride", "8", "--keep", "0.8",
            "--data-root", str(ctx.data), "--out", str(ctx.out), "--model", str(ckpt)]
    assert cli_main(["build", *opts]) == 0
    assert cli_main(["eval", *opts, "--reference", str(ctx.good_bt)]) == 0
    capsys.readouterr()
    # the same name under another data root
    other = tmp_path / "other"
    link_copy(ctx.data, other)
    moved = [*opts]
    moved[moved.index(str(ctx.data))] = str(other)
    assert cli_main(["eval", *moved, "--reference", str(ctx.good_bt)]) == 2
    assert_one_error_line(capsys.readouterr().err, "stale (built with other data_root)")
    # a retrained checkpoint at the same path
    torch.manual_seed(1)
    save_checkpoint(ckpt, DepthNet(named_config("small", **tiny_net)), {"step": 1})
    assert cli_main(["eval", *opts, "--reference", str(ctx.good_bt)]) == 2
    assert_one_error_line(capsys.readouterr().err, "stale (built with other model)")
    # the table rebuilds what is stale and says so
    assert cli_main(["eval", "--table", *[o for o in opts if o not in ("--keep", "0.8")], "--keeps", "1.0"]) == 0
    assert "rebuilding" in capsys.readouterr().out


# ------------------------------------------------------------------------------------------ processes

PY = [sys.executable, "-m", "mono_map"]


def cli_env() -> dict:
    return dict(os.environ, PYTHONPATH=str(REPO), MONO_MAP_PROGRESS="0", OMP_NUM_THREADS="1")


def _default_sigint() -> None:
    # a test run started in the background (nohup, `cmd &` without job control) inherits SIGINT ignored,
    # and Python then installs no KeyboardInterrupt handler: give the child the default disposition
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def start(argv: list[str]) -> subprocess.Popen:
    return subprocess.Popen(PY + argv, cwd=REPO, env=cli_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, preexec_fn=_default_sigint)


def wait_for(proc: subprocess.Popen, stream: str, text: str, timeout: float = 120.0) -> None:
    """Read ``proc``'s stdout/stderr line by line until a line holds ``text``."""
    deadline = time.monotonic() + timeout
    pipe = getattr(proc, stream)
    while time.monotonic() < deadline:
        line = pipe.readline()
        if not line:
            raise AssertionError(f"process ended before printing {text!r}: {proc.wait()}")
        if text in line:
            return
    raise AssertionError(f"{text!r} not printed within {timeout} s")


SLOW_BUILD = ["build", "--seq", "tiny", "--frames", "0:6", "--res", "0.1", "--source", "lidar", "--name", "m"]


@pytest.mark.parametrize("sig, code, said", [(signal.SIGINT, 130, "mono-map: interrupted"),
                                             (signal.SIGTERM, 143, "mono-map: terminated"),
                                             (signal.SIGKILL, -9, None)])
def test_signal_during_build_leaves_no_outputs(ctx, sig, code, said):
    proc = start(SLOW_BUILD + ["--data-root", str(ctx.data), "--out", str(ctx.out), "--rrd", str(ctx.out / "m.rrd")])
    wait_for(proc, "stdout", "mono-map build:")   # printed once every check passed, before the first frame:
    proc.send_signal(sig)                          # no sleep, so a fast machine cannot finish the build first
    _, err = proc.communicate(timeout=300)
    assert proc.returncode == code, err
    assert "Traceback" not in err
    if said:
        assert err.strip().splitlines()[-1] == said
    assert not [p for p in ctx.out.iterdir() if not p.name.startswith(".")]  # no .bt, .json, .rrd
    if sig != signal.SIGKILL:
        assert not temps(ctx.tmp)
    # whatever a killed process left is removed by the next build into the folder
    assert cli_main(ctx.fill(B + ["--frames", "0:1"])) == 0
    assert not temps(ctx.out)


def test_signals_during_synth_then_resume(tmp_path):
    """SIGTERM while rendering: exit 143, one line, no half-written frame files and no complete-marker;
    a later synth resumes, also over a truncated partial marker."""
    root = tmp_path / "kitti"
    proc = start(["synth", "--seq", "tiny", "--data-root", str(root), "--workers", "2"])
    wait_for(proc, "stderr", "rendering")
    images = root / SEQ / "image_2"
    deadline = time.monotonic() + 120         # signal once the workers are rendering (the first frame is
    while time.monotonic() < deadline and not any(images.glob("[0-9]*.png")):   # written), not before
        time.sleep(0.02)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=300)
    assert proc.returncode == 143 and "Traceback" not in err
    assert err.strip().splitlines()[-1] == "mono-map: terminated"
    seq = root / SEQ
    assert not temps(root) and not (seq / "synth.json").exists() and (seq / ".synth_partial.json").is_file()
    replace(seq / ".synth_partial.json", '{"recipe": "ti')
    done = subprocess.run(PY + ["synth", "--seq", "tiny", "--data-root", str(root)], cwd=REPO, env=cli_env(),
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert (seq / "synth.json").is_file() and not (seq / ".synth_partial.json").exists() and not temps(root)


def test_sigint_during_eval_table_leaves_no_outputs(ctx):
    proc = start(["eval", "--table", "--seq", "tiny", "--data-root", str(ctx.data), "--out", str(ctx.out),
                  "--frames", "0:6", "--res", "0.1", "--model", "oracle", "--keeps", "1.0"])
    wait_for(proc, "stdout", "mono-map eval --table")   # before the first map is built
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=300)
    assert proc.returncode == 130 and "Traceback" not in err
    assert err.strip().splitlines()[-1] == "mono-map: interrupted"
    # maps finished before the signal stay as a cache (each published whole, .bt with its .json);
    # nothing half-written, no temporaries, and no table
    left = list(ctx.out.iterdir())
    assert not [p for p in left if p.name.startswith(".")]
    assert all(bt.with_suffix(".json").is_file() for bt in ctx.out.glob("*.bt"))
    assert len(list(ctx.out.glob("*.json"))) == len(list(ctx.out.glob("*.bt")))
    assert not list(ctx.out.glob("table_*"))


def test_res_too_fine_under_a_memory_limit_is_refused_with_the_estimate(ctx):
    """The issue's case: --res 0.01 on one LiDAR frame under a 3 GB address-space limit (ulimit -v)
    was a MemoryError; now it is refused before building, with the estimate."""
    import resource

    def limit():
        resource.setrlimit(resource.RLIMIT_AS, (3 << 30, 3 << 30))

    r = subprocess.run(PY + ctx.fill(B + ["--res", "0.01", "--frames", "0:1"]), cwd=REPO, env=cli_env(),
                       capture_output=True, text=True, timeout=120, preexec_fn=limit)
    assert r.returncode == 2
    line = assert_one_error_line(r.stderr, "--res: 0.01 m cells")
    assert "GB, more than the 3.0 GB allowed (ulimit -v)" in line
    assert not any(ctx.out.iterdir())


def test_concurrent_builds_with_one_recording(ctx):
    """Two builds writing the same map and --rrd: both finish, the published set is one build's
    whole, consistent output, the recording decodes, no temporary file is left."""
    argv = ["build", "--seq", "tiny", "--frames", "0:3", "--res", "0.4", "--source", "lidar-fov", "--name", "m",
            "--data-root", str(ctx.data), "--out", str(ctx.out), "--rrd", str(ctx.out / "m.rrd")]
    procs = [start(argv) for _ in range(2)]
    results = [p.communicate(timeout=300) for p in procs]
    for p, (_, err) in zip(procs, results):
        assert p.returncode == 0, err
    stats = json.loads((ctx.out / "m.json").read_text())["stats"]
    assert stats["bt_bytes"] == (ctx.out / "m.bt").stat().st_size
    assert not temps(ctx.out)
    assert cli_main(["view", str(ctx.out / "m.rrd"), "--save", str(ctx.tmp / "copy.rrd")]) == 0


@pytest.fixture
def mount_tmpfs(tmp_path):
    """Mount a small tmpfs (root only; skipped otherwise, saying why); unmounted afterwards."""
    mounted = []

    def mount(name: str, options: str) -> Path:
        where = tmp_path / name
        where.mkdir()
        r = subprocess.run(["mount", "-t", "tmpfs", "-o", options, "tmpfs", str(where)], capture_output=True,
                           text=True)
        if r.returncode != 0:
            pytest.skip(f"cannot mount a tmpfs here (needs root): {r.stderr.strip() or r.returncode}")
        mounted.append(where)
        return where

    yield mount
    for where in mounted:
        subprocess.run(["umount", str(where)], check=False)


def test_full_disk_leaves_nothing(ctx, capfd, mount_tmpfs):
    """The disk fills while the map is written: one line naming the map (not a temporary file),
    nothing left. A recording is refused up front on a disk that cannot hold one (rerun's file
    sink would block for good once the disk is full)."""
    full = mount_tmpfs("full", "size=24k")
    assert cli_main(ctx.fill(B + ["--out", str(full), "--name", "m"])) == 2
    line = assert_one_error_line(capfd.readouterr().err, str(full / "m.bt"))
    assert "No space left" in line and ".tmp" not in line
    assert list(full.iterdir()) == []
    assert cli_main(ctx.fill(B + ["--out", str(ctx.out), "--rrd", str(full / "r.rrd")])) == 2
    assert_one_error_line(capfd.readouterr().err, "--rrd")
    assert list(full.iterdir()) == [] and not any(ctx.out.iterdir())


def test_read_only_output_is_refused_before_work(ctx, capsys, mount_tmpfs):
    ro = mount_tmpfs("ro", "ro,size=64k")
    before = snapshot(ctx.data)
    assert cli_main(ctx.fill(B + ["--out", str(ro)])) == 2
    captured = capsys.readouterr()
    assert_one_error_line(captured.err, f"--out: {ro}: cannot write there")
    assert "mono-map build:" not in captured.out  # refused before the build started
    assert snapshot(ctx.data) == before


# ------------------------------------------------------------------------------------------ reliability 3: reuse keyed by content


MONO_ORACLE = ["--seq", "tiny", "--frames", "0:3", "--res", "0.4", "--stride", "8", "--model", "oracle"]


def shift_pose(c: Ctx, lineno: int, dx: float = 1.0) -> None:
    T = np.array([float(v) for v in pose_lines(c)[lineno - 1].split()] + [0, 0, 0, 1]).reshape(4, 4)
    T[0, 3] += dx
    pose_line(c, lineno, T)


def test_an_edited_pose_is_never_scored_with_the_old_map_or_reference(ctx, capsys):
    """The issue's case: a pose edited after a build. eval without --map refuses the stale map saying
    what changed, eval --map refuses to score the old map against the new data, and the reference is
    rebuilt ("poses changed"), never reused."""
    opts = MONO_ORACLE + ["--data-root", str(ctx.data), "--out", str(ctx.out)]
    assert cli_main(["build", *opts]) == 0
    assert cli_main(["eval", *opts]) == 0
    out = capsys.readouterr().out
    bt = Path(out.split("scoring ")[1].split()[0])
    shift_pose(ctx, 2)
    assert cli_main(["eval", *opts]) == 2
    assert_one_error_line(capsys.readouterr().err, "stale (poses changed)")
    assert cli_main(["eval", "--map", str(bt), "--seq", "tiny", "--data-root", str(ctx.data), "--out",
                     str(ctx.out)]) == 2
    assert_one_error_line(capsys.readouterr().err, "before its data changed (poses changed)")
    assert cli_main(["build", *opts]) == 0          # rebuilt from the new poses: scored against a rebuilt reference
    capsys.readouterr()
    assert cli_main(["eval", *opts]) == 0
    out = capsys.readouterr().out
    assert "rebuilding the lidar-fov reference map" in out and "poses changed" in out
    ref = Path(out.split("reference  ")[1].split()[0])
    assert json.loads(ref.with_suffix(".json").read_text())["job"]["data"]["poses"] == \
        json.loads(bt.with_suffix(".json").read_text())["job"]["data"]["poses"]


def test_the_table_never_mixes_data_states_and_rebuilds_only_what_changed(ctx, capsys):
    """eval --table after a pose edit rebuilds every map (all rows from one data state, recorded in the
    table's JSON); after an image edit only the maps that read images are rebuilt."""
    argv = ["eval", "--table", "--paper-only", "--keeps", "1.0"] + MONO_ORACLE + ["--data-root", str(ctx.data),
                                                                                  "--out", str(ctx.out)]
    assert cli_main(argv) == 0
    capsys.readouterr()
    shift_pose(ctx, 3)
    assert cli_main(argv) == 0
    out = capsys.readouterr().out
    assert out.count("poses changed") >= 3 and "reusing" not in out  # LiDAR-FOV, keep 1.0, keep 0.8
    table = json.loads(next(ctx.out.glob("table_*.json")).read_text())
    states = {json.dumps(json.loads(Path(r["bt"]).with_suffix(".json").read_text())["job"]["data"]["poses"])
              for r in table["rows"]}
    assert len(states) == 1 and json.loads(states.pop()) == table["data"]["poses"]
    img = seq_file(ctx, "image_2/000001.png")
    replace(img, cv2.imencode(".png", cv2.imread(str(img)), [cv2.IMWRITE_PNG_COMPRESSION, 1])[1].tobytes())
    assert cli_main(argv) == 0
    out = capsys.readouterr().out
    assert "images changed" in out
    assert [ln for ln in out.splitlines() if "reusing" in ln and "lidar-fov" in ln]  # LiDAR reads no image


def test_training_cache_is_keyed_by_the_frames_contents(ctx):
    """Replacing a training image (same name) makes a new training cache instead of reusing the old one."""
    from mono_map.depth.train_config import DataConfig, RunConfig
    from mono_map.depth.train_data import build_cache

    cfg = RunConfig(name="r", model={"arch": "small", **_TINY_NET},
                    data=DataConfig(root=str(ctx.data), sequences=("tiny",), frames=2, cache_dir=str(ctx.tmp / "cache")),
                    source="test")
    images, _, cache = build_cache(cfg, cfg.model_config())
    first = np.array(images)
    replace(seq_file(ctx, "image_2/000001.png"), png_bytes(ctx, 4))
    images2, _, _ = build_cache(cfg, cfg.model_config())
    assert len(list(cache.glob("*_images.npy"))) == 2          # a new cache, the old one not reused
    assert not np.array_equal(first[1], np.array(images2)[1]) and np.array_equal(first[0], np.array(images2)[0])
    images3, _, _ = build_cache(cfg, cfg.model_config())       # unchanged data: reused
    assert len(list(cache.glob("*_images.npy"))) == 2 and np.array_equal(np.array(images3), np.array(images2))


def test_fingerprint_sees_what_a_map_reads(ctx):
    from mono_map.data.fingerprint import describe_change, sequence_fingerprint
    from mono_map.data.kitti import open_sequence

    before = sequence_fingerprint(open_sequence(ctx.data, "tiny"), [0, 1])
    replace(seq_file(ctx, "velodyne/000001.bin"), seq_file(ctx, "velodyne/000001.bin").read_bytes()[:-16])
    shift_pose(ctx, 5)                                         # frame 4: not among [0, 1]
    after = sequence_fingerprint(open_sequence(ctx.data, "tiny"), [0, 1])
    assert describe_change(before, after) == "scans changed"
    os.utime(seq_file(ctx, "calib.txt"))
    replace(seq_file(ctx, "calib.txt"), seq_file(ctx, "calib.txt").read_text().replace("P2: 7", "P2: 8", 1))
    assert "calibration changed" in describe_change(after, sequence_fingerprint(open_sequence(ctx.data, "tiny"), [0, 1]))


# ------------------------------------------------------------------------------------------ reliability 3: failures never destroy


def test_a_folder_in_place_of_the_json_keeps_the_previous_map(ctx, capsys):
    """The issue's case: out/m.json made a folder, rebuild: refused naming m.json (not a temporary), the
    previous m.bt and m.rrd untouched."""
    argv = ctx.fill(B + ["--name", "m", "--rrd", "{out}/m.rrd"])
    assert cli_main(argv) == 0
    (ctx.out / "m.json").unlink()
    (ctx.out / "m.json").mkdir()
    before = snapshot(ctx.tmp)
    capsys.readouterr()
    assert cli_main(argv) == 2
    line = assert_one_error_line(capsys.readouterr().err, str(ctx.out / "m.json"))
    assert ".tmp" not in line
    assert snapshot(ctx.tmp) == before


def test_a_failed_rename_puts_the_previous_files_back(tmp_path, monkeypatch):
    """Publishing a set: the third rename fails -> the first two targets hold their previous contents
    again, the target that did not exist is not created, no temporary or backup is left."""
    import mono_map.io as mio

    a, b, c = tmp_path / "a.bt", tmp_path / "b.rrd", tmp_path / "c.json"
    a.write_text("old a")
    b.write_text("old b")
    real = os.replace

    def failing(src, dst):
        if Path(dst) == c:
            raise OSError(28, "No space left on device", str(src))
        return real(src, dst)

    monkeypatch.setattr(mio.os, "replace", failing)
    with pytest.raises(OSError):
        with mio.atomic_outputs(a, b, c) as (ta, tb, tc):
            ta.write_text("new a")
            tb.write_text("new b")
            tc.write_text("new c")
    monkeypatch.setattr(mio.os, "replace", real)
    assert a.read_text() == "old a" and b.read_text() == "old b" and not c.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.bt", "b.rrd"]


def enospc(*args, **kwargs):
    raise OSError(28, "No space left on device")


def test_full_disk_while_writing_the_map_keeps_the_previous_one(ctx, capsys, monkeypatch):
    import mono_map.mapping.octree as octree

    argv = ctx.fill(B + ["--name", "m"])
    assert cli_main(argv) == 0
    before = snapshot(ctx.tmp)
    monkeypatch.setattr(octree, "write_tree_bt", enospc)
    capsys.readouterr()
    assert cli_main(argv) == 2
    line = assert_one_error_line(capsys.readouterr().err, f"{ctx.out / 'm.bt'}: could not write it (No space left")
    assert ".tmp" not in line
    assert snapshot(ctx.tmp) == before


def tiny_checkpoint(c: Ctx) -> Path:
    tiny_payload()
    path = c.tmp / "net.pt"
    path.write_bytes(_PAYLOAD["bytes"])
    return path


def test_eval_depth_on_a_full_disk_publishes_nothing(ctx, capsys, monkeypatch):
    """The report, its JSON and both pictures are one set: a picture failing to write (full disk) leaves
    the previous set untouched and names the picture, not the staging folder."""
    import mono_map.viz.plots as plots

    argv = ["eval-depth", "--seq", "tiny", "--frames", "0:1", "--data-root", str(ctx.data), "--out", str(ctx.out),
            "--model", str(tiny_checkpoint(ctx))]
    assert cli_main(argv) == 0
    published = sorted(p.name for p in ctx.out.iterdir())
    assert {"depth_seqtiny.json", "depth_seqtiny.md", "sparsification_seqtiny.png"} <= set(published)
    before = snapshot(ctx.tmp)

    def full(results, path):
        raise OSError(28, "No space left on device", str(path))

    monkeypatch.setattr(plots, "plot_hypotheses", full)
    capsys.readouterr()
    assert cli_main(argv) == 2
    line = assert_one_error_line(capsys.readouterr().err, f"{ctx.out / 'hypotheses_seqtiny.png'}: No space left")
    assert "tmp" not in line.replace(str(ctx.tmp), "")
    assert snapshot(ctx.tmp) == before


def test_an_interrupted_table_publishes_none_of_its_files(ctx, capsys, monkeypatch):
    """A signal while the last picture (the top-down maps) is drawn: no .md, .json or picture of the
    table is published; the previous table stays whole; no staging folder is left."""
    import mono_map.viz.plots as plots

    argv = ["eval", "--table", "--paper-only", "--keeps", "1.0"] + MONO_ORACLE + ["--data-root", str(ctx.data),
                                                                                  "--out", str(ctx.out)]
    assert cli_main(argv) == 0
    tables = sorted(p.name for p in ctx.out.glob("table_*"))
    assert len(tables) == 4  # .md, .json, sweep, top-down
    before = snapshot(ctx.tmp)

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(plots, "render_topdown", interrupted)
    assert cli_main(argv) == 130
    assert snapshot(ctx.tmp) == before


def test_a_killed_builds_recording_temp_is_swept_by_the_next_run_of_any_command(ctx, monkeypatch):
    """SIGKILL while the recording is written outside --out: the next mono-map command (whatever it
    writes) removes the temporary it left."""
    monkeypatch.setenv("XDG_CACHE_HOME", str(ctx.tmp / "cache"))
    elsewhere = ctx.tmp / "elsewhere"
    proc = start(SLOW_BUILD + ["--data-root", str(ctx.data), "--out", str(ctx.out), "--rrd", str(elsewhere / "r.rrd")])
    wait_for(proc, "stdout", "mono-map build:")
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and not temps(elsewhere if elsewhere.is_dir() else ctx.out):
        time.sleep(0.02)
    proc.kill()
    proc.communicate(timeout=60)
    assert temps(elsewhere)
    assert cli_main(["view", str(ctx.good_rrd), "--save", str(ctx.tmp / "copy.rrd")]) == 0
    assert not temps(elsewhere) and not temps(ctx.out)


def test_stale_staging_folders_and_backups_of_dead_runs_are_swept(tmp_path):
    import mono_map.io as mio

    dead = subprocess.Popen(["true"])
    dead.wait()
    stage = tmp_path / f".out.{dead.pid}.abcd1234.tmpstage"
    stage.mkdir()
    (stage / "table.md").write_text("half")
    backup = tmp_path / f".m.{dead.pid}.abcd1234.tmpbak.bt"
    backup.write_text("old")
    mine = tmp_path / f".m.{os.getpid()}.abcd1234.tmp.bt"   # a live run's: kept
    mine.write_text("writing")
    with mio.staged_dir(tmp_path) as s:
        (s / "x.txt").write_text("x")
    assert sorted(p.name for p in tmp_path.iterdir()) == [mine.name, "x.txt"]


# ------------------------------------------------------------------------------------------ reliability 3: messages


def test_view_save_on_a_full_disk_is_one_line(ctx, capsys, monkeypatch):
    import mono_map.io as mio
    import mono_map.viz.rerun_cells as rs

    monkeypatch.setattr(mio, "free_bytes", lambda path: 1 << 20)
    assert cli_main(["view", str(ctx.good_bt), "--save", str(ctx.out / "v.rrd")]) == 2
    assert_one_error_line(capsys.readouterr().err, "--save")
    monkeypatch.undo()

    def flush_fails(*args, **kwargs):
        raise RuntimeError("Flush timed out - rerun sink blocked")

    monkeypatch.setattr(rs, "log_bt_map", flush_fails)
    assert cli_main(["view", str(ctx.good_bt), "--save", str(ctx.out / "v.rrd")]) == 2
    assert_one_error_line(capsys.readouterr().err, f"{ctx.out / 'v.rrd'}: rerun could not write the recording")
    assert not any(ctx.out.iterdir())


def test_build_viewer_without_a_display_is_refused_up_front(ctx, capsys, monkeypatch):
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    t0 = time.monotonic()
    assert cli_main(ctx.fill(B + ["--viewer"])) == 2
    captured = capsys.readouterr()
    assert_one_error_line(captured.err, "--viewer: no display")
    assert "mono-map build:" not in captured.out and time.monotonic() - t0 < 10
    assert not any(ctx.out.iterdir())


def test_a_legal_245_character_name_builds(ctx, capsys):
    name = "n" * 245
    assert cli_main(ctx.fill(B + ["--name", name, "--rrd", "{out}/" + name + ".rrd"])) == 0
    assert sorted(p.name for p in ctx.out.iterdir()) == sorted([f"{name}.bt", f"{name}.json", f"{name}.rrd"])


def test_an_unreadable_marker_is_not_called_malformed(ctx, capsys, monkeypatch):
    """Root reads any file whatever its mode, so the unreadable synth.json is simulated."""
    real = Path.read_text

    def read_text(self, *args, **kwargs):
        if self.name == "synth.json":
            raise PermissionError(13, "Permission denied", str(self))
        return real(self, *args, **kwargs)

    monkeypatch.setattr(Path, "read_text", read_text)
    assert cli_main(ctx.fill(B)) == 2
    line = assert_one_error_line(capsys.readouterr().err, "synth.json: cannot read")
    assert "Permission denied" in line and "malformed" not in line and "--force" not in line


def test_schema_declares_and_checks_fields():
    """The mechanism other configs use (docs/reliability.md): types, ranges, choices, sequences, names."""
    from dataclasses import dataclass, field

    from mono_map.errors import MonoMapError
    from mono_map.schema import bounded, check_fields

    @dataclass(frozen=True)
    class Cfg:
        steps: int = field(default=1, metadata=bounded(lo=1))
        rate: float = field(default=0.5, metadata=bounded(lo=0, hi=1, lo_open=True))
        mode: str = field(default="a", metadata=bounded(choices=("a", "b")))
        size: tuple = field(default=(4, 4), metadata=bounded(item=int, length=2, lo=1))
        note: str | None = None

    assert check_fields(Cfg, {"steps": 3, "rate": 1, "size": [2, 3], "note": None}, "f") == \
        {"steps": 3, "rate": 1.0, "size": (2, 3), "note": None}
    for bad, said in [({"steps": True}, "f: steps: expected an integer"), ({"steps": 0}, "f: steps: must be >= 1"),
                      ({"rate": 0}, "f: rate: must be > 0"), ({"rate": "x"}, "f: rate: expected a number"),
                      ({"mode": "c"}, "f: mode: must be one of"), ({"size": [1, 0]}, "f: size[1]: must be >= 1"),
                      ({"size": 3}, "f: size: expected a list"), ({"zz": 1}, "f: unknown key zz")]:
        with pytest.raises(MonoMapError, match=re.escape(said)):
            check_fields(Cfg, bad, "f")
