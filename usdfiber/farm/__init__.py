"""Scale-out of bakes and frame ranges over a farm: Dask ``distributed`` clusters and shards for
farm managers, all sharing one content-addressed cache.

Modules: :mod:`~usdfiber.farm.frames` (frame ranges and ``####`` names),
:mod:`~usdfiber.farm.shard_spec` (``I/N``), :mod:`~usdfiber.farm.tasks` (the deterministic plan
of direction groups, tracing into chunks, assembly), :mod:`~usdfiber.farm.cluster` (connecting,
``local:N``, checking workers see the cache), :mod:`~usdfiber.farm.dask_bake` (bakes on Dask),
:mod:`~usdfiber.farm.shards` (bakes as shards), :mod:`~usdfiber.farm.progress` (one progress bar
and the ``--json`` summary), :mod:`~usdfiber.farm.command` (the bake command's farm options).
The core's farm layer never imports a renderer bridge.
"""
