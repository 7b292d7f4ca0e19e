"""The README stands alone and, with docs/, documents what users rely on; every example runs."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def test_readme_points_only_into_the_repository() -> None:
    readme = (ROOT / "README.md").read_text()
    assert "../shared" not in _user_docs() and "/work/shared" not in _user_docs()
    assert "docs/interfaces.md" in readme and (ROOT / "docs" / "interfaces.md").is_file()


def _user_docs() -> str:
    """The README and every page of docs/: what a user reads."""
    return "\n".join(p.read_text() for p in [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))])


def test_user_visible_names_are_documented_in_readme_and_interfaces() -> None:
    readme = _user_docs()
    interfaces = (ROOT / "docs" / "interfaces.md").read_text()
    for name in ("gradient_stamped", "/diagnostics", "uncorrected_sensors", "covariance", "sensor_timeout",
                 "output_timeout", "max_drop_fraction", "backups", ".bak", "use_sim_time"):
        assert name in readme, name
    for name in ("gradient_stamped", "/diagnostics", "uncorrected_sensors", "<name>.covariance", "sensor_timeout",
                 "output_timeout", "max_drop_fraction", "backups", "<name>.lost", "sync_window_ms"):
        assert name in interfaces, name


def test_every_node_parameter_and_progress_key_is_documented() -> None:
    """Each parameter the nodes declare (per-sensor ones as <name>.x) is named in docs/interfaces.md
    and, but for the per-sensor calibration, in the user's pages (README.md and docs/); so are the new
    topics and progress keys."""
    import rclpy
    from rclpy.context import Context

    from magcal_ros.app.ros_driver import pick_domain_id, release_domain_id
    from magcal_ros.nodes.calibration_node import CalibrationNode
    from magcal_ros.nodes.correction_node import CorrectionNode

    readme = _user_docs()
    interfaces = (ROOT / "docs" / "interfaces.md").read_text()
    context = Context()
    domain = pick_domain_id()  # never the environment's ROS_DOMAIN_ID (a vehicle's live domain)
    rclpy.init(context=context, args=["--ros-args", "-p", "uncorrected_sensors:=[mag1, mag2, mag3, mag4]"],
               domain_id=domain)
    names: set[str] = set()
    try:
        for make in (CorrectionNode, CalibrationNode):
            node = make(context=context)
            names |= {n.replace("mag1.", "<name>.") for n in node.list_parameters([], 0).names
                      if not n.startswith(("mag2.", "mag3.", "mag4.")) and n not in ("use_sim_time", "start_type_description_service")}
            node.close() if hasattr(node, "close") else None
            node.destroy_node()
    finally:
        rclpy.shutdown(context=context)
        release_domain_id(domain)
    assert {"prior", "site", "date", "max_residual", "assess_period", "interference_topics", "<name>.interference"} <= names
    assert [n for n in sorted(names) if f"`{n}`" not in interfaces] == []
    assert [n for n in sorted(names) if not n.startswith("<name>.") and n not in readme] == []
    for key in ("baseline_gradient", "stale_current", "envelope_pitch_deg", "advice", "undetermined", "assessed"):
        assert key in readme and key in interfaces, key


# --------------------------------------------------------------------------- the examples run
DOCUMENTS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
SHELLS = {"bash", "sh", "shell"}
MARKERS = {
    "ros2": "needs a ROS 2 command line and the nodes running on a vehicle's sensors",
    "repo": "runs in a checkout of the repository (set-up, the test suite, benchmarks, mutation runs)",
}
"""Fence info words after ``bash`` that mark a block the test does not run, and why."""
FENCE = re.compile(r"^(?P<indent>[ ]*)```(?P<lang>[\w-]*)(?P<tags>[^\n]*)\n(?P<code>.*?)^(?P=indent)```[ ]*$", re.M | re.S)
WARNING = re.compile(r"\bwarning\b", re.I)


def blocks(path: Path) -> list[tuple[str, set[str], str, int]]:
    """``(language, marker words, code, line)`` of each fenced block of a Markdown file."""
    text = path.read_text()
    return [(m["lang"], set(m["tags"].split()), m["code"], text.count("\n", 0, m.start()) + 1)
            for m in FENCE.finditer(text)]


def _runnable(path: Path, language: set[str]) -> list[tuple[str, int]]:
    return [(code, line) for lang, tags, code, line in blocks(path) if lang in language and not tags]


def _environment(tmp: Path) -> dict[str, str]:
    """This tree's `magcal` first on PATH (a shim running `python -m magcal_ros.app.cli` from the tree)."""
    shims = tmp / ".shims"
    shims.mkdir()
    shim = shims / "magcal"
    shim.write_text(f'#!/bin/sh\nexec "{sys.executable}" -m magcal_ros.app.cli "$@"\n')
    shim.chmod(0o755)
    return {**os.environ, "PATH": f"{shims}{os.pathsep}{os.environ.get('PATH', '')}", "PYTHONPATH": str(ROOT),
            "MPLBACKEND": "Agg", "COLUMNS": "100"}


