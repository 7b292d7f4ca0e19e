"""Calibration service node: collect a rotation manoeuvre, solve, hand the result over.

Subscribes ``<name>/raw`` (sensor_msgs/MagneticField, T) like the correction node and,
while collecting, keeps up to ``max_samples`` synchronized sets spread over the
attitudes. Services (std_srvs/srv/Trigger):

- ``~/start``: forget collected sets and start collecting;
- ``~/calibrate``: solve with the core (:func:`magcal_ros.methods.pipeline.calibrate_array`),
  write the calibration file (atomic; the previous file kept as a timestamped backup,
  the last ``backups``), then set the result on the running correction node through its
  ``set_parameters_atomically`` service (all or nothing); if that fails the previous
  file is put back, so the file and the running node never disagree and no set is ever
  corrected with a calibration that is then withdrawn. Answers the one-line summary, or
  ``success: false`` with the reason and what to do, having changed nothing. Called again
  on the same collected sets and settings it does not solve again and changes nothing
  (the answer says so);
- ``~/reset``: drop collected sets (and stop collecting).

``correction_node`` is a node name resolved like a topic: relative names live in this
node's namespace. The file's node key is the correction node's fully qualified name.

``prior``: what ``~/calibrate`` starts from and keeps where the collected sets do not
determine a quantity (partial recalibration at sea): ``running`` (default) the correction
node's calibration, fetched through its ``get_parameters`` service (when it is not
reachable or not calibrated, no prior, and the answer says so), ``none``, or a calibration
file. The reference intensity is ``reference_field``, or the World Magnetic Model's at
``site`` on ``date``; ``max_residual`` overrides the noise-aware acceptance rule. With
``interference_channels`` the currents of those channels (``interference_topics``,
``interference_types``) are collected with every set (a set without a fresh current of
every channel is not collected) and their interference is solved with the calibration.

``~/progress`` (diagnostic_msgs/DiagnosticStatus, every ``progress_period`` s): level OK
when a solve would succeed, WARN when not yet (message says why and what to fly), values
``collecting``, ``samples``, ``max_samples``, ``offered``, ``coverage`` (fraction of 42
sphere cells), ``thickness`` (thinnest/widest spread, ~0 for one rotation axis), ``ready``,
``problem`` and, from an analysis of the collected sets run at most every
``assess_period`` s in the analysis process started with the node and supervised
(:mod:`magcal_ros.nodes.analysis`: restarted when an analysis takes longer than
``analysis_timeout`` or its heartbeat stops; ``<node>: analysis`` on ``/diagnostics``), so that
it never holds up the callbacks (:func:`magcal_ros.methods.progress.assess`, 0.1-2 s of one
core each):
``assessed`` (sets analysed), ``envelope`` ("valid within pitch +-P deg, roll +-R deg"),
``envelope_pitch_deg``, ``envelope_roll_deg``, ``undetermined``, ``advice`` (what to fly
next, in words) and ``prior``. ``/diagnostics`` (DiagnosticArray, same period): the
health of the raw streams (silent or late sensors, drops, sets lost before the node, no
complete set for ``output_timeout``, stale currents), as the correction node reports it, with the
same ``hardware_id``. Reports and analyses run on the steady clock (with ``use_sim_time`` and no
``/clock`` they go on, and say so).

Recalibration during the mission (:mod:`magcal_ros.methods.recalibration`): the node keeps a
rolling window of the mission's sets and watches the correction node's calibration health on
``/diagnostics``. When it names a drift, with ``auto_recalibrate`` the sets flown since
(``recalibrate_window`` s) are solved as ``~/calibrate`` solves (held-out sets aside; with the IMU's
attitude at each set when ``imu_topic`` is heard, so its blocks and ``output_rotation`` are fitted again), checked
(what changed determined; on the held-out sets every sensor the health named better, none worse,
the sensors that did not improve kept as they run) and pushed and saved, at most once per
``recalibrate_interval`` (the status counts ``attempts`` and ``recalibrations``); without it,
``~/progress`` and the status ``<node>: recalibration`` say what to fly so that ``~/calibrate``
fixes it.

Usage::

    ros2 run magcal_ros calibration_node --ros-args -p reference_field:=5.15e-5
    ros2 service call /magcal_calibration/start std_srvs/srv/Trigger
    # ... rotate the array about at least two axes ...
    ros2 service call /magcal_calibration/calibrate std_srvs/srv/Trigger
"""

