"""Benchmark: compact, recolourable table storage (usdfiber.bake.compression) on real tables.

    python bench/bake_compression.py --tables TABLE.npz [TABLE.npz ...] [--keep-dir DIR]
    python bench/bake_compression.py --quick          # bakes a small silk table first
    python bench/bake_compression.py --sample-photons N [N ...] [--sample-incoming 30] --keep-dir DIR
    python bench/bake_compression.py --bank-memory-child RES VARIANTS [BAND] [--shared] [--ballast-gb=GB]

For every (levels-layout) table: its size in memory and on disk; the absorption-basis codec
(low-rank absorption model + blosc2 ZFP) at a 1 % bound: compression time, file size, memory,
decode (load) time, the error of p per direction against the uncompressed table at absorptions
that are not among the ones the writer checks (worst and rms over directions), and the RGB
recolouring time of both, side by side in one process; the plain blosc2 candidate (the float16
levels as float32 with TRUNC_PREC + shuffle + zstd, measured on a subset of directions and
scaled to the table); the peak resident memory of loading N compressed copies (stand-ins for
N cross-section variants) and recolouring each for 3 colours, keeping per slot what the
renderer keeps (a float16 4-vector per bin), for N = 1 and 2 (``--memory-variants``), in
subprocesses. Writes ``bench/results/compression.json`` (``--out`` names another file).

``--sample-photons``: the full 2 deg variant's compressed size measured on a sample of its
directions (a table with coarse incoming nodes, every node a full 2 deg direction) at each
photon count (:func:`sample_size`; ``compression_sample.json``). ``--bank-memory-child``: the
peak memory of a render's fiber bank for VARIANTS tables of the silk layout at RES degrees, 3
colours each (:func:`bank_memory_child`; prints one JSON line).
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from bench_common import Timer
from bake_common import Record, bench_parser, fmt_pct, results_path

#: Absorptions (1/um at the baked size) that are not among the writer's checks.
TEST_SIGMAS = (0.0, 0.4, 2.0, 9.0, 37.0, 150.0)
RGB = [(0.4, 2.0, 9.0), (1.3, 0.25, 3.3), (5.0, 0.9, 0.05)]


def rel_l2_dirs(p: np.ndarray, ref: np.ndarray, dom: np.ndarray) -> np.ndarray:
    """Relative L2 over the sphere per direction: p, ref (..., B, n_po); dom (..., B)."""
    d = dom[..., None]
    return np.sqrt(((p - ref) ** 2 * d).sum(axis=(-2, -1)) / np.maximum((ref ** 2 * d).sum(axis=(-2, -1)), 1e-300))


def summary(e: np.ndarray) -> dict[str, float]:
    e = np.asarray(e, dtype=np.float64).ravel()
    return {"max": float(e.max()), "rms": float(np.sqrt(np.mean(e ** 2))), "p99": float(np.quantile(e, 0.99))}


def median_time(fn, n: int = 3) -> dict[str, float]:
    ts = []
    for _ in range(n):
        with Timer() as t:
            fn()
        ts.append((t.wall, t.cores))
    ts.sort()
    return {"wall": ts[len(ts) // 2][0], "cores": ts[len(ts) // 2][1]}


def codec_basis(path: Path, keep: Path, bound: float) -> dict[str, Any]:
    """The absorption-basis codec on one table (levels layout)."""
    from usdfiber.bake.table import BcsdfTable

    with Timer() as t_load:
        tab = BcsdfTable.load(path)
    out: dict[str, Any] = {"table": str(path), "load_uncompressed_s": t_load.wall,
                           "summary": tab.summary(), "file_bytes": path.stat().st_size}
    with Timer() as t_c:
        comp = tab.compress(bound)
    cpath = keep / (path.stem + ".basis.npz")
    comp.save(cpath)
    out["compress"] = {"wall": t_c.wall, "cores": t_c.cores, "header": comp.header["compression"]}
    out["compressed_file_bytes"] = cpath.stat().st_size
    out["compressed_path"] = str(cpath)
    del comp
    with Timer() as t_d:
        c = BcsdfTable.load(cpath)
    out["load_compressed_s"] = {"wall": t_d.wall, "cores": t_d.cores}
    out["nbytes"] = {"uncompressed": tab.nbytes(), "compressed": c.nbytes(),
                     "compressed_basis": int(c.arrays["basis"].nbytes), "codec_bytes": int(c.arrays["basis_codec"].nbytes)}
    # Error at absorptions the writer did not check.
    dom = tab.domega_band()
    errs = {}
    for s in TEST_SIGMAS:
        e = rel_l2_dirs(c.recolour(s).p[..., 0], tab.recolour(s).p[..., 0], dom)
        errs[str(s)] = summary(e)
    out["error_vs_uncompressed"] = errs
    out["error_worst_over_tests"] = max(v["max"] for v in errs.values())
    # RGB recolouring, warm (a new colour on a table already used), side by side.
    times = {}
    for name, t in (("uncompressed", tab), ("compressed", c)):
        t.recolour(RGB[0])                       # warm-up: kernels compiled, caches built
        ts = []
        for k, rgb in enumerate(RGB[1:] + [tuple(x * 1.1 for x in RGB[0])]):
            with Timer() as tt:
                t.recolour(rgb)
            ts.append((tt.wall, tt.cores))
        ts.sort()
        times[name] = {"rgb_warm_median_s": ts[1][0], "cores": ts[1][1], "all": ts}
    out["recolour_rgb"] = times
    print(json.dumps({k: v for k, v in out.items() if k not in ("summary",)}, indent=1, default=str), flush=True)
    del tab, c
    return out


def codec_trunc(path: Path, bits: list[int], stride: int) -> list[dict[str, Any]]:
    """Candidate (a): the levels arrays p and lbar as float32 with blosc2 TRUNC_PREC (``bits``
    of mantissa kept) + shuffle + zstd, on every ``stride``-th direction; the error of the
    recoloured p against the uncompressed table at TEST_SIGMAS (the Dr.Jit recolouring of
    the decoded arrays)."""
    import blosc2

    from usdfiber.bake import recolour as kernels
    from usdfiber.bake.table import BcsdfTable

    tab = BcsdfTable.load(path)
    n_ti, n_pi, K, B, n_po = tab.arrays["p"].shape
    n = n_ti * n_pi
    idx = np.arange(0, n, stride)
    flat = lambda a: a.reshape((n,) + a.shape[2:])[idx]
    p, lb = flat(tab.arrays["p"]), flat(tab.arrays["lbar"])
    scale = flat(tab.arrays["p_scale"].astype(np.float64) * tab.arrays["albedo"])
    dom = flat(tab.domega_band())
    ref = tab.p_directions(list(TEST_SIGMAS), idx)
    raw16 = p.nbytes + lb.nbytes
    rows = []
    for m in bits:
        cp = {"codec": blosc2.Codec.ZSTD, "clevel": 5, "filters": [blosc2.Filter.TRUNC_PREC, blosc2.Filter.SHUFFLE],
              "filters_meta": [m, 0]}
        with Timer() as t_enc:
            frames = [blosc2.asarray(a.astype(np.float32), cparams=cp).to_cframe() for a in (p, lb)]
        with Timer() as t_dec:
            dec = [blosc2.ndarray_from_cframe(f)[:] for f in frames]
        got = kernels.recolour_p(dec[0], dec[1], scale, dom, tab.levels, list(TEST_SIGMAS))
        e = np.stack([rel_l2_dirs(got[..., k], ref[..., k], dom) for k in range(len(TEST_SIGMAS))])
        nbytes = sum(len(f) for f in frames)
        rows.append({"mantissa_bits": m, "bytes_subset": nbytes, "ratio_to_float16": nbytes / raw16,
                     "bytes_table_est": nbytes * n / len(idx), "error": summary(e.max(axis=0)),
                     "encode_s_subset": t_enc.wall, "decode_s_subset": t_dec.wall})
        print(json.dumps(rows[-1]), flush=True)
    return rows


def memory_child(path: str, variants: int) -> None:
    """(Run in a subprocess.) Load ``variants`` copies of a compressed table and recolour each for
    3 colours plus no absorption, keeping per slot a float16 4-vector per bin (what the renderer
    keeps: Lambda p RGB and p0); print the peak RSS."""
    from usdfiber.bake.table import BcsdfTable

    keep = []
    t0 = time.perf_counter()
    for _ in range(variants):
        t = BcsdfTable.load(path)
        p0 = t.recolour(0.0).p[..., 0]
        for rgb in RGB:
            rec = t.recolour(rgb)
            node = np.empty(rec.p.shape[:-1] + (4,), np.float16)
            node[..., :3] = rec.p
            node[..., 3] = p0
            keep.append(node)
            del rec
        keep.append(t)
    # VmHWM, not ru_maxrss: on Linux ru_maxrss survives execve, so a child would report its
    # parent's peak.
    with open("/proc/self/status") as f:
        peak = next(int(line.split()[1]) * 1024 for line in f if line.startswith("VmHWM:"))
    print(json.dumps({"variants": variants, "slots": 3 * variants, "peak_rss_bytes": peak,
                      "nodes_bytes": sum(k.nbytes for k in keep if isinstance(k, np.ndarray)),
                      "wall_s": time.perf_counter() - t0}))


def bank_memory_child(res: float, variants: int, band: int = 83, shared: bool = False,
                      ballast_gb: float = 0.0) -> None:
    """(Run in a subprocess.) What a render keeps for ``variants`` tables of the extruded
    (silk/cotton) layout at ``res`` degrees (random contents: memory does not depend on them),
    each recoloured for the 3 RGB colours: the fiber bank (``FiberBank.build``), then the
    Mitsuba BSDF made from it as ``usdfiber render`` makes it (``fiber_bsdf(...,
    release_host=True)``: the float16 nodes, the sampler's CDFs and the per-node albedo on the
    device, the host nodes dropped as they are copied), then a render of a fiber mat whose
    fibers use every slot (64 x 64, 4 spp) to show that it renders. ``shared``: the variants
    share one table's arrays (distinct tables to the bank; the tables' own bytes are then
    counted once, ``table_bytes`` says how much one is). ``ballast_gb``: that many GB held
    (written, so resident) for the whole run: a stand-in for tables larger than the synthetic
    one (e.g. four compressed 2 deg silk variants). Prints the peak RSS and each part."""
    import dataclasses

    import drjit as dr

    from bake_common import synthetic_table
    from render_bench import fiber_mat, mat_scene
    from usdfiber.backend import mitsuba
    from usdfiber.translators.mitsuba.fiber_bank import FiberBank, FiberSlot
    from usdfiber.translators.mitsuba.fiber_bsdf import fiber_bsdf
    from usdfiber.translators.mitsuba.curves import reference_normals
    from usdfiber.translators.mitsuba.integrator import register as register_integrator

    mi = mitsuba()
    register_integrator(mi)
    rss = lambda key: next(int(l.split()[1]) * 1024 for l in open("/proc/self/status") if l.startswith(key))
    ballast = np.ones(int(ballast_gb * 1e9) // 8) if ballast_gb > 0 else None
    t0 = time.perf_counter()
    if shared:
        one = synthetic_table(res, True, band, seed=0)
        tables = [one] + [dataclasses.replace(one, _recoloured={}) for _ in range(variants - 1)]
    else:
        tables = [synthetic_table(res, True, band, seed=v) for v in range(variants)]
    slots = [FiberSlot(t, rgb) for t in tables for rgb in RGB]
    after_tables = rss("VmRSS:")
    bank = FiberBank.build(slots)
    t_bank = time.perf_counter() - t0
    after_bank = rss("VmRSS:")
    fam = bank.families[False]
    device_bytes = fam.nbytes()
    nodes = int(np.prod(fam.slice_shape))
    geom, length = fiber_mat(48)
    seg_slot = (np.arange(geom.curve_count) % len(slots))[geom.segment_curve]
    seg_psi = np.zeros(geom.segment_count)
    bsdf = fiber_bsdf(mi, bank, seg_slot, seg_psi, reference_normals(geom), release_host=True)
    t_device = time.perf_counter() - t0 - t_bank
    after_device = rss("VmRSS:")
    scene = mat_scene(mi, geom, length, bsdf, 64, integrator="usdfiber_path")
    t1 = time.perf_counter()
    img = np.array(mi.render(scene, spp=4))
    dr.sync_thread()
    t_render = time.perf_counter() - t1
    print(json.dumps({"res": res, "variants": variants, "slots": len(slots), "band": band, "shared_tables": shared,
                      "stored_nodes_per_slot": nodes, "stored_grid": list(fam.slice_shape), "pages": len(bsdf.fiber.families[1].pages),
                      "table_bytes": sum(t.nbytes() for t in tables[:1 if shared else None]),
                      "device_bytes": device_bytes, "rss_after_tables": after_tables, "rss_after_bank": after_bank,
                      "rss_after_device": after_device, "rss_end": rss("VmRSS:"), "peak_rss_bytes": rss("VmHWM:"),
                      "bank_s": t_bank, "device_s": t_device, "render_s": t_render,
                      "ballast_bytes": 0 if ballast is None else int(ballast.nbytes),
                      "image_finite": bool(np.all(np.isfinite(img))), "image_mean": float(img[..., :3].mean()),
                      "wall_s": time.perf_counter() - t0}))


def memory(path: str, variants: list[int]) -> list[dict[str, Any]]:
    out = []
    for v in variants:
        r = subprocess.run([sys.executable, __file__, "--memory-child", path, str(v)], capture_output=True, text=True)
        if r.returncode != 0:
            out.append({"variants": v, "error": r.stderr.strip().splitlines()[-1:]})
        else:
            out.append(json.loads(r.stdout.strip().splitlines()[-1]))
        print(json.dumps(out[-1]), flush=True)
    return out


def quick_table(root: Path) -> Path:
    from usdfiber.bake.cache import TableCache
    from usdfiber.bake.requests import requests_from_preset
    from usdfiber.bake.settings import BakeSettings

    res = TableCache(root).get_or_bake(requests_from_preset("silk")[0],
                                       BakeSettings(resolution_deg=15, photons=8192, batches=4))
    return res.path


def sample_size(keep: Path, fiber: str, photons: list[int], incoming_deg: float, bound: float) -> list[dict[str, Any]]:
    """The full 2 deg variant's compressed size from a sample of its directions.

    A table with 2 deg outgoing bins and incoming nodes every ``incoming_deg`` holds full
    2 deg directions only (each node is traced, binned and compressed exactly as in the full
    table). The codec works per incoming direction, so the full variant's file is its bytes
    per direction x the full table's directions plus a few fixed arrays (measured here too):
    the additive parts of the full size, measured at each photon count (the trend against
    the table's own noise). Bakes through a table cache under ``keep`` (reused by a rerun)."""
    from usdfiber.bake.cache import TableCache
    from usdfiber.bake.grid import Grid
    from usdfiber.bake.requests import requests_from_preset
    from usdfiber.bake.settings import BakeSettings

    req = requests_from_preset(fiber)[0]
    full = Grid(2.0, True, False)
    n_full = full.n_theta_i * full.n_phi_i
    rows = []
    for n in photons:
        st = BakeSettings(resolution_deg=2.0, incoming_deg=incoming_deg, photons=n, batches=8)
        with Timer() as t_b:
            res = TableCache(keep / "cache").get_or_bake(req, st)
        tab = res.table
        n_dir = tab.grid.n_theta_i * tab.grid.n_phi_i
        with Timer() as t_c:
            comp = tab.compress(bound)
        cpath = keep / f"{fiber}_2deg_in{incoming_deg:g}_{n}.basis.npz"
        comp.save(cpath)
        a = comp.arrays
        # Arrays with one entry per direction scale with the table; the rest is fixed.
        per_dir = int(a["basis_codec"].nbytes) + sum(int(v.nbytes) for k, v in a.items()
                                                     if k not in ("basis", "basis_codec", "levels", "width",
                                                                  "absorptions", "basis_groups"))
        fixed = cpath.stat().st_size - per_dir
        err = tab.rel_error.astype(np.float64)
        row = {"photons": n, "directions": n_dir, "baked": res.baked, "bake_s": res.seconds,
               "bake_cores": t_b.cores if res.baked else None,
               "noise_rms": float(np.sqrt(np.mean(err ** 2))), "noise_max": float(err.max()),
               "noise_per_theta_i": np.sqrt(np.mean(err ** 2, axis=1)).tolist(),
               "band": tab.n_band, "rank": comp.header["compression"]["rank"],
               "compression_error_max": comp.header["compression"]["error_max"],
               "compress_s": t_c.wall, "compress_cores": t_c.cores,
               "uncompressed_file_bytes": res.path.stat().st_size, "compressed_file_bytes": cpath.stat().st_size,
               "codec_bytes": int(a["basis_codec"].nbytes), "per_direction_bytes": per_dir / n_dir,
               "fixed_bytes": fixed, "full_directions": n_full,
               "full_file_bytes_est": per_dir / n_dir * n_full + fixed,
               "full_uncompressed_file_bytes_est": res.path.stat().st_size / n_dir * n_full,
               "full_memory_bytes_est": comp.nbytes() / n_dir * n_full}
        rows.append(row)
        print(f"{fiber} {n} photons/direction ({n_dir} directions, noise rms {fmt_pct(row['noise_rms'])}, "
              f"max {fmt_pct(row['noise_max'])}): rank {row['rank']}, {row['per_direction_bytes'] / 1e3:.1f} kB per "
              f"direction -> full variant {row['full_file_bytes_est'] / 1e6:.0f} MB "
              f"(uncompressed {row['full_uncompressed_file_bytes_est'] / 1e6:.0f} MB)", flush=True)
        del tab, comp, res
    return rows


def cmd_compression(args: argparse.Namespace) -> int:
    rec = Record("compression", args)
    if args.sample_photons:
        keep = Path(args.keep_dir or tempfile.mkdtemp(prefix="usdfiber-compression-"))
        keep.mkdir(parents=True, exist_ok=True)
        rec.doc["results"] = sample_size(keep, args.fiber, args.sample_photons, args.sample_incoming, args.bound)
        rec.finish(results_path(args, "compression_sample"))
        return 0
    keep = Path(args.keep_dir or tempfile.mkdtemp(prefix="usdfiber-compression-"))
    keep.mkdir(parents=True, exist_ok=True)
    tables = [Path(p) for p in args.tables] or [quick_table(keep / "cache")]
    results = []
    for path in tables:
        r = codec_basis(path, keep, args.bound)
        if args.trunc_bits:
            r["trunc_prec_zstd"] = codec_trunc(path, args.trunc_bits, args.trunc_stride)
        if args.memory_variants:
            r["memory"] = memory(r["compressed_path"], args.memory_variants)
        results.append(r)
        c = r["compress"]["header"]
        print(f"{path.name}: file {r['file_bytes'] / 1e6:.1f} MB -> {r['compressed_file_bytes'] / 1e6:.1f} MB, "
              f"memory {r['nbytes']['uncompressed'] / 1e6:.0f} -> {r['nbytes']['compressed'] / 1e6:.0f} MB, "
              f"rank {c['rank']}, error max {fmt_pct(c['error_max'])} (checked), "
              f"{fmt_pct(r['error_worst_over_tests'])} (other absorptions); RGB recolour "
              f"{r['recolour_rgb']['uncompressed']['rgb_warm_median_s']:.2f} s -> "
              f"{r['recolour_rgb']['compressed']['rgb_warm_median_s']:.2f} s", flush=True)
    rec.doc["results"] = results
    rec.finish(results_path(args, "compression"))
    return 0


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["--memory-child"]:
        memory_child(argv[1], int(argv[2]))
        return 0
    if argv[:1] == ["--bank-memory-child"]:
        ballast = next((float(a.split("=")[1]) for a in argv if a.startswith("--ballast-gb=")), 0.0)
        bank_memory_child(float(argv[1]), int(argv[2]), band=int(argv[3]) if len(argv) > 3 else 83,
                          shared="--shared" in argv, ballast_gb=ballast)
        return 0
    ap = bench_parser(__doc__, "bake a small 15 deg silk table and measure it")
    ap.add_argument("--tables", nargs="*", default=[], help="uncompressed table files")
    ap.add_argument("--bound", type=float, default=0.01)
    ap.add_argument("--keep-dir", help="where the compressed tables are written (default: a temporary directory)")
    ap.add_argument("--trunc-bits", type=int, nargs="*", default=[8, 6, 4], help="TRUNC_PREC mantissa bits")
    ap.add_argument("--trunc-stride", type=int, default=16, help="every N-th direction for TRUNC_PREC")
    ap.add_argument("--memory-variants", type=int, nargs="*", default=[1, 2])
    ap.add_argument("--sample-photons", type=int, nargs="*", default=[],
                    help="measure the full 2 deg size from a sample of directions baked at these photons each")
    ap.add_argument("--sample-incoming", type=float, default=30.0, help="incoming node spacing of the sample (deg)")
    ap.add_argument("--fiber", default="silk", help="preset of the sampled table (variant 0)")
    return cmd_compression(ap.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
