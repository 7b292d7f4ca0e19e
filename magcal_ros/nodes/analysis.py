"""The calibration node's analysis worker: a process started with the node and supervised.

The progress analysis (:func:`magcal_ros.methods.progress.assess`, 0.1-2 s of one core) runs in
a separate Python process so that it never holds the interpreter lock the node's callbacks need.
That process

- is started with the node (``python -m magcal_ros.nodes.analysis``), in a session of its own:
  a terminal's Ctrl-C to the node's process group never reaches it (it cannot print a
  ``KeyboardInterrupt`` into the node's output); its stderr is the node's, and nothing in the
  node process is redirected, ever;
- talks over its stdin and stdout (length-prefixed pickles): jobs in, answers out, and a
  heartbeat every :data:`HEARTBEAT` s from a thread of its own; it ends when the node closes
  its end of the pipe or is gone;
- is supervised by :class:`AnalysisWorker`: a job without an answer within ``timeout`` s, a
  heartbeat missing for ``timeout`` s or a process that ended gets the process killed (if it is
  still there) and a new one started; the job fails with the reason and the node carries on.
  :meth:`AnalysisWorker.status` gives the counters and the heartbeat's age for ``/diagnostics``.

No ROS import: the worker process imports numpy and the methods only.
"""

from __future__ import annotations

import contextlib
import os
import pickle
import select
import signal
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import IO, Any

HEARTBEAT: float = 1.0
"""Seconds between two heartbeats of the worker process."""
NICENESS: int = 10
"""The worker yields the CPU to the nodes (and the sensors' drivers) when they need it."""
RESTART_BACKOFF: tuple[float, float] = (1.0, 60.0)
"""Seconds before starting again a process that ended by itself within :data:`EARLY_END` s of its start, the
second time in a row and after (doubling from the first to the second figure): a worker that cannot start
does not spin."""
EARLY_END: float = 10.0
START_TIMEOUT: float = 300.0
"""Seconds a new worker process may take to import the methods before it counts as stuck (a busy machine
with a cold disk); the job timeout counts from when it is ready."""
_HEADER = struct.Struct("!Q")
FUNCTIONS: tuple[str, ...] = ("assess", "ping")
"""What a job may ask the worker to run: the progress analysis, and a probe that answers after a delay."""


class AnalysisFailed(Exception):
    """An analysis job did not give an answer (the reason says why; the worker was restarted if needed)."""


# -- framing (both sides) ------------------------------------------------------------------------
def _frame(obj: Any) -> bytes:
    data = pickle.dumps(obj, protocol=pickle.HIGHEST_PROTOCOL)
    return _HEADER.pack(len(data)) + data


def _read_exactly(stream: IO[bytes], n: int) -> bytes | None:
    chunks, left = [], n
    while left:
        chunk = stream.read(left)
        if not chunk:
            return None
        chunks.append(chunk)
        left -= len(chunk)
    return b"".join(chunks)


def read_frame(stream: IO[bytes]) -> Any:
    """The next object on ``stream``; None at its end."""
    header = _read_exactly(stream, _HEADER.size)
    if header is None:
        return None
    body = _read_exactly(stream, _HEADER.unpack(header)[0])
    return None if body is None else pickle.loads(body)


def _send(fd: int, data: bytes, deadline: float) -> bool:
    """Write ``data`` to the non-blocking ``fd`` before ``deadline`` (monotonic s); False when it could not."""
    view = memoryview(data)
    while view:
        left = deadline - time.monotonic()
        if left <= 0:
            return False
        try:
            _, ready, _ = select.select([], [fd], [], left)
            if ready:
                view = view[os.write(fd, view):]
        except BlockingIOError:
            continue
        except OSError:
            return False
    return True


# -- the node's side --------------------------------------------------------------------------------
@dataclass
class _Job:
    done: threading.Event = field(default_factory=threading.Event)
    answer: Any = None
    error: str | None = None


@dataclass
class _Counters:
    jobs: int = 0
    failures: int = 0
    timeouts: int = 0
    restarts: int = 0
    last_job_s: float = float("nan")
    problem: str = ""
    """Why the process was last replaced (empty while it never was)."""
    problem_at: float = -float("inf")
    error: str = ""
    """The last job's failure (an analysis that raised), empty while none did."""


