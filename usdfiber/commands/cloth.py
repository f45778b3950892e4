"""usdfiber cloth PATTERN -o OUT.usda: procedural knitted and woven yarn centre lines.

Patterns: stockinette (plain knit), garter (knit and purl rows), plain (plain weave),
satin (warp-faced satin, floats over --floats wefts, default 4: the 5-harness satin).
Knits take --rows and --loops (loops per row), weaves --warps and --wefts. The yarns are
cubic B-spline centre lines with FiberYarnAPI + FiberAPI from a Table 3 yarn preset
(--yarn, default "CNe 50"; --fiber-kind overrides its fiber preset), widths equal to the
yarn's nominal diameter. Units: millimetres (metersPerUnit 0.001), Y up, the fabric in the
xy plane facing +z. The default prim is /Cloth with children Rows (knits) or Warp and
Weft (weaves). Geometry details: usdfiber/cloth.py.

Generation refuses parameters for which yarns would pass through each other (centre lines
of different yarns closer than --min-clearance yarn diameters, default 0.8; 0 disables),
and a cloth whose generation and writing would not fit the memory budget (about 18-24 bytes
per control point to generate, 76 while .usda text is written, 13 for .usdc): the 2,500 x
2,500-yarn shirt panel (50 M control points) takes about 0.84 GiB to generate and write as
.usdc, 3.5 GiB as .usda.

Exit status: 0 written, 2 bad parameters or the command line is wrong.
"""
from __future__ import annotations

import argparse

from usdfiber.commands.arg_types import add_memory_budget_option, finite_float, percentage, positive_int

KNITS = ("stockinette", "garter")
WEAVES = ("plain", "satin")


