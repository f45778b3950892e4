"""Fits of the standard fiber models to baked tables: :func:`fit_tables`.

Each model is fitted by ``scipy.optimize.least_squares`` (trust-region reflective, bounded)
to the objective of :mod:`usdfiber.fit.objective`, from fixed starting points, so a fit is
deterministic on a given machine.

* ``chiang`` (Mitsuba's ``hair``, MaterialX's ``chiang_hair_bsdf``): in two stages. The
  shape (``ior``, roughnesses ``beta_m``, ``beta_n``, and the cuticle tilt ``alpha`` for
  tables with cuticles; 0 for mirror-symmetric ones) is fitted to the UNDYED tables, the
  channel mean, from two starts; a dye does not change a fiber's shape in this model. Then,
  per colour channel, the absorption ``sigma_a`` (per unit radius), with the shape held,
  and then, with ``FitSettings.tints``, the three lobe tints with the absorption held (the
  dye stays in the absorption; tints correct what the model's lobes cannot carry). The undyed fit is cached
  and shared by every colour of the same tables.
* ``khungurn``: the three widths and, per channel, ``C_R`` and ``C_TT`` in one solve, from
  two starts.

Channels with identical targets (undyed tables, grey dyes) are fitted once.
"""
from __future__ import annotations

import math
import time
from typing import Any, Callable, Sequence

import numpy as np
from scipy.optimize import least_squares

from usdfiber.fit import chiang, khungurn
from usdfiber.fit.cache import FitCache, fit_key, table_identity
from usdfiber.fit.objective import FitTarget, model_albedo, relative_l2, residuals, rms_log
from usdfiber.fit.result import FitResult, FitSettings

__all__ = ["MODELS", "UnknownModelError", "check_model", "fit_tables", "fit_target", "model_values"]

#: The models :func:`fit_tables` fits, with a line about each.
MODELS: dict[str, str] = {
    "chiang": "Chiang et al. 2016 / d'Eon et al. 2011 (Mitsuba 'hair', MaterialX 'chiang_hair_bsdf')",
    "khungurn": "Khungurn et al. 2015 fabric fiber model (R and TT Gaussian lobes)",
}


class UnknownModelError(ValueError):
    """A model name :func:`fit_tables` does not know (the message lists the valid ones)."""


def check_model(model: str) -> str:
    """``model`` if it is a known model name, else UnknownModelError."""
    if model not in MODELS:
        raise UnknownModelError(f"unknown model {model!r}; valid: {', '.join(MODELS)}")
    return model


class _Counter:
    def __init__(self) -> None:
        self.n = 0


def _solve(fun: Callable[[np.ndarray], np.ndarray], starts: Sequence[np.ndarray], lo: np.ndarray,
           hi: np.ndarray, settings: FitSettings, counter: _Counter) -> np.ndarray:
    """The best of bounded least-squares solves from ``starts``."""
    best, best_cost = None, math.inf
    for x0 in starts:
        x0 = np.clip(np.asarray(x0, dtype=np.float64), lo + 1e-9, hi - 1e-9)
        res = least_squares(fun, x0, bounds=(lo, hi), method="trf", diff_step=1e-4, xtol=1e-9,
                            ftol=1e-10, gtol=1e-10, max_nfev=settings.max_evaluations)
        counter.n += int(res.nfev)
        if res.cost < best_cost:
            best, best_cost = res.x, res.cost
    return best


# ---- Chiang ----------------------------------------------------------------------------------

def _chiang_shape(target: FitTarget, settings: FitSettings, ior0: float, counter: _Counter) -> chiang.ChiangParams:
    t = target.mean_channel()
    grid = chiang.make_grid(t, settings.offsets, settings.theta_nodes)
    tilt = not target.mirror

    def params(x: np.ndarray) -> chiang.ChiangParams:
        return chiang.ChiangParams(ior=float(x[0]), beta_m=float(math.exp(x[1])), beta_n=float(math.exp(x[2])),
                                   alpha_deg=float(5.0 * x[3]) if tilt else 0.0, sigma_a=(0.0,))

    def fun(x: np.ndarray) -> np.ndarray:
        return residuals(chiang.grid_values(params(x), t, grid), t, settings.floor, settings.energy_weight)

    lo = np.array([1.2, math.log(0.02), math.log(0.02)] + ([-2.0] if tilt else []))
    hi = np.array([2.2, 0.0, 0.0] + ([2.0] if tilt else []))
    starts = [np.array([ior0, math.log(0.15), math.log(0.3)] + ([0.0] if tilt else [])),
              np.array([ior0, math.log(0.4), math.log(0.7)] + ([0.0] if tilt else []))]
    x = _solve(fun, starts, lo, hi, settings, counter)
    if not tilt:
        x = np.append(x, 0.0)
    return params(x)


