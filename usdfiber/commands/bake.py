"""``usdfiber bake [STAGE...] [--preset NAME] [--params FILE.json] [options]``: bake BCSDF tables.

Bakes exactly the tables the inputs need, into the table cache: one per distinct
(traced geometry, cross-section variant). Prims that differ only in dye, depth of shade or
diameter share a table (those recolour it), as do curves inheriting one class and yarns
made of the same fiber. Tables already cached are reused; an interrupted bake resumes
where it stopped.

Inputs: USD stages; ``--preset NAME`` for a fiber preset (``usdfiber presets``);
``--params FILE.json`` for a fiber described by a JSON object: an optional ``"preset"`` to
start from, FiberAPI values by Python name or attribute name (``"diameter": 18``,
``"fiber:roughness:beta": 12``), and optional ``"profiles"``: user cross sections
``[{"loops": [[[x, y], ...], ...], "smooth": false}]`` in um.

The cache is ``--cache-dir``, else ``$USDFIBER_CACHE_DIR``, else ``~/.cache/usdfiber``.
A progress bar with the time left is drawn on stderr; for every table one line goes to
stdout: its cache key, file, photons, error estimate (relative L2 of p), time and status.

Before baking, each missing table's cost is estimated from a quick probe of its fiber on this
machine (``usdfiber.bake.cost``: time, size on disk, peak memory) and printed on stderr;
``--dry-run`` prints it on stdout for every table to bake, with the totals. A bake estimated
longer than ``--long-bake`` seconds (default 600) says so in a warning, with cheaper settings.

``--compress [BOUND]`` keeps the tables compressed in the cache (``usdfiber.bake.compression``,
p within BOUND, default 0.01, relative L2 per direction): each baked table is compressed before
it is stored, and cached tables found uncompressed are compressed in place. They keep their
keys: renders find them as they would the uncompressed tables. A table the bound cannot hold
is stored uncompressed, with a warning.

Exit status: 0 done, 2 bad input (one line on stderr), 130 interrupted (finished
directions are kept and resumed next time).
"""
from __future__ import annotations

import argparse
import os
import sys
import warnings
from typing import Any

from usdfiber.commands.arg_types import (add_memory_budget_option, compression_bound, positive_float, positive_int,
                                         seed)


