"""usdfiber render STAGE [-o OUT.exr] [options]: render a stage with Mitsuba 3.

The stage is validated first (the checks of `usdfiber check`: errors refuse the render with
the same messages). Fiber tables missing from the cache are baked first, with progress
(render-quality settings: a 6 degree grid, 100k photons per direction; `usdfiber bake`
makes the paper's 2 degree tables, which the render then uses). The stage is translated
(fiber curves with the tabulated BCSDF, meshes, UsdLux lights, the camera) and rendered
in passes with progress. Output: a linear, scene-referred EXR (Rec.709 primaries, half
float; metadata usdfiber:stage, camera, spp, frame, times, ...) through OpenImageIO, and
a display-referred PNG next to it through OpenColorIO (default: the built-in ACES 2.0 cg
config, display "sRGB - Display", view "ACES 2.0 - SDR 100 nits (Rec.709)"; $OCIO names
another config). The EXR's channel A is the pixel's coverage (0 where camera rays meet
nothing); ``--aov albedo,normal,depth,position`` adds those layers (albedo.R/G/B, normal.X/Y/Z,
depth.Z, position.X/Y/Z) for compositing. A timing summary ends the run; ``--json`` prints
a machine-readable summary instead (files, channels, counts, times, warnings).

Resolution, samples and camera come from the options, else from the stage's render
settings (UsdRender), else 960x540, 64 spp and the first camera (or a camera framing the
visible geometry). Exit status: 0 rendered, 1 the stage was refused, 2 bad command line or
unreadable file.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from usdfiber.commands.arg_types import (add_memory_budget_option, finite_float, non_negative_float,
                                         positive_float, positive_int, seed)
from usdfiber.translators.mitsuba.render_settings import MAX_PIXELS, MAX_SPP


def _resolution(text: str) -> tuple[int, int]:
    try:
        w, h = (int(x) for x in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT (e.g. 960x540), got {text!r}") from None
    if w < 1 or h < 1 or w * h > MAX_PIXELS:
        raise argparse.ArgumentTypeError(f"expected a positive size of at most {MAX_PIXELS} pixels "
                                         f"(16384 x 16384), got {text!r}")
    return w, h


def _spp(text: str) -> int:
    n = positive_int(text)
    if n > MAX_SPP:
        raise argparse.ArgumentTypeError(f"expected at most {MAX_SPP} samples per pixel, got {text}")
    return n


#: Longest light path ``--max-depth`` takes (Mitsuba's depth is a 32-bit integer; paths this
#: long are ended by Russian roulette long before).
MAX_DEPTH = 65536


def _max_depth(text: str) -> int:
    n = positive_int(text)
    if n > MAX_DEPTH:
        raise argparse.ArgumentTypeError(f"expected a path depth of at most {MAX_DEPTH}, got {text}")
    return n


def _exposure(text: str) -> float:
    x = finite_float(text)
    if abs(x) > 100.0:
        raise argparse.ArgumentTypeError(f"expected an exposure within +-100 stops, got {text}")
    return x


def register(sub: argparse._SubParsersAction) -> None:
    """Add ``usdfiber render`` to the CLI's sub-commands (the ``usdfiber.commands`` entry point)."""
    from usdfiber.cli import one_line_errors

    p = sub.add_parser("render", help="render a stage (EXR + display PNG)", description=__doc__,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("stage", nargs="?", metavar="STAGE", help="USD file to render")
    p.add_argument("-o", "--output", type=Path, metavar="OUT.exr",
                   help="EXR to write (default: STAGE's name with .exr, in the current directory)")
    p.add_argument("--png", type=Path, metavar="OUT.png", help="display image (default: OUT with .png)")
    p.add_argument("--no-png", action="store_true", help="write the EXR only")
    p.add_argument("--resolution", type=_resolution, metavar="WxH", help="image size in pixels")
    p.add_argument("--spp", type=_spp, help="samples per pixel")
    p.add_argument("--camera", metavar="PATH", help="camera prim to render through")
    p.add_argument("--render-settings", metavar="PATH", help="UsdRender.Settings prim to use")
    p.add_argument("--frame", type=finite_float, metavar="T", help="time code (default: the default time)")
    p.add_argument("--device", choices=("cpu", "gpu"), default="cpu",
                   help="cpu: Mitsuba llvm_ad_rgb; gpu: cuda_ad_rgb (default: cpu)")
    p.add_argument("--threads", type=positive_int, help="CPU threads (default: all cores)")
    p.add_argument("--seed", type=seed, default=0, help="sampler seed, 0 to 2^32 - 1 (default: 0)")
    p.add_argument("--max-depth", type=_max_depth, default=32,
                   help=f"longest light path (default: 32, at most {MAX_DEPTH})")
    p.add_argument("--purpose", action="append", choices=("default", "render", "proxy", "guide"),
                   help="purposes to render (repeatable; default: the render settings' or default+render)")
    p.add_argument("--bake-resolution", type=positive_float, metavar="DEG",
                   help="bin size of tables baked for this render, for every fiber (default: 2 for round "
                        "fibers, 6 for others)")
    p.add_argument("--bake-photons", type=positive_int, metavar="N",
                   help="photons per direction of tables baked for this render (default: 100000)")
    p.add_argument("--no-bake", action="store_true", help="fail instead of baking missing tables")
    p.add_argument("--lod-scale", type=non_negative_float, default=1.0, metavar="S",
                   help="yarn level of detail: fibers kept per pixel of yarn width, relative (default 1; "
                        "0 expands every fiber)")
    p.add_argument("--cloth", choices=("fibers", "volume", "auto"), default="fibers",
                   help="fiber and yarn prims as curves (fibers, the default), as voxelized volumes "
                        "(volume: the paper's Section 5), or chosen per prim by pixel footprint (auto)")
    p.add_argument("--yarn-bake-resolution", type=finite_float, metavar="DEG",
                   help="bin size of yarn far fields traced for this render (yarns too small to show "
                        "their fibers, or yarn:expandFibers false; default: 6)")
    p.add_argument("--yarn-bake-photons", type=positive_int, metavar="N",
                   help="photons per direction of yarn far fields traced for this render (default: 40000)")
    p.add_argument("--float", action="store_true", help="write a 32-bit float EXR (default: half)")
    p.add_argument("--model", default="table", metavar="MODEL",
                   help="fiber model: table (the tabulated BCSDF, default), chiang (Mitsuba's hair with "
                        "fitted parameters) or khungurn (Khungurn et al. 2015, fitted)")
    p.add_argument("--aov", default=None, metavar="LIST",
                   help="also write these layers into the EXR, comma-separated: albedo, normal, depth, position "
                        "(channels albedo.R/G/B, normal.X/Y/Z, depth.Z, position.X/Y/Z; alpha is always channel A)")
    p.add_argument("--view", help="OCIO view of the PNG (see --list-views)")
    p.add_argument("--display", help="OCIO display of the PNG (default: sRGB - Display)")
    p.add_argument("--ocio-config", metavar="CONFIG", help="OCIO config (default: $OCIO or ocio://cg-config-latest)")
    p.add_argument("--exposure", type=_exposure, default=0.0, metavar="STOPS", help="exposure of the PNG in stops")
    p.add_argument("--list-views", action="store_true", help="list the OCIO displays and views and exit")
    p.add_argument("--warnings-as-errors", action="store_true", help="refuse stages with check warnings")
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    add_memory_budget_option(p)
    g = p.add_argument_group("sequences and farms")
    g.add_argument("--frames", metavar="FIRST-LAST[xSTEP]",
                   help="render a frame range (e.g. 1001-1100, 1001-1100x2, 1,5,10-20) to -o shot.####.exr; "
                        "frames already written are skipped")
    g.add_argument("--scheduler", metavar="ADDRESS", help="with --frames: render on a Dask cluster (address or local:N)")
    g.add_argument("--shard", metavar="I/N", help="with --frames: render the I-th of N disjoint parts of the frames")
    g.add_argument("--json", action="store_true",
                   help="print a JSON summary (of the render, or with --frames of the sequence) instead of text")
    p.set_defaults(func=run)
    one_line_errors(p)


def run(args: argparse.Namespace) -> int:
    """Run ``usdfiber render`` with parsed arguments; returns the exit status."""
    from usdfiber import image_output
    from usdfiber.cli import UsageError
    from usdfiber.translators.mitsuba.render import RenderJob, RenderRefused, render_stage
    from usdfiber.stage_io import StageOpenError, open_stage

    if args.list_views:
        try:
            for display, views in image_output.list_views(args.ocio_config).items():
                print(display)
                for v in views:
                    print(f"  {v}")
        except image_output.ImageOutputError as exc:
            raise UsageError(str(exc)) from None
        return 0
    if not args.stage:
        raise UsageError("render: a STAGE is required")
    try:
        open_stage(args.stage)  # unreadable files are usage errors (exit 2), as in `check`
    except StageOpenError as exc:
        raise UsageError(str(exc)) from None
    out = args.output or Path(Path(args.stage).stem + ".exr")
    if out.suffix.lower() != ".exr":
        raise UsageError(f"--output must name an .exr file, got {out}")
    png = None if args.no_png else (args.png or out.with_suffix(".png"))
    if png is not None and png.suffix.lower() != ".png":
        raise UsageError(f"--png must name a .png file, got {png}")
    job = RenderJob(stage=args.stage, output=out, png=png, frame=args.frame, resolution=args.resolution,
                    spp=args.spp, camera=args.camera, render_settings=args.render_settings,
                    device=args.device, threads=args.threads, seed=args.seed, max_depth=args.max_depth,
                    purposes=tuple(args.purpose) if args.purpose else None,
                    bake_resolution_deg=args.bake_resolution, bake_photons=args.bake_photons,
                    bake_missing=not args.no_bake, half=not args.float, view=args.view, display=args.display,
                    ocio_config=args.ocio_config, exposure=args.exposure, progress=not args.no_progress,
                    warnings_as_errors=args.warnings_as_errors, lod_scale=args.lod_scale,
                    memory_budget=args.memory_budget,
                    cloth=args.cloth,
                    yarn_resolution_deg=args.yarn_bake_resolution, yarn_photons=args.yarn_bake_photons,
                    aovs=_aov_list(args.aov) if args.aov is not None else (), model=_model(args.model))
    if args.scheduler is not None:
        from usdfiber.farm.cluster import FarmError, parse_scheduler

        try:
            parse_scheduler(args.scheduler)     # without connecting: the address's form
        except FarmError as exc:
            raise UsageError(str(exc)) from None
    if args.frames is not None:
        from usdfiber.translators.mitsuba.sequence import run_sequence_command

        return run_sequence_command(args, job, render_summary)
    if args.scheduler is not None or args.shard is not None:
        raise UsageError("--scheduler and --shard go with --frames")
    bake_progress = None if args.no_progress else _bake_progress()
    try:
        res = render_stage(job, bake_progress=bake_progress)
    except RenderRefused as exc:
        print(f"usdfiber: error: {exc}", file=sys.stderr)
        return 1
    for w in res.warnings:
        print(f"usdfiber: warning: {w}", file=sys.stderr)
    if args.json:
        print(json.dumps(render_summary(args.stage, res), indent=2))
        return 0
    from usdfiber.bake.cost import format_seconds

    t = res.times
    c = res.counts
    w, h = res.resolution
    print(f"rendered {args.stage} through {res.camera}: {w}x{h}, {res.spp} spp, "
          f"{c.get('fiber_curves', 0)} fiber curves ({c.get('fiber_segments', 0)} segments, "
          f"{c.get('fiber_tables', 0)} tables, {c.get('fiber_slots', 0)} colours), "
          f"{c.get('meshes', 0)} meshes, {c.get('lights', 0)} lights")
    if c.get("yarn_yarns"):
        print(f"yarns: {c['yarn_yarns']}, {c['yarn_fibers']} fibers expanded of {c['yarn_fibers_full']} at full "
              f"detail; with their far field: {c.get('yarn_far', 0)} in view, {c.get('yarn_culled', 0)} outside "
              f"the view near it (proxies); {c.get('yarn_skipped', 0)} far outside the view left out")
    for f in res.far_fields:
        took = f" in {f['seconds']:.1f} s" if f["far_field"] == "traced" else ""
        print(f"far field {f['prim']}: {f['far_field']}{took} ({f['reason']})")
    for b in res.bakes:
        print(f"baked {b['label']}: estimated {format_seconds(b['seconds'])}, {b['directions']} directions x "
              f"{b['photons_per_direction']} photons")
    print(f"time: validate {t['validate']:.2f} s, tables {t['tables']:.2f} s, translate {t['translate']:.2f} s, "
          f"render {t['render']:.2f} s, write {t['write']:.2f} s, total {t['total']:.2f} s")
    for f in res.files:
        print(f"wrote {f}")
    return 0


def _model(name: str) -> str:
    """``--model NAME`` checked against fitted_models.RENDER_MODELS; UsageError otherwise."""
    from usdfiber.cli import UsageError
    from usdfiber.translators.mitsuba.fitted_models import check_render_model

    try:
        return check_render_model(name)
    except ValueError as exc:
        raise UsageError(f"--model: {exc}") from None


def _aov_list(text: str) -> tuple[str, ...]:
    """The layers of ``--aov a,b,c`` (each once, in the order given); UsageError naming unknown ones."""
    from usdfiber.cli import UsageError
    from usdfiber.translators.mitsuba.scene import AOVS

    names = tuple(dict.fromkeys(a.strip() for a in text.split(",") if a.strip()))
    unknown = [a for a in names if a not in AOVS]
    if unknown or not names:
        raise UsageError(f"--aov: unknown AOV(s) {', '.join(unknown) or repr(text)}; valid: {', '.join(AOVS)}")
    return names


def render_summary(stage: str, res: Any) -> dict[str, Any]:
    """The machine-readable summary of a render (``usdfiber render --json``): what was
    rendered, the files and their channels, the scene's counts, the times and the warnings."""
    from usdfiber.translators.mitsuba.scene import AOVS

    w, h = res.resolution
    channels = ["R", "G", "B", "A"] + [c for a in res.aovs for c in AOVS[a][1]]
    return {
        "stage": stage, "camera": res.camera, "resolution": [w, h], "spp": res.spp,
        "files": [str(f) for f in res.files], "exr_channels": channels, "aovs": list(res.aovs),
        "counts": {k: int(v) for k, v in res.counts.items()},
        "bakes": list(getattr(res, "bakes", [])),
        "far_fields": list(getattr(res, "far_fields", [])),
        "times_s": {k: round(float(v), 4) for k, v in res.times.items()},
        "warnings": list(res.warnings),
    }


def _bake_progress():
    """A progress callback drawing one tqdm bar per baked table on stderr."""
    from tqdm import tqdm

    state: dict = {"bar": None}

    def progress(done: int, total: int, info: dict) -> None:
        if info.get("event") == "start":
            if state["bar"] is not None:
                state["bar"].close()
            state["bar"] = tqdm(total=total, initial=done, unit=info.get("unit", "dir"), desc=f"bake {info.get('label', 'table')}",
                                file=sys.stderr, dynamic_ncols=True)
        elif state["bar"] is not None:
            state["bar"].update(done - state["bar"].n)
            if done >= total:
                state["bar"].close()
                state["bar"] = None

    return progress
