"""Baking tabulated fiber BCSDFs: photon tracing through a cross section into tables.

The data flow: fibers (prims, presets, parameter files) -> :mod:`~usdfiber.bake.requests`
(which tables) -> :mod:`~usdfiber.bake.cache` (already baked?) -> :mod:`~usdfiber.bake.baker`
(trace every incoming direction) -> :mod:`~usdfiber.bake.assembly` -> a
:class:`~usdfiber.bake.table.BcsdfTable`, recoloured for any dye without re-tracing.

What each module holds:

* :mod:`~usdfiber.bake.requests`: ``TableRequest`` and the whole fiber -> table-request
  mapping (stages, prims, presets, JSON parameter files, ``fiber:table`` assets, the cross
  section a request traces).
* :mod:`~usdfiber.bake.settings`: ``BakeSettings`` (how a table is baked) and ``BakeError``.
* :mod:`~usdfiber.bake.baker`: the bake itself: directions traced in groups, batch seeds,
  resuming, the table's header.
* :mod:`~usdfiber.bake.statistics`: one incoming direction's histograms at every absorption
  level, its batches and error estimate, target-error planning.
* :mod:`~usdfiber.bake.chunks`: resume chunks, one verified file per finished direction.
* :mod:`~usdfiber.bake.cache`: the content-addressed table cache (key, verified loader,
  locks, double-checked making of any cached file).
* :mod:`~usdfiber.bake.table`: ``BcsdfTable`` (p, Lambda and W of one cross-section variant,
  evaluation, recolouring) and ``Recoloured``.
* :mod:`~usdfiber.bake.grid`: the angular grid (outgoing bins, incoming nodes, symmetries).
* :mod:`~usdfiber.bake.absorption`: absorption levels and the Hermite interpolation of log F
  between them (the float64 reference).
* :mod:`~usdfiber.bake.recolour`: the same interpolation in Dr.Jit kernels on all cores.
* :mod:`~usdfiber.bake.lookup`: values at arbitrary directions (interpolation between nodes
  and bins).
* :mod:`~usdfiber.bake.sampler`: importance sampling of outgoing directions.
* :mod:`~usdfiber.bake.storage`: the array layout of a table file (the container itself:
  :mod:`usdfiber.table_format`).
* :mod:`~usdfiber.bake.assembly`: the stored arrays from the per-direction histograms.
* :mod:`~usdfiber.bake.profiles`: cross sections (built-in families, user loops).
* :mod:`~usdfiber.bake.fiber_mesh`: a cross section as the tracer's mesh (cuticle scales).
* :mod:`~usdfiber.bake.tracer`: the photon tracer (Dr.Jit / Mitsuba).
* :mod:`~usdfiber.bake.reference_tracer`: a brute-force float64 tracer, the reference.
* :mod:`~usdfiber.bake.exact`: the exact far field of a smooth circle.
* :mod:`~usdfiber.bake.binning`: exact per-photon binning, the answer recolouring is checked
  against.
"""
