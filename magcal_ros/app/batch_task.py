"""One recording of ``magcal batch``: the task a Dask worker runs.

The task runs ``magcal correct`` itself (and, with ``--calibrate``, ``magcal calibrate``
first) in the worker, through the same entry point as the command line, so every rule of
a single run holds per recording: atomic outputs, exact stamps, the same refusals with
the same one-line reasons. What the commands print is kept per thread, not shown. Then it
reads the output back once (:func:`measure_output`) for the campaign report and writes the
completion record. A refusal raises :class:`RecordingFailed` with the command's one-line
reason, which is what the batch reports for that recording.

Nothing here imports Dask: a worker needs only magcal_ros.
"""

from __future__ import annotations

import io
import math
import os
import socket
import sys
import threading
import time
from collections.abc import Sequence
from typing import Any, TextIO

import numpy as np

from magcal_ros.app.campaign import Job, Outcome, digest, write_record
from magcal_ros.core.calibration import ArrayCalibration
from magcal_ros.core.streaming_stats import LogHistogram, StepNoise
from magcal_ros.errors import MagcalError


class RecordingFailed(Exception):
    """A recording could not be processed; the message is the one-line reason."""


# --------------------------------------------------------------------------- running a command in-process


class _ThreadStream(io.TextIOBase):
    """A text stream that writes to the calling thread's buffer when it has one, else to ``default``."""

    def __init__(self, default: TextIO) -> None:
        self.default = default
        self.local = threading.local()

    def _target(self) -> TextIO:
        buf = getattr(self.local, "buffer", None)
        return self.default if buf is None else buf

    def write(self, text: str) -> int:  # type: ignore[override]
        return self._target().write(text)

    def flush(self) -> None:
        self._target().flush()

    def isatty(self) -> bool:
        target = self._target()
        return bool(getattr(target, "isatty", lambda: False)())

    def fileno(self) -> int:
        if getattr(self.local, "buffer", None) is not None:
            raise io.UnsupportedOperation("fileno")
        return self.default.fileno()


_streams_lock = threading.Lock()
_streams_users = 0


def _capture_begin(out: io.StringIO, err: io.StringIO) -> None:
    global _streams_users
    with _streams_lock:
        if not isinstance(sys.stdout, _ThreadStream):
            sys.stdout = _ThreadStream(sys.stdout)
        if not isinstance(sys.stderr, _ThreadStream):
            sys.stderr = _ThreadStream(sys.stderr)
        _streams_users += 1
        sys.stdout.local.buffer = out  # type: ignore[attr-defined]
        sys.stderr.local.buffer = err  # type: ignore[attr-defined]


def _capture_end() -> None:
    global _streams_users
    with _streams_lock:
        for stream in (sys.stdout, sys.stderr):
            if isinstance(stream, _ThreadStream):
                stream.local.buffer = None
        _streams_users -= 1
        if _streams_users == 0:
            if isinstance(sys.stdout, _ThreadStream):
                sys.stdout = sys.stdout.default  # type: ignore[assignment]
            if isinstance(sys.stderr, _ThreadStream):
                sys.stderr = sys.stderr.default  # type: ignore[assignment]


def run_command(argv: Sequence[str]) -> tuple[int, str, str]:
    """Run ``magcal ARGV`` in this thread: exit code, stdout and stderr text."""
    from magcal_ros.app import cli

    out, err = io.StringIO(), io.StringIO()
    _capture_begin(out, err)
    try:
        try:
            code = cli.main(list(argv))
        except SystemExit as exc:  # argparse: a bad option
            code = exc.code if isinstance(exc.code, int) else 2
    finally:
        _capture_end()
    return code, out.getvalue(), err.getvalue()


def reason_of(command: str, code: int, stderr: str) -> str:
    """The one-line reason a command gave (its ``error:`` line), else its last line or exit code."""
    lines = [ln.strip() for ln in stderr.splitlines() if ln.strip()]
    prefix = f"magcal {command}: error: "
    for line in reversed(lines):
        if line.startswith(prefix):
            return line[len(prefix):]
    for line in reversed(lines):
        if not line.startswith("note:") and not line.startswith("usage:"):
            return line
    return f"magcal {command} exited with code {code}"


def notes_of(stderr: str) -> tuple[str, ...]:
    """The ``note:`` lines a command printed (what it dropped, left out or cleaned up)."""
    return tuple(ln.strip()[len("note:"):].strip() for ln in stderr.splitlines() if ln.strip().startswith("note:"))


# --------------------------------------------------------------------------- what the output shows


def _positive(value: object) -> float | None:
    try:
        v = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        return None
    return v if math.isfinite(v) and v > 0 else None


