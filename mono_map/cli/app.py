"""``mono-map``: a thin command line over the library.

Each concept's subcommands live in a module of this package (``mono_map/cli/<concept>.py``) and
register themselves here; heavy imports (torch, open3d, octomap) happen inside the
commands, so ``mono-map --help`` stays instant.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from mono_map import __version__
from mono_map.errors import MonoMapError

# Modules whose ``register(subparsers)`` adds subcommands, in help order.
COMMAND_MODULES = (
    "mono_map.cli.data",           # synth, render-trainset
    "mono_map.cli.depth",          # train, predict, eval-depth
    "mono_map.cli.adapt",          # adapt
    "mono_map.cli.build",          # build
    "mono_map.cli.eval",           # eval
    "mono_map.cli.view",           # view
    "mono_map.cli.demo",           # demo (the README's main job)
)


class OneLineParser(argparse.ArgumentParser):
    """An argparse parser whose usage errors are one line, like every other mono-map error."""

    def error(self, message: str):
        where = self.prog.removeprefix("mono-map").strip()
        self.exit(2, f"mono-map: error: {where + ': ' if where else ''}{message} (see {self.prog} --help)\n")


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(
        prog="mono-map",
        description="Uncertainty-aware monocular mapping: depth distributions -> OctoMap -> evaluation.",
    )
    parser.add_argument("--version", action="version", version=f"mono-map {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMAND_MODULES:
        importlib.import_module(name).register(sub)
    return parser


class Terminated(BaseException):
    """SIGTERM, raised in the main thread so that every ``finally`` (temporary files) runs."""


def _on_sigterm(signum, frame):
    raise Terminated()


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    import signal
    import threading

    from mono_map.progress import close_bars

    if threading.current_thread() is threading.main_thread():
        previous = signal.signal(signal.SIGTERM, _on_sigterm)
    else:
        previous = None
    try:
        from mono_map.schema import check_env

        check_env()  # MONO_MAP_* variables: typed and in range before any command runs
        from mono_map.temps import sweep_registered_temps

        sweep_registered_temps()  # what killed runs left, wherever they wrote
        result = args.func(args)
    except MonoMapError as exc:
        return _fail(close_bars, str(exc), 2)
    except OSError as exc:  # an output path that is a file, a full disk, no permission, ...
        where = exc.filename if exc.filename is not None else "I/O"
        return _fail(close_bars, f"{where}: {exc.strerror or exc}", 2)
    except MemoryError:
        return _fail(close_bars, "out of memory (try a coarser --res, a --max-range or fewer --frames)", 2)
    except KeyboardInterrupt:
        close_bars()
        print("mono-map: interrupted", file=sys.stderr)
        return 130
    except Terminated:
        close_bars()
        print("mono-map: terminated", file=sys.stderr)
        return 143
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)
    return int(result or 0)


def _fail(close_bars, message: str, code: int) -> int:
    from mono_map.temps import user_path

    close_bars()
    message = user_path(message)  # the outputs the user named, never a temporary or staging path
    print(f"mono-map: error: {' '.join(message.split())}", file=sys.stderr)  # one line, whatever the message
    return code


if __name__ == "__main__":
    sys.exit(main())