class AnalysisWorker:
    """Runs analysis jobs in a supervised worker process (see the module docstring).

    ``timeout`` (s): longest wait for a job's answer and for a heartbeat; ``log(text)`` reports a
    restart (a warning line in the node's log). ``command``: the worker's command line (tests).
    """

    def __init__(self, timeout: float, log: Callable[[str], None], command: Sequence[str] | None = None) -> None:
        self.timeout = float(timeout)
        self._log = log
        self._command = list(command) if command is not None else [sys.executable, "-P", "-m", __name__]
        """(-P: the working directory is not on the worker's module path: the installed package runs.)"""
        self._lock = threading.Lock()
        self._one_job = threading.Lock()
        self._proc: subprocess.Popen[bytes] | None = None
        self._started = 0.0
        self._heard = 0.0
        self._ready = threading.Event()
        self._busy_since: float | None = None
        self._jobs: dict[int, _Job] = {}
        self._next_id = 0
        self._closed = False
        self._early_ends = 0
        self._not_before = 0.0
        self.counters = _Counters()

    # -- process ------------------------------------------------------------------------------
    def start(self) -> None:
        """Start the worker process (returns at once; it imports the methods in the background)."""
        with self._lock:
            if self._proc is None and not self._closed:
                self._spawn()

    def _spawn(self) -> None:
        """Start a worker process (lock held). One that cannot be started (no memory, no process slot) is
        noted and tried again after the back-off: the node goes on without analyses meanwhile."""
        try:
            proc = subprocess.Popen(self._command, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=None,
                                    start_new_session=True, close_fds=True, bufsize=0)
        except OSError as exc:
            now = time.monotonic()
            self._early_ends += 1
            self._not_before = now + min(RESTART_BACKOFF[0] * 2 ** (self._early_ends - 1), RESTART_BACKOFF[1])
            self._note(f"cannot start the analysis process: {exc}", now)
            self._log(self.counters.problem)
            return
        assert proc.stdin is not None
        os.set_blocking(proc.stdin.fileno(), False)
        self._proc, self._ready, self._busy_since = proc, threading.Event(), None
        self._started = self._heard = time.monotonic()
        threading.Thread(target=self._read, args=(proc,), name="magcal-analysis-reader", daemon=True).start()

    def _read(self, proc: subprocess.Popen[bytes]) -> None:
        """The reader of one worker process's answers and heartbeats (a thread of its own)."""
        assert proc.stdout is not None
        while True:
            try:
                msg = read_frame(proc.stdout)
            except Exception:  # noqa: BLE001 - a garbled stream is a broken worker
                msg = None
            if msg is None:
                break
            with self._lock:
                if self._proc is not proc:
                    return
                self._heard = time.monotonic()
                kind = msg[0]
                if kind == "ready":
                    self._ready.set()
                elif kind in ("done", "error") and msg[1] in self._jobs:
                    job = self._jobs.pop(msg[1])
                    job.answer, job.error = (msg[2], None) if kind == "done" else (None, msg[2])
                    job.done.set()
        with contextlib.suppress(Exception):
            proc.wait(timeout=5.0)
        with self._lock:
            if self._proc is proc and not self._closed:
                self._ended(proc, f"the analysis process ended (exit code {proc.returncode})", crashed=True)

    def _ended(self, proc: subprocess.Popen[bytes], why: str, crashed: bool = False) -> None:
        """``proc`` is gone (or made to go): its jobs fail with ``why``; a new one starts now, or after a
        back-off when it ``crashed`` (ended by itself) soon after its start (lock held)."""
        with contextlib.suppress(OSError):
            proc.kill()
        for stream in (proc.stdin, proc.stdout):
            with contextlib.suppress(Exception):
                stream.close()  # type: ignore[union-attr]
        for job in self._jobs.values():
            job.error = why
            job.done.set()
        self._jobs.clear()
        self._ready.set()  # a job waiting for this process to start stops waiting (its answer is the error)
        self._proc = None
        now = time.monotonic()
        self._note(why, now)
        self.counters.restarts += 1
        if crashed and now - self._started < EARLY_END:
            self._early_ends += 1
            if self._early_ends > 1:  # again: wait 1, 2, 4 ... 60 s
                self._not_before = now + min(RESTART_BACKOFF[0] * 2 ** (self._early_ends - 2), RESTART_BACKOFF[1])
        else:
            self._early_ends, self._not_before = 0, 0.0
        self._log(f"{why}: {'starting a new one' if not self._not_before else 'starting a new one shortly'}")
        if not self._not_before:
            self._spawn()

    def _note(self, why: str, now: float) -> None:
        self.counters.problem, self.counters.problem_at = why, now

    def _ensure(self) -> subprocess.Popen[bytes] | None:
        """The running worker process, started if there is none and the back-off allows (lock held)."""
        if self._proc is None and not self._closed and time.monotonic() >= self._not_before:
            self._not_before = 0.0
            self._spawn()
        return self._proc

    # -- jobs ---------------------------------------------------------------------------------
    def run(self, function: str, *args: Any, **kwargs: Any) -> Any:
        """Run ``function`` (one of :data:`FUNCTIONS`) in the worker with ``args``; its answer, or
        :class:`AnalysisFailed` with the reason (no answer within the timeout: the worker is restarted)."""
        if function not in FUNCTIONS:
            raise ValueError(f"unknown analysis {function!r}")
        with self._one_job:
            with self._lock:
                wait = self._not_before - time.monotonic() if self._proc is None else 0.0
            if 0.0 < wait < self.timeout:  # a short back-off: wait it out
                time.sleep(wait)
            with self._lock:
                proc = None if self._closed else self._ensure()
                if proc is None:
                    raise AnalysisFailed(self.counters.problem or "the analysis process is not running")
                job = _Job()
                key = self._next_id = self._next_id + 1
                self._jobs[key] = job
                ready, started = self._ready, self._started
            try:
                if not ready.wait(max(started + START_TIMEOUT - time.monotonic(), 0.0)) and not job.done.is_set():
                    with self._lock:
                        if self._proc is proc:
                            self._ended(proc, f"the analysis process did not start within {START_TIMEOUT:g} s")
                if job.done.is_set():  # the process ended while starting
                    raise AnalysisFailed(job.error or "the analysis process ended")
                with self._lock:
                    start = self._busy_since = time.monotonic()
                return self._wait(proc, key, job, _frame((key, function, args, kwargs)), start)
            finally:
                with self._lock:
                    self._busy_since = None
                    self._jobs.pop(key, None)

    def _wait(self, proc: subprocess.Popen[bytes], key: int, job: _Job, frame: bytes, start: float) -> Any:
        """Send one job and wait for its answer (the job lock held)."""
        assert proc.stdin is not None
        deadline = start + self.timeout
        sent = _send(proc.stdin.fileno(), frame, deadline)
        if not sent or not job.done.wait(max(deadline - time.monotonic(), 0.0)):
            with self._lock:
                self.counters.timeouts += 1
                if self._proc is proc:
                    self._ended(proc, f"the analysis gave no answer within {self.timeout:g} s")
            raise AnalysisFailed(f"no answer within {self.timeout:g} s (analysis_timeout): the analysis process "
                                 "was restarted")
        with self._lock:
            self.counters.jobs += 1
            self.counters.last_job_s = time.monotonic() - start
            if job.error is not None:
                self.counters.failures += 1
                self.counters.error = job.error
        if job.error is not None:
            raise AnalysisFailed(job.error)
        return job.answer

    # -- supervision and reporting ------------------------------------------------------------
    def check(self) -> None:
        """Supervise between jobs (call it regularly): a worker whose heartbeat is missing for longer than the
        timeout is killed and replaced; one that ended after its back-off is started again."""
        with self._lock:
            if self._closed:
                return
            proc = self._proc
            if proc is None:
                self._ensure()
            elif time.monotonic() - self._heard > self.timeout:
                self.counters.timeouts += 1
                self._ended(proc, f"the analysis process gave no heartbeat for {self.timeout:g} s")

    def status(self) -> tuple[int, str, dict[str, str]]:
        """(level 0 OK / 1 WARN / 2 ERROR, message, values) of the worker for ``/diagnostics``."""
        now = time.monotonic()
        with self._lock:
            c, proc = self.counters, self._proc
            age = now - self._heard if proc is not None else float("nan")
            state = "stopped" if proc is None else "starting" if not self._ready.is_set() else \
                "busy" if self._busy_since is not None else "idle"
            values = {"state": state, "pid": str(proc.pid) if proc is not None else "",
                      "heartbeat_age_s": f"{age:.1f}" if proc is not None else "", "analyses": str(c.jobs),
                      "failures": str(c.failures), "timeouts": str(c.timeouts), "restarts": str(c.restarts),
                      "last_analysis_s": "" if c.last_job_s != c.last_job_s else f"{c.last_job_s:.2f}",
                      "last_restart_reason": c.problem, "last_error": c.error, "timeout_s": f"{self.timeout:g}"}
            recent = now - c.problem_at < max(60.0, 2 * self.timeout)
        summary = f"{c.jobs} analyses, {c.restarts} restarts"
        if self._closed:
            return 1, f"analysis process stopped: the node is shutting down; {summary}", values
        if proc is None:
            return 2, f"analysis process not running ({c.problem or 'not started'}); {summary}", values
        if state != "starting" and age > max(3 * HEARTBEAT, self.timeout / 2):
            return 1, f"analysis process {proc.pid} {state}, no heartbeat for {age:.0f} s; {summary}", values
        if recent and c.problem:
            return 1, f"analysis process {proc.pid} {state}; lately: {c.problem}; {summary}", values
        return 0, f"analysis process {proc.pid} {state}, heartbeat {age:.1f} s ago; {summary}", values

    @property
    def pid(self) -> int | None:
        """The worker process's id (None when none runs)."""
        with self._lock:
            return None if self._proc is None else self._proc.pid

    def close(self, wait: float = 2.0) -> None:
        """End the worker: its stdin closed (it exits at once when idle), killed after ``wait`` s."""
        with self._lock:
            self._closed = True
            proc, self._proc = self._proc, None
            for job in self._jobs.values():
                job.error = "the node is shutting down"
                job.done.set()
            self._ready.set()
        if proc is None:
            return
        with contextlib.suppress(Exception):
            proc.stdin.close()  # type: ignore[union-attr]
        try:
            proc.wait(timeout=wait)
        except subprocess.TimeoutExpired:
            with contextlib.suppress(OSError):
                proc.kill()
            with contextlib.suppress(Exception):
                proc.wait(timeout=wait)
        with contextlib.suppress(Exception):
            proc.stdout.close()  # type: ignore[union-attr]


