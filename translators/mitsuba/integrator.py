"""A path tracer whose shadow rays pass null surfaces (``usdfiber_path``), for pass-through fibers.

After :func:`register`, ``{"type": "usdfiber_path", "max_depth": 8}`` is a unidirectional path
tracer with next-event estimation and multiple importance sampling (power heuristic), the
algorithm of Mitsuba 3.9.1's ``path`` (``src/integrators/path.cpp``: same sample dimensions in
the same order, emitter hits weighted against the previous BSDF sample, ``max_depth``,
``rr_depth``, ``hide_emitters``), with two changes for BSDFs that have a ``Null`` component
(the pass-through of non-round fibers and yarn far fields, :mod:`usdfiber.translators.mitsuba.fiber_bsdf`):

* **Pass-throughs are not bounces.** A path that passes a surface goes on straight from the
  hit with weight 1 (the null sample's weight). That does not count towards ``max_depth`` or
  ``rr_depth``, no Russian roulette is played there, and the previous scattering vertex and
  its BSDF pdf (for the MIS weight of an emitter the path hits next) stay those of the last
  real scattering event. This is ``volpath``'s convention (``src/integrators/volpath.cpp``:
  ``depth`` grows only on ``non_null_bsdf``), so ``max_depth`` keeps ``path``'s meaning in
  scattering events: 1 renders the emitters seen directly (also through fibers), 2 direct
  illumination, and so on. ``path`` counts a pass-through as a bounce of ``max_depth`` and
  ``rr_depth``.
* **Shadow rays pass null surfaces.** Where some BSDF of the scene has a ``Null`` component,
  the shadow ray of next-event estimation walks towards the emitter sample: at every surface
  whose BSDF has the ``Null`` component it is multiplied by ``bsdf.eval_null_transmission(si)``
  (0 or 1 for the fiber BSDF, 1 with probability ``1 - q``) and traced on; any other surface
  blocks it. ``path`` tests shadow rays as if every surface were opaque, which makes a
  non-round fiber's shadow as wide as its tube (D) instead of its profile (W). With no such
  BSDF in the scene the shadow ray is Mitsuba's own visibility test, and the integrator
  renders what ``path`` renders, sample for sample.

Where the pass-through is decided. Generic (any BSDF with a ``Null`` component, or the
property ``fiber_pass`` false): as ``volpath``, the BSDF decides in ``sample`` at every hit
(null with probability ``1 - q``), and next-event estimation is done at every hit before,
with the full ``eval`` and ``pdf`` (both carry the factor ``q``). Fibers (the default when the
scene's only BSDF with a ``Null`` component is one :func:`~usdfiber.translators.mitsuba.fiber_bsdf.fiber_bsdf`
instance, as ``translate_stage`` makes): the integrator asks that BSDF for ``q`` at the hit
(``fiber.scatter_probability_at``, the number ``eval``, ``pdf`` and ``sample`` use) and
decides with a sample of its own, in a short loop that only intersects and looks up ``q`` until a fiber scatters or the
ray hits something else. At a scattering fiber the BSDF is then used conditioned on
scattering: sampled and its pdf taken with the ``Null`` component off (no ``q`` in them),
and ``eval`` divided by ``q``. Both give the same expectation, ``q f + (1 - q) delta``; the
fiber way saves next-event estimation and BSDF sampling at every pass-through.

MIS: a pass-through multiplies the BSDF-sampled and the emitter-sampled strategies by the same
probability of getting through, so the weights stay those of ``path`` between the scattering
vertices (generic: the BSDF's full pdf; fibers: the pdf conditioned on scattering, on both
sides). What ``volpath`` adds beyond this (media, spectral channel sampling, Russian roulette
at null events) is left out: the product has no participating media, and a medium given to
``sample`` is ignored.

Properties: ``max_depth`` (default -1: unbounded), ``rr_depth`` (default 5), ``hide_emitters``
(default false; with it, camera rays, pass-throughs included, go through area emitters and do
not see the environment), ``fiber_pass`` (default true, see above) and ``null_shadows``
(default true; false makes shadow rays opaque as in ``path``: for tests and profiling only).
A path may pass at most ``MAX_PASSES`` null surfaces in all, and a shadow ray as many: the
bound only guards against a ray that keeps meeting the same surface.
"""
from __future__ import annotations

from typing import Any

from usdfiber.translators.mitsuba.plugins import VariantPlugin

__all__ = ["MAX_PASSES", "PLUGIN_NAME", "integrator_class", "register", "scene_has_null_bsdf"]

PLUGIN_NAME = "usdfiber_path"
MAX_PASSES = 1024


