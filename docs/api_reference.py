"""Build the API reference of ``usdfiber`` and ``usdfiber.translators`` with pdoc.

    python docs/api_reference.py [-o build/docs] [--no-source]

Every public module of both packages is imported and rendered to HTML from its docstrings.
The build fails (exit 1, one report line per problem) when a module does not import or has
no docstring, when pdoc warns (an annotation it cannot read, a member it cannot inspect,
...), or when a docstring's cross-reference (``:class:`...```, ``:func:`...```,
``:mod:`...```, ...) names something that does not exist: pdoc would render such a
reference as plain text, so a reference left behind by a rename or a move would otherwise
go unnoticed.

Modules are listed explicitly, and each package page links all of its submodules, because
pdoc follows a package's ``__all__`` when it looks for submodules, and ``usdfiber.__all__``
names the package's API, not its modules.
"""
from __future__ import annotations

import argparse
import builtins
import importlib
import re
import sys
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import Any

ROOTS = ("usdfiber", "usdfiber.translators")
DEFAULT_OUTPUT = Path(__file__).resolve().parent.parent / "build" / "docs"

# Sphinx roles pdoc understands (docstrings.rst): :class:`~pkg.mod.Name`, :meth:`Name.m`, ...
_ROLE = re.compile(r"(?::py)?:(mod|func|data|const|class|meth|attr|exc|obj):`([^`]+)`")


