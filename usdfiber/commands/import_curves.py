"""usdfiber import FILE -o OUT.usda: import a BCC or HAIR curve file as fiber or yarn curves.

The format is recognised by the file's first bytes ("BCC" or "HAIR"). BCC C0 curves become
cubic catmullRom curves (closed ones periodic), PL polylines and HAIR strands linear curves
(with per-point widths from a HAIR thickness array). The curves get FiberAPI from a fiber
preset (--preset, default polyester) or, with --yarn, FiberYarnAPI + FiberAPI from a
Table 3 yarn preset (its fibers from the yarn's composition unless --preset is given).
HAIR colours and transparency are not imported: the fiber's colour comes from its dye
(--dye, --depth-of-shade; see `usdfiber presets`). Notes about what was not imported are
printed on stderr. See usdfiber/importers.py for the two formats' layouts.

Units: file coordinates times --units-per-file-unit are scene units; the stage's
metersPerUnit is --meters-per-unit (default 0.001: millimetres). Widths: the file's
thickness (HAIR) else the fiber or yarn diameter; --width fiber always uses the diameter,
--width W a constant width in scene units.

Exit status: 0 written, 2 the file could not be imported or the command line is wrong.
"""
from __future__ import annotations

import argparse
import sys

from usdfiber.commands.arg_types import add_memory_budget_option, percentage, positive_float


def _width(text: str) -> float | str:
    if text == "fiber":
        return text
    return positive_float(text)


def register(sub: argparse._SubParsersAction) -> None:
    from usdfiber.cli import one_line_errors

    p = sub.add_parser(
        "import",
        help="import a BCC or HAIR curve file as fiber or yarn curves",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("file", metavar="FILE", help="a .bcc or .hair file")
    p.add_argument("-o", "--output", required=True, metavar="OUT",
                   help="USD file to write (.usda, .usdc or .usd; overwritten)")
    p.add_argument("--preset", default=None, metavar="FIBER",
                   help="fiber preset (default polyester; with --yarn: the yarn's fibers)")
    p.add_argument("--yarn", default=None, metavar="YARN",
                   help='yarn preset, e.g. "CNe 50": the curves are yarn centre lines')
    p.add_argument("--units-per-file-unit", type=positive_float, default=1.0, metavar="X",
                   help="scene units per file unit (default 1)")
    p.add_argument("--meters-per-unit", type=positive_float, default=0.001, metavar="M",
                   help="the stage's metersPerUnit (default 0.001)")
    p.add_argument("--width", type=_width, default=None, metavar="W|fiber",
                   help="constant curve width in scene units, or 'fiber' for the fiber/yarn "
                        "diameter (default: the file's thickness, else the diameter)")
    p.add_argument("--dye", default=None, metavar="NAME", help="dye preset or colour")
    p.add_argument("--depth-of-shade", type=percentage, default=None, metavar="PERCENT",
                   help="dye depth of shade in percent on weight of fiber")
    p.add_argument("--root", default=None, metavar="NAME",
                   help="name of the default prim (default: the file's name)")
    add_memory_budget_option(p)
    p.set_defaults(func=run)
    one_line_errors(p)


def run(args: argparse.Namespace) -> int:
    from pxr import Sdf

    from usdfiber.errors import PrimError
    from usdfiber.cli import UsageError
    from usdfiber.importers import UNSET, CurveFileError, check_file_budget, read_curves, write_curves
    from usdfiber.memory_budget import MemoryBudget

    if args.root is not None and not Sdf.Path.IsValidIdentifier(args.root):
        raise UsageError(f"--root must be a valid prim name, got {args.root!r}")
    budget = MemoryBudget.resolve(args.memory_budget)
    check_file_budget(args.file, budget)
    try:
        data = read_curves(args.file)
    except CurveFileError as exc:
        raise UsageError(str(exc)) from None
    try:
        out = write_curves(
            data, args.output, preset=UNSET if args.preset is None else args.preset,
            yarn=args.yarn, units_per_file_unit=args.units_per_file_unit,
            meters_per_unit=args.meters_per_unit, width=args.width, dye=args.dye,
            depth_of_shade=args.depth_of_shade, root=args.root, memory_budget=budget)
    except (PrimError, ValueError) as exc:  # PrimError: file, prim, attribute and what was expected
        raise UsageError(str(exc)) from None
    except OSError as exc:
        raise UsageError(f"{args.output}: cannot write: {exc.strerror or exc}") from None
    for note in data.notes:
        print(f"usdfiber: note: {note}", file=sys.stderr)
    print(f"wrote {out}: {data.description}")
    return 0
