"""Kept for old command lines: the same as ``mono-map render-trainset`` (see its --help)."""
import sys

from mono_map.cli import main

sys.exit(main(["render-trainset", *sys.argv[1:]]))
