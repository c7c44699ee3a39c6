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
]


@pytest.mark.parametrize("case", CASES, ids=[c.id for c in CASES])
def test_bad_input(case: Case, ctx: Ctx, capfd, monkeypatch):
    for k, v in case.env.items():
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
    assert_one_error_line(captured.err, case.expect)
    assert "generating it from" not in captured.err and "extending it" not in captured.err  # nothing rendered
    assert snapshot(ctx.tmp) == before


def test_the_table_is_large_enough():
    assert len(CASES) >= 40 and len({c.id for c in CASES}) == len(CASES)


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