# -- the worker process -----------------------------------------------------------------------------
def _ping(delay: float = 0.0) -> int:
    """The probe job: its process id after ``delay`` s."""
    time.sleep(delay)
    return os.getpid()


def _worker_main() -> int:
    """The worker process: read jobs on stdin, answer on stdout, beat every :data:`HEARTBEAT` s."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # a session of its own; and a stray Ctrl-C is the node's
    with contextlib.suppress(OSError):
        os.nice(NICENESS)
    out = os.fdopen(os.dup(1), "wb", buffering=0)
    os.dup2(2, 1)  # (the worker's own descriptors) whatever a library prints goes to stderr, not into the answers
    jobs_in = sys.stdin.buffer
    parent = os.getppid()
    write_lock = threading.Lock()

    def send(obj: Any) -> None:
        data = _frame(obj)
        with write_lock:
            try:
                out.write(data)
            except (OSError, ValueError):
                os._exit(0)  # the node is gone

    def beat() -> None:
        while True:
            time.sleep(HEARTBEAT)
            if os.getppid() != parent:
                os._exit(0)
            send(("beat", time.time()))

    threading.Thread(target=beat, name="heartbeat", daemon=True).start()
    from magcal_ros.methods import progress  # the slow import, after the heartbeat started

    functions: dict[str, Callable[..., Any]] = {"assess": progress.assess, "ping": _ping}
    send(("ready", os.getpid()))
    while True:
        job = read_frame(jobs_in)
        if job is None:
            return 0
        key, name, args, kwargs = job
        try:
            answer = functions[name](*args, **kwargs)
        except Exception as exc:  # noqa: BLE001 - every failure is an answer
            send(("error", key, f"{type(exc).__name__}: {exc}"))
            continue
        send(("done", key, answer))


if __name__ == "__main__":
    raise SystemExit(_worker_main())
