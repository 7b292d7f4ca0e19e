"""Planted regressions and a mutation run over the core's math: do the tests notice? (not CI)

Both work on a throw-away copy of ``magcal_ros/`` and ``test/`` (never on the checkout):
a change is written into the copy, a fast subset of the tests runs against it in a
subprocess with a timeout, and the change counts as *killed* when a test fails (or the
run times out, or the package no longer imports).

``python benchmarks/mutation.py plants [NAME ...]``
    Each method's planted regression (a realistic bug that costs 10 % or more accuracy:
    an aligner angle off by 5e-5 rad, an offset 10 % off, joint refinement disabled ...)
    against the accuracy, core, method and paper tests; prints which tests fail.

``python benchmarks/mutation.py survivors [NAME ...]``
    The survivors of an independent mutation pass (``SURVIVORS``), each planted against the
    tests written for it; every one must make a test fail.

``python benchmarks/mutation.py mutants [--per-module N] [--seed S] [--modules a,b] [--json OUT]``
    AST mutations, one at a time, of the core's math (``MODULES``): numeric constants
    (ints + 1, floats x 2, 0.0 -> 1.0), index offsets (an integer index or slice bound + 1),
    comparison operators (``<`` <-> ``<=``, ``>`` <-> ``>=``, ``==`` <-> ``!=``), arithmetic
    operators (``+`` <-> ``-``, ``*`` <-> ``/``, ``//`` -> ``/``, ``**`` -> ``*``) and
    signs (unary minus removed). Error messages (f-strings, ``raise`` arguments) and type
    annotations are not mutated. With ``--per-module N`` a module with more mutation
    sites than N is sampled (N sites drawn without replacement with ``--seed``). Each
    mutant runs its module's test subset (``SUBSETS``) with ``-x`` and a timeout.

Run from the repository root with the project's venv: ``.venv/bin/python benchmarks/mutation.py ...``.
"""

from __future__ import annotations

import argparse
import ast
import copy
import json
import os
import random
import re
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

# --------------------------------------------------------------------------- the copy


class Sandbox:
    """A copy of the package and its tests in a temporary directory, one file changed at a time."""

    def __init__(self) -> None:
        self.dir = Path(tempfile.mkdtemp(prefix="magcal_mutation_"))
        shutil.copytree(ROOT / "magcal_ros", self.dir / "magcal_ros", ignore=shutil.ignore_patterns("__pycache__"))
        shutil.copytree(ROOT / "test", self.dir / "test", ignore=shutil.ignore_patterns("__pycache__"))

    def write(self, rel: str, text: str) -> None:
        """Replace ``rel`` (a path under the copy) by ``text``."""
        path = self.dir / rel
        path.write_text(text, encoding="utf-8")
        shutil.rmtree(path.parent / "__pycache__", ignore_errors=True)

    def restore(self, rel: str) -> None:
        """Put back the checkout's version of ``rel``."""
        self.write(rel, (ROOT / rel).read_text(encoding="utf-8"))

    def pytest(self, tests: list[str], timeout: float, stop_first: bool) -> tuple[str, list[str], float]:
        """Run ``tests`` in the copy: ``(status, failing test ids, seconds)``; status is
        ``passed``, ``failed``, ``timeout`` or ``error`` (collection or import failed)."""
        env = dict(os.environ)
        env.pop("PYTHONPATH", None)
        env["PYTHONDONTWRITEBYTECODE"] = "1"
        cmd = [sys.executable, "-m", "pytest", "-q", "-rf", "-p", "no:cacheprovider", "-p", "no:warnings",
               *(["-x"] if stop_first else []), *tests]
        t0 = time.perf_counter()
        try:
            proc = subprocess.run(cmd, cwd=self.dir, env=env, capture_output=True, text=True, timeout=timeout)
        except subprocess.TimeoutExpired:
            return "timeout", [], time.perf_counter() - t0
        seconds = time.perf_counter() - t0
        failing = re.findall(r"^FAILED (\S+)", proc.stdout, flags=re.M)
        if proc.returncode == 0:
            return "passed", [], seconds
        if proc.returncode == 1 and failing:
            return "failed", failing, seconds
        return "error", failing or [proc.stdout.strip().splitlines()[-1] if proc.stdout.strip() else "no output"], seconds

    def accuracy(self, method: str) -> str:
        """``method``'s held-out metrics on the copy (test/test_accuracy.py, seed 0)."""
        env = dict(os.environ, PYTHONPATH=str(self.dir), PYTHONDONTWRITEBYTECODE="1")
        proc = subprocess.run([sys.executable, "test/test_accuracy.py", "1", method], cwd=self.dir, env=env,
                              capture_output=True, text=True, timeout=600)
        found = re.search(r"gradient ([\d.]+)/.*tmi ([\d.]+)/(?:.*angle ([\d.]+)/)?", proc.stdout)
        return "/".join(g for g in found.groups() if g) if found else "fails: " + (proc.stderr.strip().splitlines() or ["?"])[-1]

    def close(self) -> None:
        shutil.rmtree(self.dir, ignore_errors=True)


