"""What the baker's benchmarks (``bench/bake_*.py``) share: the run record, the fiber cases,
2 degree histogram solid angles and errors, and the table-size model.

Every benchmark prints markdown tables and writes ``bench/results/<name>.json`` (a
:class:`Record`) with the machine (CPU model, cores, RAM, Python, Mitsuba / Dr.Jit versions
and variant), the load average before and after, the git HEAD and the SHA-256 of the baker's
sources (:data:`SOURCES`), the settings, and every measurement. ``--quick`` shrinks every
count (a smoke test, not a benchmark).

Error metrics (all on 2 degree bins, per incoming direction):

* ``2D``: relative L2 error of the exit density p(theta_o, phi_o) over the sphere,
  ``sqrt(sum dOmega (p - p_ref)^2 / sum dOmega p_ref^2)`` (90 x 180 bins, the paper's grid).
* ``marg``: relative L2 (and L1) error of the azimuthal marginal (theta_o integrated) over
  phi_o - phi_i (180 bins), the quantity :func:`usdfiber.bake.exact.azimuthal_distribution`
  gives exactly for a smooth circle.

Against a high-photon reference run of M photons of the same tracer, the measured distance d
of a run of N photons contains the reference's own noise; both are Monte Carlo estimates
(variance proportional to 1/photons), so the error of the N-photon run is
``e = d * sqrt(M / (M + N))`` (reported next to the raw d).
"""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

import bench_common
from bench_common import json_default, meminfo_gib

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))           # run from a checkout without installing

RESULTS = ROOT / "bench" / "results"
DEG = math.pi / 180.0
STEP = 2.0 * DEG                            # the paper's 2 degree bins
N_TH, N_PH = 90, 180
MAX_BOUNCES = 4096                          # BakeSettings' default, for both tracers
#: The baker's sources: every result records their SHA-256 (and which changed during the run).
SOURCES = tuple(f"usdfiber/bake/{m}.py" for m in (
    "tracer", "reference_tracer", "fiber_mesh", "exact", "settings", "statistics", "baker", "assembly", "grid",
    "absorption", "lookup", "sampler", "storage", "table", "recolour"))


def machine() -> dict[str, Any]:
    import scipy

    return bench_common.machine(scipy=scipy.__version__,
                                ram_available_gib_at_start=round(meminfo_gib("MemAvailable") or 0.0, 1))


def git_state() -> dict[str, Any]:
    return bench_common.git_state(ROOT, SOURCES, ("usdfiber",))


class Record:
    """The JSON document of one run: environment, settings, results."""

    def __init__(self, command: str, args: argparse.Namespace):
        self.t0 = time.perf_counter()
        settings = {k: v for k, v in vars(args).items() if k not in ("func", "out")}
        self.doc: dict[str, Any] = {
            "command": command,
            "argv": [sys.executable.split("/")[-1], *sys.argv],
            "started": time.strftime("%Y-%m-%d %H:%M:%S %Z"),
            "load_average_before": [round(x, 2) for x in os.getloadavg()],
            "machine": machine(),
            "git": git_state(),
            "settings": settings,
        }

    def finish(self, path: Path) -> None:
        g = git_state()
        self.doc["load_average_after"] = [round(x, 2) for x in os.getloadavg()]
        self.doc["wall_seconds"] = round(time.perf_counter() - self.t0, 1)
        changed = [s for s, h in g["sha256_16"].items() if h != self.doc["git"]["sha256_16"].get(s)]
        self.doc["sources_changed_during_run"] = changed
        if changed:
            print(f"WARNING: sources changed during the run: {changed}", file=sys.stderr)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(self.doc, indent=1, default=json_default) + "\n")
        la = self.doc["load_average_before"], self.doc["load_average_after"]
        print(f"\nwrote {path.relative_to(ROOT) if path.is_relative_to(ROOT) else path} "
              f"({self.doc['wall_seconds']} s; load average before {la[0]}, after {la[1]})")


