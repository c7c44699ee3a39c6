"""Benchmark one training step of the depth networks on this CPU: architectures, fp32 vs bf16
autocast, channels_last, torch.compile, thread counts. Variants run interleaved (round-robin), so a
change in machine load hits all of them alike; each prints min/median/max seconds per step.

    python benchmarks/bench_train.py [--archs small,resnet18-half,resnet18] [--batch 4] [--crop 192x320]
                                [--variants fp32,channels_last,bf16,bf16_channels_last,compile] [--threads 1,2]
                                [--steps 8]
bf16 = torch.autocast(bfloat16) around the forward pass (the loss in fp32); on CPUs with AMX it is faster.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
import torch

from mono_map.depth.losses import head_loss
from mono_map.depth.networks import DepthNet, named_config
from mono_map.depth.train import outputs_at_targets


def make_step(arch: str, variant: str, batch: int, crop: tuple[int, int]):
    cfg = named_config(arch, head="binary")
    net = DepthNet(cfg).train()
    cl = variant in ("channels_last", "bf16_channels_last")
    bf16 = variant in ("bf16", "bf16_channels_last")
    if cl:
        net = net.to(memory_format=torch.channels_last)
    opt = torch.optim.Adam(net.parameters(), lr=1e-4)
    rng = np.random.default_rng(0)
    x = torch.rand(batch, 3, *crop)
    if cl:
        x = x.contiguous(memory_format=torch.channels_last)
    y = torch.from_numpy(np.where(rng.random((batch, *crop)) < 0.12, rng.uniform(2, 70, (batch, *crop)), 0)
                         .astype(np.float32))
    fwd = torch.compile(net) if variant == "compile" else net

    def step():
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
            out = fwd(x, upsample=False)
        o, t = outputs_at_targets(out.float(), y)
        loss = head_loss(net.head, o, t, cfg.bins, beyond=cfg.beyond)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()

    return step, sum(p.numel() for p in net.parameters())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--archs", default="small,resnet18-half,resnet18")
    ap.add_argument("--variants", default="fp32,channels_last")
    ap.add_argument("--threads", default="2")
    ap.add_argument("--batch", type=int, default=4)
    ap.add_argument("--crop", default="192x320")
    ap.add_argument("--steps", type=int, default=6)
    a = ap.parse_args()
    crop = tuple(int(v) for v in a.crop.split("x"))
    cases = {}
    for arch in a.archs.split(","):
        for var in a.variants.split(","):
            for th in (int(v) for v in a.threads.split(",")):
                torch.set_num_threads(th)
                step, n = make_step(arch, var, a.batch, crop)
                step(), step()   # warm-up (and compilation)
                cases[(arch, var, th)] = (step, n, [])
    for _ in range(a.steps):
        for (arch, var, th), (step, n, times) in cases.items():
            torch.set_num_threads(th)
            t0 = time.perf_counter()
            step()
            times.append(time.perf_counter() - t0)
    rows = []
    for (arch, var, th), (_, n, times) in cases.items():
        t = np.array(times)
        rows.append({"arch": arch, "variant": var, "threads": th, "params_M": round(n / 1e6, 2),
                     "s_per_step": [round(float(t.min()), 3), round(float(np.median(t)), 3), round(float(t.max()), 3)],
                     "steps_per_cpu_hour_at_median": round(3600 / float(np.median(t)))})
        print(json.dumps(rows[-1]), flush=True)
    print(json.dumps({"batch": a.batch, "crop": crop, "load_average": open("/proc/loadavg").read().split()[:3]}))


if __name__ == "__main__":
    main()
