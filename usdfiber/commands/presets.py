"""``usdfiber presets [NAME] [--json]``: the fiber, dye and yarn presets.

Shows each preset's values as published in Aliaga et al. 2017 (Table 1, Section 3.1,
Table 3), the single values authored on prims (midpoints of published ranges), units and
sources. For fibers both Table 1's beta and arctan(Ra / l) are shown: they differ for
polyester, silk and wool; presets author Table 1's beta.
"""
from __future__ import annotations

import argparse
import json
from typing import Any

from usdfiber.spec.attributes import Fiber


def register(sub: argparse._SubParsersAction) -> None:
    from usdfiber.cli import one_line_errors

    p = sub.add_parser(
        "presets",
        help="list the fiber, dye and yarn presets (published and authored values)",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("name", nargs="?", help="show only this preset (fiber, dye, dye colour or yarn)")
    p.add_argument("--json", action="store_true", help="print JSON instead of text")
    p.set_defaults(func=run)
    one_line_errors(p)


def _rng(r: tuple[float, float] | None) -> Any:
    return None if r is None else [r[0], r[1]]


def _fiber(p) -> dict[str, Any]:
    t = p.published
    return {
        "type": "fiber",
        "name": p.name,
        "published": {
            "row": t.fiber,
            "diameter_um": _rng(t.diameter_um),
            "density_g_cm3": t.density_g_cm3,
            "eta_parallel": t.eta_parallel,
            "eta_perpendicular": t.eta_perpendicular,
            "ra_nm": _rng(t.ra_nm),
            "profile_length_nm": t.profile_length_nm,
            "beta_deg": _rng(t.beta_deg),
        },
        "derived": {"beta_from_ra_deg": _rng(t.beta_from_ra_deg())},
        "authored": p.fiber_attributes(),
        "profile_family": p.profile_family,
        "cuticle_source": p.cuticle.source or None,
        "note": p.note or None,
        "source": p.source,
    }


def _dye(d) -> dict[str, Any]:
    return {"type": "dye", "name": d.name, "dye_class": d.dye_class,
            "published": {"epsilon_L_mg_cm": _rng(d.epsilon_range)},
            "authored": {Fiber.DYE_CLASS: d.dye_class, Fiber.DYE_EXTINCTION: list(d.extinction)},
            "used_for": d.used_for, "source": d.source}


def _colour(c) -> dict[str, Any]:
    return {"type": "dyeColour", "name": c.name, "dye": c.dye, "dye_class": c.dye_class,
            "authored": {Fiber.DYE_CLASS: c.dye_class, Fiber.DYE_EXTINCTION: list(c.extinction)},
            "note": "per-channel values illustrative; magnitudes from the paper's range",
            "source": c.source}


def _yarn(y) -> dict[str, Any]:
    t = y.published
    return {"type": "yarn", "name": y.name,
            "published": {"sample": t.sample, "composition": t.composition,
                          "fiber_length_cm": _rng(t.fiber_length_cm) if t.fiber_length_cm else "continuous",
                          "twist_turns_per_cm": t.twist, "fibers_per_ply": t.fibers_per_ply,
                          "plies": t.plies, "dtex_per_ply": t.dtex},
            "fiber_preset": y.fiber_preset,
            "authored": y.yarn_attributes(),
            "derived": {"yarn_diameter_mm": y.yarn_diameter_mm},
            "note": y.note, "source": y.source}


def collect(name: str | None = None) -> list[dict[str, Any]]:
    """Every preset (or the one named) as JSON-able dicts."""
    from usdfiber import presets as P

    items: list[tuple[str, dict[str, Any]]] = []
    items += [(k, _fiber(v)) for k, v in P.FIBER_PRESETS.items()]
    items += [(k, _dye(v)) for k, v in P.DYE_PRESETS.items()]
    items += [(k, _colour(v)) for k, v in P.DYE_COLOURS.items()]
    items += [(k, _yarn(v)) for k, v in P.YARN_PRESETS.items()]
    if name is None:
        return [d for _, d in items]
    chosen = [d for k, d in items if k == name or k.lower().replace(" ", "") == name.lower().replace(" ", "")]
    if not chosen:
        from usdfiber.cli import UsageError

        raise UsageError(f"unknown preset {name!r}; valid: {', '.join(k for k, _ in items)}")
    return chosen


def _f(x: Any) -> str:
    if x is None:
        return "-"
    if isinstance(x, (list, tuple)):
        if len(x) == 2 and x[0] == x[1]:
            return _f(x[0])
        return "-".join(_f(v) for v in x) if len(x) == 2 else ", ".join(_f(v) for v in x)
    if isinstance(x, float):
        return f"{x:.4g}"
    return str(x)


def _text(items: list[dict[str, Any]]) -> str:
    from usdfiber import presets as P

    out: list[str] = []
    fibers = [d for d in items if d["type"] == "fiber"]
    if fibers:
        out.append("FIBERS (Table 1 as published | authored)")
        hdr = (f"  {'name':<17}{'diam um':>12}{'rho g/cm3':>10}{'eta_par':>9}{'eta_perp':>9}"
               f"{'Ra nm':>11}{'l nm':>6}{'beta deg':>9}{'atan(Ra/l)':>13}  {'family':<16}")
        out.append(hdr)
        for d in fibers:
            p, a = d["published"], d["authored"]
            out.append(f"  {d['name']:<17}{_f(p['diameter_um']):>12}{_f(p['density_g_cm3']):>10}"
                       f"{_f(p['eta_parallel']):>9}{_f(p['eta_perpendicular']):>9}{_f(p['ra_nm']):>11}"
                       f"{_f(p['profile_length_nm']):>6}{_f(p['beta_deg']):>9}"
                       f"{_f(d['derived']['beta_from_ra_deg']):>13}  {d['profile_family']:<16}")
            out.append(f"  {'  authored':<17}{_f(a['fiber:diameter']):>12}{_f(a['fiber:density']):>10}"
                       f"{_f(a['fiber:ior:parallel']):>9}{_f(a['fiber:ior:perpendicular']):>9}"
                       f"{_f(a['fiber:roughness:ra']):>11}{_f(a['fiber:roughness:profileLength']):>6}"
                       f"{_f(a['fiber:roughness:beta']):>9}  (roughness source: beta)")
            if a[Fiber.CUTICLE_HEIGHT]:
                out.append(f"    cuticle: tilt {_f(a['fiber:cuticle:tilt'])} deg, height "
                           f"{_f(a['fiber:cuticle:height'])} um, spacing {_f(a['fiber:cuticle:spacing'])} um "
                           f"({d['cuticle_source']})")
            if d["note"]:
                out.append(f"    note: {d['note']}")
        out.append("  Authored = midpoint of each published range; fiber:roughness:source = \"beta\" "
                   "(Table 1's beta; it is not arctan(Ra/l) for every row).")
        out.append(f"  Source: {P.TABLE1_SOURCE}")
        out.append("")
    dyes = [d for d in items if d["type"] in ("dye", "dyeColour")]
    if dyes:
        out.append("DYES (extinction per gram, L mg^-1 cm^-1, linear Rec.709 R, G, B)")
        for d in dyes:
            if d["type"] == "dye":
                out.append(f"  {d['name']:<17}class {d['dye_class']:<9} published "
                           f"{_f(d['published']['epsilon_L_mg_cm']):<14} authored "
                           f"{_f(d['authored']['fiber:dye:extinction'])}  (for {d['used_for']})")
            else:
                out.append(f"  {d['name']:<17}class {d['dye_class']:<9} from {d['dye']:<19} authored "
                           f"{_f(d['authored']['fiber:dye:extinction'])}")
        out.append("  Named colours: per-channel split illustrative; only the magnitude ranges are published.")
        out.append(f"  Source: {P.SECTION31_SOURCE}")
        out.append("")
    yarns = [d for d in items if d["type"] == "yarn"]
    if yarns:
        out.append("YARNS (Table 3 as published | authored)")
        out.append(f"  {'name':<11}{'fiber':<11}{'length cm':>11}{'twist/cm':>9}{'fib/ply':>8}{'plies':>6}"
                   f"{'dtex':>6}{'ply r mm':>10}{'yarn d mm':>10}")
        for d in yarns:
            p, a = d["published"], d["authored"]
            out.append(f"  {d['name']:<11}{d['fiber_preset']:<11}{_f(p['fiber_length_cm']):>11}"
                       f"{_f(p['twist_turns_per_cm']):>9}{p['fibers_per_ply']:>8}{p['plies']:>6}"
                       f"{_f(p['dtex_per_ply']):>6}{a['yarn:ply:radius']:>10.4f}"
                       f"{d['derived']['yarn_diameter_mm']:>10.4f}")
            out.append(f"  {'  authored':<11}{'':<11}{_f(a['yarn:fiber:stapleLength']):>11}"
                       f"{_f(a['yarn:ply:twist']):>9}{a['yarn:fibersPerPly']:>8}{a['yarn:plies']:>6}"
                       f"{_f(a['yarn:ply:linearDensity']):>6}")
        out.append(f"  Ply radius from dtex, fiber density and packing fraction {P.PACKING_FRACTION}; "
                   f"yarn diameter encloses touching circular plies. Staple length: range midpoint (0 = continuous).")
        out.append(f"  {yarns[0]['note']}")
        out.append(f"  Source: {P.TABLE3_SOURCE}")
    return "\n".join(line.rstrip() for line in out).rstrip()


def run(args: argparse.Namespace) -> int:
    items = collect(args.name)
    if args.json:
        print(json.dumps(items, indent=2))
    else:
        print(_text(items))
    return 0
