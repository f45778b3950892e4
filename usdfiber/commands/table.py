"""``usdfiber table inspect FILE`` and ``usdfiber table plot FILE ... -o OUT.png``.

``inspect`` prints a table's header: the fiber inputs it was baked for (with units), its
resolution and symmetries, photons, error estimate, absorption levels, storage and an
albedo summary. ``--json`` prints the header and the summary as JSON.

``plot`` writes a labelled matplotlib figure (:mod:`usdfiber.table_plot`; PNG, PDF or SVG
by extension; ``-o`` an existing directory: ``<FILE's name>-<figure>.png`` in it), chosen by
``--figure``:

* ``grid`` (the default): the paper's Figure 3 layout, rows: each ``--theta-i`` (default
  -60 -30 0), columns: each ``--psi`` (default 0 60 120), the scattered intensity
  ``Lambda(omega_i) p(omega_o | omega_i)`` (per steradian, luminance of the linear Rec.709
  channels when dyed) on a log scale over ``--decades`` decades with a colour bar, the
  specular cone dashed;
* ``longitudinal``: Figure 14-style curves over theta_o, one per ``--theta-i``;
* ``errors``: the bake's error estimate per direction against its photons;
* ``fit``: Figure 12-style slices of the table against the standard models fitted to it
  (Chiang et al. 2016 and Khungurn et al. 2015, :mod:`usdfiber.fit`; the fits are cached
  beside the table), one row per ``--theta-i``, each model's error over the sphere listed;
* ``slice``: one raw false-colour slice (one pixel block per bin, ``--scale`` pixels) for the
  light direction ``--theta-i``, ``--phi-i`` and rotation ``--psi``, through OpenImageIO
  (any image format); theta_o runs from +90 (top) to -90 degrees (bottom), phi_o from 0
  (left) to 360 degrees (right).

``compress`` rewrites tables in the compact, recolourable layout of
:mod:`usdfiber.bake.compression` (a low-rank absorption basis stored with blosc2's ZFP codec;
p within ``--bound``, default 0.01, relative L2 per direction at every checked absorption),
atomically: ``-o OUT`` (a file, or a directory for several tables: tables of the same name
are refused there, before anything is written) or ``--in-place``;
``--cache`` compresses every uncompressed table of the table cache (``--cache-dir``, else
``$USDFIBER_CACHE_DIR``, else ``~/.cache/usdfiber``) in place, under each key's lock: a render
reads a compressed table exactly as the uncompressed one (:mod:`usdfiber.bake.cache`). One line
per table: its size on disk and in memory before and after, the rank, the worst checked error
and the time. A file that is not a table, is already compressed, or cannot be kept within the
bound gets one line on stderr and is left as it was; the others are still compressed.

Light azimuth ``--phi-i`` (default 0). Undyed by default; ``--dye NAME`` (a dye preset or
colour of ``usdfiber presets``) with ``--depth-of-shade`` (percent, default 0.1 as in
Figure 3), ``--density`` and ``--diameter`` (defaults: the fiber recorded in the table), or
``--mu-a R G B`` (1/um).

Exit status: 0 done, 2 bad input or an unreadable table (one line on stderr; for ``compress``:
any table not compressed).
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
from typing import Any

import numpy as np

from usdfiber.commands.arg_types import compression_bound, finite_float


#: ``table plot --figure`` choices, and their default light longitudes (degrees).
FIGURES = ("grid", "longitudinal", "errors", "fit", "slice")
_THETA_I = {"grid": [-60.0, -30.0, 0.0], "longitudinal": [-60.0, -30.0, 0.0, 30.0], "errors": [0.0],
            "fit": [-60.0, -30.0, 0.0]}


def _nonneg(text: str) -> float:
    v = finite_float(text)
    if v < 0:
        raise argparse.ArgumentTypeError(f"must be >= 0, got {text}")
    return v


#: ``table plot --decades``: the log10 range shown. Beyond 30 decades the lower end falls under
#: anything a table of float photon counts holds (and 10^-decades underflows past ~300).
MAX_DECADES = 30.0


def _decades(text: str) -> float:
    v = finite_float(text)
    if not 0 < v <= MAX_DECADES:
        raise argparse.ArgumentTypeError(f"must be > 0 and at most {MAX_DECADES:g} decades, got {text}")
    return v


def _positive(text: str) -> float:
    v = finite_float(text)
    if v <= 0:
        raise argparse.ArgumentTypeError(f"must be > 0, got {text}")
    return v


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "table",
        help="inspect or plot a baked BCSDF table",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    tsub = p.add_subparsers(dest="table_command", metavar="ACTION")
    tsub.required = True
    pi = tsub.add_parser("inspect", help="print a table's header and summary",
                         description="Print a table's header: inputs, units, resolution, photons, "
                                     "error estimate, albedo summary.")
    pi.add_argument("file", metavar="FILE")
    pi.add_argument("--json", action="store_true", help="print JSON")
    pi.set_defaults(func=run_inspect)

    pp = tsub.add_parser("plot", help="write a figure of the BCSDF (paper Fig. 3 grid by default; 12, 14)",
                         description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    pp.add_argument("file", metavar="FILE")
    pp.add_argument("--theta-i", type=finite_float, default=None, nargs="+", metavar="DEG",
                    help="light longitude, degrees (several: the rows of grid and fit, the curves of longitudinal; "
                         "one for slice)")
    pp.add_argument("--phi-i", type=finite_float, default=0.0, metavar="DEG", help="light azimuth, degrees (default 0)")
    pp.add_argument("--psi", type=finite_float, default=None, nargs="+", metavar="DEG",
                    help="fiber rotation, degrees (several: the columns of grid; default 0 60 120, else 0)")
    pp.add_argument("--figure", choices=FIGURES, default="grid",
                    help="grid (default), longitudinal, errors, fit or slice (see above)")
    pp.add_argument("--dye", default=None, metavar="NAME", help="dye preset or colour")
    pp.add_argument("--depth-of-shade", type=_nonneg, default=0.1, metavar="PCT",
                    help="depth of shade in percent (default 0.1)")
    pp.add_argument("--density", type=_positive, default=None, metavar="G_CM3",
                    help="fiber density (default: the table's fiber)")
    pp.add_argument("--diameter", type=_positive, default=None, metavar="UM",
                    help="fiber diameter in um (default: the table's fiber)")
    pp.add_argument("--mu-a", type=_nonneg, nargs=3, default=None, metavar=("R", "G", "B"),
                    help="absorption coefficient per channel, 1/um (instead of --dye)")
    pp.add_argument("--decades", type=_decades, default=4.0,
                    help=f"log10 range shown, up to {MAX_DECADES:g} (default 4)")
    pp.add_argument("--scale", type=int, default=4, metavar="PX", help="pixels per bin (default 4)")
    pp.add_argument("--smooth", action="store_true", help="bilinear between bin centres instead of bins")
    pp.add_argument("-o", "--output", required=True, metavar="OUT.png",
                    help="image to write, its format by extension (figures: .png, .pdf, .svg; slice: any "
                         "OpenImageIO format); an existing directory: FILE's name with -FIGURE.png in it")
    pp.set_defaults(func=run_plot)
    from usdfiber.bake.compression import DEFAULT_BOUND

    pc = tsub.add_parser("compress", help="rewrite tables in the compact, recolourable layout (or a whole cache)",
                         description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    pc.add_argument("files", nargs="*", metavar="FILE", help="table files (.npz)")
    where = pc.add_mutually_exclusive_group()
    where.add_argument("-o", "--output", default=None, metavar="OUT",
                       help="the compressed table (one FILE) or a directory to write them into")
    where.add_argument("--in-place", action="store_true", help="replace each FILE with its compressed form")
    where.add_argument("--cache", action="store_true",
                       help="compress every uncompressed table of the table cache in place")
    pc.add_argument("--cache-dir", default=None, metavar="DIR",
                    help="with --cache: the table cache (default $USDFIBER_CACHE_DIR or ~/.cache/usdfiber)")
    pc.add_argument("--bound", type=compression_bound, default=DEFAULT_BOUND, metavar="E",
                    help=f"largest relative L2 error of p per direction (default {DEFAULT_BOUND:g})")
    pc.set_defaults(func=run_compress)
    from usdfiber.cli import one_line_errors

    for parser in (p, pi, pp, pc):
        one_line_errors(parser)


def _load(path: str):
    from usdfiber.bake.storage import TableLayoutError
    from usdfiber.bake.table import BcsdfTable
    from usdfiber.cli import UsageError
    from usdfiber.table_format import TableError

    try:
        return BcsdfTable.load(path)
    except (TableError, TableLayoutError) as exc:
        raise UsageError(str(exc)) from None


def _mb(n: float) -> str:
    return f"{n / 1e6:.2f} MB"


def _compressed_line(src: str, dst: str, before: tuple[int, int], table: Any, seconds: float) -> str:
    """One table's ``compress`` report: sizes on disk and in memory, rank, worst error, time."""
    after = (os.path.getsize(dst), table.nbytes())
    comp = table.header["compression"]
    target = "in place" if os.path.abspath(src) == os.path.abspath(dst) else f"-> {dst}"
    return (f"{src} {target}: {_mb(before[0])} -> {_mb(after[0])} on disk ({before[0] / after[0]:.1f}x), "
            f"{_mb(before[1])} -> {_mb(after[1])} in memory, rank {comp['rank']}, worst error "
            f"{comp['error_max']:.2%} (bound {comp['bound']:.2%}), {seconds:.1f} s")