# --------------------------------------------------------------------------- planted regressions


@dataclass(frozen=True)
class Plant:
    """A realistic bug: ``old`` replaced by ``new`` (exactly once) in ``path``."""

    name: str
    method: str
    path: str
    old: str
    new: str
    what: str
    measure: str = ""
    """What test/test_accuracy.py measures for the effect column (default: ``method``)."""
    tests: tuple[str, ...] = ()
    """The tests (pytest arguments) this plant runs against (default: :data:`PLANT_TESTS`)."""


PLANTS: tuple[Plant, ...] = (
    Plant("ml-joint-off", "ml", "magcal_ros/methods/pipeline.py",
          "joint = (spec.joint and opts.joint) or prior is not None",
          "joint = prior is not None",
          "joint refinement disabled: ml stops at per-sensor ML + Procrustes"),
    Plant("ml-tilt", "ml", "magcal_ros/core/array_fit.py",
          "    mats = np.linalg.inv(k_new)\n",
          "    mats = np.linalg.inv(k_new)\n    mats[0] = np.array([[1, -3e-5, 0], [3e-5, 1, 0], [0, 0, 1]]) @ mats[0]\n",
          "the joint fit returns sensor 1 turned by 3e-5 rad about z (a 10 % tensor regression)"),
    Plant("ml-offset", "ml", "magcal_ros/core/array_fit.py",
          "offsets=w[:, :, 3] * f,",
          "offsets=w[:, :, 3] * f * 1.1,",
          "the joint fit's offsets 10 % off"),
    Plant("ml-prior-offset", "ml", "magcal_ros/core/prior.py",
          "offset: float = 2000 * NT",
          "offset: float = 2 * NT",
          "partial recalibration: the drift model holds every offset within 2 nT of the old calibration",
          "prior"),
    Plant("ml-early-stop", "ml", "magcal_ros/core/array_fit.py",
          "done = cost - new_cost <= tolerance * max(cost, 1e-300)",
          "done = True",
          "the joint Levenberg-Marquardt stops after its first accepted step (costs no accuracy from the "
          "per-sensor start: only the check against scipy's optimum sees it)"),
    Plant("linear-angle", "linear", "magcal_ros/core/alignment.py",
          "gamma = np.arctan2(vx[1], vx[0])",
          "gamma = np.arctan2(vx[1], vx[0]) + 5e-5",
          "Li et al.'s Euler-angle aligner: azimuth off by 5e-5 rad"),
    Plant("linear-shrink", "linear", "magcal_ros/core/scalar_fit.py",
          "m = np.linalg.cholesky(mtm).T  # upper triangular, M^T M = mtm",
          "m = np.linalg.cholesky(mtm).T\n    m = np.eye(3) + (m - np.eye(3)) / 1.1",
          "the closed-form fit's matrix pulled 10 % toward the identity"),
    Plant("reference-angle", "reference", "magcal_ros/core/alignment.py",
          "alpha = np.arcsin(np.clip(vy[2] / np.cos(beta), -1.0, 1.0))",
          "alpha = np.arcsin(np.clip(vy[2] / np.cos(beta), -1.0, 1.0)) + 5e-5",
          "the angle aligner's heel off by 5e-5 rad (the reference method aligns to sensor 1 with it)"),
    Plant("regression-offset", "regression", "magcal_ros/core/alignment.py",
          "return w, -np.linalg.solve(w, coef[3])",
          "return w, -1.1 * np.linalg.solve(w, coef[3])",
          "the affine regression's offsets 10 % off"),
    Plant("regression-gain", "regression", "magcal_ros/core/alignment.py",
          "w = coef[:3].T",
          "w = coef[:3].T * (1 + 2e-5)",
          "the regressed sensors' gain 2e-5 high (1 nT in 50000 nT)"),
    Plant("paired-offset", "paired", "magcal_ros/methods/paired.py",
          "offset = sol.x[5:8] * unit if fit_offset else np.zeros(3)",
          "offset = 1.1 * sol.x[5:8] * unit if fit_offset else np.zeros(3)",
          "Wu et al.'s paired fit: offsets 10 % off"),
    Plant("pso-budget", "pso", "magcal_ros/methods/pso.py",
          "for it in range(iterations):",
          "for it in range(iterations // 3):",
          "the swarm stops at a third of its iterations (not yet at the optimum)"),
    Plant("pso-inertia", "pso", "magcal_ros/methods/pso.py",
          "vel = w * vel + c1 * r1 * (best_pos - pos) + c2 * r2 * (best_pos[g] - pos)",
          "vel = w * vel + c1 * r1 * (best_pos - pos) + 0.5 * c2 * r2 * (best_pos[g] - pos)",
          "the swarm's social term halved (a slower, less precise swarm)"),
)