from __future__ import annotations

import threading
from collections.abc import Sequence
from typing import Any

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from std_srvs.srv import Trigger

from magcal_ros.core.calibration import ArrayCalibration
from magcal_ros.errors import InputError
from magcal_ros.io import topics
from magcal_ros.methods import progress, recalibration
from magcal_ros.nodes import common
from magcal_ros.nodes.analysis import AnalysisWorker
from magcal_ros.nodes.calibration_parameters import CalibrationParameters
from magcal_ros.nodes.collection import Collection
from magcal_ros.nodes.collection_progress import ProgressReports
from magcal_ros.nodes.correction_link import CorrectionLink
from magcal_ros.nodes.entry import StopFlag
from magcal_ros.nodes.mission_recalibration import MissionRecalibration
from magcal_ros.nodes.solving import Solving

NODE_NAME = "magcal_calibration"


class CalibrationNode(CalibrationParameters, Collection, ProgressReports, MissionRecalibration, Solving, CorrectionLink,
                      Node):
    """Collects synchronized raw sets and solves the array calibration on request.

    Its parts, a module each: the parameters (:mod:`~magcal_ros.nodes.calibration_parameters`), the collection
    (:mod:`~magcal_ros.nodes.collection`), the progress analyses and reports
    (:mod:`~magcal_ros.nodes.collection_progress`), the recalibration during the mission acting on the calibration
    health (:mod:`~magcal_ros.nodes.mission_recalibration`), the solve (:mod:`~magcal_ros.nodes.solving`) and the
    push to the correction node (:mod:`~magcal_ros.nodes.correction_link`). This class holds their state and the
    services that start and drop a collection.
    """

    def __init__(self, node_name: str = NODE_NAME, **kwargs: Any) -> None:
        super().__init__(node_name, **kwargs)
        self._lock = threading.Lock()
        self._solve_lock = threading.Lock()
        self._stopping = threading.Event()
        self._worker: threading.Thread | None = None
        self._assessor: threading.Thread | None = None
        self._last_solved: tuple[str, str] | None = None
        """(fingerprint of the sets and settings, answer) of the last successful calibration."""
        self._generation = 0
        """Counts collections (start, reset, reconfiguration): an assessment belongs to one."""
        self._assessment: tuple[int, int, progress.Assessment, str] | None = None
        """(generation, sets offered, assessment, prior used) of the latest progress analysis."""
        self._progress_prior: tuple[int, ArrayCalibration | None, str] | None = None
        """(generation, prior, what it is) the progress analysis uses for that collection."""
        self._changed: set[str] = set()
        """Parameters the update being applied changes."""
        self._declare_parameters()
        self._limits = common.declare_health(self)
        common.check_ranges(self)
        try:
            self._geometry = self._validate({})
        except (TypeError, ValueError) as exc:
            raise InputError(f"invalid parameter: {exc}") from None
        self._check_prior({})
        self._analysis = AnalysisWorker(float(self.get_parameter("analysis_timeout").value),
                                        self.get_logger().warn)
        """The supervised process the progress analyses run in, started with the node."""
        self._analysis.start()
        self._collecting = bool(self.get_parameter("autostart").value)
        depth = int(self.get_parameter("qos_depth").value)
        self._raw_qos = common.raw_qos(str(self.get_parameter("raw_reliability").value), depth)
        self._calibrate_group = ReentrantCallbackGroup()
        self._wake = self.create_guard_condition(lambda: None)
        self._subs: list[Any] = []
        window_ns = int(float(self.get_parameter("recalibrate_window").value) * 1e9)
        self._watch = recalibration.DriftWatch(window_ns, self._interval_ns())
        self._recalibration: dict[str, str] = {"recalibrations": "0", "attempts": "0", "last_recalibration": "",
                                               "last_attempt": ""}
        """What the mission recalibration did last (values of its status)."""
        self._advice: tuple[int, str] | None = None
        """(mission time, text) of the latest advice on what to fly to fix a drift."""
        self._drift_worker: threading.Thread | None = None
        self._health_seen = ""
        """The latest calibration health message of the correction node ('' before the first)."""
        self._connect(self._geometry)
        self._progress_pub = self.create_publisher(DiagnosticStatus, "~/progress", 10)
        self._diagnostics_pub = self.create_publisher(DiagnosticArray, common.DIAGNOSTICS_TOPIC, 10)
        self.create_service(Trigger, "~/start", self._on_start)
        self.create_service(Trigger, "~/calibrate", self._on_calibrate, callback_group=self._calibrate_group)
        self.create_service(Trigger, "~/reset", self._on_reset)
        self._target_clients: dict[str, tuple[Any, Any]] = {}
        self._service_clients()
        self._drops = common.DropReporter(self.get_logger())
        self.add_pre_set_parameters_callback(common.numbers_from_text(self._numeric))
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self.add_post_set_parameters_callback(self._after_set_parameters)
        self._sim_time = common.SimTimeWatch(self.get_logger())
        # on the steady clock: progress, /diagnostics and the analyses go on without /clock under use_sim_time
        common.steady_timer(self, max(float(self.get_parameter("progress_period").value), 0.05), self._publish_progress)
        common.steady_timer(self, common.QUIET_CHECK, self._release_quiet)
        common.steady_timer(self, max(float(self.get_parameter("assess_period").value), 0.05), self._assess_tick)
        common.steady_timer(self, max(float(self.get_parameter("assess_period").value), 0.05), self._drift_tick)
        self.create_subscription(DiagnosticArray, common.DIAGNOSTICS_TOPIC, self._on_diagnostics, 10)
        channels = self._inputs.channels
        self.get_logger().info(
            f"listening to {', '.join(topics.raw(n) for n in self._geometry.names)}"
            + (f" and the currents of {', '.join(channels)}" if channels else "") + "; "
            f"{'collecting' if self._collecting else 'idle: call ~/start to collect'}; "
            f"method {self.get_parameter('method').value}, prior {self.get_parameter('prior').value}, results go to "
            f"{self._target_name()} and {self._calibration_path() or '(no file)'}"
        )

    # -- collecting -----------------------------------------------------------------
    def _on_start(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        with self._lock:
            self._buffer.clear()
            self._pending.clear()
            self._collecting = True
            self._generation += 1
        response.success = True
        response.message = (
            f"collecting up to {self._buffer.capacity} sets from {', '.join(self._geometry.names)}: "
            "turn the array through large angles about at least two axes, then call ~/calibrate"
        )
        self.get_logger().info(response.message)
        return response

    def _on_reset(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        with self._lock:
            dropped = len(self._buffer)
            self._buffer.clear()
            self._pending.clear()
            self._collecting = False
            self._generation += 1
        response.success = True
        response.message = f"dropped {dropped} collected sets; call ~/start to collect again"
        self.get_logger().info(response.message)
        return response

    # -- progress ---------------------------------------------------------------------

    # -- recalibration during the mission -------------------------------------------

    # -- calibrating ----------------------------------------------------------------

    def close(self) -> None:
        """Before destruction: abandon a running calibration (it changes nothing), wait for it briefly."""
        self._stopping.set()
        worker = self._worker
        if worker is not None and worker.is_alive():
            self.get_logger().info("shutting down during a calibration: it is abandoned, nothing is changed")
            worker.join(2.0)
        self._analysis.close()
        for thread in (self._assessor, self._drift_worker):
            if thread is not None and thread.is_alive():
                thread.join(2.0)


def main(args: Sequence[str] | None = None, stop: StopFlag | None = None) -> int:
    """Run the node (``ros2 run magcal_ros calibration_node`` goes through :mod:`magcal_ros.nodes.entry`)."""
    return common.run_node(lambda argv: CalibrationNode(), SingleThreadedExecutor, args, stop)


if __name__ == "__main__":
    raise SystemExit(main())
