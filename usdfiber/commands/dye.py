"""``usdfiber dye --match COLOUR (--fiber PRESET | --stage STAGE --prim PATH) [options]``.

Finds the dye's extinction per gram (per linear Rec.709 channel, L mg^-1 cm^-1) that gives a
fiber a target colour at a depth of shade (:mod:`usdfiber.dye_match`): the fiber's radiance
under a white light of radiance 1 (``--light`` names another: ``6500K`` or ``r,g,b``, each channel
1e-6 to 1e6; a blackbody below about 1950K has no blue and is refused), seen
perpendicular to the fiber (``--view-theta DEG`` another view, ``--view-theta all`` every
view, the mean colour of ``usdfiber material``), averaged over rotations and cross-section
variants. Nothing is traced again: the fiber's table is recoloured.

COLOUR is an sRGB hex colour (``#b0402a``) or three linear Rec.709 numbers (``0.43,0.05,0.02``).
The extinction stays within the dye class's industry range (paper Section 3.1: reactive
0.005-0.0158, disperse 0.045-0.246; ``--dye-class custom``: 0-10). A colour out of reach
is an error that names the nearest reachable colour (exit 1).

``--fiber PRESET`` takes the preset's fiber (``usdfiber presets``), ``--stage``/``--prim`` a
fiber or yarn prim (a yarn's fibers: light scattered between them deepens the yarn's colour
beyond this; on the Table 3 threads the yarn's own albedo is 0.25-0.58 of its fibers' per
channel, ``bench/REPORT.md`` "Fitted models"). ``--write`` authors the dye on the prim and saves the stage; ``--spectral``
authors it as a spectral extinction curve whose Rec.709 reduction is the matched extinction.
Tables missing from the cache (``--cache-dir``, else ``$USDFIBER_CACHE_DIR``, else
``~/.cache/usdfiber``) are baked (``--bake-resolution`` 6 degrees, ``--bake-photons`` 100000).

Exit status: 0 matched, 1 out of reach, 2 bad input (one line on stderr).
"""
from __future__ import annotations

import argparse
import json
import os
import stat
import sys
from typing import Any

from usdfiber.commands.arg_types import finite_float, positive_int


