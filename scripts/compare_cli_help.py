#!/usr/bin/env python3
"""Compare the ``magcal`` help texts of two source trees: ``magcal --help`` and ``magcal COMMAND --help`` of
every command, each run as ``python -m magcal_ros.app.cli`` with the tree first on PYTHONPATH (80 columns).

    python scripts/compare_cli_help.py OLD [NEW]

OLD and NEW: a source tree (the directory holding ``magcal_ros``) or a git revision of this repository
(exported to a temporary directory); NEW defaults to this tree. Prints a unified diff of every help that
differs and exits 1, or says that they are the same and exits 0. A refactoring of the command line (e.g.
moving a command into its own module) keeps every help text: run it against the commit before.
"""

from __future__ import annotations

import difflib
import os
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
COMMANDS = ("simulate", "calibrate", "correct", "plot", "batch")


def tree(spec: str, work: Path) -> Path:
    """The source tree ``spec`` names: a directory, or a git revision exported into ``work``."""
    if Path(spec, "magcal_ros").is_dir():
        return Path(spec).resolve()
    out = work / spec.replace("/", "_")
    out.mkdir()
    archive = subprocess.run(["git", "-C", str(ROOT), "archive", spec, "magcal_ros"], capture_output=True, check=True)
    subprocess.run(["tar", "-x", "-C", str(out)], input=archive.stdout, check=True)
    return out


def helps(src: Path) -> dict[str, str]:
    """Every help text of the ``magcal`` of ``src``, by command (``magcal`` for the top level)."""
    env = dict(os.environ, PYTHONPATH=str(src), COLUMNS="80")
    out = {}
    for command in ("", *COMMANDS):
        args = [sys.executable, "-m", "magcal_ros.app.cli", *([command] if command else []), "--help"]
        proc = subprocess.run(args, capture_output=True, text=True, env=env, cwd=src)
        out[command or "magcal"] = proc.stdout + (f"[exit {proc.returncode}] {proc.stderr}" if proc.returncode else "")
    return out


def main(argv: list[str]) -> int:
    if not 1 <= len(argv) <= 2:
        print(__doc__, file=sys.stderr)
        return 2
    with tempfile.TemporaryDirectory() as tmp:
        old = helps(tree(argv[0], Path(tmp)))
        new = helps(tree(argv[1], Path(tmp)) if len(argv) > 1 else ROOT)
    differ = False
    for name in old:
        if old[name] != new[name]:
            differ = True
            sys.stdout.writelines(difflib.unified_diff(old[name].splitlines(True), new[name].splitlines(True),
                                                       f"{argv[0]}: {name}", f"new: {name}"))
    print("help texts differ" if differ else f"the same help texts ({', '.join(old)})")
    return 1 if differ else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
