"""Import a script of tools/, tools/archive/ or benchmarks/ as a module (they are not packages), for the
tests of its functions. The scripts import the installed mono_map (pip install -e .) like any user code."""

import importlib.util
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SCRIPT_DIRS = (REPO / "tools", REPO / "tools" / "archive", REPO / "benchmarks")


def script_path(name: str) -> Path:
    """The one file <name>.py of tools/, tools/archive/ or benchmarks/."""
    found = [d / f"{name}.py" for d in SCRIPT_DIRS if (d / f"{name}.py").is_file()]
    if len(found) != 1:
        raise FileNotFoundError(f"{name}.py: {len(found)} copies in tools/, tools/archive/, benchmarks/")
    return found[0]


def load_tool(name: str):
    """tools/<name>.py (or tools/archive/, benchmarks/) as a module."""
    spec = importlib.util.spec_from_file_location(name, script_path(name))
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod
