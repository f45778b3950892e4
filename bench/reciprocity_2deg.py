"""Benchmark: reciprocity averaging on top of the expected value, on full 2 degree tables.

Issue 14 asks for full 2 deg silk and cotton tables at each direction's 16M-photon error 20x
faster than the plain estimator; the expected value alone reaches 11-14x (bench/REPORT.md,
section 7). Reciprocity averages every entry of a box-filtered table with its reciprocal
partner (``usdfiber.bake.reciprocity``); this script measures what it adds on real full
tables, where every direction has its partners:

``bake``: one full 2 deg box-filtered table of a preset's first variant with the expected
value (the baker's defaults otherwise), its directions' chunks kept in ``--dir`` (run it
twice with two seeds: two independent tables of the same variant).

``analyse``: from the chunks of two such bakes A and B, per theta_i row (every phi_i pooled)
and per direction, the relative L2 error of p (level 0, solid-angle weighted) of each table
as ``||p_A - p_B||^2 / (2 ||p||^2)``, with and without reciprocity averaging (applied to A and
B separately). Then the photons each row needs to reach a target error, without averaging
(each row on its own, error^2 proportional to 1/N) and with it (an entry's variance is
``a / N`` of its own row, ``a`` estimated per entry from the two tables; the averaged
entry's variance follows from the weights, which depend on the photon counts only; the rows'
photon counts are found by a fixed-point iteration that meets every row's target), and the
ratio of the total photons: reciprocity's gain at every row's target. Targets: each row's
16M-photon error of the plain estimator from ``bench/results/full_bake_2deg_silk.json``
(``--targets``), and each row's own error without averaging (equal errors before and after).

``bake --schedule``: the end-to-end bake. The analysis's photons per row at each row's
16M-photon error with averaging become the baker's row schedule (``BakeSettings.row_photons``,
converted from photons that met the fiber to photons launched with the analysed bake's own
ratio per row, rounded up to whole batches of ``--per-batch``), baked with the expected
value and reciprocity averaging (the product's own path, ``bake_request``). ``--schedule`` may
also name a computed schedule, a JSON list of photons per row: silk's is
``bench/results/reciprocity_2deg_schedule_silk.json`` (also ``usdfiber bake --row-photons FILE``).

``rows``: while such a bake runs (its averaging needs every row), each complete row's error
without averaging against the analysed pair, beside the model's prediction at the row's
photons, and the averaged error the model's averaging ratio then gives against the target.

``wall``: the bake's wall time when it ran as several processes, each resumed from the last's
chunks, less the intervals it was stopped (SIGSTOP) so that other work could have the machine.

``progress``: a scheduled bake so far (running, stopped or finished), from its chunks alone:
each row's tracer rate (stops taken out of the group they fell in), the wall to its last chunk
less the stops, each complete row's error by the model (its directions' batch-spread estimates
over the analysis's averaging ratio) and the tracing left.

``schedule``: that row schedule alone, written as a JSON list (``--schedule-out``) without
baking, from an analysis and one of its bakes' chunks.

``reschedule --model-rows``: a schedule's bake aimed at its targets: every row scaled by one factor, the
mean over rows of (averaged error / target)^2 by that bake's ``progress`` model.

``reschedule``: a row schedule moved to other targets: each row's photons scaled by (old
target / new target)^2 and rounded to whole batches (``--rounding nearest`` by default: the old
schedule's rows were already rounded up once, and rounding up again adds about 2.5 % of
photons; ``up`` as the baker would), e.g. from the 10k-photon plain table's
``e16`` to its ``e16_unbiased`` (``full_bake_2deg.py``: the estimate freed of its own noise in
the norm, checked at 16M photons by ``target_bias.py``). Error^2 goes as 1/N per row; the
averaging mixes a row with its partners' rows, mostly its own and its mirror's for a fiber whose
light stays near the specular cone, so per-row scaling is first-order. With ``--end-to-end``
(that command's result for the old schedule) it predicts each row's error over its new target,
and with ``--ns-per-photon`` (the bake's measured tracer time per photon by rows) the tracing
time of both schedules.

``end-to-end``: that table's error per row against its target, from the two analysed bakes
(each averaged as the baker averages): the new table's error^2 is ``(d_NA + d_NB - d_AB) / 2``
with ``d_XY`` the squared L2 distance between the p of tables X and Y, over ``||p_N||^2``
(:func:`three_way_error2`).

    python bench/reciprocity_2deg.py bake --fiber silk --seed 0 --photons 10000 --dir /tmp/box2/silk-a
    python bench/reciprocity_2deg.py bake --fiber silk --seed 1 --photons 10000 --dir /tmp/box2/silk-b
    python bench/reciprocity_2deg.py analyse --fiber silk /tmp/box2/silk-a /tmp/box2/silk-b \\
        --targets bench/results/full_bake_2deg_silk.json --out bench/results/reciprocity_2deg_silk.json
    python bench/reciprocity_2deg.py bake --fiber silk --seed 2 --dir /tmp/e2e/silk \\
        --schedule bench/results/reciprocity_2deg_silk.json --schedule-chunks /tmp/box2/silk-a
    # or, the same rows: --schedule bench/results/reciprocity_2deg_schedule_silk.json
    python bench/reciprocity_2deg.py rows /tmp/e2e/silk /tmp/box2/silk-a /tmp/box2/silk-b \\
        --analysis bench/results/reciprocity_2deg_silk.json --targets bench/results/full_bake_2deg_silk.json \\
        --out bench/results/reciprocity_2deg_rows_silk.json
    python bench/reciprocity_2deg.py wall --process 2026-12-03T15:02:17 2026-12-03T16:23:01 \\
        --process ... --pauses bench/results/reciprocity_2deg_end_to_end_silk_pauses.txt \\
        --out bench/results/reciprocity_2deg_end_to_end_silk_wall.json
    python bench/reciprocity_2deg.py end-to-end /tmp/e2e/silk /tmp/box2/silk-a /tmp/box2/silk-b \\
        --targets bench/results/full_bake_2deg_silk.json --out bench/results/reciprocity_2deg_end_to_end_silk.json
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bake_common import Record  # noqa: E402


def settings(photons: int, seed: int, resolution: float = 2.0, plain: bool = False,
             stratified: bool = False) -> Any:
    """The bakes' settings: box bins with the expected value (``stratified``: its photons'
    first numbers from scrambled Sobol points, ``usdfiber.bake.sampling``), or (``plain``) the
    plain estimator at centre nodes, whose errors give each row's 16M-photon error."""
    from usdfiber.bake.settings import BakeSettings

    if plain:
        return BakeSettings(resolution_deg=resolution, photons=photons, batches=4, seed=seed)
    return BakeSettings(resolution_deg=resolution, photons=photons, batches=4, seed=seed, incoming="box",
                        estimator=("expected", "stratified") if stratified else ("expected",))


def schedule(path: Path, chunks: Path, per_batch: int) -> tuple[list[int], dict[str, Any]]:
    """Photons per direction of each theta_i row from an ``analyse`` result (its allocation at
    each row's 16M-photon error, with averaging): the allocation counts photons that met the
    fiber, as multiples of the analysed bake's; ``chunks``, that bake's directory, gives its
    photons launched and met per row. Rounded up to whole batches of ``per_batch``."""
    from usdfiber.bake.chunks import ResumeDirectory
    from usdfiber.bake.grid import Grid

    res = json.loads(Path(path).read_text())["results"]
    alloc = np.asarray(res["allocation"]["e16"]["photons_per_direction_reciprocity"], dtype=np.float64)
    fp = json.loads(Path(chunks, "bake.json").read_text())
    grid = Grid.from_header(fp["grid"])
    if grid.n_theta_i != len(alloc):
        raise SystemExit(f"{path} has {len(alloc)} rows, the bake in {chunks} {grid.n_theta_i}")
    rd = ResumeDirectory(chunks, fp)
    met, launched = np.zeros(grid.n_theta_i), np.zeros(grid.n_theta_i)
    for ti in range(grid.n_theta_i):
        for pi in range(grid.n_phi_i):
            d = rd.load_scalars(ti, pi)
            if d is None:
                raise SystemExit(f"{chunks}: direction ({ti}, {pi}) missing")
            met[ti] += d["n_hit"] + d["misses"]
            launched[ti] += d["photons"]
    rows = [int(math.ceil(a * l / m / per_batch)) * per_batch for a, m, l in zip(alloc, met, launched)]
    return rows, {"analysis": str(path), "chunks": str(chunks), "met_per_launched": (met / launched).tolist(),
                  "allocated_met": alloc.tolist()}


def bake(args: argparse.Namespace) -> None:
    from dataclasses import replace

    from usdfiber.bake.baker import bake_request
    from usdfiber.bake.requests import requests_from_preset

    req = requests_from_preset(args.fiber)[0]
    if args.plain and args.stratified:
        raise SystemExit("--stratified is an option of the expected value's bakes, not of --plain")
    st = settings(args.photons, args.seed, args.resolution, args.plain, args.stratified)
    plan = None
    if args.schedule:
        # The photons each row needs at its 16M-photon error with averaging, in whole batches
        # of the baker's size (the tracer's launches then hold about GROUP_PHOTONS photons).
        listed = json.loads(Path(args.schedule).read_text())
        if isinstance(listed, list):     # a schedule already computed (usdfiber bake --row-photons FILE)
            rows, plan = [int(n) for n in listed], {"rows": str(args.schedule)}
        elif args.schedule_chunks is None:
            raise SystemExit("--schedule with an analyse result needs --schedule-chunks")
        else:
            rows, plan = schedule(args.schedule, args.schedule_chunks, args.per_batch)
        st = replace(st, photons=args.per_batch * st.batches, row_photons=tuple(rows),
                     estimator=st.estimator + ("reciprocity",))
    c0, w0 = time.process_time(), time.perf_counter()
    table = bake_request(req, st, resume_dir=args.dir)
    table.save(Path(args.dir, "table.npz"))
    out = {"fiber": args.fiber, "seed": args.seed, "photons": args.photons, "dir": str(args.dir),
           "cpu": time.process_time() - c0, "wall": time.perf_counter() - w0,
           "settings": st.result_inputs(), "error_estimate": table.header["error_estimate"],
           "header_bake": table.header["bake"], "photons_total": table.header["photons"]["total"],
           "schedule": plan}
    Path(args.dir, "result.json").write_text(json.dumps(out, indent=1))
    print(json.dumps(out, indent=1))


def load_level0(path: Path, rows: list[int] | None = None) -> tuple[Any, dict, dict[tuple[int, int], dict[str, Any]]]:
    """The grid, fingerprint and every direction's chunk of a bake (of ``rows`` only, when
    given), level 0 only."""
    from usdfiber.bake.chunks import ResumeDirectory
    from usdfiber.bake.grid import Grid

    fp = json.loads(Path(path, "bake.json").read_text())
    grid = Grid.from_header(fp["grid"])
    rd = ResumeDirectory(path, fp)
    out = {}
    for ti in (range(grid.n_theta_i) if rows is None else rows):
        for pi in range(grid.n_phi_i):
            d = rd.load(ti, pi)
            if d is None:
                raise SystemExit(f"{path}: direction ({ti}, {pi}) missing or unusable: finish the bake first")
            d["H"], d["G"] = d["H"][:1].copy(), d["G"][:1].copy()   # not views: the levels go
            out[(ti, pi)] = d
    return grid, fp, out


def count_batches(fp: dict, slices: dict[tuple[int, int], dict[str, Any]]) -> int:
    """Each direction's batches (its photons in whole batches of the bake's size, as the baker
    counts them for the averaging), set on its slice; returns the photons per batch of ``fp``."""
    per_batch = int(fp["settings"]["photons"]) // int(fp["settings"]["batches"])
    for d in slices.values():
        d["batches"] = d["photons"] / per_batch      # a fraction where a schedule shares a row's photons
    return per_batch


def dense(grid: Any, slices: dict[tuple[int, int], dict[str, Any]]) -> np.ndarray:
    """Level 0 of every direction's H / batches, (n_theta_i, n_phi_i, bins) float64: each an
    estimate of S(I, O) / |I| (usdfiber.bake.reciprocity)."""
    n_r, n_c = grid.n_theta_o, grid.n_phi_o
    h = np.zeros((grid.n_theta_i, grid.n_phi_i, n_r, n_c), dtype=np.float32)
    for (ti, pi), d in slices.items():
        r0, r1 = d["rows"]
        h[ti, pi, r0:r1] = d["H"][0] / d["batches"]
    return h.reshape(grid.n_theta_i, grid.n_phi_i, -1)


def rel_error2(a: np.ndarray, b: np.ndarray, dom: np.ndarray) -> np.ndarray:
    """Per direction: the relative L2 error^2 of p of one of two independent estimates,
    ||p_a - p_b||^2 / (2 ||p||^2), p each direction's histogram normalized, solid-angle weighted."""
    out = np.empty(a.shape[:-1])
    for ti in range(a.shape[0]):        # a row at a time: float64 temporaries of one row only
        x, y = a[ti].astype(np.float64), b[ti].astype(np.float64)
        pa = x / np.maximum(x.sum(-1, keepdims=True), 1e-300) / dom
        pb = y / np.maximum(y.sum(-1, keepdims=True), 1e-300) / dom
        m = 0.5 * (pa + pb)
        out[ti] = (dom * (pa - pb) ** 2).sum(-1) / (2.0 * (dom * m * m).sum(-1))
    return out


def three_way_error2(n: np.ndarray, a: np.ndarray, b: np.ndarray, dom: np.ndarray) -> np.ndarray:
    """Per direction: the relative L2 error^2 of p in table ``n``, from two tables ``a`` and
    ``b`` whose noise is independent of it and of each other (same expectation):
    (||p_n - p_a||^2 + ||p_n - p_b||^2 - ||p_a - p_b||^2) / (2 ||p_n||^2), each p its histogram
    normalized, solid-angle weighted. One denominator for the three distances: normalizing each
    pair by its own mean would leave the pair's noise in it and bias the difference by about
    e_a^2 e_b^2 / 4 (here comparable with e_n^2); ``n``'s own noise biases it by e_n^2, which is negligible."""
    out = np.empty(n.shape[:-1])
    for ti in range(n.shape[0]):        # a row at a time: float64 temporaries of one row only
        pn, pa, pb = (x[ti].astype(np.float64) for x in (n, a, b))
        pn, pa, pb = (x / np.maximum(x.sum(-1, keepdims=True), 1e-300) / dom for x in (pn, pa, pb))
        d = ((dom * (pn - pa) ** 2).sum(-1) + (dom * (pn - pb) ** 2).sum(-1) - (dom * (pa - pb) ** 2).sum(-1))
        out[ti] = d / (2.0 * (dom * pn * pn).sum(-1))
    return out


def averaged(grid: Any, slices: dict[tuple[int, int], dict[str, Any]], per_batch: int) -> dict:
    """The baker's reciprocity averaging of one table's slices (level 0)."""
    from usdfiber.bake.reciprocity import reciprocal_average

    return reciprocal_average(grid, slices, per_batch)


def analyse(args: argparse.Namespace) -> None:
    from usdfiber.bake.reciprocity import incoming_measure, node_weights

    rec = Record("reciprocity_2deg", args)
    t0 = time.perf_counter()
    grid, fp, A = load_level0(args.a)
    _, fp_b, B = load_level0(args.b)
    if fp["grid"] != fp_b["grid"] or fp["profile"] != fp_b["profile"]:
        raise SystemExit("the two bakes are not of one table")
    per_batch = count_batches(fp, A)
    count_batches(fp, B)
    n_ti, n_pi = grid.n_theta_i, grid.n_phi_i
    dom = np.repeat(grid.solid_angles(), grid.n_phi_o)
    hA, hB = dense(grid, A), dense(grid, B)
    e2_plain = rel_error2(hA, hB, dom)
    # The model's inputs (float32, one level of the table each), before the averaged copies.
    N0 = np.array([[0.5 * (A[(ti, pi)]["n_hit"] + A[(ti, pi)]["misses"] + B[(ti, pi)]["n_hit"]
                           + B[(ti, pi)]["misses"]) for pi in range(n_pi)] for ti in range(n_ti)])
    wbar = np.array([[A[(ti, pi)]["norm"] / A[(ti, pi)]["batches"] for pi in range(n_pi)] for ti in range(n_ti)])
    dom32 = dom.astype(np.float32)
    a = np.empty_like(hA)
    norm2 = np.empty((n_ti, n_pi))
    for ti in range(n_ti):
        a[ti] = N0[ti][:, None].astype(np.float32) * 0.5 * (hA[ti] - hB[ti]) ** 2 / dom32
        hbar = 0.5 * (hA[ti].astype(np.float64) + hB[ti])
        norm2[ti] = (hbar ** 2 / dom).sum(-1)            # ||h||^2 in the metric of p
    del hA, hB
    # The baker's own averaging, applied to each table: its measured error.
    t1 = time.perf_counter()
    rA = averaged(grid, A, per_batch)
    del A
    rB = averaged(grid, B, per_batch)
    t_avg = (time.perf_counter() - t1) / 2
    for tab in (rA, rB):
        for k, d in tab.items():
            d["batches"] = B[k]["batches"]
    del B
    dA = dense(grid, rA)
    del rA
    dB = dense(grid, rB)
    del rB
    e2_rec = rel_error2(dA, dB, dom)
    del dA, dB

    # The model: an entry's estimate h (S / |I|) has variance a / N of its row's photons N;
    # a per entry from the two tables (one degree of freedom each, summed over a row's
    # entries; stored over dOmega, the metric's weight). Averaging with partner P: lam h_I +
    # (1 - lam) (|P| / |I|) h_P, lam = c_P / (c_I + c_P), c = |I| wbar / N (the baker's
    # weights: photon counts only).
    meas = np.broadcast_to(incoming_measure(grid)[:, None], (n_ti, n_pi))

    def errors(f: np.ndarray, recip: bool) -> np.ndarray:
        """Per direction, the modelled relative error^2 with f x N0 photons."""
        N = N0 * f
        if not recip:
            return (a.sum(-1) / N) / norm2
        c = (meas * wbar / N).ravel()
        out = np.empty((n_ti, n_pi))
        for ti in range(n_ti):
            # The baker's own weights (usdfiber.bake.reciprocity.node_weights).
            flat, lam = (x.reshape(n_pi, -1) for x in node_weights(grid, ti, c))
            part, q = np.divmod(flat, dom.size)                  # partner direction and bin
            s = meas.ravel()[part] / meas[ti][:, None]
            # The partner's variance, in its own bin's metric (undone here), seen in this bin.
            aP = a.reshape(-1)[flat] * (dom[q] / dom[None, :])
            v = lam ** 2 * a[ti] / N[ti][:, None] + (1 - lam) ** 2 * s ** 2 * aP / N.ravel()[part]
            out[ti] = v.sum(-1) / norm2[ti]
        return out

    model_plain = errors(np.ones((n_ti, n_pi)), False)
    model_rec = errors(np.ones((n_ti, n_pi)), True)

    def rows(x: np.ndarray) -> np.ndarray:
        return x.mean(axis=1)

    def allocate(target_rows: np.ndarray, recip: bool) -> tuple[np.ndarray, float]:
        """Photons per row (a multiple of N0) at which every row's mean error^2 meets its
        target: fixed-point iteration, each row scaled by its error / target."""
        f = np.ones(n_ti)
        for _ in range(args.iterations):
            e = rows(errors(np.broadcast_to(f[:, None], (n_ti, n_pi)), recip))
            f = f * e / target_rows
        e = rows(errors(np.broadcast_to(f[:, None], (n_ti, n_pi)), recip))
        return f, float(np.max(np.abs(e / target_rows - 1.0)))

    result: dict[str, Any] = {
        "table": {"fiber": args.fiber, "grid": fp["grid"], "settings": fp["settings"],
                  "directions": int(n_ti * n_pi)},
        "averaging_seconds_level0": t_avg,
        "rows": [],
    }
    photons_row = N0.mean(axis=1)
    targets: dict[str, np.ndarray] = {"own": rows(model_plain)}
    if args.targets:
        plain = json.loads(Path(args.targets).read_text())["results"]["rows"]
        e16 = np.array([r["e16"] ** 2 for r in sorted(plain, key=lambda r: r["row"])])
    if args.plain_table:
        from usdfiber.bake.table import BcsdfTable

        pt = BcsdfTable.load(args.plain_table)
        rel = np.asarray(pt.arrays["rel_error"], dtype=np.float64).reshape(n_ti, -1)
        ph = np.asarray(pt.arrays["photons"], dtype=np.float64).reshape(n_ti, -1)
        # A row's noise constant mean(e^2) x N (every phi_i pooled), at 16M photons.
        e16 = (rel ** 2 * ph).mean(axis=1) / 16e6
    if args.targets or args.plain_table:
        if len(e16) == n_ti:
            targets["e16"] = e16
        else:
            print(f"--targets has {len(e16)} rows, the tables {n_ti}: its targets are left out", file=sys.stderr)
    result["allocation"] = {}
    for name, T in targets.items():
        f_plain, res_plain = allocate(T, False)
        f_rec, res_rec = allocate(T, True)
        cost_plain, cost_rec = float((f_plain * photons_row).sum()), float((f_rec * photons_row).sum())
        result["allocation"][name] = {
            "photons_per_direction_plain": (f_plain * photons_row).tolist(),
            "photons_per_direction_reciprocity": (f_rec * photons_row).tolist(),
            "residual_plain": res_plain, "residual_reciprocity": res_rec,
            "gain": cost_plain / cost_rec}
        if args.rates:
            bakes = json.loads(Path(args.rates).read_text())["results"]["bakes"]
            ev = [x for x in bakes if x["fiber"] == args.fiber and x["variant"] == "adaptive@32"]
            rate = ev[0]["photons"] * ev[0]["directions"] / ev[0]["wall"]
            result["allocation"][name].update({
                "rate_photons_per_second": rate, "rate_source": str(args.rates),
                "hours_plain": cost_plain * n_pi / rate / 3600, "hours_reciprocity": cost_rec * n_pi / rate / 3600})
    for ti in range(n_ti):
        result["rows"].append({
            "row": ti, "theta_i_deg": float(np.degrees(grid.theta_i_nodes()[ti])),
            "error_plain": float(np.sqrt(e2_plain[ti].mean())), "error_reciprocity": float(np.sqrt(e2_rec[ti].mean())),
            "variance_ratio_measured": float(e2_plain[ti].mean() / e2_rec[ti].mean()),
            "variance_ratio_model": float(model_plain[ti].mean() / model_rec[ti].mean()),
        })
    vr = e2_plain.mean() / e2_rec.mean()
    result["summary"] = {
        "variance_ratio_rms": float(vr),
        "variance_ratio_rows_min": float(min(r["variance_ratio_measured"] for r in result["rows"])),
        "variance_ratio_rows_max": float(max(r["variance_ratio_measured"] for r in result["rows"])),
        "model_against_measured_rms": float((model_plain.mean() / model_rec.mean()) / vr),
        "gains": {k: v["gain"] for k, v in result["allocation"].items()},
        "seconds": time.perf_counter() - t0,
    }
    print(json.dumps(result["summary"], indent=1))
    rec.doc["results"] = result
    rec.finish(args.out)


