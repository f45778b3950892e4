"""``usdfiber material STAGE [-o OUT] [--mtlx FILE]``: fitted materials for Hydra and MaterialX.

For every distinct fiber look of the stage (fiber and yarn curves with FiberAPI) writes a
``UsdShade.Material`` with a MaterialX ``chiang_hair_bsdf`` network fitted to the fiber's
tables for its dye (the UsdMtlx form that Hydra render delegates and Omniverse read), a
``UsdPreviewSurface`` fallback and ``primvars:displayColor`` (the mean colour under white
light) for Storm, and binds it to the curves. Running again updates the same prims.

Without ``-o`` the stage's root layer is edited in place (it must be writable). With
``-o OUT`` the stage is left alone and OUT is written as a layer that sublayers it and holds
only the materials, bindings and colours (open OUT to see both). ``--mtlx FILE`` also writes
the looks as a standalone MaterialX document. OUT (.usda, .usdc or .usd) and FILE (.mtlx) are
checked before any table is looked up. Every MaterialX document is validated with
MaterialX's ``validate()``.

Tables missing from the cache (``--cache-dir``, else ``$USDFIBER_CACHE_DIR``, else
``~/.cache/usdfiber``) are baked at the render's quality, per fiber
(:func:`usdfiber.bcsdf.render_settings_for`: 2 degrees for round fibers, 6 for
others, 100000 photons; ``--bake-resolution`` and ``--bake-photons`` set them for every
fiber) unless ``--no-bake``; fits are cached beside them.

Exit status: 0 written, 2 bad input (one line on stderr).
"""
from __future__ import annotations

import argparse
import functools
import os
from dataclasses import replace
from pathlib import Path

__all__ = ["register", "run"]


