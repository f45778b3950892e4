"""Running the usdFiber validators on a stage and reporting what they found.

:func:`check_stage` runs every validator with the ``usdFiber`` keyword through
``UsdValidation.ValidationContext`` (the same path any USD tool takes), adds the stage's
composition errors, and returns a :class:`CheckReport`.

JSON document (``CheckReport.to_json()``, ``reports_to_json()``, ``usdfiber check --json``)::

    {
      "format": "usdfiber-check",
      "version": 1,
      "stages": [
        {
          "stage": "<path as given, or the root layer identifier>",
          "error": null | "<one line: why the file could not be opened>",
          "error_code": null | "FileNotFound" | "IsADirectory" | "PermissionDenied" |
                        "Unreadable" | "EmptyFile" | "UnknownFormat" | "SyntaxError" |
                        "NotUsd" | "OpenFailed",
          "errors": <int>, "warnings": <int>,
          "problems": [
            {"code": "ValueOutOfRange", "severity": "error" | "warning",
             "layer": "<layer identifier of the strongest opinion>" | null,
             "prim": "/World/Fibers", "attribute": "fiber:diameter" | null,
             "time": <float> | null, "message": "<what is wrong; what was expected>"}
          ]
        }
      ],
      "summary": {"stages": <int>, "errors": <int>, "warnings": <int>, "unreadable": <int>}
    }

Problems are sorted by prim, attribute, time and code; errors come before warnings.
"""
from __future__ import annotations

import json
import math
import os
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from typing import Any, Iterable, Iterator

from pxr import Usd, UsdValidation, Work

from usdfiber.errors import short_path
from usdfiber.stage_io import (captured_stderr, composition_problems, open_stage,
                               stage_metrics_problems)

from usdfiber.validation import KEYWORD
from usdfiber.validation import plugin as _plugin  # registers the validators (also without ``import usdFiber``)
from usdfiber.validation.problems import Problem, Severity

FORMAT, VERSION = "usdfiber-check", 1


def _sort_key(p: Problem) -> tuple:
    return (p.severity != Severity.ERROR, p.prim, p.attribute or "",
            -math.inf if p.time is None else p.time, p.code, p.message)


@dataclass
class CheckReport:
    """What checking one stage found."""

    stage: str
    problems: list[Problem] = field(default_factory=list)
    error: str | None = None       # why the file could not be opened (problems then empty)
    error_code: str | None = None  # StageOpenError.code

    @property
    def errors(self) -> list[Problem]:
        return [p for p in self.problems if p.severity == Severity.ERROR]

    @property
    def warnings(self) -> list[Problem]:
        return [p for p in self.problems if p.severity == Severity.WARNING]

    def ok(self, warnings_as_errors: bool = False) -> bool:
        """No error (and no warning when warnings count as errors) and the file opened."""
        return self.error is None and not self.errors and not (
            warnings_as_errors and self.warnings)

    def to_dict(self) -> dict[str, Any]:
        """This stage's entry of the JSON document (see the module docs)."""
        return {
            "stage": self.stage,
            "error": self.error,
            "error_code": self.error_code,
            "errors": len(self.errors),
            "warnings": len(self.warnings),
            "problems": [problem_to_dict(p) for p in self.problems],
        }

    def to_json(self, indent: int | None = 2) -> str:
        """A JSON document holding this one stage."""
        return reports_to_json([self], indent)

    def to_text(self) -> str:
        """Readable report: a header line, then errors and warnings, one per line."""
        if self.error is not None:
            return f"{self.stage}: cannot be checked: {self.error}"
        errs, warns = self.errors, self.warnings
        head = f"{self.stage}: {_count(len(errs), 'error')}, {_count(len(warns), 'warning')}"
        lines = [head]
        for title, group in (("errors", errs), ("warnings", warns)):
            if group:
                lines.append(f"  {title}:")
                lines.extend("    " + format_problem(p) for p in group)
        return "\n".join(lines)


def _count(n: int, noun: str) -> str:
    return f"{n} {noun}{'' if n == 1 else 's'}"