def averaged_pair(a: Path, b: Path, fp: dict, cache: Path | None) -> tuple[np.ndarray, np.ndarray]:
    """Level 0 of bakes ``a`` and ``b``, each averaged as the baker averages (dense, float32);
    kept in ``cache`` (an .npz, with the two bakes' fingerprints) when given."""
    key = json.dumps([json.loads(Path(p, "bake.json").read_text()) for p in (a, b)], sort_keys=True)
    if cache is not None and Path(cache).exists():
        with np.load(cache) as z:
            if str(z["key"]) == key:
                return z["a"], z["b"]
    pair = []
    for path in (a, b):
        grid, fp2, T = load_level0(path)
        if fp2["grid"] != fp["grid"] or fp2["profile"] != fp["profile"]:
            raise SystemExit(f"{path} is not a bake of the same table")
        pair.append(dense(grid, averaged(grid, T, count_batches(fp2, T))))
        del T
    if cache is not None:
        np.savez(cache, a=pair[0], b=pair[1], key=np.array(key))
    return pair[0], pair[1]


def end_to_end(args: argparse.Namespace) -> None:
    """The error of a scheduled bake (``bake --schedule``) per row against its 16M-photon
    target, from two independent tables A and B at fewer photons (the analysed pair): with
    every table averaged as the baker averages it, the new table's relative L2 error^2 per
    direction is :func:`three_way_error2` (noise independent between the three bakes; the same
    box bins and estimators, so the same expectation)."""
    if args.pair_only:
        averaged_pair(args.a, args.b, json.loads(Path(args.a, "bake.json").read_text()), args.pair_cache)
        return
    if args.out is None:
        raise SystemExit("end-to-end needs --out")
    rec = Record("reciprocity_2deg_end_to_end", args)
    res = json.loads(Path(args.bake, "result.json").read_text())
    grid, fp, N = load_level0(args.bake)
    out_rows = []
    per_batch_n = count_batches(fp, N)
    dom = np.repeat(grid.solid_angles(), grid.n_phi_o)
    hN = dense(grid, averaged(grid, N, per_batch_n))
    photons = np.array([[N[(ti, pi)]["photons"] for pi in range(grid.n_phi_i)] for ti in range(grid.n_theta_i)])
    del N
    # (the unaveraged batch spread of each direction, the baker's own error estimate, for reference)
    for path in (args.a, args.b):
        other = json.loads(Path(path, "bake.json").read_text())
        if other["grid"] != fp["grid"] or other["profile"] != fp["profile"]:
            raise SystemExit(f"{path} is not a bake of the same table as {args.bake}")
    hA, hB = averaged_pair(args.a, args.b, fp, args.pair_cache)
    e2 = three_way_error2(hN, hA, hB, dom)
    d_ab = 2 * rel_error2(hA, hB, dom)
    plain = json.loads(Path(args.targets).read_text())["results"]["rows"]
    if any(args.target_key not in r for r in plain):
        raise SystemExit(f"{args.targets} has no {args.target_key!r} target for every row")
    e16 = np.array([r[args.target_key] ** 2 for r in sorted(plain, key=lambda r: r["row"])])
    for ti in range(grid.n_theta_i):
        out_rows.append({"row": ti, "theta_i_deg": float(np.degrees(grid.theta_i_nodes()[ti])),
                         "photons_per_direction": float(photons[ti].mean()),
                         "error": float(np.sqrt(max(e2[ti].mean(), 0.0))), "target_16m": float(np.sqrt(e16[ti])),
                         "error_over_target": float(np.sqrt(max(e2[ti].mean(), 0.0) / e16[ti])),
                         "error_pair": float(np.sqrt(d_ab[ti].mean() / 2)),
                         # the estimate's own noise: the standard error of the row's mean e^2 over
                         # its directions, carried to e (d e = d e^2 / 2e)
                         "error_standard_error": float(e2[ti].std(ddof=1) / np.sqrt(e2.shape[1])
                                                       / (2 * np.sqrt(max(e2[ti].mean(), 1e-30))))})
    ratio = np.array([r["error_over_target"] for r in out_rows])
    hb = res["header_bake"]
    summary = {
        "wall_seconds": res["wall"], "cpu_seconds": res["cpu"], "trace_seconds": hb["trace_seconds"],
        "photons_total": res["photons_total"], "directions": int(grid.n_theta_i * grid.n_phi_i),
        "error_over_target_rms": float(np.sqrt(np.mean(ratio ** 2))), "error_over_target_max": float(ratio.max()),
        "error_over_target_min": float(ratio.min()), "rows_over_target": int((ratio > 1).sum()),
        "rows_over_target_beyond_3_standard_errors": int(sum(
            r["error"] - r["target_16m"] > 3 * r["error_standard_error"] for r in out_rows)),
        "table_error_rms": float(np.sqrt(e2.mean())), "target_rms": float(np.sqrt(e16.mean())),
    }
    print(json.dumps(summary, indent=1))
    rec.doc["results"] = {"bake": res, "rows": out_rows, "summary": summary}
    rec.finish(args.out)


def parse_rates(spec: str, n_rows: int) -> np.ndarray:
    """Tracer ns per photon of every row from ``LO-HI:NS,...`` (e.g. ``0-19:2538,20-44:5000``)."""
    ns = np.full(n_rows, np.nan)
    for part in spec.split(","):
        span, value = part.split(":")
        lo, hi = (int(x) for x in span.split("-"))
        ns[lo:hi + 1] = float(value)
    if np.isnan(ns).any():
        raise SystemExit("--ns-per-photon must cover every row")
    return ns


