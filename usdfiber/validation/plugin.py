"""The usdFiber UsdValidation plugin: every registered prim check as validator ``usdFiber:<name>``.

USD loads this module through ``import usdFiber`` (see :mod:`usdfiber.validation`); importing
it imports every check module of the package and registers one prim validator per check.

A check returns :class:`~.problems.Problem` objects; the validator turns each into a
``UsdValidation.ValidationError``:

- name: the problem code; type: ``Error`` or ``Warn`` from the severity;
- one site: the stage, the prim path (or the property path when the problem names an
  attribute) and the layer holding the strongest opinion when known;
- message: ``"<code>: <text>"``; ``" @t=<time>"`` follows the code for a time-sampled
  value; ``" <prim path>"`` and ``" .<attribute>"`` follow when the prim or attribute does
  not exist on the stage (a site can only name an existing object).
  :func:`decode_message` reads it back.

A check that raises is reported as the error ``CheckFailed`` on the prim (with the
exception), instead of vanishing into a USD diagnostic.

``python -m usdfiber.validation.plugin`` rewrites ``plugInfo.json`` from the registry.
"""
from __future__ import annotations

import importlib
import json
import pkgutil
import re
import sys
from pathlib import Path
from typing import Any

from pxr import Sdf, UsdValidation

from usdfiber.validation import KEYWORD, PLUGIN_NAME, TimeSelection, thread_state
from usdfiber.validation.problems import CHECKS, PrimCheck, Problem, Severity

PLUGIN_INFO = Path(__file__).resolve().parent / "plugInfo.json"
# Infrastructure modules of the package; every other module may register checks.
_NOT_CHECKS = {"plugin", "runner", "problems"}
_MESSAGE = re.compile(
    r"(?P<code>[A-Za-z0-9_]+)(?: @t=(?P<time>[^ :]+))?(?: <(?P<prim>[^>]*)>)?"
    r"(?: \.(?P<attr>[^ ]+))?: (?P<text>.*)", re.S)


def validator_name(check_name: str) -> str:
    """USD's name of the validator running check ``check_name``."""
    return f"{PLUGIN_NAME}:{check_name}"


def load_check_modules() -> list[str]:
    """Import every check module of the package (so their ``@prim_check`` run); names."""
    pkg = sys.modules["usdfiber.validation"]
    names = sorted(
        m.name for m in pkgutil.iter_modules(pkg.__path__)
        if not m.ispkg and not m.name.startswith("_") and m.name not in _NOT_CHECKS
    )
    for name in names:
        importlib.import_module(f"usdfiber.validation.{name}")
    return names


# --- Problem <-> ValidationError -------------------------------------------------------

def encode_message(problem: Problem, prim_in_message: bool = False,
                   attribute_in_message: bool = False) -> str:
    """The ValidationError message of ``problem``: its code, time and text."""
    head = problem.code
    if problem.time is not None:
        head += f" @t={problem.time!r}"
    if prim_in_message:
        head += f" <{problem.prim}>"
    if attribute_in_message and problem.attribute:
        head += f" .{problem.attribute}"
    return f"{head}: {problem.message}"


def decode_message(message: str) -> dict[str, Any]:
    """code, time, prim, attribute (None when not in the message) and text of a message
    written by :func:`encode_message`."""
    m = _MESSAGE.fullmatch(message)
    if not m:
        return {"code": None, "time": None, "prim": None, "attribute": None, "text": message}
    t = m.group("time")
    return {"code": m.group("code"), "time": float(t) if t is not None else None,
            "prim": m.group("prim"), "attribute": m.group("attr"), "text": m.group("text")}


def to_validation_error(problem: Problem, stage) -> UsdValidation.ValidationError:
    """``problem`` as a USD validation error sited on ``stage``."""
    path = Sdf.Path(problem.prim)
    prim = stage.GetPrimAtPath(path)
    prim_in_message = attr_in_message = False
    if not prim:
        prim_in_message, path = True, Sdf.Path.absoluteRootPath
    if problem.attribute:
        if prim and prim.GetProperty(problem.attribute):
            path = path.AppendProperty(problem.attribute)
        else:
            attr_in_message = True
    layer = Sdf.Layer.Find(problem.layer) if problem.layer else None
    site = (UsdValidation.ValidationErrorSite(stage, path, layer) if layer
            else UsdValidation.ValidationErrorSite(stage, path))
    kind = (UsdValidation.ValidationErrorType.Error if problem.severity == Severity.ERROR
            else UsdValidation.ValidationErrorType.Warn)
    return UsdValidation.ValidationError(
        problem.code, kind, [site], encode_message(problem, prim_in_message, attr_in_message))


def from_validation_error(error: UsdValidation.ValidationError) -> Problem:
    """The :class:`Problem` a usdFiber validation error carries."""
    info = decode_message(error.GetMessage())
    prim, attribute, layer = info["prim"], info["attribute"], None
    for site in error.GetSites()[:1]:
        if site.IsProperty():
            prop = site.GetProperty()
            prim = prim or str(prop.GetPrimPath())
            attribute = attribute or prop.GetName()
        elif site.IsPrim():
            prim = prim or str(site.GetPrim().GetPath())
        lay = site.GetLayer()
        layer = lay.identifier if lay else None
    severity = (Severity.ERROR if error.GetType() == UsdValidation.ValidationErrorType.Error
                else Severity.WARNING)
    return Problem(info["code"] or str(error.GetName()), severity, prim or "/", attribute,
                   info["text"], layer, info["time"])