def _chiang_colour(shape: chiang.ChiangParams, target: FitTarget, settings: FitSettings,
                   counter: _Counter) -> chiang.ChiangParams:
    grid = chiang.make_grid(target, settings.offsets, settings.theta_nodes)
    sig, tints = [], []
    done: dict[bytes, tuple[float, np.ndarray]] = {}
    for c in range(target.channels):
        t = target.channel(c)
        k = t.values.tobytes()
        if k in done:
            s, tt = done[k]
            sig.append(s)
            tints.append(tt)
            continue

        def fun_sigma(x: np.ndarray) -> np.ndarray:
            return residuals(chiang.grid_values(shape.with_channels([float(x[0])]), t, grid), t, settings.floor,
                             settings.energy_weight)

        # The absorption carries the dye; tints (if fitted) then correct each lobe's energy.
        scan = [0.0, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0, 2.0, 5.0, 10.0]
        costs = [float(np.sum(fun_sigma(np.array([s])) ** 2)) for s in scan]
        counter.n += len(scan)
        x = _solve(fun_sigma, [np.array([scan[int(np.argmin(costs))]])], np.array([0.0]), np.array([50.0]),
                   settings, counter)
        tt = np.ones(3)
        if settings.tints:
            sa = float(x[0])

            def fun_tint(y: np.ndarray) -> np.ndarray:
                return residuals(chiang.grid_values(shape.with_channels([sa], y[:, None]), t, grid), t,
                                 settings.floor, settings.energy_weight)

            tt = _solve(fun_tint, [np.ones(3)], np.zeros(3), np.full(3, 3.0), settings, counter)
        done[k] = (float(x[0]), tt)
        sig.append(float(x[0]))
        tints.append(tt)
    return shape.with_channels(sig, np.stack(tints, axis=1))


# ---- Khungurn --------------------------------------------------------------------------------

def _khungurn(target: FitTarget, settings: FitSettings, counter: _Counter) -> khungurn.KhungurnParams:
    # Shape (three widths) on the channel mean, then C_R and C_TT per channel with it held.
    t = target.mean_channel()

    def params(x: np.ndarray) -> khungurn.KhungurnParams:
        return khungurn.KhungurnParams(c_r=(float(x[3]),), c_tt=(float(x[4]),),
                                       beta_r_deg=math.degrees(math.exp(x[0])),
                                       beta_tt_deg=math.degrees(math.exp(x[1])),
                                       gamma_tt_deg=math.degrees(math.exp(x[2])))

    def fun(x: np.ndarray) -> np.ndarray:
        return residuals(khungurn.grid_values(params(x), t, settings.theta_nodes), t, settings.floor,
                         settings.energy_weight)

    alb = float(np.clip(model_albedo(t.values, t)[0], 0.01, 1.5))
    lo = np.array([math.log(math.radians(0.5))] * 2 + [math.log(math.radians(2.0)), 0.0, 0.0])
    hi = np.array([math.log(math.radians(60.0))] * 2 + [math.log(math.radians(120.0)), 3.0, 3.0])
    starts = [np.array([math.log(math.radians(br)), math.log(math.radians(bt)), math.log(math.radians(g)),
                        0.05 * alb, 0.9 * alb])
              for br, bt, g in ((8.0, 15.0, 30.0), (25.0, 25.0, 60.0))]
    shape = params(_solve(fun, starts, lo, hi, settings, counter))
    r, tt = khungurn.lobe_grids(shape, target, settings.theta_nodes)
    c_r, c_tt = [], []
    done: dict[bytes, tuple[float, float]] = {}
    for c in range(target.channels):
        tc = target.channel(c)
        k = tc.values.tobytes()
        if k not in done:
            def fun_c(x: np.ndarray, tc: FitTarget = tc) -> np.ndarray:
                m = (x[0] * r + x[1] * tt)[..., None]
                return residuals(m, tc, settings.floor, settings.energy_weight)

            a = float(np.clip(model_albedo(tc.values, tc)[0], 0.0, 1.5))
            x0 = np.array([shape.c_r[0] * a / alb, shape.c_tt[0] * a / alb])
            done[k] = tuple(_solve(fun_c, [x0], np.zeros(2), np.full(2, 3.0), settings, counter))
        c_r.append(float(done[k][0]))
        c_tt.append(float(done[k][1]))
    return khungurn.channel_params(shape, c_r, c_tt)