def reschedule(args: argparse.Namespace) -> None:
    """A row schedule scaled to other targets (see the module docstring)."""
    rec = Record("reciprocity_2deg", args)
    old = np.asarray(json.loads(Path(args.schedule).read_text()), dtype=np.float64)
    source = args.model_rows if args.model_rows else args.targets
    if source is None:
        raise SystemExit("reschedule needs --targets or --model-rows")
    rows = sorted(json.loads(Path(source).read_text())["results"]["rows"], key=lambda r: r["row"])
    if [r["row"] for r in rows] != list(range(len(old))):
        raise SystemExit(f"{source} does not hold one row per row of the {len(old)}-row schedule")
    if args.model_rows:
        # One factor for every row: the schedule's bake, by its own model (each row's averaged
        # error over its target, from its chunks' batch spreads), aimed at the targets' rms.
        # Per row the model's spread is mostly its own noise (its rows hardly correlate with
        # an independent end-to-end check), so the rows keep their ratios.
        t_from = t_to = np.array([r["target_16m"] for r in rows])
        over = np.array([r["averaged_over_target"] for r in rows])
        scale = np.full(len(old), float(np.mean(over ** 2)))
    else:
        t_from = np.array([r[args.from_key] for r in rows])
        t_to = np.array([r[args.to_key] for r in rows])
        scale = (t_from / t_to) ** 2
    rnd = np.ceil if args.rounding == "up" else np.round
    new = np.maximum(rnd(old * scale / args.per_batch), 1) * args.per_batch
    out: dict[str, Any] = {"rows": [], "per_batch": args.per_batch, "rounding": args.rounding,
                           "photons_new_over_scaled": float(new.sum() / (old * scale).sum())}
    for i in range(len(old)):
        out["rows"].append({"row": i, "photons_old": int(old[i]), "photons_new": int(new[i]),
                            "target_old": float(t_from[i]), "target_new": float(t_to[i])})
    if args.end_to_end:
        e2e = {r["row"]: r for r in json.loads(Path(args.end_to_end).read_text())["results"]["rows"]}
        for r in out["rows"]:
            m = e2e[r["row"]]
            # error^2 ~ 1/N: the old bake's measured error at the new photons, over the new target.
            r["error_over_new_target_predicted"] = float(m["error"] * math.sqrt(r["photons_old"] / r["photons_new"])
                                                         / r["target_new"])
            r["error_over_new_target_at_old_photons"] = float(m["error"] / r["target_new"])
        pred = np.array([r["error_over_new_target_predicted"] for r in out["rows"]])
        out["error_over_new_target_predicted_rms"] = float(np.sqrt(np.mean(pred ** 2)))
        out["error_over_new_target_predicted_max"] = float(pred.max())
    n_pi = args.directions_per_row
    out["photons_total_old"] = float(old.sum() * n_pi)
    out["photons_total_new"] = float(new.sum() * n_pi)
    if args.ns_per_photon:
        ns = parse_rates(args.ns_per_photon, len(old))
        out["tracing_hours_old"] = float((old * n_pi * ns).sum() * 1e-9 / 3600)
        out["tracing_hours_new"] = float((new * n_pi * ns).sum() * 1e-9 / 3600)
    if args.schedule_out:
        Path(args.schedule_out).write_text(json.dumps([int(x) for x in new]) + "\n")
    rec.doc["results"] = out
    rec.finish(args.out)
    print(json.dumps({k: v for k, v in out.items() if k != "rows"}, indent=1))


#: Seconds between two chunk writes of one group (64 stored writes take about 0.4 s) are far
#: fewer than a group's tracing (40 s and more at 2 deg): a longer gap starts the next group.
GROUP_WRITE_GAP = 5.0


def when(text: str) -> float:
    """A UTC time in ISO 8601 as seconds since the epoch."""
    import datetime as dt

    return dt.datetime.fromisoformat(text).replace(tzinfo=dt.timezone.utc).timestamp()


def read_pauses(path: Path | None) -> list[tuple[float, float]]:
    """The intervals a bake was stopped (SIGSTOP): a file of 'START END' lines (UTC, ISO
    8601; '#' starts a comment line), merged where they overlap (a stop inside another is
    counted once)."""
    pauses: list[tuple[float, float]] = []
    if path is not None:
        for line in Path(path).read_text().splitlines():
            if line.strip() and not line.lstrip().startswith("#"):
                a, b = line.split()[:2]
                pauses.append((when(a), when(b)))
    merged: list[tuple[float, float]] = []
    for a, b in sorted(pauses):
        if merged and a <= merged[-1][1]:
            merged[-1] = (merged[-1][0], max(merged[-1][1], b))
        else:
            merged.append((a, b))
    return merged


def paused_within(pauses: list[tuple[float, float]], a: float, b: float) -> tuple[float, int]:
    """Seconds of ``pauses`` inside [a, b], and how many of them fall there."""
    return (sum(max(0.0, min(b, y) - max(a, x)) for x, y in pauses),
            sum(1 for x, y in pauses if min(b, y) > max(a, x)))


def wall(args: argparse.Namespace) -> None:
    """The wall time of a bake that ran as several processes (each resumed from the chunks of
    the last): each process's span (process start to its last chunk write or its end) less the
    intervals in ``--pauses`` during which the bake was stopped (SIGSTOP) so that other work
    could have the machine. Times are UTC, ISO 8601."""
    pauses = read_pauses(args.pauses)
    rec = Record("reciprocity_2deg_wall", args)
    parts = []
    for start, end in args.processes:
        a, b = when(start), when(end)
        if b <= a:
            raise SystemExit(f"--process {start} {end}: the end is not after the start")
        paused, inside = paused_within(pauses, a, b)
        parts.append({"start": start, "end": end, "span_seconds": b - a, "paused_seconds": paused,
                      "pauses": inside, "seconds": b - a - paused})
    total = sum(p["seconds"] for p in parts)
    summary = {"seconds": total, "hours": total / 3600, "paused_seconds": sum(p["paused_seconds"] for p in parts),
               "pauses": sum(p["pauses"] for p in parts)}
    print(json.dumps({"parts": parts, "summary": summary}, indent=1))
    rec.doc["results"] = {"parts": parts, "summary": summary}
    rec.finish(args.out)


