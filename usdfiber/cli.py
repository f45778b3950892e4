"""The ``usdfiber`` command: its sub-commands are the entry points of the group ``usdfiber.commands``.

Each entry point (``[project.entry-points."usdfiber.commands"]`` in pyproject.toml,
``name = "module:register"``) names a function ``register(subparsers)`` that adds the
sub-command's parser and sets ``func`` (``args -> int`` exit status). The core registers its
own commands (:mod:`usdfiber.commands`) this way, and a renderer bridge adds its commands
(``render``: :mod:`usdfiber.translators.mitsuba.command`) without the core importing it.
``usdfiber --help`` lists the commands in the order the entry points are declared.

A command whose module cannot be imported (a bridge that is not installed) is left out of
``--help``, and naming it gives one line saying why. User errors are raised as
:class:`UsageError` and printed as one line, never as a traceback.
"""
from __future__ import annotations

import argparse
import os
import sys
import warnings
from importlib.metadata import EntryPoint, entry_points
from typing import Callable

#: The entry-point group of the sub-commands.
COMMAND_GROUP = "usdfiber.commands"


class UsageError(Exception):
    """A problem with the user's input, reported as ``usdfiber: error: <message>``."""


def one_line_errors(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """Make ``parser`` report command-line errors as one line (no usage block), exit 2."""
    def error(message: str):
        parser.exit(2, f"{parser.prog}: error: {message}\n")

    parser.error = error  # type: ignore[method-assign]
    return parser


def command_entry_points() -> list[EntryPoint]:
    """The installed sub-commands, in declaration order; the first of a repeated name wins."""
    seen: dict[str, EntryPoint] = {}
    for ep in entry_points(group=COMMAND_GROUP):
        seen.setdefault(ep.name, ep)
    return list(seen.values())


def load_commands() -> tuple[dict[str, Callable[..., None]], dict[str, str]]:
    """(register function by command name, why by name of each command that cannot be imported)."""
    loaded: dict[str, Callable[..., None]] = {}
    unavailable: dict[str, str] = {}
    for ep in command_entry_points():
        try:
            loaded[ep.name] = ep.load()
        except ImportError as exc:
            unavailable[ep.name] = (f"its module {ep.module} cannot be imported ({exc}); reinstall usdfiber "
                                    f"(pip install -e . in the checkout)")
    return loaded, unavailable


def build_parser(commands: dict[str, Callable[..., None]] | None = None) -> argparse.ArgumentParser:
    """The argument parser with every sub-command of ``commands`` (default: every installed one) registered."""
    from usdfiber import __version__

    if commands is None:
        commands = load_commands()[0]

    parser = argparse.ArgumentParser(
        prog="usdfiber",
        description="Physically based textile fibers in OpenUSD.",
    )
    one_line_errors(parser)
    parser.add_argument("--version", action="version", version=f"usdfiber {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for register in commands.values():
        register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``usdfiber`` console script."""
    try:
        import usdfiber  # registers the USD plugins
    except RuntimeError as exc:  # SchemaRegistrationError: a clear line, not a traceback
        print(f"usdfiber: error: {exc}", file=sys.stderr)
        return 2
    commands, unavailable = load_commands()
    if not commands:
        print(f"usdfiber: error: no sub-commands are installed (entry points {COMMAND_GROUP!r}); "
              f"run pip install -e . in the checkout", file=sys.stderr)
        return 2
    # The top-level parser has no options that take a value: the first word is the command.
    words = sys.argv[1:] if argv is None else argv
    name = next((w for w in words if not w.startswith("-")), None)
    if name in unavailable:
        print(f"usdfiber: error: the {name} command is not available: {unavailable[name]}", file=sys.stderr)
        return 2
    warnings.showwarning = show_warning_line
    from usdfiber.memory_budget import MemoryBudgetError

    try:
        args = build_parser(commands).parse_args(argv)
        status = int(args.func(args) or 0)
        sys.stdout.flush()  # a closed pipe shows here, not at interpreter exit
        return status
    except (UsageError, MemoryBudgetError) as exc:
        print(f"usdfiber: error: {exc}", file=sys.stderr)
        return 2
    except BrokenPipeError:
        # The reader went away (`usdfiber bake ... | head -1`): stop quietly, as the shell's
        # own tools do, and keep Python from complaining when it flushes stdout at exit.
        try:
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, sys.stdout.fileno())
            os.close(devnull)
        except (OSError, ValueError, AttributeError):  # stdout without a file descriptor
            pass
        return 141
    except KeyboardInterrupt:
        print("usdfiber: interrupted", file=sys.stderr)
        return 130


def show_warning_line(message, category, filename, lineno, file=None, line=None) -> None:
    """Print a Python warning as one line, ``usdfiber: warning: <message>``, without the
    source location and line that Python adds (they name usdfiber's code, not the input)."""
    stream = file if file is not None else sys.stderr
    try:
        stream.write(f"usdfiber: warning: {' '.join(str(message).split())}\n")
    except (OSError, ValueError):
        pass


if __name__ == "__main__":
    sys.exit(main())
