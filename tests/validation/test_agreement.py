"""`usdfiber check` and the renderer agree on every stage of tests/corpus/agreement/.

The invariant: a stage that check passes (no errors) is translated by the renderer, and a
stage the renderer cannot translate has check errors (which is why `usdfiber render`, whose
first step is check, refuses it with check's messages). Every warning the translation gives
about a prim (skipped, approximated) is a check warning on that prim too. Each stage's
expected verdict and codes (tests/corpus/agreement/expected.json, written with the stages by
tests/corpus/make_agreement_corpus.py) pin what check says.

The translation is the render's own (`translate_stage`), at 8x8 pixels and 1 sample, with
tables baked once per fiber at a tiny resolution into a temporary cache.
"""
from __future__ import annotations

import json
import re
import warnings
from pathlib import Path

import pytest

import usdfiber  # noqa: F401  (registers the schemas before any stage exists)
from usdfiber.bake.cache import TableCache
from usdfiber.bake.settings import BakeSettings
from usdfiber.stage_io import open_stage
from usdfiber.translators.mitsuba.errors import TranslateError
from usdfiber.translators.mitsuba.scene import SceneOptions, translate_stage
from usdfiber.translators.mitsuba.yarn_far_field import YarnBakeSettings
from usdfiber.validation.problems import Severity
from usdfiber.validation.runner import check_stage

CORPUS = Path(__file__).resolve().parents[1] / "corpus" / "agreement"
EXPECTED: dict[str, dict] = json.loads((CORPUS / "expected.json").read_text())
FILES = sorted(p.name for p in CORPUS.glob("*.usda"))
# "<prim path>: ..." or "<instancer path>[3]<prototype prim path>: ..."
_PRIM_WARNING = re.compile(r"^(?P<path>/[^\s:\[]*)(?:\[\d+\](?P<proto>/[^\s:]*))?: ")


@pytest.fixture(scope="module")
def options(tmp_path_factory) -> SceneOptions:
    cache = TableCache(tmp_path_factory.mktemp("agreement_tables"))
    return SceneOptions(resolution=(8, 8), spp=1, cache=cache,
                        bake=BakeSettings(resolution_deg=30, photons=200, batches=2),
                        yarn_bake=YarnBakeSettings(resolution_deg=30, photons=200, realizations=1))


def test_corpus_is_large_and_described() -> None:
    assert len(FILES) >= 100
    assert set(FILES) == set(EXPECTED), "regenerate: python tests/corpus/make_agreement_corpus.py"


def _translate(path: Path, options: SceneOptions) -> tuple[bool, list[str], str]:
    stage = open_stage(path)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # Python warnings of the baker are not the render's report
        try:
            tr = translate_stage(stage, options)
        except (TranslateError, ValueError) as exc:
            return False, [], str(exc)
    return True, tr.warnings, ""


@pytest.mark.parametrize("name", FILES)
def test_check_and_render_agree(name: str, options: SceneOptions) -> None:
    path = CORPUS / name
    report = check_stage(path)
    want = EXPECTED[name]
    codes = {p.code for p in report.problems}
    errors = [p for p in report.problems if p.severity == Severity.ERROR]
    assert all("\n" not in p.message for p in report.problems)
    assert "CheckFailed" not in codes, [p.message for p in report.problems]
    assert set(want["codes"]) <= codes, (want["codes"], [(p.code, p.message) for p in report.problems])
    assert (not errors) == (want["check"] == "ok"), [(p.code, p.message) for p in errors]

    translated, render_warnings, refusal = _translate(path, options)
    if not errors:
        assert translated, f"check passes {name} but the renderer refuses it: {refusal}"
    else:
        # The renderer may be lenient where check is strict (a value beyond its documented
        # range still translates); render refuses it at its validation step. What must not
        # happen is the reverse, asserted above.
        assert translated or refusal
    if not translated:
        assert "\n" not in refusal and refusal
        return
    warned = {p.prim for p in report.problems if p.severity == Severity.WARNING}
    for w in render_warnings:
        m = _PRIM_WARNING.match(w)
        if not m:
            continue  # stage-level notes: default camera, default lights
        prim = m.group("proto") or m.group("path")
        assert prim in warned, f"the renderer warns {w!r} but check has no warning on {prim}"
