"""usdfiber check STAGE... [--json] [--warnings-as-errors] [--time T] [--all-variants]: validate stages.

Runs every usdFiber validator (USD validators with the keyword "usdFiber": fiber, yarn and
profile values, curve topology and widths, baked tables) and the stage's composition
(missing sublayers, references, payloads count as errors).

--all-variants also checks every variant that is not selected (usdchecker's habit): each
variant of each variant set is selected in turn, in memory, and the prim's subtree validated
again; variant sets are varied one at a time, not in combination. Cost: one validation of the
prim's subtree per unselected variant (a stage with 3 sets of 4 variants on one prim: 9 more).

Text output groups problems by stage, errors before warnings, one per line:
``<prim>[.<attribute>][ @ <time>]: <code>: <message>  [<layer>]``, then a summary line.

--json prints one document for pipelines:
  {"format": "usdfiber-check", "version": 1,
   "stages": [{"stage", "error", "error_code", "errors", "warnings",
               "problems": [{"code", "severity", "layer", "prim", "attribute",
                             "time", "message"}]}],
   "summary": {"stages", "errors", "warnings", "unreadable"}}
("error" is the one-line reason a file could not be opened, else null, and "error_code"
its kind: FileNotFound, IsADirectory, PermissionDenied, Unreadable, EmptyFile,
UnknownFormat, SyntaxError, NotUsd, OpenFailed; "time" is null for default values.)

Exit status: 0 no errors (warnings allowed), 1 at least one error (or warning with
--warnings-as-errors), 2 a file could not be opened or the command line is wrong.
"""
from __future__ import annotations

import argparse
import math
import sys


def _time(text: str) -> float:
    try:
        t = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a time code: {text!r}") from None
    if not math.isfinite(t):
        raise argparse.ArgumentTypeError(f"not a finite time code: {text!r}")
    return t


def register(sub: argparse._SubParsersAction) -> None:
    from usdfiber.cli import one_line_errors

    p = sub.add_parser(
        "check",
        help="validate fiber stages (values, topology, tables, composition)",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("stages", nargs="+", metavar="STAGE", help="USD files to check")
    p.add_argument("--json", action="store_true", help="print a JSON document (see above)")
    p.add_argument("--warnings-as-errors", action="store_true",
                   help="exit 1 when there are warnings")
    p.add_argument("--time", type=_time, default=None, metavar="T",
                   help="check values at time code T only (default: the default value "
                        "and every authored time sample)")
    p.add_argument("--all-variants", action="store_true",
                   help="also check every variant that is not selected, one variant set at a "
                        "time (costs one validation of the prim's subtree per variant)")
    p.set_defaults(func=run)
    one_line_errors(p)


def run(args: argparse.Namespace) -> int:
    from pxr import Tf

    from usdfiber.stage_io import StageOpenError
    from usdfiber.validation.runner import CheckReport, check_stage, reports_to_json, summary

    reports: list[CheckReport] = []
    for path in args.stages:
        try:
            reports.append(check_stage(path, time=args.time, all_variants=args.all_variants))
        except StageOpenError as exc:
            # One line on stderr in every mode; JSON also records it for pipelines.
            print(f"usdfiber: error: {exc}", file=sys.stderr)
            reports.append(CheckReport(path, error=str(exc), error_code=exc.code))
        except Tf.ErrorException as exc:  # USD failed past the open: still one line
            reason = " ".join(str(exc).split()) or "USD error"
            print(f"usdfiber: error: {path}: {reason}", file=sys.stderr)
            reports.append(CheckReport(path, error=f"{path}: {reason}", error_code="OpenFailed"))

    if args.json:
        print(reports_to_json(reports))
    else:
        for r in reports:
            if r.error is None:
                print(r.to_text())
        s = summary(reports)
        line = (f"checked {s['stages']} stage{'' if s['stages'] == 1 else 's'}: "
                f"{s['errors']} error{'' if s['errors'] == 1 else 's'}, "
                f"{s['warnings']} warning{'' if s['warnings'] == 1 else 's'}")
        if s["unreadable"]:
            line += f", {s['unreadable']} could not be opened"
        print(line)

    if any(r.error is not None for r in reports):
        return 2
    if not all(r.ok(args.warnings_as_errors) for r in reports):
        return 1
    return 0