class _Null:
    """What a render needs to know about the scene's null surfaces (plain Python values)."""

    def __init__(self, shapes: list | None, bsdfs: list, flags: int, fiber: Any) -> None:
        self.shapes = shapes    # shapes whose BSDF has a Null component; None: tell by BSDF flags
        self.bsdfs = bsdfs      # their distinct BSDFs
        self.flags = flags      # RayFlags of the interaction their null transmission needs
        self.fiber = fiber      # the one fiber BSDF plugin, when the fiber way decides pass-throughs


def _null_shapes(mi: Any, scene: Any) -> tuple[list, list, bool]:
    """(shapes whose BSDF has a ``Null`` component, their distinct BSDFs, whether the scene
    has instances, whose inner shapes the first list does not name)."""
    shapes: list = []
    bsdfs: list = []
    instanced = False
    for shape in scene.shapes():
        instanced |= shape.class_name() in ("Instance", "ShapeGroup")
        b = shape.bsdf()
        if b is not None and mi.has_flag(b.flags(), mi.BSDFFlags.Null):
            shapes.append(shape)
            if all(b is not x for x in bsdfs):
                bsdfs.append(b)
    return shapes, bsdfs, instanced


def scene_has_null_bsdf(mi: Any, scene: Any) -> bool:
    """Whether a shape of ``scene`` has a BSDF with a ``Null`` (pass-through) component."""
    return bool(_null_shapes(mi, scene)[0])


def _mis_weight(pdf_a: Any, pdf_b: Any) -> Any:
    """Power heuristic, as ``path``: 0 where it is not finite."""
    import drjit as dr

    a2, b2 = dr.square(pdf_a), dr.square(pdf_b)
    w = a2 / (a2 + b2)
    return dr.detach(dr.select(dr.isfinite(w), w, 0.0))


def _on_shapes(shape_ptr: Any, shapes: list) -> Any:
    """Whether each lane's shape is one of ``shapes``."""
    import mitsuba as mi

    m = mi.Bool(False)
    for sh in shapes:
        m |= shape_ptr == mi.ShapePtr(sh)
    return m


def _fiber_q(null: _Null, si: Any, active: Any) -> tuple[Any, Any]:
    """(on a fiber, q): the probability that the fiber BSDF scatters at a hit (1 elsewhere),
    the number its eval, pdf and sample use (:meth:`FiberBcsdf.scatter_probability_at
    <usdfiber.translators.mitsuba.fiber_bsdf.FiberBcsdf.scatter_probability_at>`)."""
    import drjit as dr

    fib = null.fiber.fiber
    on = _on_shapes(si.shape, null.shapes) & si.is_valid() & active & fib.hit_is_finite(si)
    return on, dr.select(on, fib.scatter_probability_at(si, on), 1.0)


