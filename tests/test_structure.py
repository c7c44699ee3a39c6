"""Structure rules of docs/architecture.md, checked on the source (ast, nothing imported):

* no import cycles between mono_map modules (function-level imports included), and no module
  importing a later layer of data -> depth -> mapping -> eval -> viz -> commands;
* no private name (``_x``, or a ``_x`` module) imported from another module, nor reached as an
  attribute of an imported mono_map module — in mono_map/ (any module, third-party included) and in
  tools/, benchmarks/ and tests/ (mono_map modules);
* no C source in Python strings in mono_map/ (the kernels are mono_map/csrc/*.c);
* no ``sys.path`` edits in tools/ and benchmarks/ (they import the installed package);
* the package data (pyproject.toml) ships every data file of the package but the comparison
  heads' checkpoints: of mono_map/checkpoints/, only the default model;
* no module in mono_map/ is longer than MAX_LINES lines but the ones listed in KNOWN_LONG.
* no module but mono_map/mapping/strategies.py compares a map's ``source`` or ``integrate`` to a
  string literal (the source and the integration are strategies resolved there once);
* no module outside mono_map/cli/ imports argparse (nothing below the command line sees its options);
* the shared options (``--seq``, ``--frames``, ``--data-root``, ``--model``, ``--threads``,
  ``--precision``) are declared only by mono_map/cli/options.py's helpers, in the commands and in
  benchmarks/ and tools/ alike (SHARED_OPTION_OTHER_MEANING lists the few that mean something else).

Violations that other work is removing are listed below with their owner; the lists may only
shrink: a new violation fails, and so does a listed one that is gone (delete its line then).
"""

from __future__ import annotations

import ast
import fnmatch
import re
import subprocess
import sys
import tomllib
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PACKAGE = "mono_map"

# Import cycles (strongly connected modules) still present, owner in the comment.
KNOWN_CYCLES: set[frozenset[str]] = set()

# (file, line text) of private imports still present, owner in the comment.
KNOWN_PRIVATE: set[tuple[str, str]] = set()


# Imports against the one-way flow (see LAYERS) still present, owner in the comment.
KNOWN_UPWARD: set[tuple[str, str]] = set()


# Modules longer than MAX_LINES still to be split by concept (issue 35); a listed module that is split must
# leave the list, so it can only shrink.
MAX_LINES = 400
KNOWN_LONG: set[str] = set()


def layer(module: str) -> int:
    """Position in the one-way flow: base (config, errors, io, paths, progress, geometry) 0, data 1,
    depth 2, mapping 3, eval 4, viz 5, the command line (cli/, __main__.py) 6."""
    parts = module.split(".")
    if module == f"{PACKAGE}.__main__" or parts[1:2] == ["cli"]:
        return 6
    return {"data": 1, "depth": 2, "mapping": 3, "eval": 4, "viz": 5}.get(parts[1] if len(parts) > 2 else "", 0)


