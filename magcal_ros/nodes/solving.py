"""The calibration node's solve in stages: the sets, the settings and prior, the solve, the hand-over to the file
and the correction node, the answer."""

from __future__ import annotations

import contextlib
import hashlib
import os
import threading
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from rcl_interfaces.msg import Parameter as ParameterMsg
from rclpy.task import Future
from std_srvs.srv import Trigger

from magcal_ros.core.calibration import ArrayCalibration
from magcal_ros.core.geomagnetic import SiteField
from magcal_ros.core.geometry import ArrayGeometry
from magcal_ros.core.metrics import rms, tensor_rms, tmi_rms
from magcal_ros.core.recording import Recording
from magcal_ros.core.tensor import baseline_gradient, gradient, method_for
from magcal_ros.errors import InputError, MagcalError
from magcal_ros.io import calibration_file as calfile
from magcal_ros.methods.attitude import with_saved_imu
from magcal_ros.methods.pipeline import (
    CalibrationResult,
    SolveOptions,
    calibrate_array,
)
from magcal_ros.nodes import common
from magcal_ros.nodes.buffer import MissionSets
from magcal_ros.nodes.correction_link import CallFailed, Stopping, channel_parameters, neutral_terms

WHAT_TO_DO = "call ~/start, turn the array through large angles about at least two axes, then call ~/calibrate"


@dataclass
class CalibrationJob:
    """One calibration as its stages fill it in (see :meth:`CalibrationNode._calibrate`)."""

    collected: Recording
    """The sets to solve, with their currents, temperatures and IMU."""
    notes: list[str]
    """What the collection left out, in words."""
    geo: ArrayGeometry
    inputs: common.CurrentInputs
    snapshot: tuple[np.ndarray, ...] | None
    """The collection buffer's sets as taken (:meth:`SetBuffer.collected`); None for a mission window."""
    method: str = ""
    reference: float | None = None
    """Reference intensity (T; None: relative)."""
    site: SiteField | None = None
    residual: float | None = None
    """max_residual (T; None: the noise-aware rule)."""
    fingerprint: str = ""
    prior: ArrayCalibration | None = None
    prior_note: str = ""


