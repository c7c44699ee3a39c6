"""The command line (``mono-map``, ``python -m mono_map``): the only package that sees argparse.

:mod:`mono_map.cli.app` builds the parser from the command modules beside it and runs one command.
"""

from mono_map.cli.app import build_parser, main

__all__ = ["build_parser", "main"]