def format_problem(p: Problem) -> str:
    """One line: where (prim.attribute, time), the code, the message, the layer."""
    where = p.prim + (f".{p.attribute}" if p.attribute else "")
    if p.time is not None:
        where += f" @ {p.time:g}"
    layer = f"  [{short_path(p.layer)}]" if p.layer else ""
    return f"{where}: {p.code}: {p.message}{layer}"


def problem_to_dict(p: Problem) -> dict[str, Any]:
    """One problem of the JSON document."""
    return {"code": p.code, "severity": p.severity.value, "layer": p.layer, "prim": p.prim,
            "attribute": p.attribute, "time": p.time, "message": p.message}


def summary(reports: Iterable[CheckReport]) -> dict[str, int]:
    reports = list(reports)
    return {
        "stages": len(reports),
        "errors": sum(len(r.errors) for r in reports),
        "warnings": sum(len(r.warnings) for r in reports),
        "unreadable": sum(r.error is not None for r in reports),
    }


def reports_to_json(reports: Iterable[CheckReport], indent: int | None = 2) -> str:
    """The JSON document of several stages (see the module docs)."""
    reports = list(reports)
    doc = {"format": FORMAT, "version": VERSION,
           "stages": [r.to_dict() for r in reports], "summary": summary(reports)}
    return json.dumps(doc, indent=indent)


def validation_context() -> UsdValidation.ValidationContext:
    """A context holding every usdFiber validator (and only those)."""
    _plugin.register_validators()  # no-op once registered; picks up late-imported checks
    # includeAllAncestors=False: our validators declare no schema types, and ancestors
    # would pull in validators of other plugins.
    return UsdValidation.ValidationContext(keywords=[KEYWORD], includeAllAncestors=False)


@contextmanager
def _one_worker() -> Iterator[None]:
    """Run USD's validation tasks on one thread.

    Every usdFiber validator is Python: worker threads would only take turns on the GIL,
    and handing it over between them costs more than it gains (measured on 2 cores, all
    validators, 20k fiber prims: 5.7-6.4 s CPU on one worker, 7.5-8.1 s on two).
    """
    previous = Work.GetConcurrencyLimit()
    Work.SetConcurrencyLimit(1)
    try:
        yield
    finally:
        Work.SetConcurrencyLimit(previous)


def _time_range(time: float | None):
    return (UsdValidation.ValidationTimeRange() if time is None
            else UsdValidation.ValidationTimeRange(Usd.TimeCode(float(time))))


def variant_problems(stage: Usd.Stage, ctx: UsdValidation.ValidationContext,
                     time: float | None = None) -> list[Problem]:
    """The problems of every variant that is not selected (``usdfiber check --all-variants``).

    Each variant of each variant set is selected in turn, in the session layer (the stage's
    files are not touched; the selection is restored after), and the prim's subtree is
    validated; a problem is reported with the variant set and the variant in its message.
    Variant sets are varied one at a time, not in every combination: the cost is one
    validation of the prim's subtree per variant that is not selected.
    """
    predicate = Usd.TraverseInstanceProxies(Usd.PrimDefaultPredicate)
    todo = []
    for prim in stage.Traverse():
        if not prim.HasVariantSets():
            continue
        sets = prim.GetVariantSets()
        for name in sets.GetNames():
            vset = sets.GetVariantSet(name)
            selected = vset.GetVariantSelection()
            todo.extend((prim.GetPath(), name, v) for v in vset.GetVariantNames() if v != selected)
    out: list[Problem] = []
    session = stage.GetSessionLayer()
    for path, name, variant in todo:
        with Usd.EditContext(stage, session):
            stage.GetPrimAtPath(path).GetVariantSets().GetVariantSet(name).SetVariantSelection(variant)
        try:
            root = stage.GetPrimAtPath(path)
            prims = list(Usd.PrimRange(root, predicate)) if root else []
            problems = composition_problems(stage)
            problems += [_plugin.from_validation_error(e)
                         for e in ctx.Validate(prims, _time_range(time))]
        finally:
            with Usd.EditContext(stage, session):
                stage.GetPrimAtPath(path).GetVariantSets().GetVariantSet(name).ClearVariantSelection()
        where = f" (with variant set {name!r} of {path} = {variant!r})"
        out.extend(replace(p, message=p.message + where) for p in problems)
    return out


