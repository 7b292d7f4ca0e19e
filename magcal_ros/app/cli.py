"""The ``magcal`` command: offline calibration tools over CSV and rosbag2 recordings.

The commands live one module each in :mod:`magcal_ros.app.commands` (their options, examples and what they
run; what they share in :mod:`magcal_ros.app.commands.common`); this module assembles the parser from them and
runs it (:func:`main`: one line and exit 2 for bad input, signals, outputs left by a killed run).
"""

from __future__ import annotations

import argparse
import os
import re
import signal
import sys
import threading
from collections.abc import Sequence
from pathlib import Path
from types import FrameType
from typing import Any

import numpy as np

from magcal_ros.allocator import keep_freed_memory
from magcal_ros.app.commands import batch, calibrate, correct, plot, simulate
from magcal_ros.app.commands.common import (  # re-exported: the option groups other modules add
    _note,
    add_common_options,
    add_current_options,
    add_imu_options,
    add_input_options,
    add_sync_options,
    add_temperature_options,
    add_window_options,
)
from magcal_ros.errors import InputError, MagcalError, Stopped
from magcal_ros.io.atomic import STOP_SIGNALS, recover

COMMANDS = (simulate, calibrate, correct, plot, batch)
"""The command modules, each adding its parser (``add_parser``), in the order ``magcal --help`` lists them."""

__all__ = [
    "add_common_options",
    "add_current_options",
    "add_imu_options",
    "add_input_options",
    "add_sync_options",
    "add_temperature_options",
    "add_window_options",
    "build_parser",
    "main",
]


EXIT_CODES = """exit codes: 0 done; 2 refused (one line on stderr, nothing written); 130, 143, 129 stopped
by SIGINT, SIGTERM, SIGHUP (the unfinished output is removed). An output is replaced only when
the new one is complete; what a killed run leaves beside it is cleaned up by the next run."""


def build_parser() -> argparse.ArgumentParser:
    """The ``magcal`` argument parser."""
    import magcal_ros  # the package's version

    parser = argparse.ArgumentParser(
        prog="magcal",
        description="Calibrate, correct and inspect recordings of an array of three-axis magnetometers: one\n"
        "sensor, two (a gradiometer), the four-fluxgate cross of a gradient tensor array, or any number\n"
        "anywhere (Tesla on every topic and in every file).",
        epilog="examples:\n"
        "  magcal simulate rotation_bag && magcal calibrate rotation_bag -o cal.yaml --plot cal.png\n"
        "  magcal correct survey_bag -c cal.yaml -o corrected_bag\n"
        "  magcal batch campaign/ -c cal.yaml -o corrected/   # every recording, on Dask, with a report\n"
        "  magcal COMMAND --help      # options and examples of a command\n\n" + EXIT_CODES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"magcal {magcal_ros.__version__} (magcal_ros)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for command in COMMANDS:
        command.add_parser(sub)
    return parser


def _value_options(parser: argparse.ArgumentParser) -> frozenset[str]:
    """The option strings (of every subcommand) that take a value."""
    found: set[str] = set()
    stack = [parser]
    while stack:
        p = stack.pop()
        for action in p._actions:  # noqa: SLF001 - argparse keeps its actions here
            if isinstance(action, argparse._SubParsersAction):  # noqa: SLF001
                stack.extend(action.choices.values())
            elif action.option_strings and action.nargs != 0:
                found.update(action.option_strings)
    return frozenset(found)


def _attach_negative_values(argv: Sequence[str], options: frozenset[str]) -> list[str]:
    """``--positions -0.25,0,0,...`` as ``--positions=-0.25,0,0,...`` for every option that takes a
    value (numbers, or lists of them, may start with a minus sign): argparse takes a leading '-'
    followed by anything but a plain number for an option."""
    out: list[str] = []
    for arg in argv:
        if out and out[-1] in options and re.match(r"-\.?\d", arg):
            out[-1] = f"{out[-1]}={arg}"
        else:
            out.append(arg)
    return out


def _stop(signum: int, frame: FrameType | None) -> None:
    """Signal handler: ignore further stop signals while cleaning up, then unwind."""
    for s in STOP_SIGNALS:
        signal.signal(s, signal.SIG_IGN)
    raise Stopped(signum)


def _outputs(args: argparse.Namespace) -> list[str]:
    """Every path the command will write."""
    outs = [args.output]
    if args.command == "simulate":
        from magcal_ros.io.truth_file import truth_paths

        outs += [str(p) for p in truth_paths(args.output)]
    if getattr(args, "plot", None):
        outs.append(args.plot)
    return outs


def _check_paths(args: argparse.Namespace) -> None:
    """Refuse an output that is one of the command's inputs, or two outputs at one path."""
    inputs = [p for p in (getattr(args, "input", None), getattr(args, "calibration", None)) if p]
    seen: dict[Path, str] = {Path(p).resolve(): p for p in inputs}
    folders = [(Path(p).resolve(), p) for p in inputs if Path(p).is_dir()]  # a bag is a directory
    for out in _outputs(args):
        where = Path(out).resolve()
        if where in seen and seen[where] in inputs:
            raise InputError(f"output {out} would overwrite the input {seen[where]}: write to another path")
        inside = next((p for folder, p in folders if folder in where.parents), None)
        if inside is not None:
            raise InputError(f"output {out} is inside the input bag {inside}: write outside it")
        if where in seen:
            raise InputError(f"outputs {seen[where]} and {out} are the same file: give different paths")
        seen[where] = out


def _silence_stdout() -> None:
    """Point stdout at the null device so the interpreter's final flush cannot fail again."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)
    except (OSError, ValueError):
        pass


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point: one clear line on stderr and exit 2 for any bad input.

    SIGINT, SIGTERM and SIGHUP stop a run like Ctrl-C: the partial output is removed, one
    line says so, and the exit code is 128 + the signal number (130, 143, 129).
    """
    keep_freed_memory()
    parser = build_parser()
    args = parser.parse_args(_attach_negative_values(sys.argv[1:] if argv is None else argv, _value_options(parser)))
    previous: dict[signal.Signals, Any] = {}
    try:
        if threading.current_thread() is threading.main_thread():
            previous = {s: signal.signal(s, _stop) for s in STOP_SIGNALS}
        _check_paths(args)
        for out in _outputs(args):
            for note in recover(out):
                _note(note)
        with np.errstate(all="ignore"):  # a fit's overflow on bad data ends in a clear error, not a numpy warning
            return int(args.func(args) or 0)
    except MagcalError as exc:
        print(f"magcal {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except BrokenPipeError:
        # The reader of stdout went away (``magcal ... | head``): stop quietly as shell tools do.
        _silence_stdout()
        return 128 + int(signal.SIGPIPE)
    except OSError as exc:
        where = f"{exc.filename}: " if getattr(exc, "filename", None) else ""
        print(f"magcal {args.command}: error: {where}{exc.strerror or exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as exc:
        signum = exc.signum if isinstance(exc, Stopped) else signal.SIGINT
        print(f"magcal {args.command}: stopped by {signal.Signals(signum).name}; unfinished output removed", file=sys.stderr)
        return 128 + int(signum)
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)


if __name__ == "__main__":
    sys.exit(main())