_CLI_CURRENTS = "test/test_interference.py::test_bags_with_battery_state_and_float64_channels_via_the_cli"
SURVIVORS: tuple[Plant, ...] = (
    Plant("undetermined-800", "ml", "magcal_ros/core/identifiability.py",
          "UNDETERMINED_EFFECT: float = 400.0", "UNDETERMINED_EFFECT: float = 800.0",
          "the identifiability threshold doubled: undetermined only above 800 noise sd",
          tests=("test/test_limits.py",)),
    Plant("jackknife-off", "ml", "magcal_ros/methods/pipeline.py",
          "    n = len(order)\n    blocks = np.array_split(order, JACKKNIFE_BLOCKS)",
          "    return 1.0\n    n = len(order)\n    blocks = np.array_split(order, JACKKNIFE_BLOCKS)",
          "the block-jackknife widening skipped (stated sigmas 1.1-1.9x too small)",
          tests=("test/test_field.py::test_reported_uncertainty_matches_the_spread_with_correlated_noise",)),
    Plant("quantity-unit", "ml", "magcal_ros/core/identifiability.py",
          'scale = {"nT": 1.0 / NT,', 'scale = {"nT": NT,',
          "quantities reported in nT (summary, file uncertainty.*_nT) off by 1e18",
          tests=("test/test_user_numbers.py",)),
    Plant("corrected-set-stamp", "ml", "magcal_ros/app/correct.py",
          "self.sensor_template.fill(blocks, off[k], batch.stamps[:, k], sets.vectors[:, k])",
          "self.sensor_template.fill(blocks, off[k], batch.set_stamps, sets.vectors[:, k])",
          "magcal correct stamps /<name>/corrected with the set's stamp instead of the sensor's own",
          tests=(_CLI_CURRENTS,)),
    Plant("currents-bag-time", "ml", "magcal_ros/io/cdr.py",
          "    return stamp or int(bag_time_ns), float(msg.current)",
          "    return int(bag_time_ns), float(msg.current)",
          "BatteryState currents stamped by bag time instead of their header",
          tests=(_CLI_CURRENTS,)),
    Plant("matrix-transposed", "ml", "magcal_ros/core/calibration.py",
          'params[name] = {"matrix": [float(x) for x in m.reshape(-1)]',
          'params[name] = {"matrix": [float(x) for x in m.T.reshape(-1)]',
          "the calibration matrix written transposed (column-major) to the file",
          tests=("test/test_calibration_file.py",)),
    Plant("stamp-truncated", "ml", "magcal_ros/core/stamps.py",
          "np.rint((t - whole) * NS_PER_S).astype(np.int64)", "((t - whole) * NS_PER_S).astype(np.int64)",
          "float seconds truncated instead of rounded to the nanosecond (1 ns off)",
          tests=("test/test_bagio.py::test_stamp_conversion",)),
)
"""The survivors of an independent mutation pass (docs/mutation_report.md), each with the tests
written to kill it. The node's own stamp mutant (``correction_node``) needs the package installed
(the DDS tests run the installed executables), so it is planted by hand: see the report."""

