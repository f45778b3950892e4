"""The ``usdfiber`` command: one sub-command per module in :mod:`usdfiber.commands`.

Every sub-command module defines ``register(subparsers)`` which adds its parser and sets
``func`` (``args -> int`` exit status). User errors are raised as :class:`UsageError` and
printed as one line, never as a traceback.
"""
from __future__ import annotations

import argparse
import importlib
import sys

# Order is the order of ``usdfiber --help``.
COMMAND_MODULES = ("check", "render", "import_curves", "cloth", "presets", "bake", "table", "plugin_path")


class UsageError(Exception):
    """A problem with the user's input, reported as ``usdfiber: error: <message>``."""


def build_parser() -> argparse.ArgumentParser:
    """The argument parser with every sub-command registered."""
    from usdfiber import __version__

    parser = argparse.ArgumentParser(
        prog="usdfiber",
        description="Physically based textile fibers in OpenUSD.",
    )
    parser.add_argument("--version", action="version", version=f"usdfiber {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for name in COMMAND_MODULES:
        importlib.import_module(f"usdfiber.commands.{name}").register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``usdfiber`` console script."""
    try:
        import usdfiber  # registers the USD plugins
    except RuntimeError as exc:  # SchemaRegistrationError: a clear line, not a traceback
        print(f"usdfiber: error: {exc}", file=sys.stderr)
        return 2
    try:
        args = build_parser().parse_args(argv)
        return int(args.func(args) or 0)
    except UsageError as exc:
        print(f"usdfiber: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("usdfiber: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
