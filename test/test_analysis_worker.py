"""The calibration node's analysis worker (magcal_ros.nodes.analysis): a process started with the node,
supervised, that can neither hang the node nor silence it.

Each test drives :class:`AnalysisWorker` as the node does and asserts what it counted and answered: a job
without an answer in time, a process killed, a process that stops beating, a Ctrl-C to the node's process
group, the node gone. Deadlines are generous: nothing depends on spare CPU (the worker runs at nice 10).
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest

from magcal_ros.nodes.analysis import AnalysisFailed, AnalysisWorker

STARTUP = 180.0
"""Generous deadline (s) for a worker process to start (it imports numpy and the methods)."""


def _until(predicate, timeout: float = STARTUP, step: float = 0.05) -> bool:  # type: ignore[no-untyped-def]
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(step)
    return predicate()


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    try:  # a zombie (ended, not yet reaped by its parent) is gone too
        with open(f"/proc/{pid}/stat", encoding="ascii") as fh:
            return fh.read().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


@pytest.fixture
def worker() -> AnalysisWorker:
    lines: list[str] = []
    w = AnalysisWorker(5.0, lines.append)
    w.lines = lines  # type: ignore[attr-defined]
    w.start()
    yield w
    w.close()


def test_the_worker_starts_with_the_node_and_runs_the_progress_analysis(worker: AnalysisWorker) -> None:
    """Started at once (a process before the first job), it answers the analysis the node asks for: the
    same assessment as in this process, and counts it."""
    from magcal_ros.core.field import earth_field
    from magcal_ros.core.geometry import ArrayGeometry
    from magcal_ros.methods import progress
    from magcal_ros.sim.attitudes import uniform_random
    from magcal_ros.sim.simulator import ArraySimulation, random_sensor_errors

    assert worker.pid is not None and _alive(worker.pid)
    rng = np.random.default_rng(4)
    geo = ArrayGeometry.cross()
    sim = ArraySimulation(geo, tuple(random_sensor_errors(rng) for _ in geo.names), earth_field(5.15e-5, 60.0, 5.0),
                          noise=1e-9)
    rec, _ = sim.run(uniform_random(120, rng), rng, rate=50.0)
    worker.timeout = STARTUP  # the first analysis may import lazily on a busy machine
    there = worker.run("assess", rec.vectors, geo, 5.15e-5, None, rec.stamps)
    here = progress.assess(rec.vectors, geo, 5.15e-5, None, rec.stamps)
    assert there == here
    level, _, values = worker.status()
    assert level == 0 and values["analyses"] == "1" and values["restarts"] == "0" and values["state"] == "idle"


def test_a_job_without_an_answer_in_time_restarts_the_worker(worker: AnalysisWorker) -> None:
    """A job that does not answer within the timeout fails with the reason, the process is killed and a new
    one started; the next job is answered by it."""
    first = worker.run("ping")  # ready (the timeout counts from then)
    started = time.monotonic()
    with pytest.raises(AnalysisFailed, match="no answer within 5 s"):
        worker.run("ping", 600.0)
    assert time.monotonic() - started < 120.0
    assert _until(lambda: not _alive(first))
    second = worker.run("ping")
    assert second != first and _alive(second)
    _, message, values = worker.status()
    assert (values["timeouts"], values["restarts"], values["analyses"]) == ("1", "1", "2"), values
    assert "no answer within 5 s" in values["last_restart_reason"] and "lately" in message
    assert any("no answer within 5 s" in line for line in worker.lines)  # type: ignore[attr-defined]


def test_a_killed_worker_is_replaced_and_an_analysis_error_is_only_an_answer(worker: AnalysisWorker) -> None:
    first = worker.run("ping")
    os.kill(first, signal.SIGKILL)
    assert _until(lambda: worker.pid not in (None, first))
    second = worker.run("ping")
    assert second != first
    assert worker.status()[2]["restarts"] == "1"
    with pytest.raises(AnalysisFailed, match="TypeError"):  # a job that raises: the worker stays
        worker.run("assess", "not sets")
    assert worker.run("ping") == second
    values = worker.status()[2]
    assert (values["failures"], values["restarts"]) == ("1", "1") and "TypeError" in values["last_error"]


def test_a_worker_that_stops_beating_is_replaced_between_jobs(worker: AnalysisWorker) -> None:
    """A stopped process (no heartbeat for the timeout) is found by the supervision the node runs with its
    reports, killed and replaced."""
    first = worker.run("ping")
    assert _until(lambda: float(worker.status()[2]["heartbeat_age_s"]) < 4.0)  # it beats
    os.kill(first, signal.SIGSTOP)

    def replaced() -> bool:
        worker.check()
        return worker.pid not in (None, first)

    assert _until(replaced)
    assert "no heartbeat for 5 s" in worker.status()[2]["last_restart_reason"]
    assert worker.run("ping") not in (None, first)
    assert _until(lambda: not _alive(first))


def test_ctrl_c_to_the_nodes_process_group_never_reaches_the_worker_nor_silences_the_node() -> None:
    """A terminal's Ctrl-C goes to the node's process group, maybe while the worker still imports: the worker
    has a session of its own, so it goes on (no KeyboardInterrupt in the node's output), and nothing in the
    node process is redirected: its stderr works throughout."""
    script = textwrap.dedent("""
        import os, signal, sys, time
        from magcal_ros.nodes.analysis import AnalysisWorker
        signal.signal(signal.SIGINT, lambda *a: print("node got Ctrl-C", file=sys.stderr))
        w = AnalysisWorker(120.0, print)
        w.start()
        os.killpg(os.getpgid(0), signal.SIGINT)  # while the worker imports
        print("node stderr works", file=sys.stderr)
        print("ping", w.run("ping") == w.pid, w.status()[2]["restarts"])
        w.close()
    """)
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=STARTUP,
                          start_new_session=True)
    assert "Traceback" not in proc.stderr and "KeyboardInterrupt" not in proc.stderr, proc.stderr
    assert "node got Ctrl-C" in proc.stderr and "node stderr works" in proc.stderr, proc.stderr
    assert proc.stdout.strip() == "ping True 0", proc.stdout


def test_the_worker_ends_when_the_node_is_gone() -> None:
    """The node killed (no clean-up): the worker sees its pipe close, or its parent change, and ends."""
    script = textwrap.dedent("""
        import os
        from magcal_ros.nodes.analysis import AnalysisWorker
        w = AnalysisWorker(120.0, print)
        w.start()
        w.run("ping")
        print(w.pid, flush=True)
        os._exit(9)
    """)
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=STARTUP)
    pid = int(proc.stdout.split()[-1])
    assert _until(lambda: not _alive(pid), timeout=60.0), f"worker {pid} outlived its node"


def test_a_worker_that_cannot_be_started_is_an_error_on_diagnostics_not_an_exception_in_the_node() -> None:
    """The supervision runs in the node's report timer: a process that cannot be started (here: no such program;
    at sea: no memory or process slot) must not raise there (a timer that raises ends the node). It is an
    ERROR status with the reason, analyses fail with it, and it is tried again after a back-off."""
    lines: list[str] = []
    w = AnalysisWorker(5.0, lines.append, command=["/nonexistent/python3"])
    try:
        w.start()
        w.check()
        level, message, values = w.status()
        assert level == 2 and "cannot start the analysis process" in message and values["state"] == "stopped"
        with pytest.raises(AnalysisFailed, match="cannot start the analysis process"):
            w.run("ping")
        assert any("cannot start" in line for line in lines)
    finally:
        w.close()