PLANT_TESTS = ["test/test_accuracy.py", "test/test_tensor_geometry.py", "test/test_core.py", "test/test_methods.py",
               "test/test_papers.py"]


def run_survivors(names: list[str]) -> int:
    """Each survivor plant against its own tests: which fail (every one must)."""
    box = Sandbox()
    missed = 0
    try:
        print("| plant | bug | tests run | result |\n| --- | --- | --- | --- |")
        for p in SURVIVORS:
            if names and p.name not in names:
                continue
            text = (ROOT / p.path).read_text(encoding="utf-8")
            assert text.count(p.old) == 1, f"{p.name}: the text to replace is not unique in {p.path}"
            base, failing, _ = box.pytest(list(p.tests), 1800, stop_first=False)
            if base != "passed":
                print(f"| {p.name} | {p.what} | unchanged copy {base}: {failing} | - |")
                missed += 1
                continue
            box.write(p.path, text.replace(p.old, p.new))
            status, failing, secs = box.pytest(list(p.tests), 1800, stop_first=False)
            box.restore(p.path)
            shown = ", ".join(f.split("::", 1)[1] if "::" in f else f for f in failing) or "NONE"
            missed += status != "failed"
            print(f"| {p.name} | {p.what} | {', '.join(p.tests)} | {status} ({secs:.0f} s): {shown} |", flush=True)
    finally:
        box.close()
    return 1 if missed else 0


def run_plants(names: list[str]) -> int:
    box = Sandbox()
    try:
        base, failing, secs = box.pytest(PLANT_TESTS, 1800, stop_first=False)
        print(f"unchanged copy: {base} in {secs:.0f} s", flush=True)
        if base != "passed":
            print("the unchanged tests must pass first:", failing)
            return 1
        print("| plant | method | bug | held-out gradient / TMI ratio / angle (urad) of test_accuracy.py, seed 0: "
              "unchanged -> planted | "
              "failing tests |\n| --- | --- | --- | --- | --- |")
        for p in PLANTS:
            if names and p.name not in names:
                continue
            text = (ROOT / p.path).read_text(encoding="utf-8")
            assert text.count(p.old) == 1, f"{p.name}: the text to replace is not unique in {p.path}"
            box.write(p.path, text.replace(p.old, p.new))
            status, failing, secs = box.pytest(PLANT_TESTS, 1800, stop_first=False)
            effect = box.accuracy(p.measure or p.method)
            box.restore(p.path)
            shown = ", ".join(f.split("::", 1)[1] if "::" in f else f for f in failing) or "NONE"
            before = box.accuracy(p.measure or p.method)
            print(f"| {p.name} | {p.method} | {p.what} | {before} -> {effect} | {status}: {len(failing)} - {shown} |",
                  flush=True)
    finally:
        box.close()
    return 0