def _compress_file(src: str, dst: str, bound: float) -> str:
    """Compress the table ``src`` into ``dst`` (atomically); its report line. UsageError (one
    line naming ``src``) for a file that is not a table, is compressed, or exceeds the bound."""
    import time

    from usdfiber.bake.compression import CompressionError
    from usdfiber.cli import UsageError

    t0 = time.perf_counter()
    table = _load(src)
    if table.compressed:
        comp = table.header.get("compression", {})
        raise UsageError(f"{src}: is already compressed (bound {comp.get('bound')}, rank {comp.get('rank')}); "
                         f"expected an uncompressed table")
    before = (os.path.getsize(src), table.nbytes())
    try:
        small = table.compress(bound)
    except CompressionError as exc:
        why = str(exc).split(": ", 1)[1] if str(exc).startswith(f"{src}: ") else str(exc)
        raise UsageError(f"{src}: cannot be compressed within {bound:g}: {why}") from None
    del table
    try:
        small.save(dst)
    except OSError as exc:
        raise UsageError(f"cannot write {dst}: {exc.strerror or exc}") from None
    return _compressed_line(src, dst, before, small, time.perf_counter() - t0)


def _compress_cache(args: argparse.Namespace) -> int:
    """``table compress --cache``: every uncompressed table of the cache, in place under its lock."""
    import time
    import warnings

    from usdfiber import table_format
    from usdfiber.bake.cache import TableCache, TableCacheError, TableCacheWarning
    from usdfiber.bake.compression import LAYOUT, CompressionError
    from usdfiber.cli import UsageError

    cache = TableCache(args.cache_dir)
    tables = cache.root / "tables"
    if not tables.is_dir():
        raise UsageError(f"{cache.root}: no table cache here (expected a tables/ directory); "
                         f"--cache-dir or $USDFIBER_CACHE_DIR chooses another")
    failed = skipped = done = 0
    for path in sorted(tables.glob("*.npz")):
        memory = 0
        try:
            header = table_format.read_header(path)
            if header.get("layout", {}).get("name") == LAYOUT:
                skipped += 1
                continue
            memory = sum(int(np.prod(a["shape"])) * np.dtype(a["dtype"]).itemsize
                         for a in header.get("arrays", {}).values())
        except (table_format.TableError, OSError, AttributeError, KeyError, TypeError, ValueError):
            pass          # the verified loader reports it
        t0 = time.perf_counter()
        try:
            before = (path.stat().st_size, memory)
        except OSError:
            continue      # removed meanwhile
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always", TableCacheWarning)
            try:
                small = cache.compress_entry(path.stem, args.bound)
            except CompressionError as exc:
                why = str(exc).split(": ", 1)[1] if str(exc).startswith(f"{path}: ") else str(exc)
                print(f"usdfiber: error: {path}: cannot be compressed within {args.bound:g}: {why}", file=sys.stderr)
                failed += 1
                continue
            except TableCacheError as exc:
                raise UsageError(str(exc)) from None
        for w in caught:
            print(f"usdfiber: warning: {w.message}", file=sys.stderr)
        if small is None:
            failed += 1
            continue
        print(_compressed_line(str(path), str(path), before, small, time.perf_counter() - t0), flush=True)
        done += 1
    print(f"{done} table{'s' if done != 1 else ''} compressed, {skipped} already compressed"
          + (f", {failed} not compressed" if failed else ""))
    return 2 if failed else 0


