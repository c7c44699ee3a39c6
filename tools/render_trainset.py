"""Kept for old command lines: the same as ``mono-map render-trainset`` (see its --help)."""
import sys; from pathlib import Path; sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # noqa: E702
from mono_map.cli import main; sys.exit(main(["render-trainset", *sys.argv[1:]]))  # noqa: E402,E702
