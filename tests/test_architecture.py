"""The shape of the code: layers that point one way, no import cycles, no private seams crossed,
and a core that works without the renderer bridges.

The import graph is read from the source (``ast``), with imports inside functions included
(they run too, only later) and imports under ``if TYPE_CHECKING:`` left out (they never run).
``usdfiber/`` is the core; ``translators/`` is installed as ``usdfiber.translators`` and holds
the bridges, which may import the core but never the other way round.
"""
from __future__ import annotations

import ast
import json
import os
import subprocess
import sys
import tomllib
from dataclasses import dataclass
from importlib.metadata import entry_points
from pathlib import Path


ROOT = Path(__file__).resolve().parents[1]
CORE = "usdfiber"
BRIDGES = "usdfiber.translators"
#: Source trees whose ``from X import _name`` lines are checked.
CHECKED_TREES = ("usdfiber", "translators", "bench", "tests", "examples")


@dataclass(frozen=True)
class Import:
    """One import statement: who imports what (module names), where, and which names."""

    importer: str
    target: str           # the module named after ``import`` or ``from``
    names: tuple[str, ...]  # the names of a ``from`` import (empty for ``import``)
    file: Path
    line: int


def module_name(path: Path) -> str:
    """The import name of a project file: ``translators/`` is installed as ``usdfiber.translators``."""
    rel = path.relative_to(ROOT).with_suffix("")
    parts = list(rel.parts)
    if parts[0] == "translators":
        parts = ["usdfiber", *parts]
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def project_files() -> list[Path]:
    return sorted(p for tree in ("usdfiber", "translators") for p in (ROOT / tree).rglob("*.py")
                  if "__pycache__" not in p.parts)


def _type_checking_only(tree: ast.AST) -> set[int]:
    """ids of the import nodes under ``if TYPE_CHECKING:``."""
    skip: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            for stmt in node.body:
                skip.update(id(n) for n in ast.walk(stmt))
    return skip


