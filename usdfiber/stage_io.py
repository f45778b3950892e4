"""Opening stages with one clear line for every way a file can be unusable.

:func:`open_stage` raises :class:`StageOpenError` (a ``ValueError``) whose message is one
line naming the file and the reason: missing, a directory, unreadable, empty, an unknown
format, a syntax error (with line and column), or content that is not USD.

Missing sublayers, references and payloads do not stop USD from opening a stage; it only
prints warnings. :func:`composition_problems` turns the stage's composition errors into
error :class:`~usdfiber.validation.problems.Problem` s instead, so that ``usdfiber check``
reports them as errors of the check.

USD prints diagnostics straight to the process's stderr, from its worker threads too, so
Python-level redirection cannot catch them: :func:`captured_stderr` redirects file
descriptor 2 while USD works.

:func:`stage_metrics_problems` reports a ``metersPerUnit`` or ``upAxis`` that no length or
camera can be built on; ``usdfiber check`` and the renderer refuse such stages with its
messages.
"""
from __future__ import annotations

import math
import os
import re
import sys
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

from pxr import Pcp, Sdf, Tf, Usd, UsdGeom

from usdfiber.validation.problems import Problem, Severity

USD_EXTENSIONS = ("usd", "usda", "usdc", "usdz")


class StageOpenError(ValueError):
    """A file that cannot be opened as a USD stage; the message is one line.

    ``code`` says why, for programs: ``FileNotFound``, ``IsADirectory``,
    ``PermissionDenied``, ``Unreadable``, ``EmptyFile``, ``UnknownFormat``, ``SyntaxError``,
    ``NotUsd`` (content USD cannot read) or ``OpenFailed`` (anything else).
    """

    def __init__(self, message: str, code: str = "OpenFailed", path: str | None = None) -> None:
        super().__init__(message)
        self.code = code
        self.path = path


@contextmanager
def captured_stderr() -> Iterator[list[str]]:
    """Collect what is written to file descriptor 2 (USD's diagnostics) while inside.

    The yielded list is filled with the captured lines on exit. If fd 2 cannot be
    redirected, nothing is captured.
    """
    lines: list[str] = []
    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, AttributeError, ValueError):
        yield lines
        return
    tmp = tempfile.TemporaryFile()
    try:
        os.dup2(tmp.fileno(), 2)
        try:
            yield lines
        finally:
            try:
                sys.stderr.flush()
            except (OSError, ValueError):
                pass
            os.dup2(saved, 2)
    finally:
        os.close(saved)
        tmp.seek(0)
        lines.extend(tmp.read().decode("utf-8", "replace").splitlines())
        tmp.close()


# --- open ---------------------------------------------------------------------------------

_SYNTAX = re.compile(r":(?P<line>\d+):(?P<col>\d+): (?P<msg>[^\n']*(?:'[^']*'[^\n']*)*)")
_TF_MESSAGE = re.compile(r" : '(?P<msg>.*?)'\s*(?=\n\s*Error in|\Z)", re.S)


def _tf_messages(text: str) -> list[str]:
    """The quoted messages of a Tf.ErrorException's text, innermost first."""
    return [m.group("msg").strip() for m in _TF_MESSAGE.finditer(text)]


