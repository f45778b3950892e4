"""Every command's --help prints and exits 0 (argparse formats help strings with %, so a
literal percent sign in a help text breaks --help with a traceback)."""
from __future__ import annotations

import pytest

from usdfiber.cli import build_parser, load_commands

COMMANDS = sorted(load_commands()[0])


@pytest.mark.parametrize("command", COMMANDS)
def test_command_help_prints(command: str, capsys: pytest.CaptureFixture[str]) -> None:
    parser = build_parser()
    with pytest.raises(SystemExit) as exc:
        parser.parse_args([command, "--help"])
    assert exc.value.code == 0
    assert "usage:" in capsys.readouterr().out


def test_command_list_is_not_empty() -> None:
    assert {"check", "bake", "render", "table"} <= set(COMMANDS)
