"""The calibration node's progress reports: ``~/progress``, ``/diagnostics`` and the analyses of the collected
sets in the supervised analysis process."""

from __future__ import annotations

import threading
from typing import Any

import numpy as np
from diagnostic_msgs.msg import DiagnosticStatus, KeyValue

from magcal_ros.core.geometry import ArrayGeometry
from magcal_ros.core.observability import excitation
from magcal_ros.methods import progress
from magcal_ros.nodes import common
from magcal_ros.nodes.correction_link import Stopping

BAD_SAMPLES: tuple[str, ...] = ("nonfinite", "out_of_range", "out_of_order", "duplicate", "zero_stamp",
                                "negative_stamp")


class ProgressReports:
    """The calibration node's part that analyses the collection and reports (a mixin of
    :class:`~magcal_ros.nodes.calibration_node.CalibrationNode`)."""

    def _assess_tick(self) -> None:
        """Start an analysis of the collected sets (a worker thread hands it to the analysis process), if they
        changed and none is running."""
        if self._stopping.is_set() or (self._assessor is not None and self._assessor.is_alive()):
            return
        with self._lock:
            if not self._collecting or len(self._buffer) == 0:
                return
            key = (self._generation, self._buffer.offered)
            if self._assessment is not None and self._assessment[:2] == key:
                return
            stamps, raw, currents = self._buffer.snapshot_all()
            geo, channels = self._geometry, self._inputs.channels
        self._assessor = threading.Thread(target=self._assess, args=(key, geo, channels, stamps, raw, currents),
                                          name="magcal-progress", daemon=True)
        self._assessor.start()

    def _assess(self, key: tuple[int, int], geo: ArrayGeometry, channels: tuple[str, ...], stamps: np.ndarray,
                raw: np.ndarray, currents: np.ndarray) -> None:
        """The progress analysis (worker thread; the math in the analysis process, so the GIL stays free for
        the callbacks): envelope, what is undetermined, what to fly."""
        try:
            cached = self._progress_prior
            if cached is None or cached[0] != key[0]:
                prior, note = self._resolve_prior(geo)
                cached = self._progress_prior = (key[0], prior, note)
            _, prior, note = cached
            reference, site = self._reference()
            result = self._analyse(raw, geo, reference, prior, stamps, currents if channels else None, channels,
                                   inclination_deg=site.inclination_deg if site is not None else None)
        except Stopping:
            return
        except Exception as exc:  # noqa: BLE001 - progress must never stop the node
            if self._stopping.is_set():
                return
            note = "none"
            result = progress.Assessment(len(raw), False, None, (), f"cannot analyse the collected sets: {exc}")
        with self._lock:
            if key[0] == self._generation:
                self._assessment = (*key, result, note)

    def _analyse(self, *args: Any, **kwargs: Any) -> progress.Assessment:
        """:func:`magcal_ros.methods.progress.assess` in the analysis process;
        :class:`~magcal_ros.nodes.analysis.AnalysisFailed` with the reason when it gives no answer (the process is
        then restarted)."""
        result: progress.Assessment = self._analysis.run("assess", *args, **kwargs)
        return result

    def _publish_progress(self) -> None:
        now = common.now_ns(self)
        with self._lock:
            self._flush_pending(force=False)
            _, raw = self._buffer.snapshot()
            collecting, offered, capacity = self._collecting, self._buffer.offered, self._buffer.capacity
            stats = self._sync.stats.as_dict()
            stats["pending"] = self._sync.pending
            self._health.output(stats["sets"], now)
            stale, current_values = self._current_health.assess(self._currents, "not collected")
            stale_t, temperature_values = self._temperature_health.assess(self._temperatures, "not collected")
            stale_i, imu_values = self._imu_health.assess(self._imu, "not collected")
            clock = self._sim_time.problem(bool(self.get_parameter("use_sim_time").value), now)
            stale = "; ".join(x for x in (stale, stale_t, stale_i, clock) if x) or None
            health = self._health.assess(now, stats, "complete sets", stale)
            health.values.update(current_values)
            health.values.update(temperature_values)
            health.values.update(imu_values)
            latest = self._assessment if self._assessment and self._assessment[0] == self._generation else None
        self._drops.update(stats, f"{stats['sets']} complete sets")
        for line in health.notices:
            self.get_logger().warn(line)
        exc = excitation(raw.mean(axis=1)) if len(raw) else excitation(np.zeros((0, 3)))
        assessed = latest[2] if latest is not None else None
        with_prior = latest is not None and not latest[3].startswith("none")
        problem = None if with_prior else exc.problem()
        if problem is None and assessed is not None and not assessed.ready:
            problem = (f"undetermined: {', '.join(assessed.undetermined)}; " if assessed.undetermined else "") + \
                assessed.advice
        values = {
            "collecting": str(collecting).lower(),
            "samples": str(len(raw)),
            "max_samples": str(capacity),
            "offered": str(offered),
            "coverage": f"{exc.coverage:.3f}",
            "thickness": f"{exc.thickness:.3f}",
            "ready": str(problem is None and len(raw) > 0).lower(),
            "problem": problem or "",
            "unmatched": str(stats["unmatched"]),
            "bad_samples": str(sum(stats[k] for k in BAD_SAMPLES)),
            "assessed": str(assessed.samples if assessed is not None else 0),
            "envelope": _envelope_text(assessed),
            "envelope_pitch_deg": f"{assessed.envelope.pitch_deg:g}" if assessed and assessed.envelope else "",
            "envelope_roll_deg": f"{assessed.envelope.roll_deg:g}" if assessed and assessed.envelope else "",
            "undetermined": ", ".join(assessed.undetermined) if assessed is not None else "",
            "advice": assessed.advice if assessed is not None else "",
            "prior": latest[3] if latest is not None else "",
        }
        recal = self._recalibration_status()
        values |= {
            "calibration_health": self._watch.health if self._watch.since is not None else self._health_seen,
            "recalibration": recal.message,
        }
        if not collecting and not len(raw):
            message = "idle: call ~/start to collect"
        elif problem is None and len(raw):
            where = f", {values['envelope']}" if assessed is not None else ""
            message = f"ready: {len(raw)} sets, coverage {exc.coverage:.0%}{where}; call ~/calibrate"
        else:
            message = problem or "collecting"
        status = DiagnosticStatus(
            level=DiagnosticStatus.OK if values["ready"] == "true" else DiagnosticStatus.WARN,
            name=self.get_fully_qualified_name(),
            message=message,
            hardware_id=self._hardware_id(),
            values=[KeyValue(key=k, value=v) for k, v in values.items()],
        )
        self._progress_pub.publish(status)
        health.values.update(collecting=values["collecting"], samples=values["samples"])
        self._diagnostics_pub.publish(common.diagnostic_array(
            self, [common.diagnostic_status(self.get_fully_qualified_name(), self._hardware_id(), health), recal,
                   self._analysis_status()]))

    def _hardware_id(self) -> str:
        """The array's ``hardware_id`` on ``/diagnostics``, the same as the correction node's."""
        return common.hardware_id(self, self._geometry.names)

    def _analysis_status(self) -> DiagnosticStatus:
        """``<node>: analysis``: the analysis process supervised (restarted when it hangs or ends), its heartbeat."""
        self._analysis.check()
        level, message, values = self._analysis.status()
        return DiagnosticStatus(level=bytes([level]), name=self.get_fully_qualified_name() + ": analysis",
                                message=message, hardware_id=self._hardware_id(),
                                values=[KeyValue(key=k, value=v) for k, v in values.items()])


def _envelope_text(assessed: progress.Assessment | None) -> str:
    """The envelope of an assessment in words ('' before the first one)."""
    if assessed is None:
        return ""
    return assessed.envelope_text()