def traced_rows(args: argparse.Namespace) -> None:
    """The rows a scheduled bake (``bake --schedule``) has traced so far, before its averaging
    (which needs every row): each complete row's error without averaging, against the analysed
    pair (unaveraged, :func:`three_way_error2`), beside the model's prediction at the row's
    photons (the pair's own error in that row, scaled by the photons that met the fiber); with
    the analysis's averaging ratio of that row, the averaged error the model then gives,
    against the row's 16M-photon target. And the tracer's wall time per photon by row (its chunks)."""
    rec = Record("reciprocity_2deg_traced_rows", args)
    fp = json.loads(Path(args.bake, "bake.json").read_text())
    from usdfiber.bake.grid import Grid
    grid = Grid.from_header(fp["grid"])
    names = {p.name for p in Path(args.bake).glob("d*.npz")}
    done = [ti for ti in range(grid.n_theta_i)
            if all(f"d{ti:04d}_{pi:04d}.npz" in names for pi in range(grid.n_phi_i))]
    if not done:
        raise SystemExit(f"{args.bake}: no complete theta_i row yet")
    _, _, N = load_level0(args.bake, done)
    _, fa, A = load_level0(args.a, done)
    _, fb, B = load_level0(args.b, done)
    for other in (fa, fb):
        if other["grid"] != fp["grid"] or other["profile"] != fp["profile"]:
            raise SystemExit(f"{args.a} / {args.b} are not bakes of the same table as {args.bake}")
    dom = np.repeat(grid.solid_angles(), grid.n_phi_o)
    for f, T in ((fp, N), (fa, A), (fb, B)):
        count_batches(f, T)
    hN, hA, hB = (dense(grid, T)[done] for T in (N, A, B))
    e2 = three_way_error2(hN, hA, hB, dom)
    e2_pair = rel_error2(hA, hB, dom)
    an = {r["row"]: r for r in json.loads(Path(args.analysis).read_text())["results"]["rows"]}
    targets = {r["row"]: r["e16"] for r in json.loads(Path(args.targets).read_text())["results"]["rows"]}
    out_rows = []
    for k, ti in enumerate(done):
        met = lambda T: np.mean([T[(ti, pi)]["n_hit"] + T[(ti, pi)]["misses"] for pi in range(grid.n_phi_i)])  # noqa: E731
        m_n, m_ab = met(N), 0.5 * (met(A) + met(B))
        err = float(np.sqrt(max(e2[k].mean(), 0.0)))
        se = float(e2[k].std(ddof=1) / np.sqrt(e2.shape[1]) / (2 * max(err, 1e-15)))
        pred = float(np.sqrt(e2_pair[k].mean() * m_ab / m_n))
        ratio_model = an[ti]["variance_ratio_model"]
        out_rows.append({
            "row": ti, "theta_i_deg": float(np.degrees(grid.theta_i_nodes()[ti])),
            "photons_per_direction": float(np.mean([N[(ti, pi)]["photons"] for pi in range(grid.n_phi_i)])),
            "met_per_direction": float(m_n), "error_unaveraged": err, "error_standard_error": se,
            "predicted_unaveraged": pred, "measured_over_predicted": err / pred,
            "averaging_variance_ratio_model": ratio_model,
            "averaged_error_model": float(err / np.sqrt(ratio_model)), "target_16m": targets[ti],
            "averaged_over_target": float(err / np.sqrt(ratio_model) / targets[ti]),
            "trace_wall_ns_per_photon": float(1e9 * sum(N[(ti, pi)]["seconds"] for pi in range(grid.n_phi_i))
                                       / sum(N[(ti, pi)]["photons"] for pi in range(grid.n_phi_i)))})
    mop = np.array([r["measured_over_predicted"] for r in out_rows])
    aot = np.array([r["averaged_over_target"] for r in out_rows])
    pred2 = np.array([r["predicted_unaveraged"] ** 2 for r in out_rows])
    pooled = float(np.sqrt(e2.mean(-1).sum() / pred2.sum()))
    var_sum = float((e2.var(-1, ddof=1) / e2.shape[1]).sum())
    pooled_se = float(np.sqrt(var_sum) / pred2.sum() / (2 * pooled))
    traced = sum(d["photons"] for d in N.values())
    ns = 1e9 * sum(d["seconds"] for d in N.values()) / traced
    rows_sched = fp["settings"].get("row_photons") or [int(fp["settings"]["photons"])] * grid.n_theta_i
    schedule_total = sum(rows_sched) * grid.n_phi_i
    summary = {"rows_complete": len(done), "rows": grid.n_theta_i, "photons_traced": int(traced),
               "photons_scheduled": int(schedule_total), "trace_wall_ns_per_photon": ns,
               "trace_hours_whole_schedule_at_that_rate": schedule_total * ns * 1e-9 / 3600,
               # all complete rows pooled: sum of measured e^2 over sum of predicted, with the
               # standard error of that ratio (the rows' e^2 means are independent)
               "measured_over_predicted_pooled": pooled, "measured_over_predicted_pooled_standard_error": pooled_se,
               "measured_over_predicted_rms": float(np.sqrt(np.mean(mop ** 2))),
               "measured_over_predicted_range": [float(mop.min()), float(mop.max())],
               "averaged_over_target_rms": float(np.sqrt(np.mean(aot ** 2))),
               "averaged_over_target_max": float(aot.max()), "rows_over_target": int((aot > 1).sum()),
               "rows_over_target_beyond_3_standard_errors": int(sum(
                   r["averaged_error_model"] - r["target_16m"]
                   > 3 * r["error_standard_error"] / np.sqrt(r["averaging_variance_ratio_model"]) for r in out_rows))}
    print(json.dumps(summary, indent=1))
    rec.doc["results"] = {"rows": out_rows, "summary": summary}
    rec.finish(args.out)


def box_against_centre(args: argparse.Namespace) -> None:
    """The expected value's noise and CPU per photon with box bins (each photon its own light
    direction in the 2 deg bin) against centre nodes: the extrapolations of centre tables'
    gains carry over to box tables only if these agree."""
    from usdfiber.bake import tracer
    from usdfiber.bake.grid import Grid
    from usdfiber.bake.requests import requests_from_preset
    from usdfiber.bake.settings import BakeSettings
    from usdfiber.bake.statistics import level_histograms

    rec = Record("reciprocity_2deg box", args)
    req = requests_from_preset(args.fiber)[0]
    st = BakeSettings(estimator=("expected",))
    fs = tracer.prepare(req.profile())
    g = Grid(2.0)
    dom = np.repeat(g.solid_angles(), g.n_phi_o)
    hist = tracer.ExitHistogram.for_grid(g, np.array([0.0]))
    h = math.radians(1.0)
    rows = []
    for t_deg, p_deg in ((1, 25), (41, 115), (71, 205), (87, 335)):
        t, p = math.radians(t_deg), math.radians(p_deg)
        out = {"theta_i_deg": t_deg, "phi_i_deg": p_deg}
        for name, sp in (("centre", None), ("box", (max(0.0, t - h), min(0.5 * math.pi, t + h), p - h, p + h))):
            c0 = time.process_time()
            rs = tracer.trace_many(fs, [(t, p)] * args.seeds, args.direction_photons, eta=req.eta,
                                   beta_deg=req.beta_deg, seed=[1000 + k for k in range(args.seeds)],
                                   expected=st.expected_normals, histogram=hist, max_bounces=st.max_bounces,
                                   spread=None if sp is None else [sp] * args.seeds)
            cpu = time.process_time() - c0
            ps = np.stack([level_histograms(r, g, np.array([0.0]))[0][0] / r.n_hit / dom for r in rs])
            m = ps.mean(0)
            e2 = float((dom * ps.var(0, ddof=1)).sum() / (dom * m * m).sum())   # one seed's error^2
            out[name] = {"cpu": cpu, "error_one_seed": math.sqrt(e2),
                         "variance_x_photons": e2 * args.direction_photons}
        out["variance_ratio_box_over_centre"] = out["box"]["variance_x_photons"] / out["centre"]["variance_x_photons"]
        out["cpu_ratio_box_over_centre"] = out["box"]["cpu"] / out["centre"]["cpu"]
        print(json.dumps(out), flush=True)
        rows.append(out)
    rec.doc["results"] = {"fiber": args.fiber, "photons": args.direction_photons, "seeds": args.seeds,
                          "expected_normals": st.expected_normals, "directions": rows}
    rec.finish(args.out)