# ---- public API ------------------------------------------------------------------------------

def model_values(model: str, params: Any, target: FitTarget, settings: FitSettings | None = None) -> np.ndarray:
    """A model's ``s`` on ``target``'s bins (n_i, n_o, n_phi, C) (:mod:`usdfiber.fit.objective`)."""
    st = settings or FitSettings()
    if check_model(model) == "chiang":
        return chiang.grid_values(params, target, chiang.make_grid(target, st.offsets, st.theta_nodes))
    return khungurn.grid_values(params, target, st.theta_nodes)


def errors(model: str, params: Any, target: FitTarget, settings: FitSettings) -> dict[str, list[float]]:
    """The reported errors of ``params`` against ``target`` (see :class:`FitResult`)."""
    m = model_values(model, params, target, settings)
    return {"rel_l2": relative_l2(m, target).tolist(), "rms_log": rms_log(m, target, settings.floor).tolist(),
            "albedo_table": model_albedo(target.values, target).tolist(),
            "albedo_model": model_albedo(m, target).tolist()}


def fit_target(model: str, target: FitTarget, settings: FitSettings | None = None, *,
               shape_target: FitTarget | None = None, ior: float = 1.55,
               shape: chiang.ChiangParams | None = None) -> tuple[Any, int]:
    """Fit ``model`` to ``target``; returns (params, objective evaluations).

    Chiang: the shape is fitted to ``shape_target`` (the undyed tables; default ``target``)
    from ``ior`` unless ``shape`` is given, then the colour to ``target``.
    """
    st = settings or FitSettings()
    counter = _Counter()
    if check_model(model) == "chiang":
        if shape is None:
            shape = _chiang_shape(shape_target or target, st, ior, counter)
        return _chiang_colour(shape, target, st, counter), counter.n
    return _khungurn(target, st, counter), counter.n


def fit_tables(tables: Sequence[Any], model: str = "chiang", sigma_a: float | Sequence[float] = 0.0,
               diameter_scale: float = 1.0, settings: FitSettings | None = None, *,
               cache: FitCache | None | bool = None) -> FitResult:
    """Fit ``model`` to the tables of one fiber (its cross-section variants) recoloured for
    ``sigma_a`` (1/um, a scalar or one per channel) at ``diameter_scale``.

    ``cache``: a :class:`FitCache`; None: the one beside the first table's file (none for a
    table never saved); False: no cache. A cached fit is returned as it was stored.
    """
    check_model(model)
    st = settings or FitSettings()
    tables = list(tables)
    if not tables:
        raise ValueError("no tables to fit")
    ds = float(diameter_scale)
    if not (math.isfinite(ds) and ds > 0):
        raise ValueError(f"diameter_scale must be > 0, got {diameter_scale}")
    sig = np.atleast_1d(np.asarray(sigma_a, dtype=np.float64)).reshape(-1)
    if not np.all(np.isfinite(sig)) or np.any(sig < 0):
        raise ValueError(f"sigma_a must be finite and >= 0, got {sig.tolist()}")
    eff = [float(s * ds) for s in sig]
    ids = [table_identity(t) for t in tables]
    key = fit_key(ids, eff, model, st)
    store = FitCache.beside(tables[0]) if cache is None else (None if cache is False else cache)
    if store is not None:
        hit = store.load(key)
        if hit is not None:
            return hit
    t0 = time.perf_counter()
    target = FitTarget.from_tables(tables, sig, ds)
    evaluations = 0
    if model == "chiang":
        if any(eff):
            undyed = fit_tables(tables, "chiang", [0.0] * len(sig), 1.0, st, cache=store if store else False)
            shape = undyed.params
        else:
            shape = None
        ior0 = float(tables[0].header.get("eta") or 1.55)
        params, evaluations = fit_target("chiang", target, st, ior=ior0, shape=shape)
    else:
        params, evaluations = fit_target("khungurn", target, st)
    result = FitResult(model=model, params=params, error=errors(model, params, target, st), key=key,
                       tables=ids, sigma_a=eff, settings=st, seconds=time.perf_counter() - t0,
                       evaluations=evaluations)
    if store is not None:
        store.save(result)
    return result
