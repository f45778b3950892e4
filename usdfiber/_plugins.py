"""Locating and registering the usdFiber USD plugins (schema and validators)."""
from __future__ import annotations

from pathlib import Path

SCHEMA_NAMES = ("FiberAPI", "FiberYarnAPI", "FiberProfileAPI")
_PKG = Path(__file__).resolve().parent


class SchemaRegistrationError(RuntimeError):
    """The usdFiber schemas could not be made known to USD."""


def _schema_dir() -> Path:
    # An installed wheel carries the resources CMake installed; a source checkout (and an
    # editable install, whose Python files stay in the checkout) uses the checked-in copy.
    for cand in (_PKG / "resources" / "usdFiber", _PKG.parent / "schema" / "generated"):
        if (cand / "plugInfo.json").is_file():
            return cand
    raise SchemaRegistrationError(
        f"usdFiber schema resources not found (looked in {_PKG / 'resources' / 'usdFiber'} "
        f"and {_PKG.parent / 'schema' / 'generated'}); reinstall usdfiber"
    )


def plugin_paths() -> list[Path]:
    """Directories holding usdfiber's plugInfo.json files (for PXR_PLUGINPATH_NAME)."""
    paths = [_schema_dir()]
    validation = _PKG / "validation"
    if (validation / "plugInfo.json").is_file():
        paths.append(validation)
    return paths


def register_plugins() -> None:
    """Register the schema and validator plugins; idempotent.

    Raises SchemaRegistrationError when USD's schema registry was built before the
    plugins were registered (a stage was opened before ``import usdfiber``).
    """
    from pxr import Plug, Usd

    Plug.Registry().RegisterPlugins([str(p) for p in plugin_paths()])
    registry = Usd.SchemaRegistry()
    missing = [n for n in SCHEMA_NAMES if registry.FindAppliedAPIPrimDefinition(n) is None]
    if missing:
        dirs = ":".join(str(p) for p in plugin_paths())
        raise SchemaRegistrationError(
            f"USD's schema registry was initialized before usdfiber was imported, so "
            f"{', '.join(missing)} are unknown. Import usdfiber before opening any stage, "
            f"or start the program with PXR_PLUGINPATH_NAME={dirs}"
        )
