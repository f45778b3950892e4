"""The module USD imports to load the usdFiber validators (plugInfo.json: a python plugin
named ``usdFiber``), so that a program that only sets ``PXR_PLUGINPATH_NAME=$(usdfiber
plugin-path)`` and never imports usdfiber (usdview, a DCC, a plain ``pxr`` script) gets them.
Installed at the top level next to the ``usdfiber`` package (CMakeLists.txt)."""
from usdfiber.validation import plugin  # noqa: F401  (registers every usdFiber validator)