def public_modules(roots: tuple[str, ...] = ROOTS) -> list[str]:
    """Every public module under ``roots`` (no name part starting with ``_``), found in the
    packages' folders: folders without ``__init__.py`` (namespace packages) included.

    Only the roots are imported here; :func:`build` imports the rest and reports failures.
    """
    names: set[str] = set()
    for root in roots:
        package = importlib.import_module(root)
        # The package's own folder, not ``__path__``: an editable install adds the checkout
        # root to ``usdfiber.__path__``, where a walk would find ``usdfiber.usdfiber``.
        folder = Path(package.__file__).parent
        names.add(root)
        for path in folder.rglob("*.py"):
            parts = list(path.relative_to(folder).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts.pop()
            if any(p.startswith("_") or not p.isidentifier() for p in parts):
                continue
            # the module and the (namespace) packages above it
            names.update(".".join([root, *parts[:i]]) for i in range(1, len(parts) + 1))
    return sorted(names)


def _lookup(obj: Any, parts: list[str]) -> bool:
    for part in parts:
        try:
            obj = getattr(obj, part)
        except Exception:
            return False
    return True


def _resolves_absolute(parts: list[str]) -> bool:
    for i in range(len(parts), 0, -1):
        try:
            module = importlib.import_module(".".join(parts[:i]))
        except Exception:
            continue
        return _lookup(module, parts[i:])
    return False


def resolves(target: str, module: str, scope: Any = None) -> bool:
    """Whether a docstring reference ``target`` names something, Sphinx-style: in the
    enclosing class ``scope`` (a pdoc ``Class``: its attributes and the instance variables
    pdoc found), then in ``module``'s namespace, then as an absolute name;
    a leading ``.`` searches ``module`` and the packages above it; ``~`` only shortens the
    displayed text."""
    name = target.strip().lstrip("~").removesuffix("()")
    if name.startswith("."):
        parts = name.lstrip(".").split(".")
        base = module.split(".")
        return any(_resolves_absolute(base[:i] + parts) for i in range(len(base), 0, -1))
    parts = name.split(".")
    if scope is not None and (_lookup(scope.obj, parts) or (len(parts) == 1 and parts[0] in scope.members)):
        return True
    if _lookup(importlib.import_module(module), parts):
        return True
    return _resolves_absolute(parts) or (len(parts) == 1 and hasattr(builtins, parts[0]))


def _where(doc: Any) -> str:
    """``path:line`` of a documented object's definition (path relative to the checkout)."""
    path = doc.source_file
    if path is None:
        return "?"
    path = Path(path)
    root = DEFAULT_OUTPUT.parent.parent
    name = path.relative_to(root) if path.is_relative_to(root) else path
    return f"{name}:{max(1, doc.source_lines[0]) if doc.source_lines else 1}"


def _documented(doc: Any, module: str, scope: Any = None) -> Iterator[tuple[Any, str, Any]]:
    """(pdoc doc, docstring, class scope) of ``doc`` and its own members, recursively."""
    inner = doc if doc.kind == "class" else scope         # a class's docstring sees its members
    yield doc, doc.docstring or "", inner
    own = getattr(doc, "own_members", None)
    if own is None:
        return
    for member in own:
        if member.taken_from[0] == module:          # defined here, not imported
            yield from _documented(member, module, inner)


def broken_references(modules: dict[str, Any]) -> list[str]:
    """One line per docstring reference that names nothing, for the pdoc ``Module`` docs given."""
    problems = []
    for name, mod in modules.items():
        for doc, docstring, scope in _documented(mod, name):
            for role, target in _ROLE.findall(docstring):
                if not resolves(target, name, scope):
                    problems.append(f"{_where(doc)}: {doc.fullname}: :{role}:`{target}` names nothing "
                                    f"(expected an existing module, class, function or attribute)")
    return problems


def build(output: Path, modules: list[str] | None = None, *, show_source: bool = True) -> list[str]:
    """Render the reference of ``modules`` (default: :func:`public_modules`) into ``output``;
    ``show_source=False`` leaves out each function's highlighted source (three times faster).

    Returns the problems found (modules that do not import or have no docstring, pdoc
    warnings, broken references), one line each; the HTML of the rest is written either way.
    """
    import pdoc
    import pdoc.doc
    import pdoc.render

    pdoc.render.configure(docformat="restructuredtext", show_source=show_source,
                          footer_text="usdfiber API reference")
    problems: list[str] = []
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        docs = {}
        for name in modules if modules is not None else public_modules():
            try:
                docs[name] = pdoc.doc.Module.from_name(name)
            except Exception as e:  # the module does not import: say why, document the rest
                cause = f" ({type(e.__cause__).__name__}: {e.__cause__})" if e.__cause__ else ""
                problems.append(f"{name}: {type(e).__name__}: {e}{cause}")
        _link_submodules(docs)
        _write(output, docs)
        problems += [f"{name}: no module docstring (expected one saying what the module holds; "
                     f"a folder without __init__.py has none)"
                     for name, doc in docs.items() if not doc.docstring.strip()]
        problems += broken_references(docs)
    pdoc_dir = str(Path(pdoc.__file__).parent)
    for w in caught:
        # Warnings of the libraries imported along the way are theirs to fix; pdoc's are ours.
        if str(w.filename).startswith(pdoc_dir):
            problems.append(f"pdoc: {str(w.message).strip()}")
    return problems


def _link_submodules(docs: dict[str, Any]) -> None:
    """Give every package page all its documented submodules: pdoc lists only those named in
    ``__all__`` when a package has one, so ``usdfiber``'s page would list none."""
    for name, mod in docs.items():
        # replaces pdoc's cached value (pdoc would import each child again, and warn twice
        # about one that does not import)
        mod.submodules = [d for n, d in docs.items() if n.rpartition(".")[0] == name]


def _write(output: Path, docs: dict[str, Any]) -> None:
    """What ``pdoc.pdoc`` writes, for exactly these modules (it would walk each package's
    submodules again, which repeats every module given)."""
    import pdoc.render

    for name, mod in docs.items():
        out = output / f"{name.replace('.', '/')}.html"
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(pdoc.render.html_module(mod, docs), encoding="utf-8")
    (output / "index.html").write_text(pdoc.render.html_index(docs), encoding="utf-8")
    (output / "search.js").write_text(pdoc.render.search_index(docs), encoding="utf-8")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("-o", "--output", type=Path, default=DEFAULT_OUTPUT,
                        help=f"output folder (default: {DEFAULT_OUTPUT})")
    parser.add_argument("--no-source", action="store_true",
                        help="leave out the functions' source code (faster; the same checks)")
    args = parser.parse_args(argv)
    problems = build(args.output, show_source=not args.no_source)
    for p in problems:
        print(f"api reference: {p}", file=sys.stderr)
    if problems:
        print(f"api reference: {len(problems)} problem(s); HTML in {args.output}", file=sys.stderr)
        return 1
    print(f"API reference written to {args.output / 'index.html'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