def progress(args: argparse.Namespace) -> None:
    """A scheduled bake so far (running, stopped or finished), from its chunks alone: per
    theta_i row, the tracer's wall time per photon (the chunks' ``seconds``) beside the rate a
    projection assumed (``--ns-per-photon``, as ``reschedule`` takes it); the process's wall
    from ``--start`` to its last chunk write, less ``--pauses``, split into tracing and the rest
    (statistics and chunk writes between groups); and the schedule's remaining photons at the
    measured rate of the last complete row, rising by rows as the projection's rates do. With
    ``--analysis`` and ``--targets``, each complete row's error: its directions' own
    batch-spread estimates (rms, before averaging) over the root of the analysis's averaging
    variance ratio for that row, against the row's target (a model check of the table's error
    before it is finished; ``end-to-end`` measures the finished table against a reference pair).

    A chunk's ``seconds`` is its share of the tracer's wall, which runs on while the process is
    stopped: a pause that falls inside a group's tracing (from the previous group's last chunk
    write for as long as the group's seconds add up to; its statistics and chunk writes follow)
    is taken out of that group's directions in proportion to their seconds."""
    from usdfiber.bake.chunks import ResumeDirectory
    from usdfiber.bake.grid import Grid

    rec = Record("reciprocity_2deg_progress", args)
    fp = json.loads(Path(args.bake, "bake.json").read_text())
    grid = Grid.from_header(fp["grid"])
    sched = fp["settings"].get("row_photons") or [int(fp["settings"]["photons"])] * grid.n_theta_i
    projected = parse_rates(args.ns_per_photon, grid.n_theta_i) if args.ns_per_photon else None
    pauses = read_pauses(args.pauses)
    ratios = ({r["row"]: r["variance_ratio_model"] for r in json.loads(Path(args.analysis).read_text())["results"]["rows"]}
              if args.analysis else None)
    targets = ({r["row"]: r[args.target_key] for r in json.loads(Path(args.targets).read_text())["results"]["rows"]}
               if args.targets else None)
    rd = ResumeDirectory(args.bake, fp)
    chunks = []                                  # (written, ti, seconds, photons, error)
    for ti in range(grid.n_theta_i):
        for pi in range(grid.n_phi_i):
            if rd.has(ti, pi):
                d = rd.load_scalars(ti, pi)
                if d is None:
                    raise SystemExit(f"{rd.chunk_path(ti, pi)}: unusable chunk (see the warning)")
                chunks.append([rd.chunk_path(ti, pi).stat().st_mtime, ti, d["seconds"], d["photons"],
                               d["rel_error"]])
    if not chunks:
        raise SystemExit(f"{args.bake}: no chunk yet")
    chunks.sort()
    start = when(args.start)
    groups, prev_end, paused_in_tracing = 0, start, 0.0
    i = 0
    while i < len(chunks):
        j = i + 1
        while j < len(chunks) and chunks[j][0] - chunks[j - 1][0] < GROUP_WRITE_GAP:
            j += 1
        # The group's tracing: from the last group's writes for as long as its seconds say
        # (a stop inside it is in them); its statistics and writes follow.
        total = sum(c[2] for c in chunks[i:j])
        paused, _ = paused_within(pauses, prev_end, min(prev_end + total, chunks[i][0]))
        if paused > 0 and total > 0:
            keep = max(0.0, total - paused) / total
            for c in chunks[i:j]:
                c[2] *= keep
        paused_in_tracing += paused
        groups, prev_end, i = groups + 1, chunks[j - 1][0], j
    last_write = chunks[-1][0]
    rows = []
    for ti in range(grid.n_theta_i):
        mine = [c for c in chunks if c[1] == ti]
        if not mine:
            continue
        seconds, photons = sum(c[2] for c in mine), sum(c[3] for c in mine)
        r = {"row": ti, "theta_i_deg": float(np.degrees(grid.theta_i_nodes()[ti])), "directions": len(mine),
             "photons_per_direction": photons / len(mine), "trace_seconds": seconds,
             "trace_wall_ns_per_photon": 1e9 * seconds / photons}
        if projected is not None:
            r["projected_ns_per_photon"] = float(projected[ti])
            r["measured_over_projected"] = r["trace_wall_ns_per_photon"] / float(projected[ti])
        if len(mine) == grid.n_phi_i:
            # The row's own error before averaging: its directions' batch-spread estimates
            # (rms), the figure the averaging's variance ratio applies to.
            r["error_unaveraged"] = float(np.sqrt(np.mean([c[4] ** 2 for c in mine])))
            if ratios is not None:
                r["averaged_error_model"] = r["error_unaveraged"] / math.sqrt(ratios[ti])
            if targets is not None:
                r["target_16m"] = targets[ti]
                if ratios is not None:
                    r["averaged_over_target"] = r["averaged_error_model"] / targets[ti]
        rows.append(r)
    paused, n_paused = paused_within(pauses, start, last_write)
    wall_s = last_write - start - paused
    traced_s = sum(c[2] for c in chunks)
    complete = [r for r in rows if r["directions"] == grid.n_phi_i]
    done = {r["row"]: r["directions"] for r in rows}
    left_per_row = [(grid.n_phi_i - done.get(ti, 0)) * sched[ti] for ti in range(grid.n_theta_i)]
    summary = {"rows_complete": len(complete), "rows_started": len(rows), "groups": groups,
               "photons_traced": int(sum(c[3] for c in chunks)),
               "photons_scheduled": int(sum(sched) * grid.n_phi_i), "photons_left": int(sum(left_per_row)),
               "wall_seconds_to_last_chunk": wall_s, "paused_seconds": paused, "pauses": n_paused,
               "paused_seconds_inside_tracing": paused_in_tracing,
               "trace_seconds": traced_s, "between_groups_seconds": wall_s - traced_s}
    if projected is not None:
        proj_traced = sum(r["photons_per_direction"] * r["directions"] * r["projected_ns_per_photon"]
                          for r in rows) * 1e-9
        summary["projected_trace_seconds_of_traced"] = proj_traced
        summary["measured_over_projected_trace"] = traced_s / proj_traced
    if complete:
        ref = complete[-1]
        rise = projected / projected[ref["row"]] if projected is not None else np.ones(grid.n_theta_i)
        summary["trace_seconds_left_estimate"] = float(
            sum(n * ref["trace_wall_ns_per_photon"] * k for n, k in zip(left_per_row, rise)) * 1e-9)
    aot = np.array([r["averaged_over_target"] for r in rows if "averaged_over_target" in r])
    if len(aot):
        summary["averaged_over_target_rms"] = float(np.sqrt(np.mean(aot ** 2)))
        summary["averaged_over_target_max"] = float(aot.max())
        summary["rows_over_target"] = int((aot > 1).sum())
    print(json.dumps(summary, indent=1))
    rec.doc["results"] = {"rows": rows, "summary": summary}
    rec.finish(args.out)