def reference_of(path: str, calibration: ArrayCalibration) -> tuple[float | None, float | None]:
    """F (T) and the noise per axis (T) a calibration file states: its provenance (``intensity``,
    ``noise``), else for a simulation's truth file the simulated ``intensity`` and ``noise``."""
    intensity, noise = calibration_intensity(calibration), calibration_noise(calibration)
    if intensity is None or noise is None:
        from magcal_ros.io.truth_file import read_simulation_parameters

        sim = read_simulation_parameters(path)
        intensity = intensity or _positive(sim.get("intensity"))
        noise = noise or _positive(sim.get("noise"))
    return intensity, noise


def calibration_noise(calibration: ArrayCalibration) -> float | None:
    """The calibration's noise per axis (T): RMS of its provenance ``noise`` over sensors, or None."""
    values = calibration.metadata.get("noise")
    try:
        v = np.asarray(values, dtype=float).reshape(-1)
    except (TypeError, ValueError):
        return None
    v = v[np.isfinite(v) & (v > 0)]
    return float(np.sqrt(np.mean(v * v))) if len(v) else None


def calibration_intensity(calibration: ArrayCalibration) -> float | None:
    """The intensity F (T) the calibration was solved for (provenance ``intensity``), or None."""
    return _positive(calibration.metadata.get("intensity"))


def measure_output(path: str, calibration: ArrayCalibration, intensity: float | None) -> dict[str, Any]:
    """Sets, time span, TMI residual quantiles and tensor noise of a corrected output.

    ``| |B| - F |`` over every corrected vector of every sensor (T; None without ``intensity``);
    tensor noise from the six measured components ``xx, xy, xz, yx, yy, yz`` (or the three of a
    baseline gradient) by :class:`~magcal_ros.core.streaming_stats.StepNoise` (T/m). Streams
    the output (:func:`~magcal_ros.io.output_scan.output_chunks`).
    """
    from magcal_ros.io.output_scan import output_chunks

    names = calibration.geometry.names
    tmi = LogHistogram()
    steps = StepNoise()
    sets = 0
    first: int | None = None
    last: int | None = None
    for chunk in output_chunks(path, names):
        if intensity:
            for v in chunk.vectors:
                if len(v):
                    tmi.add(np.linalg.norm(v, axis=1) - intensity)
        if len(chunk.field_stamps):
            first = int(chunk.field_stamps[0]) if first is None else first
            last = int(chunk.field_stamps[-1])
            sets += len(chunk.field_stamps)
        g = chunk.gradient
        if g.size:
            steps.add(g[:, :6] if g.shape[1] == 9 else g)
    return {
        "sets": sets, "start_ns": first, "end_ns": last,
        "tmi_median": tmi.quantile(0.5), "tmi_p95": tmi.quantile(0.95), "tensor_noise": steps.value(),
    }


# --------------------------------------------------------------------------- the task


def run_job(job: Job) -> Outcome:
    """Calibrate (``--calibrate``) and correct one recording, measure its output, record it done.

    Raises :class:`RecordingFailed` with the one-line reason when a command refuses.
    """
    if job.problem:
        raise RecordingFailed(job.problem)
    t0 = time.perf_counter()
    cal_digest = digest(job.calibration) if job.calibration else ""
    notes: list[str] = []
    if job.calibrate_args is not None:
        prior = ["--prior", job.calibration] if job.calibration else []
        code, _, err = run_command(["calibrate", job.input, "-o", job.calibration_out, "-q", *prior, *job.calibrate_args])
        if code != 0:
            raise RecordingFailed(f"calibrate: {reason_of('calibrate', code, err)}")
        notes += notes_of(err)
    code, _, err = run_command(["correct", job.input, "-c", job.used_calibration, "-o", job.output, "-q",
                                *job.correct_args])
    if code != 0:
        raise RecordingFailed(reason_of("correct", code, err))
    notes += notes_of(err)
    try:
        from magcal_ros.io import calibration_file as calfile
        from magcal_ros.io.output_scan import input_samples

        cal = calfile.read(job.used_calibration, uncorrected=job.uncorrected)
        stated, noise = reference_of(job.used_calibration, cal)
        intensity = job.reference_field or stated
        found = measure_output(job.output, cal, intensity)
        offered = input_samples(job.input, cal.geometry.names)
    except MagcalError as exc:
        raise RecordingFailed(f"corrected, but its output could not be read back: {exc}") from None
    outcome = job.outcome(
        "corrected", drops=max(0, offered - found["sets"]), intensity=intensity, noise=noise,
        seconds=time.perf_counter() - t0, worker=f"{socket.gethostname()}:{os.getpid()}", notes=tuple(notes), **found,
    )
    write_record(job, cal_digest, outcome)
    return outcome