def imports_of(path: Path, importer: str) -> list[Import]:
    """Every import of a file (module level and inside functions), relative ones resolved."""
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    skip = _type_checking_only(tree)
    is_package = path.name == "__init__.py"
    out = []
    for node in ast.walk(tree):
        if id(node) in skip:
            continue
        if isinstance(node, ast.Import):
            out.extend(Import(importer, a.name, (), path, node.lineno) for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = importer.split(".") if is_package else importer.split(".")[:-1]
                base = base[: len(base) - (node.level - 1)]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            out.append(Import(importer, target, tuple(a.name for a in node.names), path, node.lineno))
    return out


def project_imports() -> tuple[set[str], list[Import]]:
    files = project_files()
    modules = {module_name(p) for p in files}
    return modules, [imp for p in files for imp in imports_of(p, module_name(p))]


def dependencies(imp: Import, modules: set[str]) -> set[str]:
    """The project modules an import runs: ``from P import m`` names the module P.m when it is one."""
    deps = set()
    if imp.names:
        for name in imp.names:
            if f"{imp.target}.{name}" in modules:
                deps.add(f"{imp.target}.{name}")
            elif imp.target in modules:
                deps.add(imp.target)
    elif imp.target in modules:
        deps.add(imp.target)
    return deps


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """One cycle (a closed path of modules) per strongly connected component that has one (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def strong(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                strong(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1 or v in graph.get(v, ()):
                found.append(_path_within(graph, set(comp)))

    sys.setrecursionlimit(max(10_000, sys.getrecursionlimit()))
    for v in sorted(graph):
        if v not in index:
            strong(v)
    return found


def _path_within(graph: dict[str, set[str]], comp: set[str]) -> list[str]:
    """A closed path through the component, from its first module back to it (breadth first)."""
    start = min(comp)
    prev: dict[str, str] = {}
    frontier = [start]
    while frontier:
        nxt = []
        for v in frontier:
            for w in sorted(graph.get(v, set()) & comp):
                if w == start:
                    path = [v]
                    while path[-1] != start:
                        path.append(prev[path[-1]])
                    return [start, *reversed(path[:-1]), start] if v != start else [start, start]
                if w not in prev:
                    prev[w] = v
                    nxt.append(w)
        frontier = nxt
    return sorted(comp)


# ---------------------------------------------------------------------------------------------
# The checks themselves can fail
# ---------------------------------------------------------------------------------------------

def test_cycle_finder_reports_cycles_and_only_cycles():
    assert cycles({"a": {"b"}, "b": {"c"}, "c": set()}) == []
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c", "a"]]
    assert cycles({"a": {"a"}}) == [["a", "a"]]
    assert len(cycles({"a": {"b"}, "b": {"a"}, "c": {"d"}, "d": {"c"}})) == 2


def test_import_reader_resolves_relative_and_nested_imports(tmp_path):
    f = tmp_path / "mod.py"
    f.write_text("from __future__ import annotations\nfrom typing import TYPE_CHECKING\n"
                 "from . import sibling\nfrom ..up import _hidden\n"
                 "if TYPE_CHECKING:\n    import never.runs\n"
                 "def f():\n    import usdfiber.translators.mitsuba\n")
    got = {(i.target, i.names) for i in imports_of(f, "usdfiber.pkg.mod")}
    assert ("usdfiber.pkg", ("sibling",)) in got and ("usdfiber.up", ("_hidden",)) in got
    assert ("usdfiber.translators.mitsuba", ()) in got          # inside a function: counted
    assert not any(t.startswith("never") for t, _ in got)        # TYPE_CHECKING only: not run


# ---------------------------------------------------------------------------------------------
# Layers, cycles, private names
# ---------------------------------------------------------------------------------------------

def test_the_core_never_imports_a_bridge():
    _, imps = project_imports()
    bad = [f"{i.file.relative_to(ROOT)}:{i.line}: {i.importer} imports {i.target}"
           for i in imps if not i.importer.startswith(BRIDGES) and i.importer.startswith(CORE)
           and (i.target == BRIDGES or i.target.startswith(BRIDGES + ".")
                or (i.target == CORE and "translators" in i.names))]
    assert not bad, "the core (usdfiber/) imports the bridges (translators/):\n" + "\n".join(bad)


def test_no_import_cycles():
    modules, imps = project_imports()
    graph: dict[str, set[str]] = {m: set() for m in modules}
    for imp in imps:
        graph[imp.importer] |= dependencies(imp, modules) - {imp.importer}
    found = cycles(graph)
    assert not found, "import cycles:\n" + "\n".join(" -> ".join(c) for c in found)


def _checked_files() -> list[Path]:
    return sorted(p for tree in CHECKED_TREES for p in (ROOT / tree).rglob("*.py")
                  if "__pycache__" not in p.parts and "results" not in p.parts)


def test_no_private_names_imported_across_modules():
    """``from X import _name`` reaches into another module's internals: a public name is missing.
    Dunder names are public; a package may import its own private submodules."""
    bad = []
    for path in _checked_files():
        in_package = path.parts[len(ROOT.parts)] in ("usdfiber", "translators")
        importer = module_name(path) if in_package else path.stem
        for imp in imports_of(path, importer):
            for name in imp.names:
                if not name.startswith("_") or (name.startswith("__") and name.endswith("__")):
                    continue
                if path.name == "__init__.py" and imp.target == importer:
                    continue                    # the package's own private submodule
                bad.append(f"{path.relative_to(ROOT)}:{imp.line}: from {imp.target} import {name}")
    assert not bad, "private names imported from other modules:\n" + "\n".join(bad)


# ---------------------------------------------------------------------------------------------
# Packaging: one layout for editable and wheel installs; commands by entry point
# ---------------------------------------------------------------------------------------------

def _pyproject() -> dict:
    return tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))


def test_wheel_and_editable_installs_map_the_same_folders():
    packages = _pyproject()["tool"]["scikit-build"]["wheel"]["packages"]
    assert packages == {"usdfiber": "usdfiber", "usdfiber/translators": "translators"}
    import usdfiber
    import usdfiber.translators

    assert Path(usdfiber.__file__).resolve().parent == ROOT / "usdfiber"
    assert Path(usdfiber.translators.__file__).resolve().parent == ROOT / "translators"
    # Every folder of Python modules is a regular package (no namespace packages, which an
    # install may leave out or take from elsewhere).
    missing = sorted(str(d.relative_to(ROOT)) for tree in ("usdfiber", "translators")
                     for d in [ROOT / tree, *(ROOT / tree).rglob("*")]
                     if d.is_dir() and "__pycache__" not in d.parts and any(d.glob("*.py"))
                     and not (d / "__init__.py").exists())
    assert not missing, f"folders of modules without __init__.py: {missing}"


def test_installed_commands_are_those_of_pyproject():
    """The ``usdfiber.commands`` entry points installed are the ones pyproject.toml declares, in
    its order (a stale install means: run tools/setup.sh), and each names a register function
    of a module in this tree."""
    declared = _pyproject()["project"]["entry-points"]["usdfiber.commands"]
    installed = [(ep.name, ep.value) for ep in entry_points(group="usdfiber.commands")]
    assert installed == list(declared.items()), "installed entry points differ from pyproject.toml: run tools/setup.sh"
    files = {module_name(p): p for p in project_files()}
    for name, value in declared.items():
        module, _, func = value.partition(":")
        assert module in files, f"{name}: no module {module} in the tree"
        tree = ast.parse(files[module].read_text(encoding="utf-8"))
        assert any(isinstance(n, ast.FunctionDef) and n.name == func for n in tree.body), f"{name}: no {value}"


def test_help_lists_render_when_the_bridge_is_installed():
    from usdfiber.cli import build_parser

    text = build_parser().format_help()
    listed = [line.split()[0] for line in text.split("COMMAND\n", 1)[1].split("options:")[0].splitlines()
              if line.startswith("    ") and not line.startswith("     ")]
    assert listed == list(_pyproject()["project"]["entry-points"]["usdfiber.commands"])
    assert listed[:2] == ["check", "render"]


#: Run in a fresh interpreter: every import of ``usdfiber.translators`` fails, as if the bridges
#: were not installed.
_WITHOUT_BRIDGES = r"""
import importlib.abc, json, sys

class NoBridges(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name == "usdfiber.translators" or name.startswith("usdfiber.translators."):
            raise ImportError(f"No module named {name!r} (bridges not installed)")
        return None

sys.meta_path.insert(0, NoBridges())
import usdfiber
from usdfiber.cli import main

check = main(["check", sys.argv[1]])
render = main(["render", sys.argv[1], "-o", sys.argv[2]])
print(json.dumps({"check": check, "render": render,
                  "bridges": sorted(m for m in sys.modules if m.startswith("usdfiber.translators")),
                  "mitsuba": "mitsuba" in sys.modules}))
"""


def test_core_imports_and_checks_without_the_bridges(tmp_path):
    out = tmp_path / "never.exr"
    proc = subprocess.run([sys.executable, "-c", _WITHOUT_BRIDGES, str(ROOT / "examples" / "demo.usda"), str(out)],
                          capture_output=True, text=True, timeout=300, cwd=tmp_path,
                          env={**os.environ, "PYTHONDONTWRITEBYTECODE": "1"})
    assert proc.returncode == 0, proc.stderr
    res = json.loads(proc.stdout.strip().splitlines()[-1])
    assert res["check"] == 0 and res["bridges"] == [] and not res["mitsuba"], (res, proc.stderr)
    # `usdfiber render` without the bridge: exit 2 and one line saying why; nothing written.
    assert res["render"] == 2 and not out.exists()
    lines = [ln for ln in proc.stderr.splitlines() if ln.startswith("usdfiber: error:")]
    assert len(lines) == 1 and "render command is not available" in lines[0] and "pip install -e ." in lines[0]
    assert "Traceback" not in proc.stderr