def register(sub: argparse._SubParsersAction) -> None:
    """Add ``usdfiber dye`` (the ``usdfiber.commands`` entry point)."""
    from usdfiber.cli import one_line_errors

    p = sub.add_parser("dye", help="find the dye that gives a fiber a colour", description=__doc__,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--match", required=True, metavar="COLOUR", help="target colour: #rrggbb (sRGB) or r,g,b (linear)")
    p.add_argument("--fiber", metavar="PRESET", help="fiber preset (usdfiber presets)")
    p.add_argument("--stage", metavar="STAGE", help="stage holding the fiber or yarn prim")
    p.add_argument("--prim", metavar="PATH", help="fiber or yarn prim on --stage")
    p.add_argument("--depth-of-shade", type=finite_float, metavar="PCT",
                   help="depth of shade, percent (default: the prim's, or 1 with --fiber)")
    p.add_argument("--dye-class", choices=("reactive", "disperse", "custom"),
                   help="dye class (default: the prim's, else disperse for polyester, reactive otherwise)")
    p.add_argument("--light", default="white", metavar="LIGHT", help="white (default), 6500K or r,g,b")
    p.add_argument("--view-theta", default="0", metavar="DEG",
                   help="view angle to the fiber's normal plane in degrees, or 'all' (default 0)")
    p.add_argument("--write", action="store_true", help="author the dye on --prim and save --stage")
    p.add_argument("--spectral", action="store_true", help="author (and print) a spectral extinction curve")
    p.add_argument("--json", action="store_true", help="print the result as JSON")
    p.add_argument("--cache-dir", default=None, metavar="DIR", help="table cache (default: the user's)")
    p.add_argument("--bake-resolution", type=finite_float, default=6.0, metavar="DEG",
                   help="bin size of tables baked here (default: 6)")
    p.add_argument("--bake-photons", type=positive_int, default=100_000, metavar="N",
                   help="photons per direction of tables baked here (default: 100000)")
    p.add_argument("--no-bake", action="store_true", help="fail instead of baking missing tables")
    p.set_defaults(func=run)
    one_line_errors(p)


def _fiber(args: argparse.Namespace) -> tuple[Any, Any, Any, Any]:
    """(FiberParams, tables, prim, stage) of the command's fiber (prim and stage None for a
    preset; the stage is returned to keep the prim alive)."""
    from usdfiber.bake.cache import TableCache
    from usdfiber.bake.requests import params_from_preset, requests_for_params
    from usdfiber.bake.settings import BakeError, BakeSettings
    from usdfiber.cli import UsageError
    from usdfiber.spec.fiber import FiberParams, FiberParamsError
    from usdfiber.stage_io import StageOpenError, open_stage

    if bool(args.fiber) == bool(args.stage or args.prim):
        raise UsageError("give either --fiber PRESET or --stage STAGE with --prim PATH")
    if args.write and not args.stage:
        raise UsageError("--write needs --stage and --prim")
    try:
        settings = BakeSettings(resolution_deg=args.bake_resolution, photons=args.bake_photons, batches=4)
    except (BakeError, ValueError) as exc:
        raise UsageError(f"bake settings: {exc}") from None
    cache = TableCache(args.cache_dir)
    prim = stage = None
    try:
        if args.fiber:
            params = params_from_preset(args.fiber)
            source = f"preset:{args.fiber}"
        else:
            if not (args.stage and args.prim):
                raise UsageError("--stage and --prim go together")
            try:
                stage = open_stage(args.stage)
            except StageOpenError as exc:
                raise UsageError(str(exc)) from None
            from pxr import Sdf

            prim = stage.GetPrimAtPath(args.prim) if Sdf.Path.IsValidPathString(args.prim) else None
            if not prim:
                raise UsageError(f"{args.stage}: no prim at {args.prim}")
            try:
                params = FiberParams.from_prim(prim)
            except FiberParamsError as exc:
                raise UsageError(str(exc)) from None
            source = str(prim.GetPath())
        tables = []
        for req in requests_for_params(params, source):
            res = cache.get_or_bake(req, settings, bake_missing=not args.no_bake)
            if res is None:
                raise UsageError(f"{source}: no cached table for {req.label} in {cache.root}; run `usdfiber bake` "
                                 f"or leave out --no-bake")
            tables.append(res.table)
    except BakeError as exc:
        raise UsageError(str(exc)) from None
    return params, tables, prim, stage


def _writable(path: str) -> bool:
    """Writable by this process and not marked read-only (no write bit: even for root)."""
    mode = os.stat(path).st_mode
    return os.access(path, os.W_OK) and bool(mode & (stat.S_IWUSR | stat.S_IWGRP | stat.S_IWOTH))


def run(args: argparse.Namespace) -> int:
    """Run ``usdfiber dye``; returns the exit status."""
    from usdfiber import dye_match as dm
    from usdfiber.authoring import AuthoringError
    from usdfiber.cli import UsageError

    try:
        target = dm.parse_colour(args.match)
        light = dm.light_rgb(args.light)
    except dm.DyeMatchError as exc:
        raise UsageError(str(exc)) from None
    if args.view_theta.strip().lower() == "all":
        theta: float | None = None
    else:
        try:
            theta = finite_float(args.view_theta)
        except argparse.ArgumentTypeError as exc:
            raise UsageError(f"--view-theta: {exc}") from None
    if args.write and args.stage and os.path.exists(args.stage) and not _writable(args.stage):
        raise UsageError(f"{args.stage}: cannot write (read-only file); leave out --write to only print the dye")
    params, tables, prim, _stage = _fiber(args)
    dos = args.depth_of_shade
    if dos is None:
        dos = params.depth_of_shade if prim is not None and params.depth_of_shade > 0 else 1.0
    if not 0 < dos <= 10:
        raise UsageError(f"--depth-of-shade must be in (0, 10] percent, got {dos:g}")
    dye_class = args.dye_class
    if dye_class is None:
        dye_class = params.dye_class if params.dye_class in ("reactive", "disperse", "custom") and prim is not None \
            else dm.default_dye_class(params.kind)
    try:
        fiber = dm.FiberColour(tables, params.density, params.diameter, dos, theta)
        match = dm.match_dye(fiber, target, dye_class, light)
    except dm.ColourOutOfReach as exc:
        if args.json:
            print(json.dumps(dict(exc.match.to_dict(), error=str(exc)), indent=2))
        print(f"usdfiber: error: {params.kind}: {exc}", file=sys.stderr)
        return 1
    except dm.DyeMatchError as exc:
        raise UsageError(str(exc)) from None
    out = match.to_dict()
    out.update(fiber=params.kind, prim=params.prim_path if prim is not None else None)
    spectrum = None
    if args.spectral:
        try:
            spectrum = dm.spectral_extinction(match.extinction)
        except dm.DyeMatchError as exc:
            raise UsageError(str(exc)) from None
        out["spectrum"] = {"wavelengths_nm": spectrum[0], "values": spectrum[1]}
    if args.write:
        try:
            dm.author_dye(prim, match, spectral=args.spectral)
        except (AuthoringError, dm.DyeMatchError) as exc:
            raise UsageError(str(exc)) from None
        try:
            saved = prim.GetStage().GetRootLayer().Save()
        except Exception as exc:  # pxr.Tf.ErrorException: the layer cannot be written
            raise UsageError(f"{args.stage}: cannot save the stage: {' '.join(str(exc).split())}") from None
        if not saved:
            raise UsageError(f"{args.stage}: cannot save the stage")
        out["written"] = args.stage
    if args.json:
        print(json.dumps(out, indent=2))
        return 0
    e = match.extinction
    view = "all views" if theta is None else f"seen at {theta:g} deg"
    print(f"{params.kind}, {dye_class} dye at {dos:g} % depth of shade: extinction per gram "
          f"{e[0]:.5g}, {e[1]:.5g}, {e[2]:.5g} L/(mg cm) (R, G, B)")
    print(f"colour {dm.srgb_hex(match.colour)} (linear {', '.join(f'{c:.4f}' for c in match.colour)}) under "
          f"light {', '.join(f'{c:.3g}' for c in light)}, {view}; target {dm.srgb_hex(target)}")
    if spectrum is not None:
        print("spectrum (nm: L/(mg cm)): " + ", ".join(f"{w:g}: {v:.4g}" for w, v in zip(*spectrum)))
    if args.write:
        print(f"wrote the dye on {params.prim_path} in {args.stage}")
    return 0