def run_compress(args: argparse.Namespace) -> int:
    from usdfiber.cli import UsageError

    if args.cache:
        if args.files:
            raise UsageError("give FILE arguments or --cache, not both")
        return _compress_cache(args)
    if args.cache_dir is not None:
        raise UsageError("--cache-dir goes with --cache")
    if not args.files:
        raise UsageError("nothing to compress: give FILE arguments or --cache")
    if args.output is None and not args.in_place:
        raise UsageError("say where the compressed tables go: -o OUT or --in-place")
    if args.output is not None and len(args.files) > 1 and not os.path.isdir(args.output):
        raise UsageError(f"{args.output}: expected a directory for {len(args.files)} tables (-o OUT)")
    failed = 0
    for src, dst in _compress_targets(args.files, args.output, args.in_place):
        try:
            print(_compress_file(src, dst, args.bound), flush=True)
        except UsageError as exc:
            print(f"usdfiber: error: {exc}", file=sys.stderr)
            failed += 1
    return 2 if failed else 0


def _compress_targets(files: list[str], output: str | None, in_place: bool) -> list[tuple[str, str]]:
    """(source, destination) of each table; a UsageError, before anything is written, when two
    sources would be written to one file (tables of the same name from different folders into
    one -o directory, or a table given twice)."""
    from usdfiber.cli import UsageError

    pairs, seen = [], {}
    for src in files:
        if in_place:
            dst = src
        elif os.path.isdir(output):
            dst = os.path.join(output, os.path.basename(src))
        else:
            dst = output
        key = os.path.realpath(dst)
        if key in seen:
            first = seen[key]
            if os.path.realpath(first) == os.path.realpath(src):
                raise UsageError(f"{src}: given twice; expected each table once")
            raise UsageError(f"{first} and {src} would both be written to {dst}; expected tables of different "
                             f"names, or compress them into different directories (or --in-place)")
        seen[key] = src
        pairs.append((src, dst))
    return pairs


