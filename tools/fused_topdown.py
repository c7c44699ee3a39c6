#!/usr/bin/env python3
"""Top-down pictures of maps side by side (docs/fused.md): ``LABEL=MAP.bt`` pairs → one PNG.

    PYTHONPATH=. python tools/fused_topdown.py docs/images/fused_topdown_00.png \\
        LiDAR-FOV=outputs/seq00/lidar-fov_res0.2_f0-500.bt "keep 0.8=..." distribution=... fused=...
"""

from __future__ import annotations

import sys
from pathlib import Path


from mono_map.errors import MonoMapError  # noqa: E402
from mono_map.mapping.octree import load_tree, tree_leaves  # noqa: E402
from mono_map.viz.plots import render_topdown  # noqa: E402


def main(argv=None) -> int:
    args = sys.argv[1:] if argv is None else argv
    if len(args) < 2 or any("=" not in a for a in args[1:]):
        raise SystemExit("usage: fused_topdown.py OUT.png LABEL=MAP.bt [LABEL=MAP.bt ...]")
    maps = []
    for a in args[1:]:
        label, path = a.split("=", 1)
        try:
            maps.append((label, tree_leaves(load_tree(Path(path)))))
        except MonoMapError as exc:
            raise SystemExit(str(exc)) from None
    print(render_topdown(maps, args[0], dpi=80))
    return 0


if __name__ == "__main__":
    sys.exit(main())
