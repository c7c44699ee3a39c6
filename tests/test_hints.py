"""Depth Hints (depth/hints.py): the plane sweep's best depth, metric through the poses, and the mask where it
beats the prediction."""

from __future__ import annotations

import numpy as np
import torch

from mono_map.depth.adapt import AdaptConfig, load_frames
from mono_map.depth.adapter import Adapter, downsample_images
from mono_map.depth.bins import DepthBins
from mono_map.depth.hints import compute_hints, hint_mask
from mono_map.depth.multiview import parabola_peak
from mono_map.depth.sources import choose_sources
from mono_map.geometry import scaled_intrinsics
from tiny_net import write_tiny_checkpoint

BINS = DepthBins()
H, W = 64, 160
K = np.array([[120.0, 0.0, 80.0], [0.0, 120.0, 32.0], [0.0, 0.0, 1.0]])
WALL = 10.0


def wall_images(n=5, step=0.5):
    """A camera sliding sideways ``step`` m a frame in front of a textured fronto-parallel wall at z = WALL:
    images (n,H,W,3) uint8 and poses T_world_cam (n,4,4)."""
    rng = np.random.default_rng(3)
    waves = [(rng.uniform(2, 12), rng.uniform(2, 12), rng.uniform(0, 6.3)) for _ in range(12)]
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)
    images, poses = [], []
    for i in range(n):
        x = step * i + (u - K[0, 2]) / K[0, 0] * WALL
        y = (v - K[1, 2]) / K[1, 1] * WALL
        t = 0.5 + 0.5 * sum(np.sin(fx * x + ph) * np.cos(fy * y + 2 * ph) for fx, fy, ph in waves) / 12 * 3
        images.append((np.repeat(np.clip(t, 0, 1)[..., None], 3, -1) * 255).round().astype(np.uint8))
        T = np.eye(4)
        T[0, 3] = step * i
        poses.append(T)
    return np.stack(images), np.stack(poses)


def test_parabola_peak_refines_between_planes():
    k = torch.arange(BINS.num_bins, dtype=torch.float32).view(-1, 1, 1)
    peak = torch.tensor([[20.3, 40.0, 0.0, 63.0]]).view(1, 1, 4)
    loglik = -(k - peak) ** 2
    got = parabola_peak(loglik, BINS.log_centres)[0].numpy()
    lc, step = BINS.log_centres, BINS.log_width
    assert abs(got[0] - (lc[20] + 0.3 * step)) < 1e-4       # a parabola's vertex between planes
    assert abs(got[1] - lc[40]) < 1e-5                      # on a plane
    assert got[2] == np.float32(lc[0]) and got[3] == np.float32(lc[-1])   # first/last plane: not refined
    flat = parabola_peak(torch.zeros(BINS.num_bins, 2, 2), BINS.log_centres)
    assert torch.all(flat == float(np.float32(lc[0])))      # a flat curve: the first plane, no refinement


def wall_hints(pose_scale=1.0, min_contrast=0.0):
    images, poses = wall_images()
    poses = poses.copy()
    poses[:, :3, 3] *= pose_scale
    sources = choose_sources(poses[:, :3, 3], 0.3, 4.0 * pose_scale, 10)
    return compute_hints(images, K, poses, sources, BINS, min_contrast=min_contrast), sources


def test_hints_on_a_textured_wall_lie_at_its_depth_and_are_metric():
    hints, sources = wall_hints()
    inner = (slice(None), slice(None), slice(8, H - 8), slice(30, W - 30))
    d = hints.depth[inner]
    assert sorted(sources) == [0, 1, 2, 3, 4] and (d > 0).float().mean() > 0.9
    err = (d[d > 0].log() - np.log(WALL)).abs()
    assert (err < BINS.log_width).float().mean() > 0.9      # within one bin at 9 pixels in 10
    assert float(err.median()) < 0.25 * BINS.log_width      # the refinement lands between the planes
    assert torch.isfinite(hints.error[inner][d > 0]).all() and (hints.error[inner][d > 0] < 0.1).float().mean() > 0.9
    # the poses carry the scale: translations ×2, hints ×2
    double, _ = wall_hints(pose_scale=2.0)
    d2 = double.depth[inner]
    both = (d > 0) & (d2 > 0)
    assert abs(float((d2[both] / d[both]).median()) - 2.0) < 0.1
    # a contrast floor keeps the distinct minima (the textured wall) and drops all above the planes' spread
    kept, _ = wall_hints(min_contrast=0.02)
    assert torch.equal(kept.depth[kept.depth > 0], hints.depth[kept.depth > 0])
    assert 0.5 < float((kept.depth[inner] > 0).float().mean()) <= float((d > 0).float().mean())
    none, _ = wall_hints(min_contrast=10.0)
    assert not (none.depth > 0).any() and torch.isinf(none.error).all()


