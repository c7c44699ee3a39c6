"""``mono-map synth --stereo``: KITTI's right colour camera (image_3), opt-in, leaving every other file as it was."""

from __future__ import annotations

import json

import numpy as np
import pytest

from mono_map.cli import main

H, W = 376, 1241
N = 2                                   # frames of tiny rendered with --stereo


@pytest.fixture(scope="module")
def stereo_root(tmp_path_factory):
    """A KITTI root holding the first N frames of ``tiny`` rendered with --stereo (one worker: no pool start-up)."""
    root = tmp_path_factory.mktemp("kitti_stereo")
    assert main(["synth", "--seq", "tiny", "--frames", str(N), "--data-root", str(root), "--stereo",
                 "--workers", "1"]) == 0
    return root


def _rgb(path) -> np.ndarray:
    import cv2

    img = cv2.imread(str(path))
    assert img is not None, path
    return img[..., ::-1].astype(np.float32)


def test_stereo_adds_image_3_and_changes_no_other_byte(stereo_root, tiny_root):
    seq, ref = stereo_root / "sequences/tiny", tiny_root / "sequences/tiny"
    assert sorted(p.name for p in (seq / "image_3").iterdir()) == [f"{i:06d}.png" for i in range(N)]
    for sub, ext in (("image_2", "png"), ("depth_2", "png"), ("velodyne", "bin")):
        names = sorted(p.name for p in (seq / sub).iterdir())
        assert names == [f"{i:06d}.{ext}" for i in range(N)]
        for name in names:
            assert (seq / sub / name).read_bytes() == (ref / sub / name).read_bytes(), (sub, name)
    assert (seq / "calib.txt").read_bytes() == (ref / "calib.txt").read_bytes()
    img3 = _rgb(seq / "image_3/000000.png")
    assert img3.shape == (H, W, 3) and img3.std() > 10
    assert not np.array_equal(img3, _rgb(seq / "image_2/000000.png"))
    marker = json.loads((seq / "synth.json").read_text())
    assert marker["image_3"] == N and marker["n_frames"] == N
    # without --stereo: no image_3 and the marker as before (the tiny fixture renders without it)
    assert not (ref / "image_3").exists()
    assert "image_3" not in json.loads((ref / "synth.json").read_text())


def _warp_mad(img2, img3, depth, shift_sign: float, fx: float, baseline: float) -> float:
    """Mean |image_2 - image_3 sampled at u - sign·fx·b/z| over pixels with depth whose sample lies inside."""
    import cv2

    v, u = np.mgrid[0:H, 0:W].astype(np.float32)
    valid = depth > 0
    u3 = u - shift_sign * fx * baseline / np.where(valid, depth, 1.0)
    warped = cv2.remap(img3, u3.astype(np.float32), v, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                       borderValue=-1)
    ok = valid & (u3 >= 0) & (u3 <= W - 1) & (warped.min(axis=2) >= 0)
    assert ok.mean() > 0.4
    return float(np.abs(warped[ok] - img2[ok]).mean())


def test_image_3_is_the_right_camera(stereo_root):
    """Warped into image_2 by the dense depth and the P2/P3 baseline, image_3 matches image_2 far better
    than unwarped or warped the wrong way."""
    from mono_map.data.depth_png import read_depth_png
    from mono_map.data.synth.writer import read_calib

    calib = read_calib()
    K = calib["P2"][:, :3]
    assert np.allclose(calib["P3"][:, :3], K)
    t2x, t3x = (np.linalg.inv(K) @ calib["P2"][:, 3])[0], (np.linalg.inv(K) @ calib["P3"][:, 3])[0]
    baseline = t2x - t3x
    assert 0.5 < baseline < 0.6                          # cam2 +0.06 m, cam3 -0.47 m along x from cam0
    seq = stereo_root / "sequences/tiny"
    img2, img3 = _rgb(seq / "image_2/000000.png"), _rgb(seq / "image_3/000000.png")
    depth = read_depth_png(seq / "depth_2/000000.png")
    right = _warp_mad(img2, img3, depth, +1, K[0, 0], baseline)
    unwarped = _warp_mad(img2, img3, depth, 0, K[0, 0], baseline)
    wrong = _warp_mad(img2, img3, depth, -1, K[0, 0], baseline)
    print(f"image_3 warped into image_2: mean |diff| {right:.2f}, unwarped {unwarped:.2f}, wrong sign {wrong:.2f}")
    assert right < 0.5 * unwarped and right < 0.5 * wrong


def test_stereo_again_renders_only_the_missing_image_3(stereo_root, capsys):
    seq = stereo_root / "sequences/tiny"
    gone = seq / "image_3/000001.png"
    before = gone.read_bytes()
    others = {p: p.stat().st_mtime_ns for sub in ("image_2", "depth_2", "velodyne", "image_3")
              for p in (seq / sub).iterdir() if p != gone}
    gone.unlink()
    capsys.readouterr()
    assert main(["synth", "--seq", "tiny", "--frames", str(N), "--data-root", str(stereo_root), "--stereo",
                 "--workers", "1"]) == 0
    assert "the image_3 of 1 frames already there" in capsys.readouterr().err
    assert gone.read_bytes() == before
    assert {p: p.stat().st_mtime_ns for p in others} == others      # nothing else rewritten
    assert json.loads((seq / "synth.json").read_text())["image_3"] == N
    # all there: a third run renders nothing
    assert main(["synth", "--seq", "tiny", "--frames", str(N), "--data-root", str(stereo_root), "--stereo"]) == 0
    assert "rendering" not in capsys.readouterr().err
    assert gone.stat().st_mtime_ns != 0 and {p: p.stat().st_mtime_ns for p in others} == others


def test_stereo_with_the_raw_layout_is_refused_in_one_line(tmp_path, capsys):
    assert main(["synth", "--seq", "tiny", "--data-root", str(tmp_path), "--stereo", "--layout", "raw"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "--stereo" in err and "--layout raw" in err
    assert not (tmp_path / "sequences").exists()
