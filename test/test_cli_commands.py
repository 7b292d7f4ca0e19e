"""The command line as a module per command: ``magcal_ros.app.cli`` assembles the parser from
``magcal_ros.app.commands``; each command module adds its whole parser alone and runs its own function.
(``scripts/compare_cli_help.py REV`` compares every help text with another revision's.)"""

from __future__ import annotations

import argparse
import ast
from pathlib import Path

import pytest

from magcal_ros.app import cli

COMMANDS = Path(cli.__file__).parent / "commands"


def _subparsers(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    action = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))  # noqa: SLF001
    return dict(action.choices)


def test_the_parser_has_one_command_per_module_in_its_order() -> None:
    names = [m.__name__.rsplit(".", 1)[1] for m in cli.COMMANDS]
    assert list(_subparsers(cli.build_parser())) == names == ["simulate", "calibrate", "correct", "plot", "batch"]


@pytest.mark.parametrize("module", cli.COMMANDS, ids=lambda m: m.__name__.rsplit(".", 1)[1])
def test_each_command_module_adds_its_whole_parser_alone(module, monkeypatch: pytest.MonkeyPatch) -> None:  # noqa: ANN001
    monkeypatch.setenv("COLUMNS", "100")
    name = module.__name__.rsplit(".", 1)[1]
    alone = argparse.ArgumentParser(prog="magcal")
    module.add_parser(alone.add_subparsers(dest="command"))
    assembled = _subparsers(cli.build_parser())[name]
    assert _subparsers(alone)[name].format_help() == assembled.format_help()
    func = assembled.get_default("func")
    owner = "magcal_ros.app.batch" if name == "batch" else module.__name__
    assert func.__module__ == owner and func.__name__ == f"cmd_{name}"


def test_every_function_of_the_command_line_says_what_it_does() -> None:
    """Each function of cli.py and the command modules (moved from one 1,350-line cli.py) has its docstring."""
    missing = []
    for path in [Path(cli.__file__), *sorted(COMMANDS.glob("*.py"))]:
        tree = ast.parse(path.read_text(encoding="utf-8"))
        assert ast.get_docstring(tree), f"{path.name} has no module docstring"
        missing += [f"{path.name}:{n.name}" for n in tree.body
                    if isinstance(n, ast.FunctionDef) and not ast.get_docstring(n)]
    assert not missing, missing


def test_the_entry_point_and_the_option_groups_stay_in_cli() -> None:
    """setup.py's ``magcal = magcal_ros.app.cli:main``; the option groups other modules add are re-exported."""
    setup = (Path(cli.__file__).parents[2] / "setup.py").read_text(encoding="utf-8")
    assert '"magcal": "magcal_ros.app.cli:main"' in setup and callable(cli.main)
    for name in ("add_common_options", "add_input_options", "add_sync_options", "add_current_options",
                 "add_temperature_options", "add_imu_options", "add_window_options"):
        assert getattr(cli, name).__module__ == "magcal_ros.app.commands.common"
