"""The calibration node's recalibration during the mission: the correction node's calibration health watched,
a named drift recalibrated from the mission's sets (``auto_recalibrate``) or advice on what to fly."""

from __future__ import annotations

import threading
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

from magcal_ros.core.calibration import ArrayCalibration
from magcal_ros.core.calibration_health import DRIFTED_SENSORS
from magcal_ros.methods import recalibration
from magcal_ros.methods.pipeline import (
    CalibrationResult,
)
from magcal_ros.nodes import drift
from magcal_ros.nodes.buffer import MissionSets
from magcal_ros.nodes.correction_link import CallFailed, Stopping


class MissionRecalibration:
    """The calibration node's part that acts on the calibration health (a mixin of
    :class:`~magcal_ros.nodes.calibration_node.CalibrationNode`)."""

    def _interval_ns(self) -> int:
        return int(float(self.get_parameter("recalibrate_interval").value) * 1e9)

    def _on_diagnostics(self, msg: DiagnosticArray) -> None:
        """The correction node's calibration health: a drift named starts the mission recalibration's clock."""
        target = self._target_name()
        for status in msg.status:
            if status.name != target + drift.STATUS_SUFFIX:
                continue
            values = {kv.key: kv.value for kv in status.values}
            drifted = values.get("drifted") == "true"
            sensors = [n for n in values.get(DRIFTED_SENSORS, "").split(",") if n]
            with self._lock:
                self._health_seen = status.message
                named = self._watch.report(drifted, status.message, self._mission.newest, sensors)
            if named:
                auto = bool(self.get_parameter("auto_recalibrate").value)
                window = self._watch.window_ns / 1e9
                self.get_logger().warn(
                    f"{target}: {status.message}; " + (
                        f"auto_recalibrate: recalibrating from the next {window:.0f} s of sets" if auto else
                        "auto_recalibrate is off: ~/progress and /diagnostics say what to fly, then call ~/calibrate"))

    def _drift_tick(self) -> None:
        """While a drift is named: recalibrate (auto_recalibrate) or advise, in a worker thread."""
        if self._stopping.is_set() or (self._drift_worker is not None and self._drift_worker.is_alive()):
            return
        with self._lock:
            now = self._mission.newest
            due, _ = self._watch.due(now)
            if self._watch.since is None and not self._watch.refining:
                return
            start = self._watch.window_start(now)
            refining = self._watch.refining
        if bool(self.get_parameter("auto_recalibrate").value):
            if not due or not self._solve_lock.acquire(blocking=False):
                return
            with self._lock:
                window = self._mission.snapshot(start)
            target, args = self._auto_recalibrate, (now, window)
        else:
            if refining or now - start < self._watch.window_ns // 3 or \
                    (self._advice is not None and self._advice[0] == now):
                return
            with self._lock:
                window = self._mission.snapshot(start)
            target, args = self._advise, (now, window)
        self._drift_worker = threading.Thread(target=target, args=args, name="magcal-recalibrate", daemon=True)
        self._drift_worker.start()

    def _auto_recalibrate(self, now: int, window: MissionSets) -> None:
        """Fit the sets flown since the drift was named (held-out sets aside), check, push and save (worker thread).

        As ``~/calibrate`` solves: with the running calibration as the prior and, when the window's sets carry the
        IMU's attitudes (:meth:`~magcal_ros.nodes.buffer.MissionWindow.snapshot`), with the IMU, so that its blocks
        (output rotation, site gradient, the array's lag behind it) are fitted again, not kept as running."""
        pushed = False
        with self._lock:
            refining = self._watch.refining  # (a push's refinement: no drift named, no sensor to fix)
            health = self._watch.health  # what named the drift (a push makes the next report say otherwise)
            drifted = self._watch.sensors
            self._recalibration["attempts"] = str(int(self._recalibration["attempts"]) + 1)
        try:
            stamps, raw, currents, temperatures = window.stamps, window.raw, window.currents, window.temperatures
            fit, held = recalibration.split(stamps)
            seen: dict[str, Any] = {}
            warm = None if temperatures is None else (temperatures[fit], temperatures[held])

            def check(result: CalibrationResult,
                      prior: ArrayCalibration | None) -> tuple[str | None, CalibrationResult]:
                judged = recalibration.judge(result, prior, raw[fit], raw[held], currents[fit], currents[held], drifted,
                                             seconds_fit=(stamps[fit] - stamps[0]) / 1e9, temperatures=warm,
                                             refine=refining)
                seen.update(verdict=judged, prior=prior, fitted=result.calibration)
                return judged.problem, judged.result or result

            fallback = self._running_intensity() if self._reference()[0] is None else None
            pushed, message = self._calibrate(window.take(fit), check, fallback)
            if pushed:
                judged = seen["verdict"]
                kept = f" ({', '.join(judged.kept)} kept as running)" if judged.kept else ""
                kept += f" ({judged.scope})" if judged.scope else ""
                kept += recalibration.timing_note(seen["fitted"], judged.result.calibration)
                why = (f"refining the last push with the {int(fit.sum())} sets flown since its drift was named"
                       if refining else f"its calibration health said: {health}")
                message = (f"recalibrated {self._target_name()} during the mission from {int(fit.sum())} sets ({why}): "
                           f"{recalibration.changes(seen['prior'], judged.result.calibration)}{kept}; "
                           f"{judged.figures.describe()}; {message}")
                self.get_logger().info(message)
                with self._lock:
                    self._recalibration["recalibrations"] = str(int(self._recalibration["recalibrations"]) + 1)
                    self._recalibration["last_recalibration"] = message
                    self._recalibration["last_attempt"] = ""
            else:
                with self._lock:
                    self._recalibration["last_attempt"] = message
        except Stopping:
            return
        except Exception as exc:  # noqa: BLE001 - the mission goes on whatever happened here
            if self._stopping.is_set():
                return
            self.get_logger().error(f"recalibration during the mission failed unexpectedly ({type(exc).__name__}: "
                                    f"{exc}); nothing was changed")
            with self._lock:
                self._recalibration["last_attempt"] = f"failed unexpectedly: {exc}; nothing was changed"
        finally:
            with self._lock:
                self._watch.attempted(now, pushed)
            self._solve_lock.release()

    def _running_intensity(self) -> float | None:
        """The intensity (T) the correction node's calibration maps |B| to, when it says (else None)."""
        try:
            value = self._target_values(self._geometry.names).get(drift.INTENSITY)
        except CallFailed:
            return None
        return float(value) if isinstance(value, (int, float)) and value > 0 else None

    def _advise(self, now: int, window: MissionSets) -> None:
        """What to fly so that ~/calibrate fixes the drift: the progress analysis of the sets flown since it was
        named, with the running calibration as the prior (worker thread; the math in the analysis process)."""
        stamps, raw, currents = window.stamps, window.raw, window.currents
        try:
            prior, _ = self._resolve_prior(self._geometry)
            reference, site = self._reference()
            channels = self._inputs.channels
            assessed = self._analyse(raw, self._geometry, reference or self._running_intensity(), prior, stamps,
                                     currents if channels else None, channels,
                                     inclination_deg=site.inclination_deg if site is not None else None)
            text = recalibration.advice(assessed, prior is not None, self._watch.window_ns / 1e9)
        except Stopping:
            return
        except Exception as exc:  # noqa: BLE001 - advice must never stop the node
            if self._stopping.is_set():
                return
            text = f"cannot analyse the sets flown since the drift was named: {exc}"
        with self._lock:
            self._advice = (now, text)

    def _recalibration_status(self) -> DiagnosticStatus:
        """``<node>: recalibration``: a drift named and what is done about it (WARN until fixed)."""
        auto = bool(self.get_parameter("auto_recalibrate").value)
        with self._lock:
            advice = self._advice[1] if self._advice is not None else ""
            warn, message, values = recalibration.status(self._target_name(), auto, self._watch, self._mission.newest,
                                                         self._health_seen, advice, self._recalibration)
        return DiagnosticStatus(level=DiagnosticStatus.WARN if warn else DiagnosticStatus.OK,
                                name=self.get_fully_qualified_name() + ": recalibration", message=message,
                                hardware_id=self._hardware_id(),
                                values=[KeyValue(key=k, value=v) for k, v in values.items()])