def register(sub: argparse._SubParsersAction) -> None:
    from usdfiber.commands.arg_types import finite_float
    from usdfiber.cli import one_line_errors

    p = sub.add_parser("material", help="write fitted MaterialX / Storm materials for the fibers of a stage",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("stage", metavar="STAGE")
    p.add_argument("-o", "--output", default=None, metavar="OUT",
                   help="write a layer sublayering STAGE instead of editing STAGE")
    p.add_argument("--mtlx", default=None, metavar="FILE", help="also write a standalone .mtlx document")
    p.add_argument("--cache-dir", default=None, metavar="DIR", help="table cache (default: the user's)")
    p.add_argument("--bake-resolution", type=finite_float, default=None, metavar="DEG",
                   help="bin size of tables baked here (default: the render's, 2 for round fibers, 6 for others)")
    p.add_argument("--bake-photons", type=int, default=None, metavar="N",
                   help="photons per direction of tables baked here (default: 100000)")
    p.add_argument("--no-bake", action="store_true", help="fail instead of baking missing tables")
    p.set_defaults(func=run)
    one_line_errors(p)


def _writable(path: Path) -> bool:
    return os.access(path, os.W_OK) and os.access(path.parent if str(path.parent) else Path("."), os.W_OK)


def _output_problem(path: Path, suffixes: tuple[str, ...]) -> str | None:
    """Why ``path`` cannot be written as a file of one of ``suffixes`` (None when it can):
    checked before any table is fitted, so that a bad path costs nothing."""
    if path.is_dir():
        return f"is a directory; expected a {' or '.join(suffixes)} file"
    if path.suffix.lower() not in suffixes:
        return f"expected a {' or '.join(suffixes)} file"
    parent = path.parent if str(path.parent) else Path(".")
    if not parent.is_dir():
        return f"cannot write: no directory {parent}"
    if path.exists() and not _writable(path) or not path.exists() and not os.access(parent, os.W_OK):
        return "cannot write (read-only file or directory)"
    return None


def run(args: argparse.Namespace) -> int:
    from pxr import Sdf, Tf, Usd

    from usdfiber.bcsdf import TableCache
    from usdfiber.cli import UsageError
    from usdfiber.stage_io import StageOpenError, open_stage
    from usdfiber.translators.materialx.document import DocumentError, look_document, write_document
    from usdfiber.bake.settings import RENDER_BAKE_SETTINGS
    from usdfiber.translators.materialx.looks import MATERIAL_BAKE_SETTINGS, LookError
    from usdfiber.translators.materialx.usd_material import author_materials

    src = Path(args.stage)
    try:
        stage = open_stage(src)
    except StageOpenError as exc:
        raise UsageError(str(exc)) from None
    settings = MATERIAL_BAKE_SETTINGS
    if args.bake_resolution is not None or args.bake_photons is not None:
        try:   # checked here, before any table is looked up
            replace(RENDER_BAKE_SETTINGS, **({} if args.bake_resolution is None else {"resolution_deg": args.bake_resolution}),
                    **({} if args.bake_photons is None else {"photons": args.bake_photons}))
        except ValueError as exc:
            raise UsageError(f"bake settings: {exc}") from None
        settings = functools.partial(MATERIAL_BAKE_SETTINGS, resolution_deg=args.bake_resolution,
                                     photons=args.bake_photons)

    for name, value, suffixes in (("-o", args.output, (".usda", ".usdc", ".usd")), ("--mtlx", args.mtlx, (".mtlx",))):
        problem = value and _output_problem(Path(value), suffixes)
        if problem:
            raise UsageError(f"{value}: {name}: {problem}")
    if args.output:
        out = Path(args.output)
        if out.resolve() == src.resolve():
            raise UsageError(f"{out}: -o names the stage itself; leave -o out to edit it in place")
        layer = Sdf.Layer.FindOrOpen(str(out)) if out.exists() else None
        if layer is None:
            layer = Sdf.Layer.CreateNew(str(out))
            if layer is None:
                raise UsageError(f"{out}: cannot create a USD layer there (is the extension .usda, .usdc or .usd?)")
        rel = os.path.relpath(src.resolve(), out.resolve().parent)
        if rel not in layer.subLayerPaths:
            layer.subLayerPaths.append(rel)
        root = stage.GetRootLayer()
        layer.defaultPrim = layer.defaultPrim or root.defaultPrim
        stage = Usd.Stage.Open(layer)
        stage.SetEditTarget(layer)
        target = out
    else:
        if not _writable(src):
            raise UsageError(f"{src}: cannot write (read-only file); use -o OUT to write the materials to another layer")
        target = src

    def progress(msg: str) -> None:
        print(f"  {msg}", flush=True)

    try:
        report = author_materials(stage, cache=TableCache(args.cache_dir), settings=settings,
                                  bake_missing=not args.no_bake, progress=progress)
    except LookError as exc:
        raise UsageError(str(exc)) from None
    mtlx_path = None
    if args.mtlx:
        looks = [(Path(p).name, samples[0][1]) for p, samples in report.looks.items()]
        try:
            mtlx_path = write_document(look_document(looks), args.mtlx)
        except DocumentError as exc:
            raise UsageError(f"{args.mtlx}: {exc}") from None
        except OSError as exc:
            raise UsageError(f"{args.mtlx}: cannot write: {exc.strerror or exc}") from None
    try:
        stage.GetEditTarget().GetLayer().Save()
    except Tf.ErrorException as exc:   # a disk that filled up, a file replaced by a directory meanwhile
        lines = [line.strip() for line in str(exc).splitlines() if line.strip()]
        reason = lines[-1].split(" : ", 1)[-1].strip("'") if lines else "USD could not save the layer"
        raise UsageError(f"{target}: cannot write: {reason}") from None
    for path, samples in report.looks.items():
        lk = samples[0][1]
        print(f"{path}: {lk.kind}, colour {', '.join(f'{c:.4f}' for c in lk.colour)} (linear Rec.709), "
              f"fit error (relative L2) {', '.join(f'{e:.3f}' for e in lk.rel_l2)}"
              + (f", {len(samples)} time samples" if len(samples) > 1 else ""))
    for note in report.notes:
        print(f"note: {note}")
    print(f"wrote {target}: {len(report.materials)} material(s) bound to {len(report.bound)} prim(s)"
          + (f", {len(report.removed)} unused removed" if report.removed else "")
          + (f"; {mtlx_path}" if mtlx_path else ""))
    return 0