# --------------------------------------------------------------------------- mutants

MODULES: tuple[str, ...] = (
    "magcal_ros/core/scalar_fit.py",
    "magcal_ros/core/array_fit.py",
    "magcal_ros/core/alignment.py",
    "magcal_ros/core/tensor.py",
    "magcal_ros/core/sync.py",
    "magcal_ros/core/sync_rules.py",
    "magcal_ros/core/sync_interpolate.py",
    "magcal_ros/core/sample_clock.py",
    "magcal_ros/io/cdr.py",
    "magcal_ros/core/rotation.py",
)
_FIT = ["test/test_accuracy.py", "test/test_methods.py", "test/test_core.py",
        # the three slowest core tests (9-15 s) only repeat what the accuracy tests check
        "--deselect", "test/test_core.py::test_a_wrong_reference_field_or_a_non_uniform_field_is_refused",
        "--deselect", "test/test_core.py::test_48_random_attitudes_stay_near_the_floor_and_joint_refinement_matters",
        "--deselect", "test/test_core.py::test_pipeline_on_fresh_data_is_at_the_floor"]
SUBSETS: dict[str, list[str]] = {
    "magcal_ros/core/scalar_fit.py": ["test/test_papers.py::test_ding2024_ml_at_noise_floor",
                                      "test/test_papers.py::test_li2018_table3_misalignment", *_FIT],
    "magcal_ros/core/array_fit.py": _FIT,
    "magcal_ros/core/alignment.py": ["test/test_papers.py::test_li2018_table3_misalignment",
                                     "test/test_papers.py::test_coaxial2022_axis_angle", *_FIT],
    "magcal_ros/core/tensor.py": ["test/test_tensor_geometry.py", "test/test_core.py",
                                  "test/test_methods.py::test_pipeline_methods"],
    "magcal_ros/core/sync.py": ["test/test_sync.py", "test/test_bagio.py", "test/test_streams.py"],
    "magcal_ros/core/sync_rules.py": ["test/test_sync.py", "test/test_streams.py"],
    "magcal_ros/core/sync_interpolate.py": ["test/test_streams.py"],
    "magcal_ros/core/sample_clock.py": ["test/test_sample_clock.py", "test/test_streams.py", "test/test_health.py"],
    "magcal_ros/io/cdr.py": ["test/test_bagio.py", "test/test_node_helpers.py"],
    "magcal_ros/core/rotation.py": ["test/test_papers.py::test_li2018_table3_misalignment", *_FIT],
}
"""The fast test subset each module's mutants run (pytest arguments), a few seconds each."""


@dataclass
class Mutant:
    module: str
    index: int
    kind: str
    line: int
    before: str
    after: str
    line_before: str = ""
    """The changed line, as ``ast.unparse`` writes the module (comments dropped)."""
    line_after: str = ""
    status: str = ""
    killer: str = ""
    seconds: float = 0.0


_SWAP_CMP = {ast.Lt: ast.LtE, ast.LtE: ast.Lt, ast.Gt: ast.GtE, ast.GtE: ast.Gt, ast.Eq: ast.NotEq, ast.NotEq: ast.Eq}
_SWAP_BIN = {ast.Add: ast.Sub, ast.Sub: ast.Add, ast.Mult: ast.Div, ast.Div: ast.Mult, ast.FloorDiv: ast.Div,
             ast.Pow: ast.Mult}


def _excluded(tree: ast.AST) -> set[int]:
    """ids of nodes never mutated: messages (f-strings, raise arguments), annotations, docstrings."""
    out: set[int] = set()

    def mark(node: ast.AST | None) -> None:
        if node is not None:
            out.update(id(n) for n in ast.walk(node))

    for node in ast.walk(tree):
        if isinstance(node, ast.JoinedStr):
            mark(node)
        elif isinstance(node, ast.Raise):
            mark(node.exc)
        elif isinstance(node, (ast.AnnAssign, ast.arg)):
            mark(node.annotation)
        elif isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            mark(node.returns)
        elif isinstance(node, ast.If) and ast.unparse(node.test) == "TYPE_CHECKING":
            mark(node)
    return out