def _fmt_inputs(inputs: dict[str, Any]) -> str:
    parts = []
    units = inputs.get("units", {})
    for k, v in inputs.items():
        if k == "units":
            continue
        if k == "user_profiles":
            parts.append(f"user_profiles={len(v)} ({sum(len(u['loops']) for u in v)} loops, um)")
            continue
        if isinstance(v, dict):
            inner = ", ".join(f"{ik}={iv}" + (f" {units.get(f'{k}.{ik}', '')}".rstrip()) for ik, iv in v.items())
            parts.append(f"{k}: {inner}")
            continue
        u = units.get(k, "")
        parts.append(f"{k}={v}" + (f" {u}" if u and u != "1" else ""))
    return "; ".join(parts)


def run_inspect(args: argparse.Namespace) -> int:
    """``usdfiber table inspect``: the table's header and summary (one line for a header whose
    fields have the wrong types, as a crafted file's may)."""
    from usdfiber.cli import UsageError

    table = _load(args.file)
    try:
        return _inspect(args, table)
    except (AttributeError, TypeError, KeyError, ValueError, IndexError) as exc:
        reason = " ".join(str(exc).split()) or type(exc).__name__
        raise UsageError(f"{args.file}: malformed table header: {reason[:300]}") from None


def _inspect(args: argparse.Namespace, table: Any) -> int:
    h = table.header
    s = table.summary()
    alb = table.arrays["albedo"][:, :, 0].astype(np.float64)
    fiber = h.get("fiber") or {}
    dyed = None
    if fiber.get("mu_a_per_um") and any(fiber["mu_a_per_um"]):
        rec = table.recolour(fiber["mu_a_per_um"], fiber.get("diameter_um", 1.0) / table.baked_diameter_um)
        a = rec.albedo.astype(np.float64)
        dyed = {"mu_a_per_um": fiber["mu_a_per_um"], "diameter_um": fiber.get("diameter_um"),
                "albedo_min": a.min(axis=(0, 1)).tolist(), "albedo_mean": a.mean(axis=(0, 1)).tolist(),
                "albedo_max": a.max(axis=(0, 1)).tolist()}
    size = os.path.getsize(args.file)
    summary = dict(s, file_bytes=size,
                   albedo={"min": float(alb.min()), "mean": float(alb.mean()), "max": float(alb.max())},
                   albedo_dyed=dyed)
    if args.json:
        hdr = {k: v for k, v in h.items() if k not in ("checksums",)}
        print(json.dumps({"file": args.file, "header": hdr, "summary": summary}, indent=2, sort_keys=True))
        return 0
    res = h["resolution"]
    err = h.get("error_estimate", {})
    ph = h.get("photons", {})
    lay = h.get("layout", {})
    sym = []
    if res.get("theta_symmetric"):
        sym.append("theta symmetric (theta_i >= 0 stored)")
    else:
        sym.append("no theta symmetry (cuticle)")
    if res.get("rotationally_symmetric"):
        sym.append("rotationally symmetric (one phi_i)")
    cut = h.get("cuticle")
    lines = [
        f"{args.file}",
        f"  format:      {h.get('format')} v{h.get('version')}, layout {lay.get('name')} v{lay.get('version')}, "
        f"created {h.get('created', '?')}",
        f"  geometry:    key {h.get('geometry_key')}",
        f"  cache key:   {h.get('cache_key', '-')}",
        f"  fiber:       {h.get('kind', '?')} / {h.get('profile_family', '?')}, variant {h.get('variant', 0)}"
        + (f" of {h['variant_count']}" if 'variant_count' in h else "")
        + (f", first baked for {fiber.get('prim')}" if fiber.get("prim") else ""),
        f"  inputs:      {_fmt_inputs(h.get('inputs', {}))}",
        f"  traced:      eta {h.get('eta')}, beta {h.get('beta_deg')} deg, "
        f"profile {h.get('profile', {}).get('name')} ({h.get('profile', {}).get('edges')} edges, "
        f"{h.get('profile', {}).get('loops')} loops), baked diameter {h.get('baked_diameter_um')} um"
        + (f", cuticle tilt {cut['tilt_deg']} deg height {cut['height_um']:.4g} um spacing {cut['spacing_um']:.4g} um"
           if cut else ""),
        f"  resolution:  {res['deg']} deg: omega_i {res['theta_i']} theta x {res['phi_i']} phi, "
        f"omega_o {res['theta_o']} theta x {res['phi_o']} phi (band of {table.n_band} theta_o rows); "
        + "; ".join(sym),
        f"  photons:     {ph.get('total')} in all, {ph.get('min_per_direction')}-{ph.get('max_per_direction')} "
        f"per direction, {ph.get('batches')} batches",
        f"  error:       relative L2 of p: rms {err.get('rms', float('nan')):.4f}, median "
        f"{err.get('median', float('nan')):.4f}, max {err.get('max', float('nan')):.4f}"
        + (f" (target {err['target']})" if err.get("target") else ""),
        f"  levels:      {len(table.levels)} absorption levels, optical depth per diameter "
        f"{', '.join(f'{x:g}' for x in h.get('levels_optical_depth', []))}",
        f"  albedo:      sigma_a = 0: min {alb.min():.5f}, mean {alb.mean():.5f}, max {alb.max():.5f}",
    ]
    if dyed:
        lines.append(f"               recorded dye (mu_a {', '.join(f'{x:.4g}' for x in dyed['mu_a_per_um'])} 1/um,"
                     f" {dyed['diameter_um']} um): mean " + ", ".join(f"{x:.4f}" for x in dyed["albedo_mean"]))
    q = h.get("quantization_error", {}).get("per_level", [])
    comp = h.get("compression") if table.compressed else None
    if comp:
        lines.append(f"  compressed:  {comp.get('codec')}, rank {comp.get('rank')}, p within "
                     f"{comp.get('bound', 0):.2%} relative L2 per direction (worst {comp.get('error_max', 0):.2%}, "
                     f"rms {comp.get('error_rms', 0):.2%})")
    lines += [
        f"  storage:     {h.get('storage')} ({max(q) if q else 0:.1e} relative L2 from rounding), "
        f"{table.nbytes() / 1e6:.2f} MB in memory, {size / 1e6:.2f} MB on disk",
        "  units:       angles deg (header), p 1/sr, W um at the baked size, levels 1/um at the baked size",
        f"  bake:        {h.get('bake', {}).get('wall_seconds', float('nan')):.1f} s on "
        f"{h.get('bake', {}).get('machine', {}).get('cpus', '?')} CPUs",
    ]
    print("\n".join(lines))
    return 0