def _define_plugin(mi: Any) -> type:
    import drjit as dr

    from usdfiber.translators.mitsuba.fiber_bsdf import bsdf_class

    fiber_cls = bsdf_class(mi)

    class FiberPathIntegrator(mi.SamplingIntegrator):
        """Path tracing with pass-through surfaces (see the module docstring)."""

        def __init__(self, props: Any) -> None:
            super().__init__(props)
            max_depth = int(props.get("max_depth", -1))
            if max_depth < -1:
                raise ValueError("usdfiber_path: max_depth must be -1 (infinite) or >= 0")
            rr_depth = int(props.get("rr_depth", 5))
            if rr_depth <= 0:
                raise ValueError("usdfiber_path: rr_depth must be > 0")
            self.max_depth = (1 << 32) - 1 if max_depth == -1 else max_depth
            self.rr_depth = rr_depth
            self.null_shadows = bool(props.get("null_shadows", True))
            self.fiber_pass = bool(props.get("fiber_pass", True))

        def null_info(self, scene: Any) -> _Null | None:
            """None when no BSDF of ``scene`` has a Null component (or ``null_shadows`` is off)."""
            if not self.null_shadows:
                return None
            shapes, bsdfs, instanced = _null_shapes(mi, scene)
            if not shapes:
                return None
            fibers_only = all(isinstance(b, fiber_cls) for b in bsdfs)
            if instanced or len(shapes) > 8:
                # Tell null surfaces by their BSDF's flags (a dispatch over all shapes).
                return _Null(None, bsdfs, int(mi.RayFlags.All), None)
            # The fiber BSDF reads the tangent (dp_du), the shading frame and the position only.
            flags = (mi.RayFlags.Minimal | mi.RayFlags.dPdUV | mi.RayFlags.ShadingFrame) if fibers_only \
                else mi.RayFlags.All
            fiber = bsdfs[0] if (self.fiber_pass and len(bsdfs) == 1 and fibers_only) else None
            return _Null(shapes, bsdfs, int(flags), fiber)

        # ---- shadow rays ---------------------------------------------------------------------
        @dr.syntax
        def transmittance(self, scene: Any, si: Any, target: Any, active: Any, null: _Null) -> Any:
            """Transmittance of the segment from ``si`` to the point ``target``: the product of
            the null transmissions of the surfaces between them; 0 at any other surface."""
            import drjit as dr   # (dr.syntax functions see module globals only, not closures)
            import mitsuba as mi

            tr = mi.Spectrum(1.0)
            ray = si.spawn_ray_to(target)
            active = mi.Bool(active)
            n = mi.UInt32(0)
            while dr.hint(active, label="usdfiber_path shadow ray"):
                pi = scene.ray_intersect_preliminary(ray, coherent=False, active=active)
                hit = pi.is_valid()
                if dr.hint(null.shapes is None, mode="scalar"):
                    bsdf = pi.shape.bsdf()
                    passable = hit & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Null)
                    si_s = pi.compute_surface_interaction(ray, null.flags, passable)
                    t_s = bsdf.eval_null_transmission(si_s, passable)
                else:
                    # Null surfaces told by shape pointer; one null BSDF is called directly.
                    passable = hit & _on_shapes(pi.shape, null.shapes)
                    si_s = pi.compute_surface_interaction(ray, null.flags, passable)
                    if dr.hint(len(null.bsdfs) == 1, mode="scalar"):
                        t_s = null.bsdfs[0].eval_null_transmission(si_s, passable)
                    else:
                        t_s = pi.shape.bsdf().eval_null_transmission(si_s, passable)
                tr = dr.select(passable, tr * t_s, dr.select(hit, 0.0, tr))
                ray = si_s.spawn_ray_to(target)
                n += 1
                active = passable & dr.any(tr != 0.0) & (n < MAX_PASSES)
            return tr

        # ---- fiber pass-throughs ---------------------------------------------------------------
        @dr.syntax
        def pass_fibers(self, scene: Any, sampler: Any, d: Any, si: Any, active: Any, passes: Any,
                        null: _Null) -> tuple[Any, Any, Any]:
            """(si, q, passes): from the hit ``si`` on, pass fibers (each with probability
            1 - q) along the direction ``d`` until a fiber scatters or the ray meets anything
            else or nothing; q at the final hit (1 off fibers)."""
            import drjit as dr   # (dr.syntax functions see module globals only, not closures)
            import mitsuba as mi

            on, q = _fiber_q(null, si, active)
            go = on & (sampler.next_1d() >= q)
            while dr.hint(go, label="usdfiber_path fiber pass"):
                si = scene.ray_intersect(si.spawn_ray(d), mi.RayFlags.All, coherent=False, active=go)
                passes += 1
                on, q = _fiber_q(null, si, go)
                go = on & (sampler.next_1d() >= q) & (passes < MAX_PASSES)
            return si, q, passes

        # ---- the path --------------------------------------------------------------------------
        def sample(self, scene: Any, sampler: Any, ray: Any, medium: Any = None,
                   active: Any = True) -> tuple[Any, Any, list]:
            """(radiance, valid, AOVs) of one camera ray; ``medium`` is ignored (no media)."""
            if self.max_depth == 0:
                return mi.Spectrum(0.0), mi.Bool(False), []
            spec, valid = self.trace(scene, sampler, ray, active, self.null_info(scene), bool(self.hide_emitters))
            return spec, valid, []

        @dr.syntax
        def trace(self, scene: Any, sampler: Any, ray_: Any, active: Any, null: _Null | None,
                  hide: bool) -> tuple[Any, Any]:
            """(radiance, valid) of a camera ray; ``null``: see :meth:`null_info`."""
            import drjit as dr   # (dr.syntax functions see module globals only, not closures)
            import mitsuba as mi

            Flags = mi.BSDFFlags
            max_depth, rr_depth = self.max_depth, self.rr_depth
            fibers = null is not None and null.fiber is not None
            bsdf_ctx = mi.BSDFContext()
            if dr.hint(fibers, mode="scalar"):
                # The fiber way: pass-throughs are decided before the BSDF is used.
                bsdf_ctx.type_mask = int(Flags.All) & ~int(Flags.Null)

            ray = mi.Ray3f(ray_)
            throughput = mi.Spectrum(1.0)
            result = mi.Spectrum(0.0)
            eta = mi.Float(1.0)
            depth = mi.UInt32(0)                 # scattering events so far (pass-throughs excluded)
            passes = mi.UInt32(0)                # pass-throughs so far
            valid_ray = mi.Bool((not hide) and scene.environment() is not None)
            prev_si = dr.zeros(mi.Interaction3f)  # the last scattering vertex
            prev_bsdf_pdf = mi.Float(1.0)
            prev_bsdf_delta = mi.Bool(True)
            active = mi.Bool(active)
            # As path: the camera rays' intersection is coherent, later ones are not.
            pi = scene.ray_intersect_preliminary(ray, coherent=True, active=active)

            while dr.hint(active, label="usdfiber_path"):
                si = pi.compute_surface_interaction(ray, mi.RayFlags.All)
                q = mi.Float(1.0)
                if dr.hint(fibers, mode="scalar"):
                    si, q, passes = self.pass_fibers(scene, sampler, ray.d, si, active, passes, null)
                # hide_emitters: a camera ray (depth 0, also after pass-throughs) goes through
                # area emitters, as path's skip_area_emitters does for the first segment.
                skip = mi.Bool(False)
                if dr.hint(hide, mode="scalar"):
                    skip = (depth == 0) & si.is_valid() & (si.shape.emitter() != None)  # noqa: E711

                # ---- emission the path hits (MIS against the previous scattering vertex) ----
                ds_hit = mi.DirectionSample3f(scene, si=si, ref=prev_si)
                em_pdf = scene.pdf_emitter_direction(prev_si, ds_hit, ~prev_bsdf_delta)
                mis_bsdf = _mis_weight(prev_bsdf_pdf, em_pdf)
                emitted = ds_hit.emitter.eval(si, (prev_bsdf_pdf > 0.0) & ~skip)
                result = dr.fma(throughput, emitted * mis_bsdf, result)

                active_next = (depth + 1 < max_depth) & si.is_valid()
                bsdf = si.bsdf(ray)

                # ---- emitter sampling ----
                active_em = active_next & mi.has_flag(bsdf.flags(), Flags.Smooth) & ~skip
                ds, em_weight = scene.sample_emitter_direction(si, sampler.next_2d(), null is None, active_em)
                active_em &= ds.pdf != 0.0
                if dr.hint(null is not None, mode="scalar"):
                    em_weight = em_weight * self.transmittance(scene, si, ds.p, active_em, null)
                wo = si.to_local(ds.d)

                # ---- BSDF: evaluate towards the emitter sample, and sample ----
                sample_1 = sampler.next_1d()
                sample_2 = sampler.next_2d()
                bsdf_val, bsdf_pdf, bs, bsdf_weight = bsdf.eval_pdf_sample(bsdf_ctx, si, wo, sample_1, sample_2)
                if dr.hint(fibers, mode="scalar"):
                    bsdf_val = bsdf_val / q          # the fiber's eval carries q; given it scatters
                mis_em = dr.select(ds.delta, 1.0, _mis_weight(ds.pdf, bsdf_pdf))
                result[active_em] = dr.fma(throughput, bsdf_val * em_weight * mis_em, result)

                # ---- next ray ----
                passed = mi.has_flag(bs.sampled_type, Flags.Null) | skip
                real = si.is_valid() & ~passed     # a scattering event: counts as a bounce
                ray = si.spawn_ray(dr.select(skip, ray.d, si.to_world(bs.wo)))
                bsdf_weight[skip] = 1.0
                throughput *= bsdf_weight
                eta[real] *= bs.eta
                valid_ray |= real
                prev_si[real] = mi.Interaction3f(si)
                prev_bsdf_pdf[real] = bs.pdf
                prev_bsdf_delta[real] = mi.has_flag(bs.sampled_type, Flags.Delta)
                depth[real] += 1
                passes[passed] += 1

                # ---- stopping: Russian roulette at scattering events only ----
                throughput_max = dr.max(throughput)
                rr_prob = dr.minimum(throughput_max * dr.square(eta), 0.95)
                rr_active = real & (depth >= rr_depth)
                rr_continue = sampler.next_1d() < rr_prob
                throughput[rr_active] *= dr.rcp(rr_prob)
                go_on = dr.select(real, active_next & (~rr_active | rr_continue), passes < MAX_PASSES)
                active = si.is_valid() & go_on & (throughput_max != 0.0)
                pi = scene.ray_intersect_preliminary(ray, coherent=False, active=active)

            return dr.select(valid_ray, result, 0.0), valid_ray

        def aov_names(self) -> list:
            return []

        def to_string(self) -> str:
            return (f"FiberPathIntegrator[max_depth={self.max_depth}, rr_depth={self.rr_depth}, "
                    f"fiber_pass={self.fiber_pass}, null_shadows={self.null_shadows}]")

    return FiberPathIntegrator


_PLUGIN = VariantPlugin(PLUGIN_NAME, "integrator", _define_plugin)


def integrator_class(mi: Any) -> type:
    """The integrator class for Mitsuba's active variant (defined once per variant)."""
    return _PLUGIN.plugin_class(mi)


def register(mi: Any) -> type:
    """Register ``usdfiber_path`` with Mitsuba's active variant (once); returns the class."""
    return _PLUGIN.register(mi)
