"""The Python snippets of the README and the docs work as written.

Every ```python block of ``README.md``, ``docs/*.md`` and ``examples/README.md`` runs in a
fresh temporary directory in its own interpreter (as a reader would paste it), with a
private table cache. Every USD file a snippet writes must hold what the snippet authored
(a stage that was never saved is an empty file) and pass ``usdfiber check``.
"""
from __future__ import annotations

import os
import re
import subprocess
import sys
import textwrap
from dataclasses import dataclass
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
SOURCES = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md")), REPO / "examples" / "README.md"]
_FENCE = re.compile(r"^```\s*(\w*)\s*$")
_STAGE_SUFFIXES = {".usda", ".usd", ".usdc"}


@dataclass(frozen=True)
class Snippet:
    path: Path
    line: int            # line of the first code line in ``path``
    code: str

    @property
    def where(self) -> str:
        return f"{_name(self.path)}:{self.line}"


def _name(path: Path) -> str:
    return str(path.relative_to(REPO)) if path.is_relative_to(REPO) else str(path)


def python_snippets(path: Path) -> list[Snippet]:
    """The ```python (or ```py) blocks of a Markdown file, with their line numbers."""
    out, lang, start, body = [], None, 0, []
    for i, text in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
        m = _FENCE.match(text.strip())
        if lang is None:
            if m:
                lang, start, body = m.group(1).lower(), i + 1, []
        elif m and not m.group(1):
            if lang in ("python", "py"):
                # dedented: a block inside a list item is indented with it
                out.append(Snippet(path, start, textwrap.dedent("\n".join(body)) + "\n"))
            lang = None
        else:
            body.append(text)
    if lang is not None:
        raise AssertionError(f"{_name(path)}:{start - 1}: code block never closed")
    return out


SNIPPETS = [s for p in SOURCES if p.is_file() for s in python_snippets(p)]


def _run(args: list[str], cwd: Path) -> subprocess.CompletedProcess:
    env = dict(os.environ, USDFIBER_CACHE_DIR=str(cwd.parent / "cache"), PYTHONDONTWRITEBYTECODE="1")
    return subprocess.run(args, cwd=cwd, env=env, capture_output=True, text=True, timeout=300)


def test_the_readme_has_snippets_to_run():
    """The extraction finds the README's authoring example (so the tests below run something)."""
    readme = [s for s in SNIPPETS if s.path.name == "README.md" and s.path.parent == REPO]
    assert any("Usd.Stage.CreateNew" in s.code for s in readme), [s.where for s in readme]


def test_blocks_are_found_with_their_lines(tmp_path):
    md = tmp_path / "x.md"
    md.write_text("# T\n```sh\nls\n```\n- item:\n\n  ```python\n  x = 1\n  ```\n```py\ny = 2\n```\n")
    assert [(s.line, s.code) for s in python_snippets(md)] == [(8, "x = 1\n"), (11, "y = 2\n")]


def test_an_unclosed_block_is_reported(tmp_path):
    bad = tmp_path / "x.md"
    bad.write_text("text\n```python\nprint(1)\n")
    with pytest.raises(AssertionError, match=r"x.md:2: code block never closed"):
        python_snippets(bad)


@pytest.mark.parametrize("snippet", SNIPPETS, ids=[s.where for s in SNIPPETS])
def test_snippet_runs_and_its_stages_check(snippet: Snippet, tmp_path: Path):
    work = tmp_path / "work"
    work.mkdir()
    # Padded so that a traceback's line numbers are the Markdown file's.
    script = tmp_path / f"{snippet.path.name.replace('.', '_')}_line{snippet.line}.py"
    script.write_text("\n" * (snippet.line - 1) + snippet.code, encoding="utf-8")
    r = _run([sys.executable, str(script)], work)
    assert r.returncode == 0, (f"{snippet.where}: the snippet fails (exit {r.returncode}; traceback lines are "
                               f"{snippet.path.name}'s):\n{r.stderr[-3000:]}")

    import usdfiber  # noqa: F401  (registers the schemas)
    from pxr import Sdf

    for stage_file in sorted(p for p in work.rglob("*") if p.suffix in _STAGE_SUFFIXES):
        name = stage_file.relative_to(work)
        layer = Sdf.Layer.OpenAsAnonymous(str(stage_file))
        assert layer is not None and len(layer.rootPrims) > 0, (
            f"{snippet.where}: the snippet writes {name} but leaves it empty (expected the stage saved: "
            f"stage.GetRootLayer().Save())")
        check = _run([sys.executable, "-m", "usdfiber", "check", str(stage_file)], work)
        assert check.returncode == 0, (f"{snippet.where}: `usdfiber check {name}` on what the snippet wrote "
                                       f"exits {check.returncode}:\n{check.stdout}{check.stderr}")