# Perceptual false colour (an inferno-like ramp): anchors at equal steps from 0 to 1.
_RAMP = np.array([
    [0.000, 0.000, 0.016], [0.122, 0.047, 0.282], [0.333, 0.059, 0.427], [0.533, 0.133, 0.416],
    [0.729, 0.212, 0.333], [0.890, 0.349, 0.200], [0.976, 0.549, 0.039], [0.976, 0.788, 0.196],
    [0.988, 1.000, 0.643],
])


def false_colour(x: np.ndarray) -> np.ndarray:
    """Map values in [0, 1] to RGB through the ramp (linear between anchors)."""
    x = np.clip(np.asarray(x, dtype=np.float64), 0.0, 1.0) * (len(_RAMP) - 1)
    i = np.minimum(np.floor(x).astype(np.int64), len(_RAMP) - 2)
    t = (x - i)[..., None]
    return (1 - t) * _RAMP[i] + t * _RAMP[i + 1]


def _plot_output(args: argparse.Namespace) -> str:
    """Where ``table plot`` writes: ``-o``, or ``<FILE's name>-<figure>.png`` inside ``-o`` when it is
    a directory; a name without an extension (no format to write) is a usage error."""
    from usdfiber.cli import UsageError

    out = args.output
    if os.path.isdir(out):
        stem = os.path.basename(args.file.rstrip(os.sep))
        stem = stem[:-4] if stem.lower().endswith(".npz") else stem
        return os.path.join(out, f"{stem}-{args.figure}.png")
    if not os.path.splitext(os.path.basename(out))[1]:
        raise UsageError(f"-o {out}: no extension to choose the image format by; expected e.g. {out}.png, "
                         f"or an existing directory")
    return out


