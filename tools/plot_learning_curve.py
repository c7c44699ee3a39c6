"""Learning curves of training runs: validation AbsRel, δ1, AUC-ARE and sky→beyond accuracy vs CPU-hours.

    python tools/plot_learning_curve.py RUN_DIR [RUN_DIR ...] --out docs/images/learning_curve.png
        [--row "heads=v2-binary,v2-softmax" --row "bins=v2-binary,v2-binary-k32"]

Each RUN_DIR holds the ``curve.jsonl`` that ``mono-map train`` appends at every validation
(``<work_dir>/<name>/``; default work dir ``~/.cache/mono-map/train``). ``--row LABEL=RUN,…`` draws those runs
in a row of their own (a run may stand in several rows); without it, one row of every run.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+")
    ap.add_argument("--out", required=True)
    ap.add_argument("--continues", action="append", default=[], metavar="RUN=PARENT",
                    help="RUN was started from PARENT's weights (train.init): its CPU-hours are drawn after PARENT's")
    ap.add_argument("--row", action="append", default=[], metavar="LABEL=RUN,RUN",
                    help="a row of panels with only these runs (names as the run directories'); repeatable")
    a = ap.parse_args()
    curves = {}
    for r in a.runs:
        f = Path(r).expanduser() / "curve.jsonl"
        if not f.is_file():
            sys.exit(f"plot_learning_curve: {f}: no such file")
        curves[Path(r).name] = [json.loads(line) for line in f.read_text().splitlines() if line.strip()]
    for spec in a.continues:
        child, _, parent = spec.partition("=")
        if child not in curves or parent not in curves:
            sys.exit(f"plot_learning_curve: --continues {spec}: both runs must be given (names: {', '.join(curves)})")
        offset = curves[parent][-1]["cpu_hours"]
        curves[child] = [dict(r, cpu_hours=r["cpu_hours"] + offset) for r in curves[child]]
    rows_spec = []
    for spec in a.row:
        label, _, names = spec.partition("=")
        names = [n.strip() for n in names.split(",") if n.strip()]
        missing = [n for n in names if n not in curves]
        if not label or not names or missing:
            sys.exit(f"plot_learning_curve: --row {spec}: expected LABEL=RUN,RUN with given runs "
                     f"(unknown: {', '.join(missing) or '-'}; names: {', '.join(curves)})")
        rows_spec.append((label, names))
    if not rows_spec:
        rows_spec = [("", list(curves))]
    steps = sorted({b["step"] - a_["step"] for rows in curves.values() for a_, b in zip(rows, rows[1:])})
    every = f", every {steps[0]} steps" if len(steps) == 1 else ""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from mono_map.io import atomic_path

    keys = [("abs_rel", "AbsRel (validation town)"), ("delta1", "δ<1.25"), ("auc_are", "AUC ARE (entropy-ranked)"),
            ("sky_beyond_acc", "sky pixels predicted beyond range")]
    fig, grid = plt.subplots(len(rows_spec), 4, figsize=(17, 3.8 * len(rows_spec)), squeeze=False)
    colours = plt.get_cmap("tab10").colors
    for axes, (label, names) in zip(grid, rows_spec):
        for c, name in enumerate(names):
            rows = curves[name]
            x = [r["cpu_hours"] for r in rows]
            style = "o-" if c < len(colours) else "s--"
            for ax, (k, lab) in zip(axes, keys):
                ax.plot(x, [r[k] if r[k] is not None else float("nan") for r in rows], style, ms=3, label=name,
                        color=colours[c % len(colours)])
        for ax, (k, lab) in zip(axes, keys):
            ax.set_xlabel("CPU-hours (process time)")
            ax.set_ylabel(lab)
            ax.grid(alpha=0.3)
        if label:
            axes[0].set_title(label, loc="left", fontsize=10, fontweight="bold")
        axes[0].legend(fontsize=8)
    fig.suptitle(f"Learning curves: held-out randomised town val09 (LiDAR ground truth ≤ 80 m){every}")
    fig.tight_layout()
    with atomic_path(Path(a.out)) as tmp:
        fig.savefig(tmp, dpi=100, format="png")
    print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
