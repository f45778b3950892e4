"""Renderer-independent geometry: curves and the procedural yarn.

* :mod:`usdfiber.geometry.curves`: UsdGeomBasisCurves -> uniform cubic B-spline segments,
  their evaluation and rotation-minimizing reference frames.
* :mod:`usdfiber.geometry.yarn`: :func:`~usdfiber.geometry.yarn.expand_yarn`, yarn centre lines
  to fiber curves (Zhao et al. 2016), built from :mod:`~usdfiber.geometry.yarn_centre`,
  :mod:`~usdfiber.geometry.yarn_plies`, :mod:`~usdfiber.geometry.yarn_fibers`,
  :mod:`~usdfiber.geometry.yarn_flyaways`, :mod:`~usdfiber.geometry.yarn_random` and
  :mod:`~usdfiber.geometry.expanded_fibers`.
* :mod:`usdfiber.geometry.voxelize`: fiber curves to a voxel grid.
* :mod:`usdfiber.geometry.yarn_density`: yarn centre lines to a voxel grid from the yarn
  model's fiber density, without expanding fibers.
"""