def run_plot(args: argparse.Namespace) -> int:
    from usdfiber.cli import UsageError

    args.output = _plot_output(args)
    table = _load(args.file)
    fiber = table.header.get("fiber") or {}
    if args.scale < 1 or args.scale > 64:
        raise UsageError(f"--scale must be 1 to 64 pixels per bin, got {args.scale}")
    if args.theta_i is None:
        if args.figure == "slice":
            raise UsageError("--figure slice needs --theta-i (one light longitude, degrees)")
        args.theta_i = _THETA_I[args.figure]
    if args.psi is None:
        args.psi = [0.0, 60.0, 120.0] if args.figure == "grid" else [0.0]
    for ti in args.theta_i:
        if abs(ti) > 90:
            raise UsageError(f"--theta-i must be within [-90, 90] degrees, got {ti:g}")
    diameter = args.diameter if args.diameter is not None else float(fiber.get("diameter_um") or table.baked_diameter_um)
    if args.mu_a is not None and args.dye is not None:
        raise UsageError("give either --dye or --mu-a, not both")
    if args.mu_a is not None:
        mu_a = [float(x) for x in args.mu_a]
    elif args.dye is not None:
        from usdfiber import presets
        from usdfiber.spec.fiber import mu_a_per_um

        try:
            _cls, eps = presets.dye_values(args.dye)
        except KeyError:
            valid = list(presets.DYE_PRESETS) + list(presets.DYE_COLOURS)
            raise UsageError(f"unknown dye {args.dye!r}; valid: {', '.join(valid)}") from None
        density = args.density if args.density is not None else float(fiber.get("density_g_cm3") or 1.4)
        mu_a = [mu_a_per_um(density, args.depth_of_shade, e) for e in eps]
    else:
        mu_a = [0.0, 0.0, 0.0]
    if args.figure != "slice":
        return _write_figure(args, table, mu_a, diameter / table.baked_diameter_um)
    args.theta_i, args.psi = args.theta_i[0], args.psi[0]
    rec = table.recolour(mu_a, diameter / table.baked_diameter_um)
    g = table.grid
    h_px, w_px = g.n_theta_o * args.scale, g.n_phi_o * args.scale
    theta = np.radians(90.0 - (np.arange(h_px) + 0.5) * 180.0 / h_px)
    phi = np.radians((np.arange(w_px) + 0.5) * 360.0 / w_px)
    T, P = np.meshgrid(theta, phi, indexing="ij")
    ti, pi, psi = math.radians(args.theta_i), math.radians(args.phi_i), math.radians(args.psi)
    p = rec.eval_p(ti, pi, T, P, psi=psi, interp_o="bilinear" if args.smooth else "nearest")
    alb = rec.albedo_at(ti, pi, psi=psi)
    val = p * alb                                       # (H, W, 3)
    lum = val @ np.array([0.2126, 0.7152, 0.0722])
    top = float(lum.max())
    if not top > 0:
        raise UsageError("the slice is empty (no light scattered)")
    lo = math.log10(top) - args.decades
    with np.errstate(divide="ignore"):
        x = (np.log10(np.maximum(lum, 1e-300)) - lo) / args.decades
    img = false_colour(x)
    img[lum <= 0] = 0.0
    import OpenImageIO as oiio

    ext = os.path.splitext(args.output)[1].lower()
    if ext in (".exr", ".hdr", ".tif", ".tiff"):
        buf = oiio.ImageBuf(img.astype(np.float32))
    else:
        buf = oiio.ImageBuf((np.round(img * 255.0)).astype(np.uint8))
    spec = buf.specmod()
    spec.attribute("ImageDescription",
                   f"usdfiber BCSDF slice: log10(Lambda p) per sr, theta_i {args.theta_i:g} deg, "
                   f"phi_i {args.phi_i:g} deg, psi {args.psi:g} deg; rows theta_o +90..-90, cols phi_o 0..360")
    if not buf.write(args.output):
        raise UsageError(f"cannot write {args.output}: {buf.geterror() or oiio.geterror()}")
    print(f"wrote {args.output} ({w_px}x{h_px}): log10(Lambda p) from {lo:.3g} to {lo + args.decades:.3g} "
          f"per sr; albedo {', '.join(f'{a:.4f}' for a in np.atleast_1d(alb))}")
    return 0


