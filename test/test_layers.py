"""The tree is the architecture: no import runs from a lower layer to a higher one.

Layers, lowest first: core, then methods and sim (side by side), io, nodes, app. The
math layers import no I/O or middleware package at all.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "magcal_ros"
BASE = {"errors", "_lazy", "allocator", ""}  # below every layer: errors, lazy names, the process allocator
ALLOWED: dict[str, set[str]] = {
    "core": {"core"},
    "methods": {"core", "methods"},
    "sim": {"core", "sim"},
    "io": {"core", "sim", "io"},
    "nodes": {"core", "methods", "io", "nodes"},
    "app": {"core", "methods", "sim", "io", "nodes", "app"},
}
FORBIDDEN_THIRD_PARTY: dict[str, set[str]] = {
    layer: {"rclpy", "rosbags", "yaml", "matplotlib", "apsw", "sensor_msgs", "std_msgs", "diagnostic_msgs"}
    for layer in ("core", "methods", "sim")
}


def imports(path: Path) -> list[tuple[int, str]]:
    """(line, absolute module name) of every import in a file, inside functions too."""
    out = []
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            out.append((node.lineno, node.module))
            if node.module == "magcal_ros":
                out += [(node.lineno, f"magcal_ros.{a.name}") for a in node.names]
    return out


MODULES = sorted(p for p in PACKAGE.rglob("*.py"))


@pytest.mark.parametrize("path", MODULES, ids=lambda p: str(p.relative_to(PACKAGE)))
def test_no_import_from_a_higher_layer(path: Path) -> None:
    rel = path.relative_to(PACKAGE)
    layer = rel.parts[0] if len(rel.parts) > 1 else ""
    allowed = ALLOWED.get(layer, set(ALLOWED)) | BASE
    for line, module in imports(path):
        parts = module.split(".")
        if parts[0] == "magcal_ros" and len(parts) > 1:
            assert parts[1] in allowed, f"{rel}:{line} ({layer or 'top'} layer) imports {module}"
        assert parts[0] not in FORBIDDEN_THIRD_PARTY.get(layer, set()), f"{rel}:{line} imports {module}"


def test_every_subpackage_states_its_job_and_exports_its_names() -> None:
    for sub in sorted(p for p in PACKAGE.iterdir() if p.is_dir() and (p / "__init__.py").exists()):
        text = (sub / "__init__.py").read_text(encoding="utf-8")
        tree = ast.parse(text)
        assert ast.get_docstring(tree), f"{sub.name}/__init__.py has no docstring"
        assert "__all__" in text, f"{sub.name}/__init__.py defines no __all__"


def test_the_layer_check_catches_a_planted_upward_import(tmp_path: Path) -> None:
    planted = tmp_path / "planted.py"
    planted.write_text("def f():\n    from magcal_ros.io import topics\n    import rclpy\n")
    assert [m for _, m in imports(planted)] == ["magcal_ros.io", "rclpy"]


def test_the_command_line_starts_without_the_slow_scipy_modules() -> None:
    """``scipy.stats`` and ``scipy.optimize`` take about a second each to import, ``scipy.spatial`` and
    ``scipy.linalg`` a third: a calibration needs none of them (its chi-square quantiles come from
    ``scipy.special``, its solves and decompositions from numpy), so ``magcal`` (its whole parser) and
    the solver do not load them at start (the few functions that use them import them when called)."""
    import os
    import subprocess
    import sys

    code = ("import sys, magcal_ros.app.cli, magcal_ros.methods.pipeline, magcal_ros.core.array_fit; "
            "magcal_ros.app.cli.build_parser(); "
            "print(sorted(m for m in ('scipy.stats', 'scipy.optimize', 'scipy.spatial', 'scipy.linalg') "
            "if m in sys.modules))")
    env = dict(os.environ, PYTHONPATH=str(PACKAGE.parent) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True)
    assert out.stdout.strip() == "[]"