def register(sub: argparse._SubParsersAction) -> None:
    from usdfiber.cli import one_line_errors

    p = sub.add_parser(
        "bake",
        help="bake the BCSDF tables that stages, presets or parameter files need",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("stages", nargs="*", metavar="STAGE", help="USD files whose fibers need tables")
    p.add_argument("--preset", action="append", default=[], metavar="NAME",
                   help="bake the tables of a fiber preset (repeatable)")
    p.add_argument("--params", action="append", default=[], metavar="FILE.json",
                   help="bake the tables of a fiber given as JSON (repeatable)")
    p.add_argument("--photons", type=positive_int, default=None, metavar="N",
                   help="photons per incoming direction (default 1000000; with --target-error "
                        "the first amount)")
    p.add_argument("--row-photons", type=_row_photons, default=None, metavar="N,N,...|FILE.json",
                   help="photons per incoming direction of each theta_i row of the grid (a schedule that "
                        "meets each row's error target, e.g. with --estimator expected,reciprocity; "
                        "met exactly, in batches of at most --photons / --batches, at least "
                        "--batches of them): numbers separated by commas, or a JSON file holding a list")
    p.add_argument("--target-error", type=positive_float, default=None, metavar="E",
                   help="trace each direction until the relative L2 error of p is below E "
                        "(e.g. 0.01)")
    p.add_argument("--max-photons", type=positive_int, default=None, metavar="N",
                   help="cap per direction with --target-error (default 64000000)")
    p.add_argument("--resolution", type=_resolution, default=2.0, metavar="DEG",
                   help="angular bin size in degrees, dividing 90 (default 2, the paper's), or 'auto': "
                        "the bins and incoming nodes each fiber's band limit allows against 2 degrees "
                        "(usdfiber.bake.band_limit)")
    p.add_argument("--batches", type=positive_int, default=None, metavar="B",
                   help="independent batches per direction for the error estimate (default 8)")
    p.add_argument("--max-bounces", type=positive_int, default=None, metavar="N",
                   help="interactions before a photon is dropped (default 4096)")
    p.add_argument("--seed", type=seed, default=0, help="random seed, 0 to 2^32 - 1 (default 0)")
    p.add_argument("--estimator", type=_estimator, default=None, metavar="NAME[,NAME]",
                   help="variance reduction: plain (default), expected (the exit lobe's expectation at "
                        "the outer surface, fibers without cuticle scales: about 25x less variance per "
                        "photon, 5-5.7x less time than plain at equal error on whole 2 degree tables), "
                        "stratified, reciprocity (with --incoming box) or split; combine with commas")
    p.add_argument("--expected-normals", type=positive_int, default=None, metavar="K",
                   help="microfacet normals per outer-surface event of --estimator expected (default 32; "
                        "the most per event with --expected-allocation adaptive)")
    p.add_argument("--expected-allocation", choices=("adaptive", "uniform"), default=None,
                   help="normals per event of --estimator expected: adaptive (default: 1 to K, in "
                        "proportion to the Fresnel weight of the exiting branch) or uniform (K each)")
    p.add_argument("--expected-sampler", choices=("ndf", "visible"), default=None,
                   help="how --estimator expected draws its normals: ndf (default: from the normal "
                        "distribution, weighted by their visibility) or visible (the visible normals, "
                        "about 1.2x slower at equal error)")
    p.add_argument("--incoming", choices=("centre", "box"), default="centre",
                   help="light of a table node from the bin centre (default, the paper's) or spread "
                        "over the bin (box: a reciprocal bin-averaged table)")
    p.add_argument("--cache-dir", default=None, metavar="DIR",
                   help="table cache (default $USDFIBER_CACHE_DIR or ~/.cache/usdfiber)")
    p.add_argument("--jobs", type=positive_int, default=1, metavar="N",
                   help="tables baked at once in separate processes (default 1)")
    p.add_argument("--dry-run", action="store_true",
                   help="list the tables (key, cached or not) and the estimated time and size of "
                        "those to bake, without baking")
    p.add_argument("--long-bake", type=positive_float, default=None, metavar="SECONDS",
                   help="warn before a bake estimated to take longer than this (default 600)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--compress", type=compression_bound, nargs="?", const=_default_bound(), default=None,
                   metavar="BOUND",
                   help="store the tables compressed, p within BOUND relative L2 per direction "
                        "(default 0.01; usdfiber table compress)")
    p.add_argument("--plot", action="store_true",
                   help="write each table's error-against-photons figure next to it (KEY.errors.png; "
                        "not with --scheduler or --shard)")
    add_memory_budget_option(p)
    from usdfiber.farm.command import add_bake_options

    add_bake_options(p)   # --scheduler, --shard, --task-photons, --json
    p.set_defaults(func=run)
    one_line_errors(p)


def _default_bound() -> float:
    from usdfiber.bake.compression import DEFAULT_BOUND

    return DEFAULT_BOUND


def _row_photons(text: str) -> tuple[int, ...]:
    """``--row-photons``: integers separated by commas, or a JSON file holding a list of them."""
    import json
    from pathlib import Path

    if text.strip().lower().endswith(".json"):
        try:
            value = json.loads(Path(text).read_text(encoding="utf-8"))
        except (OSError, ValueError) as exc:
            raise argparse.ArgumentTypeError(f"cannot read {text}: {exc}") from None
        if not isinstance(value, list):
            raise argparse.ArgumentTypeError(f"{text}: expected a JSON list of photons per theta_i row")
        items = value
    else:
        items = [t.strip() for t in text.split(",")]
    out = []
    for item in items:
        try:
            whole = isinstance(item, float) and item.is_integer()     # 3.5e5 in JSON
            n = positive_int(str(int(item)) if whole else str(item))
        except argparse.ArgumentTypeError:
            raise argparse.ArgumentTypeError(f"photons per row must be positive integers, got {item!r}") from None
        out.append(n)
    return tuple(out)


def _estimator(text: str) -> tuple[str, ...]:
    """``--estimator``: names separated by commas (``plain`` alone: none)."""
    names = tuple(n.strip().lower() for n in text.split(",") if n.strip())
    if not names:
        raise argparse.ArgumentTypeError("give an estimator name, e.g. expected")
    return () if names == ("plain",) else names


def _refuse_schedule(reqs: list, settings) -> str | None:
    """A one-line error if ``--row-photons`` does not have one entry per theta_i row of a
    requested table's grid, before any bake."""
    from usdfiber.bake.baker import table_grid
    from usdfiber.bake.settings import BakeError

    if settings.row_photons is None:
        return None
    for r in reqs:
        try:
            settings.check_rows(table_grid(r, settings))
        except BakeError as exc:
            prims = ", ".join(r.prims[:3]) or r.label
            return f"--row-photons for {r.label} ({prims}): {exc}"
    return None


def _refuse_unsupported_estimators(reqs: list, settings) -> str | None:
    """A one-line error if ``settings`` asks for an estimator that a requested fiber cannot take
    (the expected value and splitting need fibers without cuticle scales), before any bake."""
    need = [e for e in ("expected", "split") if e in settings.estimator]
    if not need:
        return None
    for r in reqs:
        if r.cuticle_scales is not None:
            prims = ", ".join(r.prims[:3]) or r.label
            return (f"--estimator {need[0]} needs fibers without cuticle scales; {r.label} ({prims}) has "
                    f"them: bake it separately with --estimator plain")
    return None


def _resolution(text: str) -> float | str:
    """``--resolution``: a positive number of degrees or ``auto``."""
    return "auto" if text.strip().lower() == "auto" else positive_float(text)


def _settings(args: argparse.Namespace):
    from usdfiber.bake.settings import BakeError, BakeSettings
    from usdfiber.cli import UsageError

    kw: dict[str, Any] = {"seed": args.seed, "incoming": args.incoming}
    if args.resolution == "auto":
        kw["auto_resolution"] = True
    else:
        kw["resolution_deg"] = args.resolution
    if args.photons is not None:
        kw["photons"] = args.photons
    if args.target_error is not None:
        if args.target_error >= 1:
            raise UsageError(f"--target-error must be below 1, got {args.target_error:g}")
        kw["target_error"] = args.target_error
    if args.max_photons is not None:
        kw["max_photons"] = args.max_photons
    if args.row_photons is not None:
        kw["row_photons"] = args.row_photons
    if args.batches is not None:
        kw["batches"] = args.batches
    if args.max_bounces is not None:
        kw["max_bounces"] = args.max_bounces
    if args.estimator is not None:
        kw["estimator"] = args.estimator
    if args.expected_normals is not None:
        kw["expected_normals"] = args.expected_normals
    if args.expected_allocation is not None:
        kw["expected_allocation"] = args.expected_allocation
    if args.expected_sampler is not None:
        kw["expected_sampler"] = args.expected_sampler
    try:
        return BakeSettings(**kw)
    except (BakeError, ValueError) as exc:
        raise UsageError(str(exc).replace("resolution", "--resolution", 1)) from None


def _requests(args: argparse.Namespace) -> list:
    from usdfiber.bake.requests import requests_from_params, requests_from_preset, tables_for_stage
    from usdfiber.bake.settings import BakeError
    from usdfiber.cli import UsageError
    from usdfiber.stage_io import StageOpenError, open_stage

    if not (args.stages or args.preset or args.params):
        raise UsageError("nothing to bake: give STAGE files, --preset NAME or --params FILE.json")
    reqs = []
    try:
        for path in args.stages:
            try:
                stage = open_stage(path)
            except StageOpenError as exc:
                raise UsageError(str(exc)) from None
            _validate(stage, path)
            for r in tables_for_stage(stage):
                r.prims = [f"{path}:{p}" for p in r.prims]
                reqs.append(r)
        for name in args.preset:
            reqs.extend(requests_from_preset(name))
        for path in args.params:
            reqs.extend(requests_from_params(path))
    except BakeError as exc:
        raise UsageError(str(exc)) from None
    return reqs


#: Check problems of a prim's ``fiber:table`` asset, which baking resolves.
_TABLE_PROBLEMS = frozenset({"TableMissing", "TableUnreadable", "TableStale"})


class StageRefused(Exception):
    """A stage with ``usdfiber check`` errors: nothing of it is baked (exit 1)."""


def _validate(stage: Any, path: str) -> None:
    """Refuse a stage with ``usdfiber check`` errors, with check's messages, as render does:
    its values are read only once they are known to be usable (no allocation before that)."""
    from usdfiber.validation.runner import check_stage

    report = check_stage(stage)
    # A missing or damaged table asset is what a bake makes: only the other errors refuse it.
    if any(p.code not in _TABLE_PROBLEMS for p in report.errors):
        raise StageRefused(f"{path}: the stage does not pass `usdfiber check`; not baking:\n" + report.to_text())


def _dedupe(reqs: list, cache, settings) -> list[tuple[str, Any]]:
    out: dict[str, Any] = {}
    for r in reqs:
        k = cache.key(r, settings)
        if k in out:
            out[k].prims.extend(p for p in r.prims if p not in out[k].prims)
        else:
            out[k] = r
    return list(out.items())


def _line(res, req) -> str:
    t = res.table
    ph = t.arrays["photons"]
    err = t.header.get("error_estimate", {})
    status = "cached" if not res.baked else ("baked" if not res.resumed else f"baked (resumed {res.resumed} directions)")
    per = f"{int(ph.min())}" if int(ph.min()) == int(ph.max()) else f"{int(ph.min())}-{int(ph.max())}"
    comp = t.header.get("compression")
    if isinstance(comp, dict) and "rank" in comp:
        status += f", compressed (rank {comp['rank']}, worst {comp.get('error_max', float('nan')):.2%})"
    users = ", ".join(req.prims[:3]) + (f" (+{len(req.prims) - 3})" if len(req.prims) > 3 else "")
    return (f"{res.key}  {res.path}  photons={int(ph.sum())} ({per}/direction)  "
            f"error={err.get('rms', float('nan')):.4f} rms, {err.get('max', float('nan')):.4f} max  "
            f"time={res.seconds:.1f}s  {status}  [{req.label}: {users}]")


def _write_error_plot(res) -> str:
    """``bake --plot``: the table's error against photons (usdfiber.table_plot) beside it."""
    from pathlib import Path

    from usdfiber import table_plot
    from usdfiber.cli import UsageError

    out = Path(res.path).with_suffix(".errors.png")
    try:
        table_plot.save(table_plot.error_against_photons(res.table), out)
    except (ValueError, OSError) as exc:
        raise UsageError(f"cannot write {out}: {getattr(exc, 'strerror', None) or exc}") from None
    return f"wrote {out}"


def _estimate(req, settings, cache):
    """The cost of baking ``req`` (usdfiber.bake.cost), probing its fiber if not done before;
    a fiber that cannot be traced is the bake's error (BakeError, one line)."""
    from usdfiber.bake.cost import estimate_request

    return estimate_request(req, settings, cache)


def _totals(estimates: list) -> str:
    """``", N to bake: about T, S on disk"`` for the estimates (empty when there are none)."""
    if not estimates:
        return ""
    from usdfiber.bake.cost import format_seconds, total
    from usdfiber.memory_budget import format_bytes

    t = total(estimates)
    return (f", {t['tables']} to bake: about {format_seconds(t['seconds'])} on this machine, "
            f"{format_bytes(t['disk_bytes'])} on disk")


def _warn_if_long(estimates: list, settings, args: argparse.Namespace) -> None:
    """One warning line when the bake is estimated longer than ``--long-bake`` seconds."""
    from usdfiber.bake.cost import LONG_BAKE_SECONDS, cheaper_hint, format_seconds, total

    limit = args.long_bake if args.long_bake is not None else LONG_BAKE_SECONDS
    seconds = total(estimates)["seconds"]
    if estimates and seconds > limit:
        print(f"usdfiber: warning: this bake is estimated at {format_seconds(seconds)} on this machine "
              f"(over {format_seconds(limit)}); for a cheaper table: {cheaper_hint(settings)}", file=sys.stderr)


def _worker_init(threads: int) -> None:
    try:
        from usdfiber.backend import mitsuba

        mitsuba()
        import drjit as dr

        dr.set_thread_count(threads)
    except Exception:  # noqa: BLE001 - the bake reports Mitsuba problems itself
        pass


def _worker(job: tuple) -> tuple:
    root, key, req, settings, bound = job
    import usdfiber  # noqa: F401
    from usdfiber.bake.cache import TableCache

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        res = TableCache(root).get_or_bake(req, settings, compress=bound)
    res.table = _Light(res.table)
    return key, res, [str(w.message) for w in caught]


class _Light:
    """What the parent needs of a table a worker baked (arrays stay in the worker)."""

    def __init__(self, table) -> None:
        self.header = table.header
        self.arrays = {"photons": table.arrays["photons"]}


def run(args: argparse.Namespace) -> int:
    from usdfiber.bake.cache import TableCache
    from usdfiber.cli import UsageError

    from usdfiber.bake.settings import BakeError
    from usdfiber.memory_budget import MemoryBudget

    from usdfiber.farm.command import check_farm_options

    check_farm_options(args)   # --dry-run too: it refuses what the bake would
    settings = _settings(args)
    budget = MemoryBudget.resolve(args.memory_budget)
    cache = TableCache(args.cache_dir)
    try:
        reqs = _requests(args)
    except StageRefused as exc:
        print(f"usdfiber: error: {exc}", file=sys.stderr)
        return 1
    refused = _refuse_unsupported_estimators(reqs, settings) or _refuse_schedule(reqs, settings)
    if refused:
        print(f"usdfiber: error: {refused}", file=sys.stderr)
        return 1
    jobs = _dedupe(reqs, cache, settings)
    if jobs and not args.dry_run:
        # Tables are baked --jobs at a time: that many must fit together.
        together = min(args.jobs, len(jobs))
        budget.require(together * settings.table_bytes(),
                       f"baking {together} table{'s' if together > 1 else ''} at a time at --resolution "
                       f"{'auto' if settings.auto_resolution else format(settings.resolution_deg, 'g')}")

    def show_warning(message, category, filename, lineno, file=None, line=None):
        print(f"usdfiber: warning: {message}", file=sys.stderr)

    warnings.showwarning = show_warning  # one line per warning, no source location

    if args.dry_run:
        estimates = []
        for key, req in jobs:
            serving = cache.find_serving(req, settings)
            state = "to bake" if serving is None else ("cached" if serving == key else f"served by {serving}")
            if serving is None:
                try:
                    est = _estimate(req, settings, cache)
                except BakeError as exc:
                    print(f"usdfiber: error: {exc}", file=sys.stderr)
                    return 1
                estimates.append(est)
                state += f": {est.describe()}"
            print(f"{key}  {cache.table_path(key)}  {state}  [{req.label}: {', '.join(req.prims[:3])}]")
        print(f"{len(jobs)} table{'s' if len(jobs) != 1 else ''}" + _totals(estimates))
        _warn_if_long(estimates, settings, args)
        return 0
    if not jobs:
        print("nothing to bake: no fiber prims need tables")
        return 0
    try:
        cache.root.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UsageError(f"cannot create the cache directory {cache.root}: {exc.strerror or exc}") from None
    from usdfiber.farm.command import run_bake, wants_farm

    if wants_farm(args):
        # No estimate here: the probe measures this machine, not the cluster's workers (and a
        # shard does only part of the work); the farm reports its own progress.
        return run_bake(args, reqs, settings, cache)
    # What the bake will cost, before it starts (the tables no cached table serves).
    try:
        estimates = [_estimate(req, settings, cache) for _, req in jobs
                     if cache.find_serving(req, settings) is None]
    except BakeError as exc:   # a profile that cannot be traced
        print(f"usdfiber: error: {exc}", file=sys.stderr)
        return 1
    for est in estimates:
        print(f"estimate: {est.label}: {est.describe()}", file=sys.stderr)
    if len(estimates) > 1:
        print(f"estimate: {len(jobs)} tables{_totals(estimates)}", file=sys.stderr)
    _warn_if_long(estimates, settings, args)

    from tqdm import tqdm

    show = not args.no_progress
    if args.jobs > 1 and len(jobs) > 1:
        import multiprocessing as mp

        threads = max(1, (os.cpu_count() or 1) // args.jobs)
        ctx = mp.get_context("spawn")
        bar = tqdm(total=len(jobs), unit="table", desc="tables", file=sys.stderr, disable=not show)
        with ctx.Pool(min(args.jobs, len(jobs)), initializer=_worker_init, initargs=(threads,)) as pool:
            order = {k: r for k, r in jobs}
            try:
                work = [(cache.root, k, r, settings, args.compress) for k, r in jobs]
                for key, res, msgs in pool.imap_unordered(_worker, work):
                    for m in msgs:
                        print(f"usdfiber: warning: {m}", file=sys.stderr)
                    bar.write(_line(res, order[key]), file=sys.stdout)
                    if args.plot:
                        bar.write(_write_error_plot(res), file=sys.stdout)
                    bar.update(1)
            except BakeError as exc:
                bar.close()
                print(f"usdfiber: error: {exc}", file=sys.stderr)
                return 1
        bar.close()
        return 0

    for i, (key, req) in enumerate(jobs):
        bar = None
        desc = f"[{i + 1}/{len(jobs)}] {req.label}"

        def progress(done: int, total: int, info: dict) -> None:
            nonlocal bar
            if not show:
                return
            if info.get("event") == "start":
                bar = tqdm(total=total, initial=done, unit="dir", desc=desc, file=sys.stderr,
                           dynamic_ncols=True, leave=True)
            elif bar is not None:
                bar.update(done - bar.n)
                if "rel_error" in info:
                    bar.set_postfix_str(f"err {info['rel_error']:.3f}", refresh=False)

        try:
            res = cache.get_or_bake(req, settings, progress, compress=args.compress)
        except BakeError as exc:  # a cache that cannot be written, a profile that cannot be traced
            print(f"usdfiber: error: {exc}", file=sys.stderr)
            return 1
        finally:
            if bar is not None:
                bar.close()
        print(_line(res, req), flush=True)
        if args.plot:
            print(_write_error_plot(res), flush=True)
    return 0