def _write_figure(args: argparse.Namespace, table: Any, mu_a: list[float], diameter_scale: float) -> int:
    """``table plot --figure``: a matplotlib figure of :mod:`usdfiber.table_plot`."""
    from usdfiber import table_plot
    from usdfiber.cli import UsageError

    sigma = [float(s) for s in table.sigma_for(mu_a, diameter_scale * table.baked_diameter_um)]
    ds = 1.0  # sigma_for has applied the diameter
    try:
        if args.figure == "grid":
            fig = table_plot.scattering_grid(table, sigma, ds, theta_i=args.theta_i, psi=args.psi,
                                             phi_i=args.phi_i, decades=args.decades)
        elif args.figure == "longitudinal":
            fig = table_plot.longitudinal_curves(table, sigma, ds, theta_i=args.theta_i, phi_i=args.phi_i,
                                                 psi=args.psi[0])
        elif args.figure == "fit":
            fig = table_plot.fit_comparison([table], sigma, ds, theta_i=args.theta_i)
        else:
            fig = table_plot.error_against_photons(table)
    except ValueError as exc:
        raise UsageError(f"{args.file}: {exc}") from None
    except OSError as exc:      # the fits' cache beside the table cannot be written
        raise UsageError(f"{args.file}: cannot cache the fits beside the table: {exc.strerror or exc}") from None
    try:
        table_plot.save(fig, args.output)
    except (ValueError, OSError) as exc:
        raise UsageError(f"cannot write {args.output}: {getattr(exc, 'strerror', None) or exc}") from None
    print(f"wrote {args.output} ({args.figure})")
    return 0