def register(sub: argparse._SubParsersAction) -> None:
    from usdfiber.cli import one_line_errors

    p = sub.add_parser(
        "cloth",
        help="generate knitted or woven yarn centre lines (stockinette, garter, plain, satin)",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("pattern", choices=KNITS + WEAVES, help="the fabric structure")
    p.add_argument("-o", "--output", required=True, metavar="OUT",
                   help="USD file to write (.usda, .usdc or .usd; overwritten)")
    p.add_argument("--rows", type=positive_int, default=None, metavar="N", help="knits: rows (default 8)")
    p.add_argument("--loops", type=positive_int, default=None, metavar="N",
                   help="knits: loops per row (default 8)")
    p.add_argument("--loop-size", type=finite_float, default=None, metavar="X",
                   help="knits: loop size factor in the fabric plane (default 1)")
    p.add_argument("--spacing-scale", type=finite_float, default=None, metavar="X",
                   help="knits: row spacing factor (default 1)")
    p.add_argument("--warps", type=positive_int, default=None, metavar="N",
                   help="weaves: warp yarns (default 16 plain, 20 satin)")
    p.add_argument("--wefts", type=positive_int, default=None, metavar="N",
                   help="weaves: weft yarns (default 16 plain, 20 satin)")
    p.add_argument("--spacing", type=finite_float, default=None, metavar="MM",
                   help="weaves: distance between neighbouring yarns in mm "
                        "(default 2.5 yarn diameters)")
    p.add_argument("--crimp", type=finite_float, default=None, metavar="X",
                   help="weaves: warp/weft depth separation at crossings in yarn diameters "
                        "(default 1)")
    p.add_argument("--floats", type=positive_int, default=None, metavar="N",
                   help="satin: wefts each warp floats over (default 4)")
    p.add_argument("--yarn", default="CNe 50", metavar="YARN",
                   help='Table 3 yarn preset (default "CNe 50")')
    p.add_argument("--fiber-kind", default=None, metavar="FIBER",
                   help="fiber preset for the yarn's fibers (default: the yarn's composition)")
    p.add_argument("--dye", default=None, metavar="NAME", help="dye preset or colour")
    p.add_argument("--depth-of-shade", type=percentage, default=None, metavar="PERCENT",
                   help="dye depth of shade in percent on weight of fiber")
    p.add_argument("--min-clearance", type=finite_float, default=None, metavar="X",
                   help="smallest allowed distance between yarn centre lines, in yarn "
                        "diameters (default 0.8; 0 disables the check)")
    add_memory_budget_option(p)
    p.set_defaults(func=run)
    one_line_errors(p)


def write_format(suffix: str) -> str:
    """The format USD writes a file with this suffix in: .usda text, .usdc and .usd crate
    (.usd: text where ``$USD_DEFAULT_FILE_FORMAT`` is usda). The budget check counts the
    writer's memory, which for text is about five times the points' own."""
    import os

    suffix = suffix.lower().lstrip(".")
    if suffix == "usd":
        return "usda" if os.environ.get("USD_DEFAULT_FILE_FORMAT", "").strip().lower() == "usda" else "usdc"
    return suffix


def run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from pxr import Tf, Usd, UsdGeom

    from usdfiber import cloth
    from usdfiber.errors import PrimError
    from usdfiber.cli import UsageError

    knit = args.pattern in KNITS
    wrong = ([("--warps", args.warps), ("--wefts", args.wefts), ("--spacing", args.spacing),
              ("--crimp", args.crimp), ("--floats", args.floats)] if knit else
             [("--rows", args.rows), ("--loops", args.loops), ("--loop-size", args.loop_size),
              ("--spacing-scale", args.spacing_scale)])
    given = [flag for flag, v in wrong if v is not None]
    if args.pattern == "plain" and args.floats is not None:
        given.append("--floats")
    if given:
        kind = "knits" if knit else "weaves"
        raise UsageError(f"cloth {args.pattern}: {', '.join(given)} "
                         f"{'does' if len(given) == 1 else 'do'} not apply to {kind}")
    out = Path(args.output)
    if out.suffix.lower() not in (".usd", ".usda", ".usdc"):
        raise UsageError(f"--output must be a .usd, .usda or .usdc file, got {args.output}")

    from usdfiber.memory_budget import MemoryBudget

    common: dict = {"yarn": args.yarn, "fiber": args.fiber_kind, "dye": args.dye,
                    "depth_of_shade": args.depth_of_shade,
                    "memory_budget": MemoryBudget.resolve(args.memory_budget),
                    "write_format": write_format(out.suffix)}
    if args.min_clearance is not None:
        common["min_clearance"] = args.min_clearance
    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageMetersPerUnit(stage, 0.001)
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    try:
        if knit:
            kw = dict(common)
            for name in ("rows", "loops", "loop_size", "spacing_scale"):
                if getattr(args, name) is not None:
                    kw[name] = getattr(args, name)
            gen = cloth.stockinette if args.pattern == "stockinette" else cloth.garter
            prim = gen(stage, "/Cloth", **kw)
        else:
            kw = dict(common)
            for name in ("warps", "wefts", "spacing", "crimp"):
                if getattr(args, name) is not None:
                    kw[name] = getattr(args, name)
            if args.pattern == "plain":
                prim = cloth.plain_weave(stage, "/Cloth", **kw)
            else:
                if args.floats is not None:
                    kw["floats"] = args.floats
                prim = cloth.satin(stage, "/Cloth", **kw)
    except (cloth.ClothError, PrimError) as exc:
        raise UsageError(f"cloth {args.pattern}: {exc}") from None
    stage.SetDefaultPrim(prim)
    stage.GetRootLayer().documentation = prim.GetDocumentation()

    tmp = out.with_name(f".{out.stem}.tmp{out.suffix}")
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        if not stage.GetRootLayer().Export(str(tmp)):
            raise OSError("USD could not write the file")
        tmp.replace(out)
    except (OSError, Tf.ErrorException) as exc:
        reason = getattr(exc, "strerror", None) or " ".join(str(exc).split())
        raise UsageError(f"{args.output}: cannot write: {reason}") from None
    finally:
        if tmp.exists():
            tmp.unlink()
    counts = [len(c.GetAttribute("curveVertexCounts").Get() or [])
              for c in prim.GetChildren() if c.IsA(UsdGeom.BasisCurves)]
    print(f"wrote {out}: {args.pattern}, {sum(counts)} yarn curves")
    return 0
