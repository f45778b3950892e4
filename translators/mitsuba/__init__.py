"""The Mitsuba 3 bridge: a USD stage with fibers, yarns, meshes, lights and cameras to a Mitsuba
scene, the tabulated fiber BCSDF as a Mitsuba plugin, the integrator it renders with, and the
``usdfiber render`` command.

Modules, from the command down:

* :mod:`~usdfiber.translators.mitsuba.command`: ``usdfiber render`` (an entry point of the
  ``usdfiber.commands`` group); :mod:`~usdfiber.translators.mitsuba.render`: the render
  (validate, tables, translate, passes, images); :mod:`~usdfiber.translators.mitsuba.device`:
  ``--device`` to a Mitsuba variant; :mod:`~usdfiber.translators.mitsuba.errors`: what cannot
  be translated or rendered.
* :mod:`~usdfiber.translators.mitsuba.scene`: a stage to a Mitsuba scene, timed by
  :mod:`~usdfiber.translators.mitsuba.profile`; :mod:`~usdfiber.translators.mitsuba.stage_walk`
  (visible prims, instances expanded), :mod:`~usdfiber.translators.mitsuba.render_settings`,
  :mod:`~usdfiber.translators.mitsuba.camera`, :mod:`~usdfiber.translators.mitsuba.lights`,
  :mod:`~usdfiber.translators.mitsuba.meshes`, :mod:`~usdfiber.translators.mitsuba.images`
  (texture files), :mod:`~usdfiber.translators.mitsuba.curves` (BasisCurves to Mitsuba curves).
* Fibers: :mod:`~usdfiber.translators.mitsuba.fibers` (fiber and yarn prims to curves, tables
  and per-segment data), :mod:`~usdfiber.translators.mitsuba.lod` (the level-of-detail policy),
  :mod:`~usdfiber.translators.mitsuba.yarn_far_field` (far fields of small yarns),
  :mod:`~usdfiber.translators.mitsuba.fiber_bank` (tables packed for the device),
  :mod:`~usdfiber.translators.mitsuba.fiber_bsdf` (the BCSDF plugin) and
  :mod:`~usdfiber.translators.mitsuba.integrator` (``usdfiber_path``), both Python plugins
  defined and registered per Mitsuba variant by :mod:`~usdfiber.translators.mitsuba.plugins`.
"""