def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="part", required=True)
    b = sub.add_parser("bake", help="one full 2 deg box-filtered table, chunks kept")
    b.add_argument("--fiber", default="silk")
    b.add_argument("--seed", type=int, default=0)
    b.add_argument("--photons", type=int, default=10_000)
    b.add_argument("--dir", type=Path, required=True)
    b.add_argument("--resolution", type=float, default=2.0, help="deg (2: the paper's; coarser for a smoke run)")
    b.add_argument("--plain", action="store_true", help="the plain estimator at centre nodes (the targets' table)")
    b.add_argument("--stratified", action="store_true",
                   help="the expected value's photons from scrambled Sobol points (the analysed bakes and the "
                        "scheduled one alike)")
    b.add_argument("--schedule", type=Path, help="an analyse result: bake each row at its 16M-photon error with "
                   "the expected value and reciprocity averaging (the end-to-end bake)")
    b.add_argument("--schedule-chunks", type=Path, help="the directory of one of the bakes that result analysed")
    b.add_argument("--per-batch", type=int, default=16384,
                   help="photons per batch with --schedule, at most (a row's photons are shared among its batches)")
    an = sub.add_parser("analyse", help="two bakes' errors with and without reciprocity, and the gain")
    an.add_argument("a", type=Path)
    an.add_argument("b", type=Path)
    an.add_argument("--fiber", default="silk")
    an.add_argument("--targets", type=Path, help="full_bake_2deg.py results: each row's 16M-photon error")
    an.add_argument("--plain-table", type=Path, help="a full plain 2 deg table (bake --plain): each row's "
                    "16M-photon error from its batch spread, instead of --targets")
    an.add_argument("--rates", type=Path, help="bake_estimator_bakes.py results with the fiber's adaptive@32 "
                    "bake: hours at its photon rate")
    an.add_argument("--iterations", type=int, default=25)
    an.add_argument("--out", type=Path, required=True)
    ee = sub.add_parser("end-to-end", help="a scheduled bake's error per row against its 16M-photon target")
    ee.add_argument("bake", type=Path, help="the directory of a bake --schedule")
    ee.add_argument("a", type=Path, help="one of the two bakes the schedule's analysis compared")
    ee.add_argument("b", type=Path, help="the other")
    ee.add_argument("--targets", type=Path, required=True, help="full_bake_2deg.py results: each row's 16M-photon error")
    ee.add_argument("--target-key", default="e16_unbiased",
                    help="which of their targets (default: e16_unbiased; e16: the former, stricter ones)")
    ee.add_argument("--out", type=Path, help="required unless --pair-only")
    ee.add_argument("--pair-cache", type=Path, help="an .npz keeping the averaged pair between runs")
    ee.add_argument("--pair-only", action="store_true", help="only fill --pair-cache (before the bake ends)")
    tr = sub.add_parser("rows", help="a scheduled bake's complete rows so far, unaveraged, against the model")
    tr.add_argument("bake", type=Path, help="the directory of a bake --schedule (finished or not)")
    tr.add_argument("a", type=Path, help="one of the two bakes the schedule's analysis compared")
    tr.add_argument("b", type=Path, help="the other")
    tr.add_argument("--analysis", type=Path, required=True, help="the analyse result the schedule came from")
    tr.add_argument("--targets", type=Path, required=True, help="full_bake_2deg.py results: each row's 16M-photon error")
    tr.add_argument("--out", type=Path, required=True)
    wl = sub.add_parser("wall", help="a bake's wall time over its resumed processes, less the pauses")
    wl.add_argument("--process", dest="processes", nargs=2, action="append", required=True,
                    metavar=("START", "END"),
                    help="one process: its start and its end or last chunk write (UTC, ISO 8601)")
    wl.add_argument("--pauses", type=Path, required=True, help="a file of 'START END' lines: the bake stopped")
    wl.add_argument("--out", type=Path, required=True)
    pg = sub.add_parser("progress", help="a scheduled bake so far: its rows' tracer rates and its wall, from its chunks")
    pg.add_argument("bake", type=Path, help="the directory of a bake --schedule (running, stopped or finished)")
    pg.add_argument("--start", required=True, help="when its process started (UTC, ISO 8601)")
    pg.add_argument("--pauses", type=Path, help="a file of 'START END' lines: the bake stopped")
    pg.add_argument("--ns-per-photon", help="the rates a projection assumed, e.g. 0-19:2538,20-44:5000")
    pg.add_argument("--analysis", type=Path, help="the analyse result the schedule came from: its rows' averaging "
                    "variance ratios (the model), for each complete row's error after averaging")
    pg.add_argument("--targets", type=Path, help="full_bake_2deg.py results: each row's 16M-photon error")
    pg.add_argument("--target-key", default="e16_unbiased", help="which of their targets (default: e16_unbiased)")
    pg.add_argument("--out", type=Path, required=True)
    sc = sub.add_parser("schedule", help="an analyse result's row schedule, written as a JSON list (no bake)")
    sc.add_argument("analysis", type=Path, help="an analyse result")
    sc.add_argument("--schedule-chunks", type=Path, required=True, help="the directory of one of the bakes it analysed")
    sc.add_argument("--per-batch", type=int, default=16384, help="rows rounded up to whole batches of this many")
    sc.add_argument("--schedule-out", type=Path, required=True)
    rs = sub.add_parser("reschedule", help="a row schedule scaled to other per-row targets")
    rs.add_argument("--schedule", type=Path, required=True, help="a JSON list of photons per direction of each row")
    rs.add_argument("--targets", type=Path, help="full_bake_2deg.py results holding both keys")
    rs.add_argument("--model-rows", type=Path,
                    help="instead of --targets: a `progress` result of this schedule's bake; every row scaled by "
                         "the mean of its rows' (averaged error / target)^2, aiming the schedule at its targets")
    rs.add_argument("--from-key", default="e16", help="the targets the schedule was made for")
    rs.add_argument("--to-key", default="e16_unbiased", help="the targets to move it to")
    rs.add_argument("--per-batch", type=int, default=16384)
    rs.add_argument("--rounding", choices=("nearest", "up"), default="nearest",
                    help="to whole batches: nearest (the old schedule was rounded up already) or up")
    rs.add_argument("--directions-per-row", type=int, default=180)
    rs.add_argument("--end-to-end", type=Path, help="the end-to-end result of the old schedule's bake")
    rs.add_argument("--ns-per-photon", help="tracer ns per photon by rows, e.g. 0-19:2538,20-44:5000")
    rs.add_argument("--schedule-out", type=Path, help="where to write the new schedule (a JSON list)")
    rs.add_argument("--out", type=Path, required=True)
    bx = sub.add_parser("box", help="the expected value's noise and CPU per photon: box bins against centre nodes")
    bx.add_argument("--fiber", default="silk")
    bx.add_argument("--direction-photons", type=int, default=1 << 18)
    bx.add_argument("--seeds", type=int, default=8)
    bx.add_argument("--out", type=Path, required=True)
    args = ap.parse_args()
    if args.part == "bake":
        bake(args)
    elif args.part == "box":
        box_against_centre(args)
    elif args.part == "end-to-end":
        end_to_end(args)
    elif args.part == "rows":
        traced_rows(args)
    elif args.part == "wall":
        wall(args)
    elif args.part == "schedule":
        rows, _ = schedule(args.analysis, args.schedule_chunks, args.per_batch)
        args.schedule_out.write_text(json.dumps(rows) + "\n")
        print(json.dumps(rows))
    elif args.part == "reschedule":
        reschedule(args)
    elif args.part == "progress":
        progress(args)
    else:
        analyse(args)


if __name__ == "__main__":
    main()