def _index_constants(tree: ast.AST) -> set[int]:
    """ids of integer constants used as an index or slice bound."""
    out: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Subscript):
            for n in ast.walk(node.slice):
                if isinstance(n, ast.Constant) and type(n.value) is int:
                    out.add(id(n))
    return out


def _sites(tree: ast.AST) -> list[tuple[ast.AST, str]]:
    """Every (node, kind) that can be mutated, in a deterministic order."""
    skip = _excluded(tree)
    index = _index_constants(tree)
    sites: list[tuple[ast.AST, str]] = []
    for node in ast.walk(tree):
        if id(node) in skip:
            continue
        if isinstance(node, ast.Constant) and type(node.value) in (int, float):
            sites.append((node, "index" if id(node) in index else "number"))
        elif isinstance(node, ast.Compare):
            sites += [(node, f"compare{k}") for k, op in enumerate(node.ops) if type(op) in _SWAP_CMP]
        elif isinstance(node, (ast.BinOp, ast.AugAssign)) and type(node.op) in _SWAP_BIN:
            sites.append((node, "arithmetic"))
        elif isinstance(node, ast.UnaryOp) and isinstance(node.op, ast.USub):
            sites.append((node, "sign"))
    return sites


def _mutate(node: ast.AST, kind: str) -> ast.AST | None:
    """The mutated replacement of ``node`` (a new node), or None to drop a unary minus."""
    new = copy.deepcopy(node)
    if kind in ("number", "index"):
        v = new.value  # type: ignore[attr-defined]
        new.value = v + 1 if type(v) is int else (1.0 if v == 0 else v * 2.0)  # type: ignore[attr-defined]
    elif kind.startswith("compare"):
        k = int(kind[7:])
        new.ops[k] = _SWAP_CMP[type(new.ops[k])]()  # type: ignore[attr-defined]
    elif kind == "arithmetic":
        new.op = _SWAP_BIN[type(new.op)]()  # type: ignore[attr-defined]
    elif kind == "sign":
        return new.operand  # type: ignore[attr-defined]
    return new


def _replace(tree: ast.AST, target: ast.AST, new: ast.AST) -> None:
    for parent in ast.walk(tree):
        for name, value in ast.iter_fields(parent):
            if value is target:
                setattr(parent, name, new)
                return
            if isinstance(value, list):
                for i, item in enumerate(value):
                    if item is target:
                        value[i] = new
                        return
    raise LookupError("mutation site not found")


def mutants_of(module: str) -> list[tuple[Mutant, str]]:
    """Every mutant of ``module`` with its mutated source."""
    source = (ROOT / module).read_text(encoding="utf-8")
    plain = ast.unparse(ast.parse(source)).splitlines()
    out = []
    count = len(_sites(ast.parse(source)))
    for i in range(count):
        tree = ast.parse(source)  # a fresh tree per mutant: sites are found again in the same order
        node, kind = _sites(tree)[i]
        new = _mutate(node, kind)
        before = ast.unparse(node)
        _replace(tree, node, new)
        text = ast.unparse(tree)
        changed = [(a, b) for a, b in zip(plain, text.splitlines()) if a != b][:1] or [("", "")]
        out.append((Mutant(module, i, kind.rstrip("0123456789"), getattr(node, "lineno", 0), _short(before),
                           _short(ast.unparse(new)), _short(changed[0][0].strip(), 160),
                           _short(changed[0][1].strip(), 160)), text))
    return out


def _short(text: str, width: int = 90) -> str:
    text = " ".join(text.split())
    return text if len(text) <= width else text[: width - 3] + "..."


