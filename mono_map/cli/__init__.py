"""The command line (``mono-map``, ``python -m mono_map``): the only package that sees argparse.

:mod:`mono_map.cli.main` builds the parser from the command modules beside it and runs one command.
"""

from mono_map.cli.main import build_parser, main

__all__ = ["build_parser", "main"]