def bench_parser(doc: str, quick_help: str | None = None) -> argparse.ArgumentParser:
    """A bake bench's command line: the script's docstring ``doc`` as description (its first
    line) and epilog, with the options every bake bench has: ``--quick`` (smaller sizes) and
    ``--out`` (the results file, else :func:`results_path`'s)."""
    ap = argparse.ArgumentParser(description=doc.splitlines()[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter, epilog=doc)
    ap.add_argument("--quick", action="store_true", help=quick_help)
    ap.add_argument("--out", type=Path)
    return ap


def results_path(args: argparse.Namespace, name: str) -> Path:
    """Where a run's results go: ``--out``, else ``bench/results/<name>.json``
    (``<name>_quick.json`` with ``--quick``, so a smoke run never replaces a full one)."""
    return args.out or RESULTS / (f"{name}_quick.json" if args.quick else f"{name}.json")


def fmt_pct(x: float | None, digits: int = 2) -> str | None:
    return None if x is None or not math.isfinite(x) else f"{100 * x:.{digits}f}%"


def fmt_time(s: float | None) -> str | None:
    if s is None or not math.isfinite(s):
        return None
    if s < 120:
        return f"{s:.3g} s"
    if s < 7200:
        return f"{s / 60:.3g} min"
    return f"{s / 3600:.3g} h"


def parse_counts(text: str) -> list[int]:
    """'16:21' -> 2^16 .. 2^21; '16,18,20' -> those powers of two."""
    if ":" in text:
        a, b = (int(x) for x in text.split(":"))
        return [1 << k for k in range(a, b + 1)]
    return [1 << int(x) for x in text.split(",") if x]


#: Benchmark cases: name -> (preset, beta override, keep the cuticle, exact answer).
CASES: dict[str, tuple[str, float | None, bool, bool]] = {
    "circle-smooth": ("polyester", 0.0, False, True),
    "polyester": ("polyester", None, False, False),
    "silk": ("silk", None, False, False),
    "cotton": ("cotton", None, False, False),
    "mercerizedCotton": ("mercerizedCotton", None, False, False),
    "wool": ("wool", None, False, False),
    "wool-cuticle": ("wool", None, True, False),
}


def fiber_case(name: str) -> dict[str, Any]:
    """Profile (variant 0, circumscribed diameter 1 um, as the baker traces it) and optics."""
    from usdfiber.bake.requests import requests_from_preset

    preset, beta, keep_cut, exact = CASES[name]
    req = requests_from_preset(preset)[0]
    return {
        "name": name, "preset": preset, "profile": req.profile(), "eta": req.eta,
        "beta_deg": req.beta_deg if beta is None else beta,
        "cuticle": req.cuticle if keep_cut else None, "exact": exact,
    }


_SOLID = None


def solid_angles() -> np.ndarray:
    global _SOLID
    if _SOLID is None:
        e = np.linspace(-0.5 * np.pi, 0.5 * np.pi, N_TH + 1)
        _SOLID = np.repeat(((np.sin(e[1:]) - np.sin(e[:-1])) * STEP)[:, None], N_PH, axis=1)
    return _SOLID


def rel_l2(p: np.ndarray, q: np.ndarray, w: np.ndarray | float = 1.0) -> float:
    den = float(np.sum(w * q * q))
    return math.sqrt(float(np.sum(w * (p - q) ** 2)) / den) if den > 0 else float("inf")


def bytes_per_direction(K: int, band: int, n_po: int, storage_bytes: int = 2) -> int:
    """Bytes of one incoming direction in the table layout (see usdfiber.bake.table):
    p and lbar (K x band x n_po each), p_scale / albedo / albedo_lbar (K float32 each),
    band_start (int16), rel_error (float32), photons (int64)."""
    return 2 * K * band * n_po * storage_bytes + 3 * 4 * K + 2 + 4 + 8


def fixed_bytes(K: int, n_width: int = 720) -> int:
    return 8 * K + 4 * n_width


def model_nbytes(n_dir: int, K: int, band: int, n_po: int) -> int:
    return n_dir * bytes_per_direction(K, band, n_po) + fixed_bytes(K)


def table_facts(table, path: Path | None = None) -> dict[str, Any]:
    g = table.grid
    K = len(table.levels)
    n_dir = g.n_theta_i * g.n_phi_i
    out = {
        "resolution_deg": g.resolution_deg, "incoming": [g.n_theta_i, g.n_phi_i], "directions": n_dir,
        "outgoing": [g.n_theta_o, g.n_phi_o], "levels": K, "band_rows": table.n_band,
        "nbytes": table.nbytes(), "model_nbytes": model_nbytes(n_dir, K, table.n_band, g.n_phi_o),
        "bytes_per_direction": bytes_per_direction(K, table.n_band, g.n_phi_o),
        "rel_error_rms": float(np.sqrt(np.mean(table.rel_error.astype(np.float64) ** 2))),
        "rel_error_max": float(table.rel_error.max()),
        "photons_per_direction": int(table.arrays["photons"].max()),
    }
    if path is not None:
        out["file_bytes"] = path.stat().st_size
    return out


def synthetic_table(res_deg: float, theta_symmetric: bool, band: int | None, seed: int = 0):
    """A table with the real layout and random contents (timing only)."""
    from usdfiber.bake.absorption import DEFAULT_LEVELS
    from usdfiber.bake.grid import Grid
    from usdfiber.bake.storage import LAYOUT, LAYOUT_VERSION
    from usdfiber.bake.table import BcsdfTable

    g = Grid(res_deg, theta_symmetric, False)
    K = len(DEFAULT_LEVELS)
    B = g.n_theta_o if band is None else min(band, g.n_theta_o)
    n_ti, n_pi, n_po = g.n_theta_i, g.n_phi_i, g.n_phi_o
    rng = np.random.default_rng(seed)
    shape = (n_ti, n_pi, K, B, n_po)
    p = np.empty(shape, dtype=np.float16)
    lb = np.empty(shape, dtype=np.float16)
    for ti in range(n_ti):          # slice by slice: no float64 temporaries of the full size
        p[ti] = rng.random((n_pi, K, B, n_po), dtype=np.float32)
        lb[ti] = rng.random((n_pi, K, B, n_po), dtype=np.float32) * 3.0
    lv = np.asarray(DEFAULT_LEVELS)
    alb = np.broadcast_to(np.exp(-lv * 0.8), (n_ti, n_pi, K)).astype(np.float32)
    arrays = {
        "p": p, "p_scale": np.ones((n_ti, n_pi, K), np.float32), "lbar": lb,
        "band_start": np.full((n_ti, n_pi), (g.n_theta_o - B) // 2, np.int16),
        "albedo": alb, "albedo_lbar": np.full((n_ti, n_pi, K), 0.8, np.float32), "levels": lv,
        "width": np.ones(720, np.float32), "rel_error": np.zeros((n_ti, n_pi), np.float32),
        "photons": np.zeros((n_ti, n_pi), np.int64),
    }
    header = {"layout": {"name": LAYOUT, "version": LAYOUT_VERSION}, "resolution": g.to_header(),
              "baked_diameter_um": 1.0}
    return BcsdfTable(header=header, arrays=arrays)