def _describe_failure(path: Path, text: str, head: bytes) -> tuple[str, str]:
    """(code, reason) for a Tf error raised while USD opened ``path``."""
    ext = path.suffix.lower().lstrip(".")
    m = _SYNTAX.search(text)
    if m:
        msg = m.group("msg").strip().rstrip(".")
        return "SyntaxError", f"syntax error at line {m.group('line')}, column {m.group('col')}: {msg}"
    messages = [msg for msg in _tf_messages(text) if not msg.startswith("Failed to open layer")]
    looks_text = head.startswith(b"#usda")
    looks_crate = head.startswith(b"PXR-USDC")
    looks_zip = head.startswith(b"PK\x03\x04")
    if ext == "usda" and not looks_text:
        kind = "binary data" if _is_binary(head) else "text"
        return "NotUsd", f"not a text USD (usda) file: it does not start with '#usda 1.0' ({kind})"
    if ext == "usdc" or (ext == "usd" and looks_crate):
        reason = f": {messages[0]}" if messages else ""
        return "NotUsd", f"not a valid binary USD (usdc) file{reason}"
    if ext == "usdz" or looks_zip:
        reason = f": {messages[0]}" if messages else ""
        return "NotUsd", f"not a valid USDZ package{reason}"
    if ext == "usd" and not (looks_text or looks_crate):
        return "NotUsd", "not a USD file: neither text (#usda) nor binary (usdc) USD content"
    if messages:
        return "OpenFailed", messages[0]
    return "OpenFailed", "USD could not open it"


def _is_binary(head: bytes) -> bool:
    return b"\0" in head or any(b < 9 or 13 < b < 32 for b in head)


def open_stage(path: str | os.PathLike[str]) -> Usd.Stage:
    """Open ``path`` as a USD stage; :class:`StageOpenError` with one line if it can't be.

    USD's own diagnostics during the open are swallowed (composition problems remain
    available from :func:`composition_problems`).
    """
    name = os.fspath(path)
    p = Path(name)

    def fail(code: str, reason: str) -> StageOpenError:
        return StageOpenError(f"{name}: {reason}", code, name)

    if not p.exists():
        raise fail("FileNotFound", "broken symbolic link" if p.is_symlink() else "no such file")
    if p.is_dir():
        raise fail("IsADirectory", "is a directory; expected a USD file (."
                   + ", .".join(USD_EXTENSIONS) + ")")
    try:
        with open(p, "rb") as fh:
            head = fh.read(64)
    except PermissionError:
        raise fail("PermissionDenied", "permission denied; cannot read the file") from None
    except OSError as exc:
        raise fail("Unreadable", f"cannot read the file: {exc.strerror or exc}") from None
    if not head:
        raise fail("EmptyFile", "empty file; expected a USD layer")
    ext = p.suffix.lower().lstrip(".")
    if not ext or Sdf.FileFormat.FindByExtension(ext) is None:
        shown = f"'.{ext}'" if ext else "no extension"
        raise fail("UnknownFormat", f"unknown file format ({shown}); expected ."
                   + ", .".join(USD_EXTENSIONS))
    with captured_stderr():
        try:
            stage = Usd.Stage.Open(name)
        except Tf.ErrorException as exc:
            raise fail(*_describe_failure(p, str(exc), head)) from None
        except Exception as exc:  # anything else from USD: still one line
            raise fail("OpenFailed", f"{type(exc).__name__}: {exc}".splitlines()[0]) from None
    if not stage:
        raise fail("OpenFailed", "USD could not open it")
    return stage


# --- composition errors -------------------------------------------------------------------

def _composition_code(err) -> str:
    et = err.errorType
    if et == Pcp.ErrorType_InvalidSublayerPath:
        # USD appends the parse error after " -- " when the sublayer exists but is broken.
        return "InvalidSublayer" if " -- " in str(err) else "MissingSublayer"
    if et in (Pcp.ErrorType_InvalidAssetPath, Pcp.ErrorType_MutedAssetPath):
        text = str(err)
        if "for payload" in text:
            return "MissingPayload"
        if "for reference" in text:
            return "MissingReference"
        return "MissingAsset"
    return "CompositionError"


def composition_problems(stage: Usd.Stage) -> list[Problem]:
    """The stage's composition errors (missing sublayers, references, ...) as errors."""
    out = []
    for err in stage.GetCompositionErrors():
        site = err.rootSite
        try:
            layer = site.layerStack.rootLayer.identifier  # a Pcp.LayerStackIdentifier
        except Exception:
            layer = None
        prim = str(site.path) if site.path and not site.path.isEmpty else "/"
        text = " ".join(str(err).split()).removesuffix(" skipping.").rstrip(" .;")
        out.append(Problem(_composition_code(err), Severity.ERROR, prim, None,
                           f"{text}; expected every sublayer, reference and payload to "
                           f"resolve to a readable layer", layer))
    return out