class Solving:
    """The calibration node's part that solves and hands over (a mixin of
    :class:`~magcal_ros.nodes.calibration_node.CalibrationNode`)."""

    async def _on_calibrate(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        """Solve and hand over in a worker thread; the executor keeps serving meanwhile."""
        if not self._solve_lock.acquire(blocking=False):
            response.success = False
            response.message = "a calibration is already running; wait for its answer"
            return response
        done: Future = Future()

        def work() -> None:
            try:
                outcome = self._calibrate()
            except Stopping:
                return  # shutting down: nothing changed, nobody to answer
            except Exception as exc:  # noqa: BLE001 - the service must answer, whatever happened
                if self._stopping.is_set():
                    return
                outcome = (False, f"calibration failed unexpectedly ({type(exc).__name__}: {exc}); "
                                  "nothing was changed")
                self.get_logger().error(outcome[1])
            if self._stopping.is_set():
                return
            done.set_result(outcome)
            with contextlib.suppress(Exception):  # the node may be going down
                self._wake.trigger()

        self._worker = threading.Thread(target=work, name="magcal-calibrate", daemon=True)
        self._worker.start()
        try:
            response.success, response.message = await done
        finally:
            self._solve_lock.release()
        return response

    def _check_stop(self) -> None:
        if self._stopping.is_set():
            raise Stopping()

    def _fingerprint(self, raw: np.ndarray, currents: np.ndarray, geo: ArrayGeometry, settings: tuple[Any, ...],
                     collected: Recording | None = None) -> str:
        """Identifies a calibration: the collected sets, currents, temperatures and IMU, geometry, settings and
        where it goes."""
        h = hashlib.sha256(np.ascontiguousarray(raw).tobytes())
        h.update(np.ascontiguousarray(currents).tobytes())
        if collected is not None and collected.temperatures is not None:
            h.update(np.ascontiguousarray(collected.temperatures).tobytes())
        if collected is not None and collected.imu is not None:
            h.update(np.ascontiguousarray(collected.imu.orientation).tobytes())
            h.update(np.ascontiguousarray(collected.imu.angular_velocity).tobytes())
        where = (self._target_name(), self._calibration_path())
        h.update(repr((geo.names, geo.positions.tolist(), settings, where)).encode())
        return h.hexdigest()

    def _resolve_prior(self, geo: ArrayGeometry) -> tuple[ArrayCalibration | None, str]:
        """The prior of a calibration and what it is, in words (``none ...`` when there is none).

        ``running``: the correction node's calibration, or none (with the reason) when it cannot be
        fetched or is not calibrated. A file that cannot be read is an :class:`InputError`.
        """
        setting = str(self.get_parameter("prior").value).strip()
        if setting == "none":
            return None, "none (prior: none)"
        if setting == "running":
            target = self._target_name()
            try:
                values = self._target_values(geo.names)
            except CallFailed as exc:
                return None, f"none (the running calibration could not be fetched: {exc})"
            prior, why = common.running_calibration(values, geo)
            if prior is None:
                return None, f"none ({target} is not calibrated: {why})"
            return with_saved_imu(prior, self._saved_calibration()), f"the running calibration of {target}"
        path = os.path.expanduser(setting)
        prior = calfile.read(path, self._target_name().lstrip("/"))
        return prior, f"the calibration file {path}"

    def _calibrate(self, window: MissionSets | None = None, check: Any = None,
                   reference_fallback: float | None = None) -> tuple[bool, str]:
        """Solve, save and push (the ~/calibrate service; a recalibration during the mission), in stages: the
        sets (:meth:`_take_sets`), the settings and prior (:meth:`_settle`), the solve (:meth:`_solve`), the
        hand-over to the file and the correction node (:meth:`_hand_over`). Every stage that refuses changes
        nothing and says why.

        ``window``: the mission's sets to fit instead of the collected ones; ``check(result, prior)``:
        (why the result must not be applied or None, the result to apply), asked before anything changes;
        ``reference_fallback``: the intensity (T) when neither reference_field nor site gives one."""
        job = self._take_sets(window)
        if len(job.collected) == 0:
            return self._fail("no synchronized sets collected" + ("" if self._collecting else " (not collecting)")
                              + f"; {WHAT_TO_DO}")
        refused = self._settle(job, reference_fallback)
        if refused is not None:
            return refused
        result = self._solve(job, check)
        if isinstance(result, tuple):
            return result
        path = self._calibration_path()
        failed = self._hand_over(job, result, path)
        if failed is not None:
            return self._fail(failed)
        return self._succeeded(job, result, path)

    def _take_sets(self, window: MissionSets | None) -> CalibrationJob:
        """Stage 1: the sets to solve (the collected ones, or a mission window) and what they were taken with."""
        with self._lock:
            if window is None:
                collected, notes = self._collected()  # sets waiting for the IMU go in first
                snapshot = self._buffer.collected()
            else:
                snapshot = None
                collected = window.recording(self._geometry.names, self._inputs.channels, self._imu.frame_id)
                notes = []
            return CalibrationJob(collected, notes, self._geometry, self._inputs, snapshot)

    def _settle(self, job: CalibrationJob, reference_fallback: float | None) -> tuple[bool, str] | None:
        """Stage 2: method, reference, residual and prior; the answer when the solve is refused, or when these sets
        and settings gave the calibration in force already (``unchanged``); None to go on."""
        job.method = str(self.get_parameter("method").value)
        try:
            reference, job.site = self._reference()
        except InputError as exc:
            return self._fail(f"calibration not possible: {exc}; nothing was changed")
        job.reference = reference or reference_fallback
        job.residual = float(self.get_parameter("max_residual").value) or None
        setting = str(self.get_parameter("prior").value).strip()
        collected = job.collected
        settings = (job.method, job.reference, job.residual, setting, job.inputs.channels)
        job.fingerprint = self._fingerprint(collected.vectors, collected.currents, job.geo, settings, collected)
        last = self._last_solved
        if job.snapshot is not None and last is not None and last[0] == job.fingerprint:
            message = (f"unchanged: these {len(collected)} sets and settings gave the calibration already in force, "
                       f"so nothing was solved, applied or written again; call ~/start to collect new sets "
                       f"(last result: {last[1]})")
            self.get_logger().info(message)
            return True, message
        try:
            job.prior, job.prior_note = self._resolve_prior(job.geo)
        except InputError as exc:
            return self._fail(f"calibration not possible: prior {exc}; set prior (running, none or a file); "
                              "nothing was changed")
        return None

    def _solve(self, job: CalibrationJob, check: Any) -> CalibrationResult | tuple[bool, str]:
        """Stage 3: the solve and the caller's check; the result to apply, or the answer why there is none."""
        self._check_stop()
        rec, site, channels = job.collected, job.site, job.inputs.channels
        self.get_logger().info(f"solving from {len(rec)} sets (method {job.method}, prior: {job.prior_note})")
        opts = SolveOptions(max_residual=job.residual,
                            inclination_deg=site.inclination_deg if site is not None else None,
                            site_field=site.vector if site is not None else None)
        try:
            result = calibrate_array(rec.vectors, job.geo, job.reference, job.method, opts, job.prior,
                                     rec.currents if channels else None, channels, rec.stamps, rec.temperatures,
                                     rec.imu)
        except MagcalError as exc:
            return self._fail(f"calibration not possible: {exc}; nothing was changed (prior: {job.prior_note})")
        self._check_stop()
        why, result = check(result, job.prior) if check is not None else (None, result)
        if why:
            return self._fail(f"not recalibrated: {why}; nothing was changed (prior: {job.prior_note})")
        if site is not None:
            result.calibration.metadata.update(site.provenance())
        if job.prior is not None:
            result = _before_with_prior(result, job)
        return result

    def _hand_over(self, job: CalibrationJob, result: CalibrationResult, path: str) -> str | None:
        """Stage 4: write the file (``path``, '' none) and set the calibration on the correction node, both or
        neither; None when done, else why not (what was put back said)."""
        cal = result.calibration
        try:
            previous = self._get_target_parameters(cal.geometry.names)
        except CallFailed as exc:
            return f"solved but not applied: {exc}; nothing was changed"
        params = calfile.parameters(cal)
        params.update(channel_parameters(job.inputs, cal.channels))  # no channels: the node's earlier ones go too
        for name in cal.geometry.names:  # replace any covariance the node holds from an earlier calibration
            params[name].setdefault("covariance", list(common.UNKNOWN_COVARIANCE))
            params[name].setdefault("time_offset", 0.0)  # and any time offset
        params.update(neutral_terms(params, cal.geometry.names))  # nor temperature terms or a rotation
        keep = int(self.get_parameter("backups").value)
        staged = calfile.replace(path, cal, self._target_name(), keep) if path else contextlib.nullcontext()
        try:
            with staged:
                self._check_stop()
                self._push(params)
        except OSError as exc:
            why = f"{exc.strerror} ({exc.filename})" if exc.strerror and exc.filename else str(exc)
            if isinstance(exc.__context__, CallFailed):  # the push failed, then putting the old file back did
                return (f"solved but not applied: {exc.__context__}; and the previous {path} could NOT be put back "
                        f"({why}): the file holds a calibration the correction node does not run")
            return f"solved but cannot write {path}: {why}; set calibration_file; nothing was changed"
        except CallFailed as exc:
            if isinstance(exc, Stopping):
                raise
            return f"solved but not applied: {exc}; {self._undo_push(exc, previous, path)}"
        return None

    def _undo_push(self, exc: CallFailed, previous: list[ParameterMsg], path: str) -> str:
        """After a failed push: what was left or put back, in words (a push without an answer may have been
        applied: the previous calibration is set again)."""
        undo = "the file was left as it was" if path else "no file was written"
        if exc.unknown_outcome:
            try:
                self._push(previous, raw_messages=True)
                undo += "; the previous calibration was set again on the correction node"
            except CallFailed as again:
                undo += f"; could NOT set the previous calibration again on the correction node ({again})"
        return undo

    def _succeeded(self, job: CalibrationJob, result: CalibrationResult, path: str) -> tuple[bool, str]:
        """Stage 5: the calibration is in force. After ~/calibrate the collection stops and holds exactly the sets
        solved (sets that came during the solve are dropped), so that calling it again answers ``unchanged``."""
        if job.snapshot is None:  # the calibration in force changed: a ~/calibrate is never "unchanged" now
            self._last_solved = None
            return True, self._success_message(result, path, job.prior_note, job.site)
        with self._lock:
            self._collecting = False
            self._generation += 1
            self._pending.clear()
            self._buffer.restore(*job.snapshot)
        message = self._success_message(result, path, job.prior_note, job.site, job.notes)
        self._last_solved = (job.fingerprint, message)
        self.get_logger().info(message)
        return True, message

    def _success_message(self, result: CalibrationResult, path: str, prior_note: str, site: SiteField | None,
                         notes: Sequence[str] = ()) -> str:
        where = f"applied to {self._target_name()}" + (f", written {path}" if path else ", no file written")
        parts = [result.summary()]
        if not int(result.outliers.sum()):
            parts.append("no outlying readings excluded")
        parts.append(f"prior: {prior_note}")
        if site is not None:
            parts.append(f"reference F from {site.describe()} (the model's own error, ~"
                         f"{site.intensity_error * 1e9:.0f} nT, sets the absolute scale only)")
        if result.calibration.channels:
            parts.append(f"interference of {', '.join(result.calibration.channels)} solved")
        parts.extend(w for w in result.warnings if not w.startswith(result.envelope.describe()))  # said already
        return "; ".join(parts + list(notes) + [where])

    def _fail(self, message: str) -> tuple[bool, str]:
        self.get_logger().warn(message)
        return False, message

    def _saved_calibration(self) -> ArrayCalibration | None:
        """The calibration in ``calibration_file`` (what this node saved last, or started from), None when there is
        none or it cannot be read (it only lends the running calibration its IMU report)."""
        path = self._calibration_path()
        if not path or not os.path.isfile(path):
            return None
        try:
            return calfile.read(path, self._target_name().lstrip("/"))
        except (MagcalError, OSError):
            return None

    def _calibration_path(self) -> str:
        text = str(self.get_parameter("calibration_file").value).strip()
        return os.path.expanduser(text) if text else ""


def _gradient_rms(vectors: np.ndarray, geo: ArrayGeometry) -> float:
    """RMS (T/m) of the gradient ``vectors`` (N, S, 3) T show in the uniform field of a manoeuvre: the tensor
    (method by the geometry), the baseline gradient, or NaN for one sensor."""
    if geo.gradient_kind == "tensor":
        return tensor_rms(gradient(vectors, geo, method_for(geo)))
    if geo.gradient_kind == "baseline":
        return float(rms(baseline_gradient(vectors, geo)))
    return float("nan")


def _before_with_prior(result: CalibrationResult, job: CalibrationJob) -> CalibrationResult:
    """``result`` with its "before" figures (per-sensor TMI RMS, T; the gradient's RMS, T/m) those of the prior
    on the same sets: with a prior, "before" is the calibration in force, not the raw readings (the file's
    provenance says so in ``before``). Unchanged when the prior cannot correct these sets (a current channel or
    the temperatures it needs were not collected)."""
    prior, rec = job.prior, job.collected
    assert prior is not None
    currents = None
    if prior.channels:
        have = list(rec.channels)
        if not set(prior.channels) <= set(have):
            return result
        currents = rec.currents[:, [have.index(c) for c in prior.channels]]
    if prior.has_temperature_terms and rec.temperatures is None:
        return result
    try:
        b = prior.apply_array(rec.vectors, currents, rec.temperatures if prior.has_temperature_terms else None)
    except (InputError, ValueError):
        return result
    out = replace(result, tmi_before=tmi_rms(b, result.intensity), tensor_before=_gradient_rms(b, job.geo))
    meta = out.calibration.metadata
    meta["tmi_rms_before"] = [float(x) for x in out.tmi_before]
    if np.isfinite(out.tensor_before):
        meta["tensor_rms_before"] = out.tensor_before
    meta["before"] = f"with the prior: {job.prior_note}"
    if "summary" in meta:
        meta["summary"] = out.summary()
    return out