_TF_QUOTED = re.compile(r"Error in '[^']*'[^:]*: '(?P<msg>[^\n]*)'")


def one_line_reason(exc: BaseException, limit: int = 300) -> str:
    """``exc`` as one short line: the innermost message of a USD (Tf) error, else
    ``Type: text`` with whitespace collapsed."""
    text = str(exc)
    quoted = [m.group("msg").strip() for m in _TF_QUOTED.finditer(text)]
    reason = quoted[-1] if quoted else f"{type(exc).__name__}: {text}"
    reason = " ".join(reason.split())
    return reason if len(reason) <= limit else reason[:limit - 3] + "..."


def _selection(time_range) -> TimeSelection:
    iv = time_range.GetInterval()
    return TimeSelection(float(iv.min), float(iv.max), bool(time_range.IncludesTimeCodeDefault()))


class _LazySelection:
    """A time range read only when a check asks (most attributes have no samples)."""

    __slots__ = ("_range", "_sel")

    def __init__(self, time_range) -> None:
        self._range = time_range
        self._sel: TimeSelection | None = None

    def get(self) -> TimeSelection:
        if self._sel is None:
            self._sel = _selection(self._range)
        return self._sel


def _make_task(check: PrimCheck):
    fn = check.fn
    local = thread_state

    def task(prim, time_range) -> list:
        # Class prims are templates, not fiber geometry: what they hold is checked on the
        # prims that inherit it. (USD's default predicate already skips them; a caller
        # passing prims explicitly may not.)
        if prim.IsAbstract():
            return []
        # Inlined selected_times(): this runs once per prim and validator.
        previous = getattr(local, "times", None)
        local.times = _LazySelection(time_range)
        try:
            problems = fn(prim)
            if not isinstance(problems, list):
                problems = list(problems)
        except Exception as exc:  # a bug in a check must not vanish into a Tf error
            problems = [Problem(
                "CheckFailed", Severity.ERROR, str(prim.GetPath()), None,
                f"check {check.name!r} failed on this prim: {one_line_reason(exc)}")]
        finally:
            if previous is None:
                del local.times
            else:
                local.times = previous
        if not problems:
            return []
        stage = prim.GetStage()
        return [to_validation_error(p, stage) for p in problems]

    task.__name__ = f"usdFiber_{check.name}"
    task.__doc__ = check.doc
    return task


def register_validators() -> list[str]:
    """Register every check with USD's validation registry; idempotent. Validator names.

    Checks declared in plugInfo.json are registered as plugin validators. A check that is
    not (plugInfo.json is stale, or USD's validation registry was created before the
    plugin was registered) is registered with explicit metadata, so that it still runs
    under the ``usdFiber`` keyword.
    """
    load_check_modules()
    registry = UsdValidation.ValidationRegistry()
    names = []
    for check in sorted(CHECKS.values(), key=lambda c: c.name):
        name = validator_name(check.name)
        names.append(name)
        if registry.HasValidator(name):
            continue
        task = _make_task(check)
        if registry.GetValidatorMetadata(name) is not None:
            registry.RegisterPluginPrimValidator(name, task)
        else:
            metadata = UsdValidation.ValidatorMetadata(
                name=name, doc=check.doc, keywords=list(check.keywords), isTimeDependent=True)
            registry.RegisterPrimValidator(metadata, task)
    return names


# --- plugInfo.json ----------------------------------------------------------------------

def plugin_info() -> dict[str, Any]:
    """The plugInfo.json document declaring every registered check."""
    load_check_modules()
    validators = {
        c.name: {"doc": c.doc, "keywords": list(c.keywords), "isTimeDependent": True}
        for c in sorted(CHECKS.values(), key=lambda c: c.name)
    }
    return {"Plugins": [{"Type": "python", "Name": PLUGIN_NAME,
                         "Info": {"Validators": validators}}]}


def write_plugin_info(path: Path = PLUGIN_INFO) -> Path:
    """Rewrite plugInfo.json from the registry (run after adding or renaming a check)."""
    text = json.dumps(plugin_info(), indent=4, sort_keys=False) + "\n"
    path.write_text(text, encoding="utf-8")
    return path


def declared_validators(path: Path = PLUGIN_INFO) -> dict[str, dict[str, Any]]:
    """The validators plugInfo.json declares, by check name."""
    doc = json.loads(path.read_text(encoding="utf-8"))
    (plugin,) = [p for p in doc["Plugins"] if p.get("Name") == PLUGIN_NAME]
    return dict(plugin["Info"]["Validators"])


if __name__ == "__main__":
    from usdfiber.validation import plugin as _self  # the importable copy, not __main__

    print(f"wrote {_self.write_plugin_info()}")
else:
    register_validators()

__all__ = [
    "KEYWORD", "PLUGIN_INFO", "decode_message", "declared_validators", "encode_message",
    "from_validation_error",
    "load_check_modules", "one_line_reason", "plugin_info", "register_validators", "to_validation_error",
    "validator_name", "write_plugin_info",
]
