"""Render the randomised training towns (and the validation town) into the training cache.

    python tools/render_trainset.py [--root DIR] [--workers 2] [--towns N]

Resumable: frames already marked done are skipped. Prints progress per town. The cache lives outside
the work tree (default ``~/.cache/mono-map/trainset``, ``$MONO_MAP_TRAINSET``).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from mono_map.data.synth.randomize import training_towns, validation_town  # noqa: E402
from mono_map.data.synth.trainset import default_root, render_trainset  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--root", default=None, help="cache directory (default ~/.cache/mono-map/trainset)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--towns", type=int, default=0, help="only the first N training towns (0 = all)")
    a = ap.parse_args()
    if a.workers < 1 or a.towns < 0:
        sys.exit("render_trainset: --workers must be >= 1 and --towns >= 0")
    specs = training_towns()
    specs = [validation_town()] + (specs[:a.towns] if a.towns else specs)
    root = Path(a.root) if a.root else default_root()
    print(f"rendering {len(specs)} towns ({sum(s.frames for s in specs)} frames) into {root}", file=sys.stderr)
    out = render_trainset(root, specs, workers=a.workers, log=lambda m: print(m, file=sys.stderr, flush=True))
    print(f"done: {out['frames_rendered']} frames in {out['seconds'] / 60:.1f} min", file=sys.stderr)


if __name__ == "__main__":
    main()