def test_hints_on_tiny_are_near_the_truth_at_textured_pixels(tiny_root):
    import cv2

    from mono_map.data.kitti import open_sequence

    seq = open_sequence(tiny_root, "tiny")
    data = load_frames(seq, list(range(len(seq))), 192, 640)
    small = downsample_images(data.images, 2)
    sources = choose_sources(data.poses[:, :3, 3], 0.3, 4.0, 10)
    hints = compute_hints(small, scaled_intrinsics(data.K, 0.5, 0.5), data.poses, sources, BINS)
    fh, fw = data.content[0] // 2, data.content[1] // 2
    errs, wrong = [], []
    for t in sources:
        gt = cv2.resize(seq.depth(t), (fw, fh), interpolation=cv2.INTER_NEAREST)
        grey = small[t, :fh, :fw].astype(np.float32).mean(-1)
        textured = np.abs(cv2.Laplacian(grey, cv2.CV_32F, ksize=3)) > 30
        h = hints.depth[t, 0, :fh, :fw].numpy()
        other = np.roll(gt, fh // 2, 0)                     # the truth of other pixels
        m = textured & (gt > 1) & (gt < 30) & (h > 0) & (other > 1)
        errs.append(np.abs(np.log(h[m] / gt[m])))
        wrong.append(np.abs(np.log(h[m] / other[m])))
    err = np.concatenate(errs)
    assert len(err) > 1000 and np.median(err) < 0.15 and np.mean(err < np.log(1.25)) > 0.55
    assert np.median(err) < 0.5 * np.median(np.concatenate(wrong))


def test_the_mask_keeps_a_pixel_only_where_the_hint_explains_the_image_better(tiny_root, tmp_path):
    hd = torch.tensor([[[[5.0, 5.0, 0.0, 5.0]]]])
    he = torch.tensor([[[[0.1, 0.3, 0.0, float("inf")]]]])
    pe = torch.tensor([[[[0.2, 0.2, 0.5, 0.5]]]])
    assert hint_mask(hd, he, pe).flatten().tolist() == [True, False, False, False]
    # in the adapter: hints whose error is 0 on the left half and inf on the right supervise the left half only
    from mono_map.data.kitti import open_sequence
    from mono_map.depth.inference import load_checkpoint

    model, _ = load_checkpoint(write_tiny_checkpoint(tmp_path / "t.pt", beyond=True))
    seq = open_sequence(tiny_root, "tiny")
    data = load_frames(seq, list(range(len(seq))), model.cfg.input_height, model.cfg.input_width)
    sources = choose_sources(data.poses[:, :3, 3], 0.3, 4.0, 10)
    ad = Adapter(model, None, data, sources, AdaptConfig(hints=1.0))
    N, _, h, w = (len(data.images), 1) + ad.small.shape[1:3]
    error = torch.zeros(N, 1, h, w)
    error[..., w // 2:] = float("inf")
    ad.hints = type("Hints", (), {"depth": torch.full((N, 1, h, w), 7.0), "error": error})()
    _, _, _, info = ad.photometric_loss([1, 2])
    _, _, _, _, mask, _ = ad.batch([1, 2])
    left = mask.clone()
    left[..., w // 2:] = False
    assert abs(info["hinted"] - float(left.sum()) / float(mask.sum())) < 1e-6
    info["hint_loss"].backward()
    assert float(info["hint_loss"].detach()) > 0
    ad.hints.error[:] = float("inf")                    # the hint never wins: nothing is supervised
    _, _, _, info = ad.photometric_loss([1, 2])
    assert info["hinted"] == 0 and float(info["hint_loss"].detach()) == 0


def test_the_hint_quality_tool_measures_hints_against_lidar(tiny_root, tmp_path, capsys):
    import json

    from tool_loader import load_tool

    tool = load_tool("hint_quality")
    ckpt = write_tiny_checkpoint(tmp_path / "t.pt", beyond=True)
    base = ["--seq", "tiny", "--data-root", str(tiny_root), "--model", str(ckpt), "--out", str(tmp_path / "o")]
    assert tool.main(base + ["--every", "2", "--contrast", "0", "--contrast", "1"]) == 0
    rows = json.loads((tmp_path / "o" / "hint_quality_tiny.json").read_text())["rows"]
    assert [r["contrast"] for r in rows] == [0, 1] and rows[0]["frames"] == 3
    assert 0.3 < rows[0]["hinted_share"] <= 1 and 0 <= rows[0]["kept_share"] <= rows[0]["hinted_share"]
    assert rows[0]["hint_median_are"] < 0.5 and 0 <= rows[0]["kept_hint_closer"] <= 1
    assert rows[1]["hinted_share"] < rows[0]["hinted_share"]          # a floor leaves fewer hints
    capsys.readouterr()
    assert tool.main(base + ["--every", "0"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--every" in err[0]
