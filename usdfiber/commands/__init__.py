"""Sub-commands of the ``usdfiber`` command line (see :mod:`usdfiber.cli`)."""
