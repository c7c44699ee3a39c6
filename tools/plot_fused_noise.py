#!/usr/bin/env python3
"""Occupied F1 of the maps against the depth error they are fed (docs/fused.md, "How good the depth must be").

    PYTHONPATH=. python tools/plot_fused_noise.py OUT.png RUN.json [RUN.json ...] [--network RUN.json:ABSREL ...]

Each RUN.json is ``tools/tune_fused.py --json`` of one oracle setting (``--model oracle --oracle-sigma S
[--oracle-shared-sigma B]``): its maps' occupied F1 are plotted at the oracle's depth error, the expected
AbsRel of a log-normal error of σ_total = √(S² + B²), E|exp(σ_total·Z) − 1| (edge noise off). Runs with
B > 0 (an error the views share) and B = 0 (independent per pixel) are two families of lines. ``--network
RUN.json:ABSREL`` adds a network's run at its prediction's measured AbsRel (stars, one per map; the fused maps of
the oracle and of the network alike go through the multi-view posterior). Prints the table.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

from mono_map.errors import MonoMapError
from mono_map.io import atomic_path, check_output_file

MAPS = ("fused", "mono keep 1", "mono keep 0.8", "depth-gt")
STYLE = {"fused": ("tab:red", "o"), "mono keep 1": ("tab:blue", "s"), "mono keep 0.8": ("tab:cyan", "^"),
         "depth-gt": ("black", "")}


def lognormal_absrel(sigma: float) -> float:
    """E|exp(σZ) − 1|, Z ~ N(0, 1): exp(σ²/2)·erf(σ/√2) (the expectation split at Z = 0)."""
    return math.exp(sigma ** 2 / 2) * math.erf(sigma / math.sqrt(2))


def load_run(path: str) -> dict:
    try:
        run = json.loads(Path(path).read_text())
        run["setting"]["seq"], run["setting"]["frames"][2]     # what every run names (a picture's title)
        return {"setting": run["setting"], "f1": {r["map"].strip(): r["f1"] for r in run["rows"]}}
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise SystemExit(f"{path}: not a tools/tune_fused.py --json file ({exc})") from None


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("out")
    p.add_argument("runs", nargs="+")
    p.add_argument("--network", action="append", default=[], help="RUN.json:ABSREL (repeatable)")
    args = p.parse_args(argv)
    try:
        check_output_file(args.out, "OUT", ".png")
    except MonoMapError as e:
        raise SystemExit(str(e))
    nets = []
    for item in args.network:
        path, _, value = item.rpartition(":")
        try:
            absrel = float(value)
        except ValueError:
            absrel = -1.0
        if not path or not 0 < absrel < 10:
            raise SystemExit(f"--network {item}: RUN.json:ABSREL, the AbsRel as a fraction")
        nets.append((load_run(path), absrel))
    families: dict[str, list] = {"independent": [], "shared": []}
    where = set()                                 # (sequence, frames) of the runs: the picture's title
    for path in args.runs:
        run = load_run(path)
        s = run["setting"]
        if s.get("oracle_sigma") is None:
            raise SystemExit(f"{path}: not an oracle run (use --network for a model's run)")
        if s.get("oracle_edge_sigma"):
            raise SystemExit(f"{path}: edge noise {s['oracle_edge_sigma']} is not a log-normal error of one σ "
                             "(run the oracle with --oracle-edge-sigma 0)")
        where.add((s["seq"], tuple(s["frames"])))
        b = s.get("oracle_shared_sigma") or 0.0
        total = float(np.hypot(s["oracle_sigma"], b))
        absrel = lognormal_absrel(total)
        for family in (("independent", "shared") if absrel < 1e-3 else ("shared" if b > 0 else "independent",)):
            families[family].append((absrel, run["f1"], s))      # near-exact depth starts both families
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(8, 6))
    print("| error | AbsRel | " + " | ".join(f"{m} F1 %" for m in MAPS) + " |")
    print("|---|---:|" + "---:|" * len(MAPS))
    for family, dash in (("independent", "-"), ("shared", "--")):
        pts = sorted(families[family], key=lambda t: t[0])
        for absrel, f1, s in pts:
            if family == "shared" and not s.get("oracle_shared_sigma"):
                continue                                          # printed once, with the independent runs
            name = (f"shared {s['oracle_shared_sigma']:g} (λ {s['oracle_shared_wavelength']:g} m) + independent "
                    f"{s['oracle_sigma']:g}" if family == "shared" else f"independent {s['oracle_sigma']:g}")
            print(f"| {name} | {absrel:.4f} | " + " | ".join(
                f"{100 * f1[m]:.1f}" if m in f1 else "–" for m in MAPS) + " |")
        for m in MAPS[:-1]:
            xy = [(a, f1[m]) for a, f1, _ in pts if m in f1]
            if len(xy) > 0:
                c, mk = STYLE[m]
                ax.plot([100 * a for a, _ in xy], [100 * f for _, f in xy], dash, color=c, marker=mk, ms=4,
                        label=f"{m}, error {'shared by the views' if family == 'shared' else 'independent per pixel'}")
    gts = [f1["depth-gt"] for fam in families.values() for _, f1, _ in fam if "depth-gt" in f1]
    if gts:
        ax.axhline(100 * np.mean(gts), color="black", lw=0.8, label="depth-gt (exact depth, every pixel)")
    ax.axhline(50, color="grey", lw=0.8, ls=":", label="issue 32's target for the fused map (on 00)")
    for run, absrel in nets:
        for m in MAPS[:-1]:
            if m in run["f1"]:
                c, mk = STYLE[m]
                ax.plot(100 * absrel, 100 * run["f1"][m], marker="*", color=c, ms=13, mec="k", ls="")
        print(f"| network {Path(run['setting']['model']).name} | {absrel:.4f} | " + " | ".join(
            f"{100 * run['f1'][m]:.1f}" if m in run["f1"] else "–" for m in MAPS) + " |")
    if nets:
        ax.plot([], [], marker="*", color="grey", ms=11, mec="k", ls="", label="a network (★; its measured AbsRel)")
    ax.set_xscale("log")
    ax.set_title("; ".join(f"sequence {q}, frames {f[0]}–{f[1]} ({f[2]})" for q, f in sorted(where)), fontsize=9)
    ax.set_xlabel("depth error fed to the map: AbsRel (%)")
    ax.set_ylabel("occupied F1 against LiDAR-FOV (%)")
    ax.set_ylim(0, 75)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.14), ncol=2)
    fig.tight_layout()
    with atomic_path(args.out) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    print(args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
