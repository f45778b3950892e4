"""usdfiber: physically based textile fibers in OpenUSD.

Importing the package registers the usdFiber schema plugin (FiberAPI, FiberYarnAPI,
FiberProfileAPI) and the usdFiber validators with USD's plugin registry.

USD builds its schema registry once, the first time any stage or schema is used. A
program that opened a stage before ``import usdfiber`` therefore cannot see the schemas;
importing then raises :class:`SchemaRegistrationError`. Either import usdfiber first, or
set ``PXR_PLUGINPATH_NAME`` to the directories printed by ``usdfiber plugin-path`` before
the program starts (this is what a DCC or usdview needs).
"""
from __future__ import annotations

from ._plugins import SchemaRegistrationError, plugin_paths, register_plugins

__all__ = ["SchemaRegistrationError", "plugin_paths", "register_plugins", "__version__"]
__version__ = "0.1.0"

register_plugins()

# USD loads the validator plugin by importing it; this makes that import resolvable.
from . import validation as _validation  # noqa: E402,F401
