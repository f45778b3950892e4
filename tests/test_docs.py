"""The API reference (``make docs``: ``docs/api_reference.py``, pdoc) builds without a problem.

A module that does not import, an annotation pdoc cannot read, or a docstring reference
(``:func:`...```) that names nothing fails the build, so it fails here.
"""
from __future__ import annotations

import importlib.util
import re
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
SCRIPT = REPO / "docs" / "api_reference.py"


def _api_reference():
    spec = importlib.util.spec_from_file_location("api_reference", SCRIPT)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_api_reference_builds(tmp_path):
    """The whole reference, as ``make docs`` builds it (without the source listings, which
    pdoc only highlights), in a fresh interpreter: no problem reported, a page per module."""
    r = subprocess.run([sys.executable, str(SCRIPT), "-o", str(tmp_path), "--no-source"],
                       capture_output=True, text=True, timeout=300, cwd=REPO)
    assert r.returncode == 0, f"the API reference has problems:\n{r.stderr}"
    for page in ("index.html", "usdfiber.html", "usdfiber/bake.html", "usdfiber/validation.html",
                 "usdfiber/translators.html", "usdfiber/translators/mitsuba.html"):
        assert (tmp_path / page).is_file(), page


@pytest.fixture()
def package(tmp_path, monkeypatch):
    """A throw-away package ``docfixture_<n>`` on ``sys.path``; returns (name, folder)."""
    name = "docfixture_" + re.sub(r"\W", "_", tmp_path.name)
    folder = tmp_path / name
    folder.mkdir()
    monkeypatch.syspath_prepend(str(tmp_path))
    yield name, folder
    for mod in [m for m in sys.modules if m == name or m.startswith(name + ".")]:
        del sys.modules[mod]


def _write(folder: Path, files: dict[str, str]) -> None:
    for rel, text in files.items():
        (folder / rel).write_text(textwrap.dedent(text))


def test_references_that_resolve_pass(package, tmp_path):
    name, folder = package
    _write(folder, {
        "__init__.py": f'"""See :mod:`.shapes`, :class:`~{name}.shapes.Circle` and :exc:`ValueError`."""\n',
        "shapes.py": '''\
            """Shapes: :class:`Circle`, :func:`area`."""
            from __future__ import annotations


            def area(c: Circle) -> float:
                """Of a :class:`Circle` (:meth:`Circle.radius`)."""
                return 3.14159 * c.radius() ** 2


            class Circle:
                """Has :meth:`radius`; :func:`area` of it."""

                def radius(self) -> float:
                    """Sibling of :meth:`diameter`."""
                    return 1.0

                def diameter(self) -> float:
                    """Twice :meth:`radius`."""
                    return 2.0
            ''',
    })
    ar = _api_reference()
    assert ar.public_modules((name,)) == [name, f"{name}.shapes"]
    assert ar.build(tmp_path / "out", [name, f"{name}.shapes"]) == []
    assert (tmp_path / "out" / name / "shapes.html").is_file()


def test_broken_references_and_pdoc_warnings_are_reported(package, tmp_path):
    name, folder = package
    _write(folder, {
        "__init__.py": '"""See :func:`nowhere`."""\n',
        "shapes.py": '''\
            """Shapes."""
            from __future__ import annotations


            def area(c: NoSuchType) -> float:
                """Of a :class:`Circle` (:meth:`Circle.perimeter`)."""


            class Circle:
                """A circle."""

                def radius(self) -> float:
                    """See :meth:`diameter`."""
            ''',
    })
    (folder / "plain").mkdir()                       # a folder without __init__.py
    _write(folder, {"bare.py": "X = 1\n", "plain/leaf.py": '"""A leaf."""\n'})
    ar = _api_reference()
    modules = ar.public_modules((name,))
    assert modules == [name, f"{name}.bare", f"{name}.plain", f"{name}.plain.leaf", f"{name}.shapes"]
    problems = ar.build(tmp_path / "out", modules)
    joined = "\n".join(problems)
    assert len(problems) == 6, joined
    assert f"{name}.bare: no module docstring" in joined and f"{name}.plain: no module docstring" in joined
    assert f"{name}/__init__.py:1: {name}: :func:`nowhere` names nothing" in joined
    assert f"{name}/shapes.py:5: {name}.shapes.area: :meth:`Circle.perimeter` names nothing" in joined
    assert f"{name}.shapes.Circle.radius: :meth:`diameter` names nothing" in joined
    assert "pdoc: Error parsing type annotation NoSuchType" in joined


def test_a_module_that_does_not_import_is_reported(package, tmp_path):
    name, folder = package
    _write(folder, {"__init__.py": '"""A package."""\n', "broken.py": "import no_such_module_here\n"})
    ar = _api_reference()
    assert ar.public_modules((name,)) == [name, f"{name}.broken"]
    problems = ar.build(tmp_path / "out", [name, f"{name}.broken"])
    assert len(problems) == 1 and f"{name}.broken" in problems[0] and "no_such_module_here" in problems[0], problems