def run_mutants(per_module: int | None, seed: int, modules: list[str], json_out: Path | None,
                only: set[tuple[str, int]] | None = None, exclude: set[tuple[str, int]] | None = None) -> int:
    box = Sandbox()
    results: list[Mutant] = []
    try:
        for module in modules:
            tests = SUBSETS[module]
            status, failing, base = box.pytest(tests, 1800, stop_first=True)
            if status != "passed":
                print(f"{module}: the unchanged subset must pass first: {status} {failing}")
                return 1
            timeout = 3.0 * base + 30.0
            everything = [m for m in mutants_of(module) if not exclude or (module, m[0].index) not in exclude]
            chosen = everything
            if per_module and len(everything) > per_module:
                chosen = sorted(random.Random(f"{seed}:{module}").sample(everything, per_module),
                                key=lambda m: m[0].index)
            if only is not None:
                chosen = [c for c in chosen if (module, c[0].index) in only]
            print(f"{module}: {len(everything)} sites left, running {len(chosen)} (subset {base:.0f} s, "
                  f"timeout {timeout:.0f} s)", flush=True)
            for mutant, text in chosen:
                box.write(module, text)
                status, failing, secs = box.pytest(tests, timeout, stop_first=True)
                mutant.status = "survived" if status == "passed" else ("killed" if status == "failed" else status)
                mutant.killer = failing[0] if failing else ""
                mutant.seconds = round(secs, 1)
                results.append(mutant)
                print(f"  {mutant.status:8s} #{mutant.index:<3d} L{mutant.line:<4d} {mutant.kind:10s} "
                      f"{mutant.line_before!r} -> {mutant.line_after!r} {mutant.killer}", flush=True)
            box.restore(module)
    finally:
        box.close()
        if json_out:
            json_out.write_text(json.dumps([asdict(m) for m in results], indent=1))
    print("\n| module | sites | tried | killed | survived |\n| --- | --- | --- | --- | --- |")
    for module in modules:
        rows = [m for m in results if m.module == module]
        killed = sum(m.status != "survived" for m in rows)
        print(f"| {module} | {len(mutants_of(module))} | {len(rows)} | {killed} | {len(rows) - killed} |")
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("plants", help="run the planted regressions")
    p.add_argument("names", nargs="*", help="only these plants (default: all)")
    sv = sub.add_parser("survivors", help="the survivors of the independent pass, each against its own tests")
    sv.add_argument("names", nargs="*", help="only these plants (default: all)")
    m = sub.add_parser("mutants", help="mutation run over the core's math")
    m.add_argument("--per-module", type=int, default=None, help="sample at most N mutants per module")
    m.add_argument("--seed", type=int, default=0)
    m.add_argument("--modules", default=",".join(MODULES), help="comma-separated module paths")
    m.add_argument("--list", action="store_true", help="only count the mutation sites")
    m.add_argument("--json", type=Path, default=None, help="write every result here")
    m.add_argument("--only", type=Path, default=None,
                   help="a JSON of an earlier run: rerun only its survivors (same sample)")
    m.add_argument("--exclude", type=Path, default=None,
                   help="a JSON of an earlier run: sample only mutants it did not try (a fresh sample)")
    args = parser.parse_args(argv)
    if args.command == "plants":
        return run_plants(args.names)
    if args.command == "survivors":
        return run_survivors(args.names)
    modules = [x for x in args.modules.split(",") if x]
    if args.list:
        for module in modules:
            print(module, len(mutants_of(module)))
        return 0
    only = None
    if args.only:
        only = {(m["module"], m["index"]) for m in json.loads(args.only.read_text()) if m["status"] == "survived"}
    exclude = None
    if args.exclude:
        exclude = {(m["module"], m["index"]) for m in json.loads(args.exclude.read_text())}
    return run_mutants(args.per_module, args.seed, modules, args.json, only, exclude)


if __name__ == "__main__":
    sys.exit(main())