def module_name(path: Path) -> str:
    parts = list(path.relative_to(REPO).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def package_modules() -> dict[str, Path]:
    return {module_name(p): p for p in sorted((REPO / PACKAGE).rglob("*.py"))}


def is_private(name: str) -> bool:
    return name.startswith("_") and not (name.startswith("__") and name.endswith("__"))


def imports(path: Path, modules: dict[str, Path]):
    """Every import in ``path`` (module level and inside functions): yields (line number, imported
    module, [(name, local name)] or None for ``import x``), relative imports resolved."""
    tree = ast.parse(path.read_text(), filename=str(path))
    me = module_name(path) if path.is_relative_to(REPO / PACKAGE) else ""
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                yield node.lineno, alias.name, None
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                pkg = me.split(".") if path.name == "__init__.py" else me.split(".")[:-1]
                pkg = pkg[: len(pkg) - (node.level - 1)]
                base = ".".join(pkg + ([base] if base else []))
            yield node.lineno, base, [(a.name, a.asname or a.name) for a in node.names]


def import_graph() -> dict[str, set[str]]:
    """mono_map module → the mono_map modules it imports (``from pkg import submodule`` counts as the submodule)."""
    modules = package_modules()
    graph: dict[str, set[str]] = {m: set() for m in modules}
    for mod, path in modules.items():
        for _, target, names in imports(path, modules):
            if not target.startswith(PACKAGE):
                continue
            for name, _local in names or [(None, None)]:
                sub = f"{target}.{name}" if name else None
                dep = sub if sub in modules else target
                if dep in modules and dep != mod:
                    graph[mod].add(dep)
    return graph


def cycles(graph: dict[str, set[str]]) -> set[frozenset[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: set[frozenset[str]] = set()

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = set()
            while True:
                w = stack.pop()
                on.discard(w)
                comp.add(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.add(frozenset(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def private_imports() -> set[tuple[str, str]]:
    """(file, stripped source line) of every private import / private attribute of an imported mono_map module."""
    modules = package_modules()
    files = [f for d in (PACKAGE, "tools", "benchmarks", "tests") for f in sorted((REPO / d).rglob("*.py"))]
    found = set()
    for path in files:
        ours = path.is_relative_to(REPO / PACKAGE)
        lines = path.read_text().splitlines()
        rel = path.relative_to(REPO).as_posix()
        bound: set[str] = set()   # local names bound to imported mono_map modules
        for lineno, target, names in imports(path, modules):
            if not (ours or target.startswith(PACKAGE)):
                continue
            private_module = any(is_private(part) for part in target.split("."))
            private_names = [n for n, _local in names or [] if is_private(n)]
            if private_module or private_names:
                found.add((rel, lines[lineno - 1].strip()))
            if target.startswith(PACKAGE):
                for n, local in names or []:
                    if f"{target}.{n}" in modules:
                        bound.add(local)
        tree = ast.parse("\n".join(lines))
        for node in ast.walk(tree):   # import mono_map.x as m / from mono_map import x; then m._y / x._y
            if isinstance(node, ast.Import):
                for a in node.names:
                    if a.name.startswith(PACKAGE) and a.asname:
                        bound.add(a.asname)
        for node in ast.walk(tree):
            if (isinstance(node, ast.Attribute) and is_private(node.attr) and isinstance(node.value, ast.Name)
                    and node.value.id in bound):
                found.add((rel, lines[node.lineno - 1].strip()))
    return found


def test_no_import_cycles_between_modules():
    found = cycles(import_graph())
    new = found - KNOWN_CYCLES
    assert not new, "import cycles: " + "; ".join(" <-> ".join(sorted(c)) for c in new)
    gone = KNOWN_CYCLES - found
    assert not gone, "cycles fixed, delete them from KNOWN_CYCLES: " + "; ".join(" <-> ".join(sorted(c)) for c in gone)


def test_imports_follow_the_one_way_flow():
    """data -> depth -> mapping -> eval, viz and the commands on top: no module imports a later layer."""
    graph = import_graph()
    found = {(m, d) for m, deps in graph.items() for d in deps if layer(d) > layer(m)}
    new = found - KNOWN_UPWARD
    assert not new, "imports against the flow: " + "; ".join(f"{m} -> {d}" for m, d in sorted(new))
    gone = KNOWN_UPWARD - found
    assert not gone, "fixed, delete from KNOWN_UPWARD: " + "; ".join(f"{m} -> {d}" for m, d in sorted(gone))


def test_no_private_names_imported_from_other_modules():
    found = private_imports()
    new = found - KNOWN_PRIVATE
    assert not new, "private imports: " + "; ".join(f"{f}: {line}" for f, line in sorted(new))
    gone = KNOWN_PRIVATE - found
    assert not gone, "fixed, delete from KNOWN_PRIVATE: " + "; ".join(f"{f}: {line}" for f, line in sorted(gone))


def test_the_checks_see_function_level_imports_and_attributes(tmp_path, monkeypatch):
    """On a tiny fake package: a cycle closed by a lazy import inside a function, a relative import,
    a private name and a private attribute of an imported module are all found."""
    pkg = tmp_path / PACKAGE
    (pkg / "sub").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "sub" / "__init__.py").write_text("")
    (pkg / "a.py").write_text("from mono_map.sub import b\n\ndef f():\n    return b._hidden\n")
    (pkg / "sub" / "b.py").write_text("def g():\n    from ..a import f\n    from . import c\n    return f\n")
    (pkg / "sub" / "c.py").write_text("from mono_map.sub.b import _x, g\n")
    monkeypatch.setattr(sys.modules[__name__], "REPO", tmp_path)
    assert cycles(import_graph()) == {frozenset({"mono_map.a", "mono_map.sub.b", "mono_map.sub.c"})}
    assert import_graph()["mono_map.sub.b"] == {"mono_map.a", "mono_map.sub.c"}
    assert private_imports() == {("mono_map/a.py", "return b._hidden"),
                                 ("mono_map/sub/c.py", "from mono_map.sub.b import _x, g")}
    assert cycles({"a": {"b"}, "b": set()}) == set()
    assert is_private("_spread_bits") and not is_private("__future__") and not is_private("spread")


# A C construct in a string: a preprocessor line, or a function definition "type name(args) {".
C_IN_STRING = re.compile(r"^[ \t]*#[ \t]*(include|define|ifn?def|pragma)\b"
                         r"|\b(void|int|float|double|char|int\d+_t|uint\d+_t|size_t)[ \t*]+\w+[ \t]*\([^;{}]*\)[ \t\n]*\{",
                         re.MULTILINE)


def c_in_strings(paths) -> set[tuple[str, int]]:
    """(file, line) of every string constant (docstrings, f-string parts included) that holds C source."""
    found = set()
    for path in paths:
        for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
            if isinstance(node, ast.Constant) and isinstance(node.value, str) and C_IN_STRING.search(node.value):
                found.add((path.relative_to(REPO).as_posix(), node.lineno))
    return found


def sys_path_edits(paths) -> set[tuple[str, int]]:
    """(file, line) of every change to ``sys.path`` (a call of one of its methods, an assignment to it or
    an augmented one) and every ``site.addsitedir``."""
    found = set()
    for path in paths:
        for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
            target = None
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute):
                target = node.func.value if node.func.attr != "addsitedir" else node.func
            elif isinstance(node, (ast.Assign, ast.AugAssign)):
                target = node.targets[0] if isinstance(node, ast.Assign) else node.target
                target = target.value if isinstance(target, ast.Subscript) else target
            if target is not None and ast.unparse(target) in ("sys.path", "site.addsitedir"):
                found.add((path.relative_to(REPO).as_posix(), node.lineno))
    return found


def test_no_c_source_in_python_strings():
    """The kernels are real C files (mono_map/csrc/), built at install; none is hidden in a Python string."""
    found = c_in_strings(sorted((REPO / PACKAGE).rglob("*.py")))
    assert not found, "C source in Python strings (move it to mono_map/csrc/): " + "; ".join(
        f"{f}:{n}" for f, n in sorted(found))
    assert sorted(p.name for p in (REPO / PACKAGE / "csrc").glob("*.c")), "no C kernels in mono_map/csrc/"


def test_tools_and_benchmarks_import_the_installed_package():
    """No script in tools/ or benchmarks/ edits sys.path to find mono_map (pip install -e . provides it)."""
    paths = [f for d in ("tools", "benchmarks") for f in sorted((REPO / d).rglob("*.py"))]
    found = sys_path_edits(paths)
    assert not found, "sys.path edits: " + "; ".join(f"{f}:{n}" for f, n in sorted(found))


def package_data_patterns() -> list[str]:
    """pyproject.toml's package-data globs of the package, relative to mono_map/."""
    cfg = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]
    assert cfg.get("include-package-data") is False, "include-package-data would add files beyond package-data"
    return cfg["package-data"][PACKAGE]


def test_package_data_is_the_default_checkpoint_and_every_other_data_file():
    """The wheel's data files (pyproject's package-data matched against the package's tracked files):
    of mono_map/checkpoints/ only the default model; every other non-Python file of the package
    (kernel sources, KITTI assets, training configs) is shipped; the sdist prunes v1/ and v2/ too."""
    tracked = subprocess.run(["git", "ls-files", PACKAGE], cwd=REPO, capture_output=True, text=True).stdout.split()
    data = [f[len(PACKAGE) + 1:] for f in tracked if not f.endswith(".py") and (REPO / f).is_file()]
    if not data:
        data = [p.relative_to(REPO / PACKAGE).as_posix() for p in (REPO / PACKAGE).rglob("*")
                if p.is_file() and p.suffix not in (".py", ".pyc", ".so")]
    patterns = package_data_patterns()
    shipped = {f for f in data if any(fnmatch.fnmatchcase(f, pat) and f.count("/") == pat.count("/") for pat in patterns)}
    checkpoints = {f for f in data if f.startswith("checkpoints/")}
    assert shipped & checkpoints == {"checkpoints/binary.pt"}
    assert len(checkpoints) > 1                   # the comparison heads stay in the repository
    missing = sorted(set(data) - checkpoints - shipped)
    assert not missing, f"package data files the wheel would leave out: {missing}"
    manifest = (REPO / "MANIFEST.in").read_text().split("\n")
    assert "prune mono_map/checkpoints/v1" in manifest and "prune mono_map/checkpoints/v2" in manifest


def test_the_source_checks_find_what_they_guard(tmp_path, monkeypatch):
    """On fake files: C in a string and each form of sys.path edit are found; prose that mentions C is not."""
    (tmp_path / "k.py").write_text('SRC = r"""\n#include <math.h>\n"""\nF = "int64_t mm_f(const float *x, int n) { return 0; }"\n'
                                   '"""Docstring: calls mm_f (int64_t), built by ckernel; #include is C\'s."""\n')
    (tmp_path / "t.py").write_text("import sys, site\nsys.path.insert(0, 'x')\nsys.path += ['y']\nsys.path[:0] = ['z']\n"
                                   "site.addsitedir('w')\nprint(sys.path)\n")
    monkeypatch.setattr(sys.modules[__name__], "REPO", tmp_path)
    assert c_in_strings([tmp_path / "k.py"]) == {("k.py", 1), ("k.py", 4)}
    assert sys_path_edits([tmp_path / "t.py"]) == {("t.py", 2), ("t.py", 3), ("t.py", 4), ("t.py", 5)}


def long_modules(root: Path, max_lines: int = MAX_LINES) -> set[str]:
    """Modules under ``root``/mono_map with more than ``max_lines`` lines, as repository-relative paths."""
    return {p.relative_to(root).as_posix() for p in sorted((root / PACKAGE).rglob("*.py"))
            if len(p.read_text().splitlines()) > max_lines}


def test_no_module_is_longer_than_the_limit():
    """One concept per module: none over MAX_LINES lines but the KNOWN_LONG ones, each still over."""
    found = long_modules(REPO)
    new = found - KNOWN_LONG
    assert not new, f"modules over {MAX_LINES} lines (split them by concept): " + ", ".join(sorted(new))
    gone = KNOWN_LONG - found
    assert not gone, "no longer over the limit, delete from KNOWN_LONG: " + ", ".join(sorted(gone))


def test_the_length_check_counts_lines(tmp_path):
    (tmp_path / PACKAGE / "sub").mkdir(parents=True)
    (tmp_path / PACKAGE / "short.py").write_text("x = 1\n" * 3)
    (tmp_path / PACKAGE / "sub" / "long.py").write_text("x = 1\n" * 4)
    assert long_modules(tmp_path, 3) == {"mono_map/sub/long.py"}
    assert long_modules(tmp_path, 4) == set()


STRATEGIES = "mono_map/mapping/strategies.py"   # the one module that compares the names
STRATEGY_NAMES = ("source", "integrate")


def is_strategy_name(node: ast.AST) -> bool:
    """``source``, ``integrate``, or an attribute of that name (``args.source``, ``job.integrate``)."""
    return (isinstance(node, ast.Name) and node.id in STRATEGY_NAMES
            or isinstance(node, ast.Attribute) and node.attr in STRATEGY_NAMES)


def is_string_literal(node: ast.AST) -> bool:
    """A str constant, or a tuple / list / set of them."""
    if isinstance(node, (ast.Tuple, ast.List, ast.Set)):
        return bool(node.elts) and all(is_string_literal(e) for e in node.elts)
    return isinstance(node, ast.Constant) and isinstance(node.value, str)


def strategy_comparisons(paths) -> set[tuple[str, int]]:
    """(file, line) of every comparison of a ``source`` / ``integrate`` name with a string literal."""
    found = set()
    for path in paths:
        for node in ast.walk(ast.parse(Path(path).read_text())):
            if isinstance(node, ast.Compare):
                operands = [node.left, *node.comparators]
                if any(map(is_strategy_name, operands)) and any(map(is_string_literal, operands)):
                    found.add((Path(path).relative_to(REPO).as_posix(), node.lineno))
    return found


def test_source_and_integration_are_compared_only_in_the_strategies_module():
    """A map's source and integration are strategy objects chosen once (mapping/strategies.py); every other
    module asks them (``source.camera``, ``integration.distributional``) instead of comparing names."""
    found = {(f, line) for f, line in strategy_comparisons(sorted((REPO / PACKAGE).rglob("*.py")))
             if f != STRATEGIES}
    assert not found, "source/integrate compared to a string (ask mono_map/mapping/strategies.py): " + ", ".join(
        f"{f}:{line}" for f, line in sorted(found))
    assert (REPO / STRATEGIES).is_file(), f"{STRATEGIES} is gone: update STRATEGIES"


def test_the_strategy_check_finds_what_it_guards(tmp_path, monkeypatch):
    (tmp_path / "m.py").write_text('a = source == "mono"\nb = job.integrate in ("fused", "distribution")\n'
                                   'c = "lidar" != args.source\nd = source == other\ne = reference == "lidar"\n'
                                   'f = kind.camera\n')
    monkeypatch.setattr(sys.modules[__name__], "REPO", tmp_path)
    assert strategy_comparisons([tmp_path / "m.py"]) == {("m.py", 1), ("m.py", 2), ("m.py", 3)}


CLI = "mono_map/cli/"


def argparse_importers(paths) -> set[str]:
    """Files that import argparse (``import argparse``, ``from argparse import ...``), as repository paths."""
    found = set()
    for path in paths:
        for node in ast.walk(ast.parse(Path(path).read_text())):
            names = ([a.name for a in node.names] if isinstance(node, ast.Import)
                     else [node.module or ""] if isinstance(node, ast.ImportFrom) else [])
            if any(n.split(".")[0] == "argparse" for n in names):
                found.add(Path(path).relative_to(REPO).as_posix())
    return found


def test_only_the_command_line_imports_argparse():
    """The options are read in mono_map/cli/ and passed down as values and small dataclasses (a MapJob, an
    OctoMapConfig, ...): no module below the command line imports argparse or takes a Namespace."""
    found = {f for f in argparse_importers(sorted((REPO / PACKAGE).rglob("*.py"))) if not f.startswith(CLI)}
    assert not found, "argparse imported outside mono_map/cli/: " + ", ".join(sorted(found))
    assert (REPO / CLI / "options.py").is_file(), "mono_map/cli/options.py is gone: update CLI"


SHARED_OPTIONS = ("--seq", "--frames", "--data-root", "--model", "--threads", "--precision")
OPTIONS_MODULE = "mono_map/cli/options.py"
# (file, option) declared by hand because it means something else there; the reason in the comment
SHARED_OPTION_OTHER_MEANING: set[tuple[str, str]] = {
    ("benchmarks/bench_depth.py", "--frames"),        # timed repetitions of a forward pass
    ("benchmarks/bench_fingerprint.py", "--frames"),  # how many stand-in frames to write
    ("benchmarks/bench_train.py", "--threads"),       # a comma list of thread counts to sweep
    ("tools/camera_stress.py", "--frames"),           # how many val09 frames of the training cache
    ("tools/eval_real.py", "--seq"),                  # ROOT:NAME:FRAMES of another real sequence, repeatable
}


def declared_options(paths) -> set[tuple[str, str]]:
    """(file, option) of every ``add_argument("--x", ...)`` of a shared option."""
    found = set()
    for path in paths:
        for node in ast.walk(ast.parse(Path(path).read_text())):
            if (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)
                    and node.func.attr == "add_argument" and node.args and isinstance(node.args[0], ast.Constant)
                    and node.args[0].value in SHARED_OPTIONS):
                found.add((Path(path).relative_to(REPO).as_posix(), node.args[0].value))
    return found


def test_shared_options_are_declared_once():
    """Every command, benchmark and tool declares --seq, --frames, --data-root, --model, --threads and
    --precision with mono_map/cli/options.py's helpers: one meaning, one default, one help text."""
    paths = [p for d in (PACKAGE, "benchmarks", "tools") for p in sorted((REPO / d).glob("**/*.py"))
             if "archive" not in p.relative_to(REPO).parts]
    found = {(f, o) for f, o in declared_options(paths) if f != OPTIONS_MODULE}
    new = found - SHARED_OPTION_OTHER_MEANING
    assert not new, "shared options declared by hand (use mono_map/cli/options.py): " + ", ".join(
        f"{f} {o}" for f, o in sorted(new))
    gone = SHARED_OPTION_OTHER_MEANING - found
    assert not gone, "no longer declared, delete from SHARED_OPTION_OTHER_MEANING: " + ", ".join(
        f"{f} {o}" for f, o in sorted(gone))


def test_the_cli_checks_find_what_they_guard(tmp_path, monkeypatch):
    (tmp_path / "a.py").write_text("import argparse\n")
    (tmp_path / "b.py").write_text("from argparse import Namespace\n")
    (tmp_path / "c.py").write_text("import os\n# import argparse\np.add_argument('--seq', default='00')\n"
                                   "p.add_argument('--res')\nq.add_argument(\"--model\", action='append')\n")
    monkeypatch.setattr(sys.modules[__name__], "REPO", tmp_path)
    assert argparse_importers([tmp_path / f for f in ("a.py", "b.py", "c.py")]) == {"a.py", "b.py"}
    assert declared_options([tmp_path / "c.py"]) == {("c.py", "--seq"), ("c.py", "--model")}
