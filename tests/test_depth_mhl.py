"""MHL baseline (relaxed winner-takes-all over M hypotheses) and the bin-count ablation's plumbing."""

import numpy as np
import torch

from mono_map.depth.bins import DepthBins
from mono_map.depth.distribution import top_bins, top_modes
from mono_map.depth.heads import decode, get_head
from mono_map.depth.inference import DepthPredictor, load_checkpoint, save_checkpoint
from mono_map.depth.losses import head_loss, relaxed_wta
from mono_map.depth.networks import DepthNet, named_config
from mono_map.eval.hypotheses import oracle_errors

BINS = DepthBins(16, 1.0, 80.0)
TINY = dict(widths=(8, 8, 8, 8), stem_width=8, spp_width=4, decoder_widths=(8, 8, 8), input_height=64,
            input_width=128)


def test_relaxed_wta_with_zero_epsilon_trains_only_the_best_hypothesis():
    out = torch.tensor([[[[0.0]], [[1.0]], [[3.0]]]], requires_grad=True)     # (1, M=3, 1, 1) log-depth offsets
    target = torch.exp(torch.tensor(head_log_mid() + 0.9)).view(1, 1, 1)        # closest to hypothesis 1
    head_loss(get_head("mhl"), out, target, BINS, wta_epsilon=0.0).backward()
    g = out.grad.view(-1)
    assert g[1] != 0 and g[0] == 0 and g[2] == 0
    out.grad = None
    head_loss(get_head("mhl"), out, target, BINS, wta_epsilon=0.1).backward()
    assert (out.grad.view(-1) != 0).all()
    sq = torch.tensor([[[[4.0]], [[1.0]], [[9.0]]]])
    assert abs(float(relaxed_wta(sq, 0.1)) - (0.9 * 1.0 + 0.1 / 2 * 13.0)) < 1e-6


def head_log_mid():
    from mono_map.depth.heads import log_mid

    return log_mid(BINS)


def test_mhl_loss_decreases_on_a_single_image():
    torch.manual_seed(0)
    cfg = named_config("small", head="mhl", num_bins=16, hypotheses=3, **TINY)
    net = DepthNet(cfg).train()
    x = torch.rand(1, 3, 64, 128)
    y = torch.where(torch.rand(1, 64, 128) < 0.3, torch.rand(1, 64, 128) * 40 + 2, torch.zeros(1, 64, 128))
    opt = torch.optim.Adam(net.parameters(), lr=3e-3)
    losses = []
    for _ in range(40):
        loss = head_loss(net.head, net(x), y, cfg.bins, wta_epsilon=cfg.wta_epsilon)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert np.mean(losses[-5:]) < 0.5 * np.mean(losses[:5])


def test_mhl_hypotheses_come_in_the_format_of_binary_modes():
    out = torch.randn(2, 5, 4, 6)
    r = decode("mhl", out, BINS)
    probs = torch.softmax(torch.randn(2, BINS.num_bins, 4, 6), 1)
    modes, _ = top_modes(probs, BINS, 5)
    assert r["modes"].shape == modes.shape == (2, 5, 4, 6)
    assert (r["modes"] >= BINS.min_depth).all() and (r["modes"] <= BINS.max_depth).all()
    gt = np.full(24, 10.0)
    e = oracle_errors(gt, r["modes"][0].reshape(5, -1).numpy(), (1, 3, 5))
    assert e[5]["abs_rel"] <= e[3]["abs_rel"] <= e[1]["abs_rel"]       # more hypotheses never hurt the oracle


def test_a_32_bin_model_saves_loads_and_predicts_through_the_same_code(tmp_path):
    cfg = named_config("small", head="binary", num_bins=32, beyond=True, **TINY)
    net = DepthNet(cfg).eval()
    save_checkpoint(tmp_path / "k32.pt", net)
    model, payload = load_checkpoint(tmp_path / "k32.pt")
    assert model.cfg.num_bins == 32 and payload["bins"]["num_bins"] == 32
    p = DepthPredictor.load(tmp_path / "k32.pt").predict(np.zeros((60, 120, 3), np.uint8), with_probs=True)
    assert p.probs.shape == (32, 60, 120) and p.depth.shape == (60, 120) and p.p_beyond.shape == (60, 120)


def test_bf16_inference_agrees_with_fp32(tmp_path):
    torch.manual_seed(0)
    cfg = named_config("small", head="binary", num_bins=16, beyond=True, **TINY)
    net = DepthNet(cfg).eval()
    img = (np.random.default_rng(0).random((60, 120, 3)) * 255).astype(np.uint8)
    a = DepthPredictor(net).predict(img)
    net2 = DepthNet(cfg).eval()
    net2.load_state_dict(net.state_dict())
    b = DepthPredictor(net2, precision="bf16").predict(img)
    assert np.abs(np.log(a.depth / b.depth)).max() < 0.05 and np.abs(a.entropy - b.entropy).max() < 0.05
    import pytest

    from mono_map.errors import MonoMapError

    with pytest.raises(MonoMapError, match="precision"):
        DepthPredictor(net, precision="fp16")


def _evaluate(head: str, tmp_path, **kw):
    from mono_map.eval.depth_evaluation import evaluate_model

    torch.manual_seed(0)
    net = DepthNet(named_config("small", head=head, num_bins=16, beyond=True, **TINY, **kw)).eval()
    rng = np.random.default_rng(1)
    frames = [(f"f{i}", (rng.random((60, 120, 3)) * 255).astype(np.uint8), rng.uniform(2, 60, (60, 120)))
              for i in range(2)]
    return evaluate_model(DepthPredictor(net), frames, time_frames=1)


def test_heads_without_uncertainty_say_so_and_mhl_counts_as_one_point_per_m(tmp_path):
    """Regression and single-hypothesis heads rank nothing: their AUC cells read "no uncertainty" (not the
    AUC of an arbitrary order); MHL-M is reported from its own M on and drawn as one line through the MHL
    models in the Fig. 6 plot."""
    from mono_map.eval.depth_evaluation import markdown_report
    from mono_map.viz.plots import plot_hypotheses, plot_sparsification

    res = {"binary": _evaluate("binary", tmp_path), "l2": _evaluate("l2", tmp_path),
           "mhl-1": _evaluate("mhl", tmp_path, hypotheses=1), "mhl-3": _evaluate("mhl", tmp_path, hypotheses=3)}
    assert [res[h]["has_uncertainty"] for h in res] == [True, False, False, True]
    assert [res[h]["has_distribution"] for h in res] == [True, False, False, False]
    assert [res[h]["n_hypotheses"] for h in res] == [None, None, 1, 3]
    md = markdown_report(res, "t")

    def rows(section: str) -> dict[str, list[str]]:
        body = md.split(section, 1)[1].split("\n## ", 1)[0]
        cells = ([c.strip() for c in line.strip().strip("|").split("|")] for line in body.splitlines()
                 if line.startswith("| "))
        return {c[0]: c[1:] for c in cells if c[0] in res}

    auc = rows("## Uncertainty")
    assert auc["l2"][:3] == auc["mhl-1"][:3] == ["no uncertainty"] * 3
    assert auc["l2"][9:] == auc["mhl-1"][9:] == ["no uncertainty"] * 3    # std-log ranks nothing either
    assert all("no uncertainty" not in auc[h] for h in ("binary", "mhl-3")) and auc["mhl-3"][9:] == ["no distribution"] * 3
    hyp = rows("## Oracle multi-hypothesis")
    assert hyp["mhl-3"][:3] == ["–"] * 3 and "–" not in hyp["mhl-3"][3:] and "–" not in hyp["binary"]
    plot_hypotheses(res, tmp_path / "h.png")
    plot_sparsification(res, tmp_path / "s.png")
    assert (tmp_path / "h.png").stat().st_size > 0 and (tmp_path / "s.png").stat().st_size > 0


def test_top_bins_are_the_papers_hypotheses_and_differ_from_modes():
    """Table III's protocol reports the M highest-scoring bins: a broad peak gives its neighbouring bins, where
    the modes give the peak and then the separate, smaller peak."""
    p = torch.zeros(1, 16, 1, 1)
    p[0, [4, 5, 6, 12], 0, 0] = torch.tensor([0.25, 0.35, 0.24, 0.16])
    c = torch.as_tensor(BINS.centres, dtype=torch.float32)
    d_bins, p_bins = top_bins(p, BINS, 3)
    d_modes, _ = top_modes(p, BINS, 2)
    assert torch.equal(d_bins[0, :, 0, 0], c[[5, 4, 6]]) and torch.allclose(p_bins[0, :, 0, 0], p[0, [5, 4, 6], 0, 0])
    assert torch.equal(d_modes[0, :, 0, 0], c[[5, 12]])


def test_eval_reports_top_bins_and_modes_and_mhl_gives_the_same_m_in_both(tmp_path):
    b, h = _evaluate("binary", tmp_path), _evaluate("mhl", tmp_path, hypotheses=3)
    assert set(b["hypotheses"]) == set(b["hypotheses_modes"]) == {"1", "3", "5", "10"}
    assert b["hypotheses"]["1"] == b["hypotheses_modes"]["1"]           # both start at the most probable bin
    assert b["hypotheses"]["10"]["abs_rel"] <= b["hypotheses"]["3"]["abs_rel"] <= b["hypotheses"]["1"]["abs_rel"]
    assert h["hypotheses"] == h["hypotheses_modes"]