#: Entry-point group of the renderer bridges' checks: each names a function
#: ``(stage, time) -> list[Problem]`` that reports what that bridge's translation would refuse
#: (cameras, lights, meshes, ...), so that ``check`` and ``render`` agree. The core never imports
#: the bridges; it loads these.
CHECK_GROUP = "usdfiber.checks"


def bridge_problems(stage: Usd.Stage, time: float | None = None) -> list[Problem]:
    """The problems the installed renderer bridges report (:data:`CHECK_GROUP`); a bridge that
    cannot be imported (its renderer is not installed) reports nothing, one whose checks fail
    (its renderer cannot run here) a warning, ``RendererCheckSkipped``."""
    from importlib.metadata import entry_points

    problems: list[Problem] = []
    for ep in sorted(entry_points(group=CHECK_GROUP), key=lambda e: e.name):
        try:
            fn = ep.load()
        except ImportError:
            continue
        try:
            problems.extend(fn(stage, time))
        except Exception as exc:
            # The renderer cannot run here (no LLVM for Mitsuba, say) or the bridge failed: one
            # line, and a warning only, so that checking works on machines that do not render.
            problems.append(Problem("RendererCheckSkipped", Severity.WARNING, "/", None,
                                    f"the {ep.name} renderer's checks could not run: "
                                    f"{_plugin.one_line_reason(exc)}; expected a working renderer "
                                    f"(`usdfiber render` will fail the same way)"))
    return problems


def check_stage(stage_or_path: Usd.Stage | str | os.PathLike[str], *,
                time: float | None = None, all_variants: bool = False,
                bridges: bool = True) -> CheckReport:
    """Check one stage with every usdFiber validator.

    ``time``: check values at that time code only (``usdfiber check --time``); by default
    every default value and every authored time sample. ``all_variants``: also check every
    variant that is not selected (:func:`variant_problems`). ``bridges``: also what the
    renderer bridges would refuse (:func:`bridge_problems`, at ``time`` or the time a render
    picks; a render leaves them to its own translation, which refuses the same). A path that
    cannot be opened raises :class:`usdfiber.stage_io.StageOpenError`.
    """
    if isinstance(stage_or_path, Usd.Stage):
        stage, name = stage_or_path, stage_or_path.GetRootLayer().identifier
    else:
        name = os.fspath(stage_or_path)
        stage = open_stage(name)
    problems = composition_problems(stage) + stage_metrics_problems(stage)
    ctx = validation_context()
    predicate = Usd.TraverseInstanceProxies(Usd.PrimDefaultPredicate)
    with captured_stderr(), _one_worker():  # USD's diagnostics: the report is the output
        if time is None:
            errors = ctx.Validate(stage, predicate)
        else:
            errors = ctx.Validate(stage, predicate,
                                  UsdValidation.ValidationTimeRange(Usd.TimeCode(float(time))))
    problems.extend(_plugin.from_validation_error(e) for e in errors)
    if bridges:
        with captured_stderr():
            problems.extend(bridge_problems(stage, time))
    if all_variants:
        seen = {(p.code, p.prim, p.attribute, p.message) for p in problems}
        with captured_stderr(), _one_worker():
            problems.extend(p for p in variant_problems(stage, ctx, time)
                            if (p.code, p.prim, p.attribute, p.message.rsplit(" (with variant set", 1)[0])
                            not in seen)
    return CheckReport(name, sorted(set(problems), key=_sort_key))


__all__ = ["CHECK_GROUP", "CheckReport", "bridge_problems", "check_stage", "format_problem", "problem_to_dict",
           "reports_to_json", "summary", "validation_context", "variant_problems"]