@pytest.mark.parametrize("path", DOCUMENTS, ids=lambda p: p.name)
def test_every_shell_block_runs_top_to_bottom_in_an_empty_directory_without_a_warning(path: Path, tmp_path: Path) -> None:
    """A page's unmarked shell blocks, in order, as one `set -euo pipefail` script in a fresh directory:
    they make their own inputs (magcal simulate) and say no "warning" on them. Blocks marked `ros2` or
    `repo` are skipped with their reason (test_marked_blocks_say_why); any other marker is refused."""
    found = blocks(path)
    unknown = [(line, tags) for lang, tags, _, line in found if lang in SHELLS and tags - set(MARKERS)]
    assert not unknown, f"{path.name}: unknown block markers {unknown} (known: {', '.join(MARKERS)})"
    script = _runnable(path, SHELLS)
    if not script:
        pytest.skip(f"{path.name} has no shell block to run")
    text = "set -euo pipefail\n" + "".join(f"# {path.name}:{line}\n{code}" for code, line in script)
    proc = subprocess.run(["bash", "-c", text], cwd=tmp_path, env=_environment(tmp_path), capture_output=True,
                          text=True, timeout=900)
    output = proc.stdout + proc.stderr
    assert proc.returncode == 0, f"{path.name}: exit {proc.returncode}\n{output[-4000:]}"
    warned = [line for line in output.splitlines() if WARNING.search(line)]
    assert not warned, f"{path.name}: the examples warn on their own data: {warned[:5]}"


@pytest.mark.parametrize("path", [p for p in DOCUMENTS if _runnable(p, {"python"})], ids=lambda p: p.name)
def test_every_python_block_runs_top_to_bottom(path: Path, tmp_path: Path) -> None:
    """A page's Python blocks, in order, as one script (their asserts check numbers against the simulation)."""
    text = "".join(f"# {path.name}:{line}\n{code}" for code, line in _runnable(path, {"python"}))
    proc = subprocess.run([sys.executable, "-c", text], cwd=tmp_path, env=_environment(tmp_path), capture_output=True,
                          text=True, timeout=900)
    assert proc.returncode == 0, f"{path.name}: exit {proc.returncode}\n{(proc.stdout + proc.stderr)[-4000:]}"


def test_marked_blocks_say_why_they_are_not_run() -> None:
    """Each block the test does not run is marked in its fence and preceded by an HTML comment naming the
    marker (what a reader needs to run it), and the README's two commands are among them."""
    marked = 0
    for path in DOCUMENTS:
        lines = path.read_text().splitlines()
        for lang, tags, _, line in blocks(path):
            if lang in SHELLS and tags:
                marked += 1
                before = lines[line - 2].strip() if line >= 2 else ""
                assert before.startswith("<!--") and any(t in before for t in tags), f"{path.name}:{line}: {before!r}"
    assert marked >= 3
    readme = [code for lang, tags, code, _ in blocks(ROOT / "README.md") if "repo" in tags]
    assert any("bash scripts/demo.sh" in c and "bash scripts/test.sh" in c for c in readme)


def test_readme_is_short_and_links_into_docs() -> None:
    readme = (ROOT / "README.md").read_text()
    assert len(readme.splitlines()) <= 300
    linked = set(re.findall(r"docs/([\w-]+\.md)", readme))
    pages = {p.name for p in (ROOT / "docs").glob("*.md")}
    assert linked <= pages and pages <= linked, (pages - linked, linked - pages)