# --- stage metrics ------------------------------------------------------------------------

def _metric_layer(stage: Usd.Stage, key: str) -> Sdf.Layer:
    """The layer whose opinion of the stage metadatum ``key`` wins (session, else root)."""
    session = stage.GetSessionLayer()
    return session if session and session.pseudoRoot.HasInfo(key) else stage.GetRootLayer()


def stage_metrics_problems(stage: Usd.Stage) -> list[Problem]:
    """Errors in the stage's ``metersPerUnit`` and ``upAxis``, each naming the file.

    Every length of a fiber stage is converted through metersPerUnit (widths against the
    fiber diameter, the fibers' absorption), so it must be a finite number > 0; the
    renderer's default camera and lights stand on upAxis, which USD defines as "Y" or "Z".
    Unauthored values take USD's fallbacks (0.01 and the fallback up axis), which are valid.
    """
    out: list[Problem] = []
    mpu = UsdGeom.GetStageMetersPerUnit(stage)
    if not (isinstance(mpu, (int, float)) and math.isfinite(mpu) and mpu > 0):
        layer = _metric_layer(stage, "metersPerUnit")
        out.append(Problem(
            "MetersPerUnitInvalid", Severity.ERROR, "/", None,
            f"{_layer_name(layer)}: metersPerUnit = {mpu:g}; expected a finite number > 0 "
            f"(metres per scene unit, e.g. 0.01 for centimetres)", layer.identifier))
    up = str(UsdGeom.GetStageUpAxis(stage))
    if up not in ("Y", "Z"):
        layer = _metric_layer(stage, "upAxis")
        out.append(Problem(
            "UpAxisInvalid", Severity.ERROR, "/", None,
            f'{_layer_name(layer)}: upAxis = "{up}"; expected "Y" or "Z"', layer.identifier))
    return out


def animated_only(attr: Usd.Attribute) -> bool:
    """Whether ``attr`` has time samples but no value at the default time code (USD does not
    look at samples there, so a render at the default time sees nothing)."""
    return bool(attr) and attr.GetNumTimeSamples() > 0 and attr.Get(Usd.TimeCode.Default()) is None


def default_render_time(stage: Usd.Stage) -> tuple[float, str] | None:
    """The time code to render when none is asked for, and the note saying so; None when the
    default time code shows the stage.

    A stage whose geometry is animated only (points with time samples and no default value,
    as animation caches are written) draws nothing at the default time. Then the stage's
    startTimeCode is rendered when authored, else the earliest such sample.
    """
    first: float | None = None
    where = ""
    for prim in Usd.PrimRange.Stage(stage, Usd.TraverseInstanceProxies(Usd.PrimDefaultPredicate)):
        if not prim.IsA(UsdGeom.PointBased):
            continue
        attr = UsdGeom.PointBased(prim).GetPointsAttr()
        if animated_only(attr):
            t = float(attr.GetTimeSamples()[0])
            if first is None or t < first:
                first, where = t, str(prim.GetPath())
    if first is None:
        return None
    if stage.HasAuthoredTimeCodeRange():
        t, why = float(stage.GetStartTimeCode()), "the stage's startTimeCode"
    else:
        t, why = first, f"the first time sample of {where}.points"
    return t, (f"no frame given and {where}.points has time samples only (nothing to draw at the "
               f"default time): rendering frame {t:g}, {why}; pass a frame to choose another")


def _layer_name(layer: Sdf.Layer) -> str:
    from usdfiber.errors import short_path

    return short_path(layer.realPath) if layer.realPath else layer.identifier


__all__ = ["StageOpenError", "USD_EXTENSIONS", "captured_stderr", "composition_problems",
           "animated_only", "default_render_time", "open_stage", "stage_metrics_problems"]
