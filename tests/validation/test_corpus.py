"""The bad-input corpus: every file in tests/corpus/bad has its exact expected problems.

``tests/corpus/expected.json`` maps a file name to the list of problems ``check_stage``
must find in it, each ``{"code", "severity", "prim", "attribute", "message"}``, compared as
a set (the same problem at several time samples counts once); ``message`` is a fragment the
problem's message must contain (what was found and what was expected). A file that cannot be opened
expects exactly one entry: ``{"code": <StageOpenError.code>, "severity": "error",
"prim": null, "attribute": null}``.

To add a case: put the file in tests/corpus/bad/, add its entry to expected.json (keep
the keys sorted), and describe the defect in a comment inside the file.
"""
from __future__ import annotations

import json
from pathlib import Path

import pytest

import usdfiber  # noqa: F401  (registers the schemas before any stage exists)
from usdfiber.stage_io import StageOpenError
from usdfiber.validation.runner import check_stage

CORPUS = Path(__file__).resolve().parents[1] / "corpus"
BAD = CORPUS / "bad"
EXPECTED: dict[str, list[dict]] = json.loads((CORPUS / "expected.json").read_text())
FILES = sorted(p.name for p in BAD.iterdir() if p.is_file())

Key = tuple[str, str, "str | None", "str | None"]


def found_messages(path: Path) -> dict[Key, list[str]]:
    """What check_stage reports for ``path``, in the expectation's terms, with messages."""
    try:
        report = check_stage(path)
    except StageOpenError as exc:
        return {(exc.code, "error", None, None): [str(exc)]}
    out: dict[Key, list[str]] = {}
    for p in report.problems:
        out.setdefault((p.code, p.severity.value, p.prim, p.attribute), []).append(p.message)
    return out


def found(path: Path) -> set[Key]:
    return set(found_messages(path))


def expected(name: str) -> set[Key]:
    return {(e["code"], e["severity"], e["prim"], e["attribute"]) for e in EXPECTED[name]}


@pytest.mark.parametrize("name", FILES)
def test_corpus_file(name: str) -> None:
    assert name in EXPECTED, f"tests/corpus/expected.json has no entry for {name}"
    got = found_messages(BAD / name)
    assert set(got) == expected(name)
    for e in EXPECTED[name]:
        key = (e["code"], e["severity"], e["prim"], e["attribute"])
        assert any(e["message"] in m for m in got[key]), (e["message"], got[key])


def test_every_expectation_has_a_file() -> None:
    assert sorted(set(EXPECTED) - set(FILES)) == []


def test_expectations_are_well_formed_and_sorted() -> None:
    assert list(EXPECTED) == sorted(EXPECTED)
    for name, entries in EXPECTED.items():
        assert entries, f"{name}: an entry must list at least one problem"
        for e in entries:
            assert set(e) == {"code", "severity", "prim", "attribute", "message"}, name
            assert len(e["message"]) >= 20, name
            assert e["severity"] in ("error", "warning"), name


def test_every_corpus_file_has_an_error_or_warning() -> None:
    # A corpus file that checks clean would test nothing.
    assert all(EXPECTED[n] for n in FILES if n in EXPECTED)


def test_directory_is_a_file_error(tmp_path: Path) -> None:
    stage_dir = tmp_path / "scene.usda"
    stage_dir.mkdir()
    assert found(stage_dir) == {("IsADirectory", "error", None, None)}


def test_missing_file_is_a_file_error(tmp_path: Path) -> None:
    assert found(tmp_path / "nope.usda") == {("FileNotFound", "error", None, None)}
