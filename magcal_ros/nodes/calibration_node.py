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
(``recalibrate_window`` s) are solved as ``~/calibrate`` solves (held-out sets aside), checked
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

import contextlib
import hashlib
import os
import threading
import time
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rcl_interfaces.msg import Parameter as ParameterMsg
from rcl_interfaces.msg import ParameterType, SetParametersResult
from rcl_interfaces.srv import GetParameters, SetParametersAtomically
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter, parameter_value_to_python
from rclpy.task import Future
from sensor_msgs.msg import MagneticField
from std_srvs.srv import Trigger

from magcal_ros.core import side_streams as side
from magcal_ros.core import sync
from magcal_ros.core.calibration import ArrayCalibration
from magcal_ros.core.calibration_health import DRIFTED_SENSORS
from magcal_ros.core.geomagnetic import SiteField, parse_date, parse_site, site_field
from magcal_ros.core.geometry import ArrayGeometry
from magcal_ros.core.imu import DEFAULT_IMU_TOLERANCE, LatestImu
from magcal_ros.core.interference import LatestCurrents, tolerance_of
from magcal_ros.core.matching import LatestValues
from magcal_ros.core.metrics import rms, tensor_rms, tmi_rms
from magcal_ros.core.observability import excitation
from magcal_ros.core.recording import Recording
from magcal_ros.core.tensor import baseline_gradient, gradient, method_for
from magcal_ros.errors import InputError, MagcalError
from magcal_ros.io import calibration_file as calfile
from magcal_ros.io import topics
from magcal_ros.methods import progress, recalibration
from magcal_ros.methods.pipeline import (
    DEFAULT_METHOD,
    METHODS,
    CalibrationResult,
    SolveOptions,
    calibrate_array,
)
from magcal_ros.nodes import common, drift
from magcal_ros.nodes.analysis import AnalysisWorker
from magcal_ros.nodes.buffer import MissionSets, MissionWindow, SetBuffer, collected_recording
from magcal_ros.nodes.entry import StopFlag
from magcal_ros.nodes.health import ArrayHealth, CurrentHealth, ImuHealth, TemperatureHealth

NODE_NAME = "magcal_calibration"
DEFAULT_CALIBRATION_FILE = "~/.ros/magcal_calibration.yaml"
WHAT_TO_DO = "call ~/start, turn the array through large angles about at least two axes, then call ~/calibrate"
PRIORS: tuple[str, ...] = ("running", "none")
"""The ``prior`` settings besides a file path."""
RECONNECT: frozenset[str] = frozenset({"sensor_names", "positions", "max_samples", "sync_tolerance", "sync_mode",
                                       "max_gap", *common.INTERFERENCE_PARAMETERS, "temperature_tolerance",
                                       "imu_topic", "imu_tolerance"})
"""Parameters whose change drops the collected sets and subscribes afresh."""
BAD_SAMPLES: tuple[str, ...] = ("nonfinite", "out_of_range", "out_of_order", "duplicate", "zero_stamp",
                                "negative_stamp")
"""The synchronizer counters ``~/progress`` sums as ``bad_samples``: messages refused for what they hold."""


class CallFailed(Exception):
    """A service call to the correction node did not complete."""

    def __init__(self, message: str, unknown_outcome: bool = False) -> None:
        super().__init__(message)
        self.unknown_outcome = unknown_outcome
        """The request went out but no answer came: the correction node may have applied it."""


class Stopping(CallFailed):
    """The node is shutting down: the calibration is abandoned."""

    def __init__(self) -> None:
        super().__init__("the calibration node is shutting down")


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


class CalibrationNode(Node):
    """Collects synchronized raw sets and solves the array calibration on request."""

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

    # -- parameters -----------------------------------------------------------------
    def _declare_parameters(self) -> None:
        d = common.describe
        common.declare_geometry(self)
        self.declare_parameter(
            "reference_field", 0.0,
            d("total field intensity during the manoeuvre (T); 0 = unknown: relative calibration "
              "(methods ml and paired only), or from site", constraints="0, or 1e-7 .. 1e-3 T", numbers=True,
              floats=(0.0, 1e-3)),
        )
        common.declare_list(
            self, "site", Parameter.Type.DOUBLE_ARRAY,
            d("where the manoeuvre is flown, for the reference intensity from the World Magnetic Model: [lat_deg, "
              "lon_deg] or [lat_deg, lon_deg, alt_m] (north and east positive, altitude above sea level, negative "
              "under water); not set or [] = not used. Excludes reference_field > 0",
              constraints="lat -90..90, lon -180..360, alt -1000..850000 m", numbers=True),
        )
        self.declare_parameter(
            "date", "",
            d("date (YYYY-MM-DD, UTC) at which site evaluates the World Magnetic Model; empty = today",
              constraints="2015-01-01 .. 2029-12-31; needs site"),
        )
        self.declare_parameter(
            "max_residual", 0.0,
            d("accept a calibration whose residual per axis is below this (T) whatever the sensor noise; 0 = the "
              "noise-aware rule (the residual compared with the noise estimated from the data)",
              numbers=True, floats=(0.0, 1e-3)),
        )
        self.declare_parameter(
            "prior", "running",
            d("what ~/calibrate starts from and keeps where the collected sets do not determine a quantity: "
              "running (the correction node's calibration; none when it is unreachable or not calibrated), none, "
              "or the path of a calibration file"),
        )
        self.declare_parameter(
            "method", DEFAULT_METHOD,
            d("calibration method: " + "; ".join(f"{m.name} ({m.source})" for m in METHODS.values()),
              constraints=" | ".join(METHODS)),
        )
        self.declare_parameter(
            "calibration_file", DEFAULT_CALIBRATION_FILE,
            d("calibration file written on success (ROS 2 params file for the correction node; previous "
              "files kept as <file>.<UTC time>.bak); empty = do not write"),
        )
        self.declare_parameter(
            "backups", calfile.DEFAULT_BACKUPS,
            d("previous calibration files kept beside calibration_file (newest first)", ints=(0, 100)),
        )
        self.declare_parameter(
            "correction_node", "magcal_correction",
            d("the running correction node that receives the calibration; a relative name is resolved in "
              "this node's namespace"),
        )
        self.declare_parameter(
            "max_samples", 2000,
            d("most synchronized sets kept; when full, sets of the most visited attitudes are replaced",
              ints=(20, 1_000_000)),
        )
        self.declare_parameter(
            "sync_tolerance", sync.DEFAULT_SYNC_TOLERANCE,
            d("exact matching: largest spread (s) of header stamps within one set; capped at half the sample "
              "period", constraints="0 < t < 1", numbers=True, floats=common.TOLERANCE_RANGE),
        )
        common.declare_sync(self)
        common.declare_currents(self)
        common.declare_temperature_tolerance(self)
        self.declare_parameter(
            "imu_topic", topics.IMU,
            d("the vehicle's IMU (sensor_msgs/Imu: orientation IMU frame -> world ENU, angular velocity rad/s), "
              "collected with every set once heard, interpolated to the set's instant, so that the fit can use it"))
        self.declare_parameter(
            "imu_tolerance", DEFAULT_IMU_TOLERANCE,
            d("a set needs an IMU sample stamped at most this (s) before it, and waits at most this long for the "
              "sample after it to interpolate between them", numbers=True, floats=(0.0, 60.0)))
        self.declare_parameter("autostart", False, d("collect from start-up without calling ~/start", read_only=True))
        self.declare_parameter(
            "service_timeout", 5.0, d("how long (s) to wait for the correction node's services", numbers=True,
                                      floats=(0.01, 3600.0))
        )
        self.declare_parameter("progress_period", 1.0, d("period (s) of ~/progress and /diagnostics",
                                                         read_only=True, numbers=True, floats=common.PERIOD_RANGE))
        self.declare_parameter(
            "assess_period", 5.0,
            d("shortest interval (s) between two analyses of the collected sets for ~/progress (envelope, what is "
              "undetermined, advice); each runs in the analysis process (0.1-2 s of one core)", read_only=True,
              numbers=True, floats=common.PERIOD_RANGE))
        self.declare_parameter(
            "analysis_timeout", 120.0,
            d("longest time (s) one analysis may take, and the analysis process may go without a heartbeat, before "
              "the process is killed and a new one started (the analysis then fails with the reason; the node goes "
              "on); shown on /diagnostics as '<node>: analysis'", numbers=True, floats=(1.0, 3600.0)))
        self.declare_parameter("raw_reliability", "best_effort", d(common.RELIABILITY_DOC, read_only=True))
        self.declare_parameter("qos_depth", 100, d("history depth of the raw subscriptions", read_only=True,
                                                   ints=common.QOS_DEPTH_RANGE))
        self.declare_parameter(
            "auto_recalibrate", False,
            d("when the correction node's calibration health names a drift: true = recalibrate from the sets "
              "flown since (running calibration as the prior, checked on held-out sets), push and save it; false = "
              "advise on /diagnostics and ~/progress what to fly so that ~/calibrate can fix it"))
        self.declare_parameter(
            "recalibrate_window", 60.0,
            d("seconds of the mission's sets (flown after the drift was named) a recalibration during the mission "
              "fits and checks (at most max_samples sets, evenly in time)", read_only=True, numbers=True,
              floats=(10.0, 3600.0)))
        self.declare_parameter(
            "recalibrate_interval", 600.0,
            d("shortest time (s, of the sets' stamps) between two recalibrations pushed by auto_recalibrate",
              numbers=True, floats=(0.0, 86400.0)))

    def _numeric(self, name: str) -> bool:
        """Whether parameter ``name`` holds numbers."""
        return name in ("positions", "site") or (self.has_parameter(name) and self.get_parameter(name).type_ in (
            Parameter.Type.DOUBLE, Parameter.Type.INTEGER, *common.NUMBER_ARRAYS))

    def _value(self, name: str, updates: dict[str, Any]) -> Any:
        return updates[name] if name in updates else self.get_parameter_or(name).value  # unset: None

    def _number(self, name: str, updates: dict[str, Any]) -> float:
        value = self._value(name, updates)
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise InputError(f"{name} must be a number, got {value!r}")
        return float(value)

    def _validate(self, updates: dict[str, Any]) -> ArrayGeometry:
        """Validate the combined parameter state; return the array geometry."""
        geo = common.geometry(self._value("sensor_names", updates), self._value("positions", updates))
        method = self._value("method", updates)
        if method not in METHODS:
            raise InputError(f"unknown method {method!r}; choose one of {', '.join(METHODS)}")
        ref = self._number("reference_field", updates)
        if not (ref == 0.0 or 1e-7 <= ref <= 1e-3):
            raise InputError(f"reference_field {ref} T is not Earth-like (1e-7 .. 1e-3 T, or 0 for relative)")
        self._site(updates)
        residual = self._number("max_residual", updates)
        if not 0.0 <= residual <= 1e-3:
            raise InputError(f"max_residual must be 0 (the noise-aware rule) or a residual in T up to 1e-3, got {residual}")
        if not str(self._value("prior", updates)).strip():
            raise InputError("prior must be running, none or the path of a calibration file")
        if int(self._value("max_samples", updates)) < 20:
            raise InputError("max_samples must be at least 20")
        common.tolerance_ns(self._number("sync_tolerance", updates))
        common.sync_settings({n: self._value(n, updates) for n in ("sync_mode", "max_gap")})
        if self._number("service_timeout", updates) <= 0:
            raise InputError("service_timeout must be > 0 s")
        if not 1.0 <= self._number("analysis_timeout", updates) <= 3600.0:
            raise InputError("analysis_timeout must be 1 .. 3600 s")
        if not 0.0 <= self._number("recalibrate_interval", updates) <= 86400.0:
            raise InputError("recalibrate_interval must be 0 .. 86400 s")
        target = str(self._value("correction_node", updates)).strip()
        if not target.strip("/"):
            raise InputError("correction_node must name a node")
        common.check_node_name("correction_node", target)
        common.current_inputs({n: self._value(n, updates) for n in common.INTERFERENCE_PARAMETERS})
        common.temperature_tolerance_ns(self._value("temperature_tolerance", updates))
        self._imu_topic(updates)
        tolerance = self._value("imu_tolerance", updates)
        if isinstance(tolerance, bool) or not isinstance(tolerance, (int, float)) or not tolerance > 0:
            raise InputError(f"imu_tolerance must be a positive number of seconds, got {tolerance!r}")
        return geo

    def _check_prior(self, updates: dict[str, Any]) -> None:
        """:class:`InputError` unless ``prior`` is running, none, or a calibration file that reads (the block of the
        correction node) with this node's sensors: a prior that cannot be used is refused when it is set."""
        setting = str(self._value("prior", updates)).strip()
        if setting in PRIORS:
            return
        target = self.resolve_service_name(str(self._value("correction_node", updates)).strip())
        try:
            prior = calfile.read(os.path.expanduser(setting), target.lstrip("/"))
        except InputError as exc:
            raise InputError(f"prior {setting!r} is neither running, none nor a usable calibration file: {exc}") \
                from None
        names = tuple(str(n) for n in self._value("sensor_names", updates))
        if prior.geometry.names != names:
            raise InputError(f"prior {setting!r} calibrates {', '.join(prior.geometry.names)}, not this node's "
                             f"sensors ({', '.join(names)})")

    def _imu_topic(self, updates: dict[str, Any]) -> str:
        """The IMU topic; :class:`InputError` for a name that is not a topic."""
        from rclpy.exceptions import InvalidTopicNameException
        from rclpy.validate_topic_name import validate_topic_name

        topic = str(self._value("imu_topic", updates) or "").strip()
        try:
            validate_topic_name(topic)
        except InvalidTopicNameException as exc:
            raise InputError(f"imu_topic: {str(exc).splitlines()[0]}: {topic!r}") from None
        return topic

    def _site(self, updates: dict[str, Any]) -> SiteField | None:
        """The model's field at ``site`` on ``date`` (None when site is not set); :class:`InputError` with the
        reason for a bad site or date, or a site given with reference_field."""
        site, when = self._value("site", updates), str(self._value("date", updates) or "")
        if not site:
            if when.strip():
                raise InputError("date needs site (the date is when the magnetic model is evaluated at the site)")
            return None
        if self._number("reference_field", updates) > 0:
            raise InputError("give either reference_field or site, not both (site looks the intensity up)")
        try:
            values = [float(v) for v in site]
        except (TypeError, ValueError):
            raise InputError(f"site must be numbers [lat_deg, lon_deg] or [lat_deg, lon_deg, alt_m], got {site!r}") from None
        try:
            return site_field(*parse_site(values), parse_date(when))
        except InputError as exc:
            raise InputError(f"site {values} date {when or 'today'}: {exc}") from None

    def _reference(self) -> tuple[float | None, SiteField | None]:
        """The reference intensity (T, None: relative) and the site it came from (None: reference_field)."""
        site = self._site({})
        if site is not None:
            return site.intensity, site
        return float(self.get_parameter("reference_field").value) or None, None

    def set_parameters_atomically(self, parameter_list: list[Parameter]) -> SetParametersResult:
        """rclpy's, with a request naming a parameter this node does not have refused with its name (rclpy's
        reason lists none: "undeclared parameter(s): []"); the parameter services come here."""
        unknown = [p.name for p in parameter_list if not self.has_parameter(p.name)]
        if unknown:
            return SetParametersResult(successful=False, reason=common.unknown_parameters(self, unknown))
        return super().set_parameters_atomically(parameter_list)

    def _on_set_parameters(self, params: list[Parameter]) -> SetParametersResult:
        for p in params:
            why = common.check_number_array(p) if p.name in ("positions", "site") else None
            if why and not (p.name == "site" and _unset(p)):
                return SetParametersResult(successful=False, reason=why)
        updates = {p.name: p.value for p in params}
        try:
            self._validate(updates)
            if "prior" in updates or "correction_node" in updates:
                self._check_prior(updates)
        except (InputError, TypeError, ValueError, ArithmeticError) as exc:  # a value of any type may come
            return SetParametersResult(successful=False, reason=str(exc))
        why = common.out_of_range(self, params)  # what the node's own checks leave (an integer out of range)
        if why:
            return SetParametersResult(successful=False, reason=why)
        self._changed = {p.name for p in params if self.get_parameter_or(p.name).value != p.value}
        return SetParametersResult(successful=True)

    def _after_set_parameters(self, params: list[Parameter]) -> None:
        names = {p.name for p in params} & self._changed  # a value set again as it was changes nothing
        if "correction_node" in names:
            self._service_clients()
        if names & RECONNECT:
            with self._lock:
                self._disconnect()
                self._geometry = self._validate({})
                self._connect(self._geometry)
                self._last_solved = None
            self._drops.reset()
            self.get_logger().info(f"reconfigured ({', '.join(sorted(names))}): collected sets dropped")
        if names & {"prior", "correction_node", "reference_field", "site", "date"}:
            with self._lock:
                self._generation += 1  # the progress analysis starts afresh with the new settings
        if "recalibrate_interval" in names:
            with self._lock:
                self._watch.interval_ns = self._interval_ns()
        if "analysis_timeout" in names:
            self._analysis.timeout = float(self.get_parameter("analysis_timeout").value)

    # -- collecting -----------------------------------------------------------------
    def _connect(self, geo: ArrayGeometry) -> None:
        inputs = common.current_inputs({n: self._value(n, {}) for n in common.INTERFERENCE_PARAMETERS})
        self._inputs = inputs
        mode, gap = common.sync_settings({n: self._value(n, {}) for n in ("sync_mode", "max_gap")})
        self._sync = common.synchronizer(geo.names, common.tolerance_ns(self.get_parameter("sync_tolerance").value),
                                         mode, gap)
        self._health = ArrayHealth(geo.names, self._sync, self._limits, common.now_ns(self))
        self._buffer = SetBuffer(int(self.get_parameter("max_samples").value), geo.size, channels=len(inputs.channels))
        window_ns = self._watch.window_ns
        self._mission = MissionWindow(2 * window_ns, window_ns // int(self.get_parameter("max_samples").value),
                                      geo.size, len(inputs.channels))
        self._generation += 1
        self._subs = [
            self.create_subscription(
                MagneticField, topics.raw(n), self._raw_callback(i), self._raw_qos
            )
            for i, n in enumerate(geo.names)
        ]
        self._currents = LatestCurrents(len(inputs.channels), inputs.tolerance_ns, check=side.CURRENT.check)
        self._current_health = CurrentHealth(inputs.channels, tuple(self.resolve_topic_name(t) for t in inputs.topics),
                                             inputs.tolerance_ns)
        clock = common.clock_reader(self)
        self._receipt_clock = clock
        self._arrival = common.arrival_reader(self)
        self._subs += common.subscribe_currents(self, inputs, self._currents, self._raw_qos, lambda: clock())
        self._connect_temperature_and_imu(geo, clock)

    def _connect_temperature_and_imu(self, geo: ArrayGeometry, clock: Any) -> None:
        """Subscribe ``<name>/temperature`` and the IMU; their values are collected with the sets once heard."""
        from sensor_msgs.msg import Imu

        temp_tol = common.temperature_tolerance_ns(self.get_parameter("temperature_tolerance").value)
        self._temperatures = LatestValues(geo.size, temp_tol, check=side.TEMPERATURE.check)
        self._temperature_health = TemperatureHealth(
            geo.names, tuple(self.resolve_topic_name(topics.temperature(n)) for n in geo.names), temp_tol)
        self._subs += common.subscribe_temperatures(self, geo.names, self._temperatures, self._raw_qos,
                                                    lambda: clock())
        topic = self._imu_topic({})
        imu_tol = tolerance_of(float(self.get_parameter("imu_tolerance").value), "IMU")
        self._imu = LatestImu(imu_tol)
        self._imu_health = ImuHealth(("imu",), (self.resolve_topic_name(topic),), imu_tol)
        self._pending: deque[tuple[int, Any, int]] = deque()
        """Sets waiting for side-stream samples due at them: (stamp, raw values, arrival ns)."""
        self._newest_set = 0
        unknown = -1.0

        def on_imu(msg: Any) -> None:
            o, w = msg.orientation, msg.angular_velocity
            q = [o.x, o.y, o.z, o.w]
            if msg.orientation_covariance[0] == unknown or not any(q):
                q = [float("nan")] * 4
            rate = [w.x, w.y, w.z]
            if msg.angular_velocity_covariance[0] == unknown:
                rate = [float("nan")] * 3
            with self._lock:
                self._imu.add(common.stamp_ns(msg.header.stamp) or clock(), q, rate, msg.header.frame_id)
                self._flush_pending(force=False)

        self._subs.append(self.create_subscription(Imu, topic, on_imu, self._raw_qos))

    def _flush_pending(self, force: bool) -> None:
        """Collect the sets nothing is due for any more (all of them with ``force``): the IMU's sample after
        them arrived (or they waited its tolerance), and no current or temperature stamped at or before them
        is on its way (or they waited :data:`~magcal_ros.core.side_streams.MAX_WAIT`); each with its side
        streams' values then. A set without a fresh value of every side stream heard is not collected. Lock
        held."""
        imu, pending = self._imu, self._pending
        now = self._receipt_clock()
        while pending:
            stamp, values, arrival = pending[0]
            waited = now - arrival
            if not force and imu.received and not imu.ready(stamp, self._newest_set, waited):
                break
            if not force and waited <= side.MAX_WAIT and self._side_due(stamp):
                break
            pending.popleft()
            self._collect(stamp, values)

    def _side_due(self, stamp: int) -> bool:
        """Whether a current or temperature stamped at or before ``stamp`` (ns) is due and has not come."""
        return bool((self._inputs.channels and self._currents.due(stamp))
                    or (any(self._temperatures.received) and self._temperatures.due(stamp)))

    def _collect(self, stamp: int, values: Any) -> None:
        """One set into the buffer with its currents, temperatures and IMU sample, when they are fresh."""
        currents: list[float] = []
        if self._inputs.channels:
            currents, fresh = self._currents.at(stamp)
            if not self._current_health.count(fresh):
                return  # a set without a fresh current of every channel is not collected
        temperatures = None
        if any(self._temperatures.received):  # once heard, every set needs them
            temperatures, fresh = self._temperatures.at(stamp)
            if not self._temperature_health.count(fresh):
                return
        if not self._imu.received:
            self._buffer.add(stamp, values, currents, temperatures)
            return
        q, w, fresh = self._imu.at(stamp)
        if self._imu_health.count([fresh]):
            self._buffer.add(stamp, values, currents, temperatures, [*q.tolist(), *w.tolist()])

    def _keep_for_mission(self, stamp: int, values: Any) -> None:
        """One set into the mission window with its currents and, once heard, its sensors' temperatures, when
        they are fresh (lock held)."""
        currents, fresh = self._currents.at(stamp) if self._inputs.channels else ([], [])
        temperatures = None
        if any(self._temperatures.received):
            temperatures, warm = self._temperatures.at(stamp)
            fresh = [*fresh, *warm]
        if all(fresh):
            self._mission.add(stamp, values, currents, temperatures)

    def _disconnect(self) -> None:
        for s in self._subs:
            self.destroy_subscription(s)
        self._subs = []

    def _raw_callback(self, index: int) -> Any:
        def callback(msg: MagneticField, info: dict[str, Any]) -> None:
            st = msg.header.stamp
            f = msg.magnetic_field
            stamp = common.stamp_ns(st)
            arrival = self._arrival(info)
            with self._lock:
                self._health.seen(index, stamp)
                for synced in self._sync.add(index, stamp, f.x, f.y, f.z, arrival):
                    if self._mission.due(synced.stamp):  # the mission's rolling window, for a recalibration at sea
                        self._keep_for_mission(synced.stamp, synced.values)
                    if not self._collecting:
                        continue
                    self._newest_set = max(self._newest_set, synced.stamp)
                    self._pending.append((synced.stamp, synced.values, self._receipt_clock()))
                self._flush_pending(force=False)

        return callback

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

    # -- recalibration during the mission -------------------------------------------
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
            if self._watch.since is None:
                return
            start = self._watch.window_start(now)
        if bool(self.get_parameter("auto_recalibrate").value):
            if not due or not self._solve_lock.acquire(blocking=False):
                return
            with self._lock:
                window = self._mission.snapshot(start)
            target, args = self._auto_recalibrate, (now, window)
        else:
            if now - start < self._watch.window_ns // 3 or (self._advice is not None and self._advice[0] == now):
                return
            with self._lock:
                window = self._mission.snapshot(start)
            target, args = self._advise, (now, window)
        self._drift_worker = threading.Thread(target=target, args=args, name="magcal-recalibrate", daemon=True)
        self._drift_worker.start()

    def _auto_recalibrate(self, now: int, window: MissionSets) -> None:
        """Fit the sets flown since the drift was named (held-out sets aside), check, push and save (worker thread)."""
        pushed = False
        with self._lock:
            health = self._watch.health  # what named the drift (a push makes the next report say otherwise)
            drifted = self._watch.sensors
            self._recalibration["attempts"] = str(int(self._recalibration["attempts"]) + 1)
        try:
            stamps, raw, currents, temperatures = window
            fit, held = recalibration.split(stamps)
            seen: dict[str, Any] = {}
            warm = None if temperatures is None else (temperatures[fit], temperatures[held])

            def check(result: CalibrationResult,
                      prior: ArrayCalibration | None) -> tuple[str | None, CalibrationResult]:
                judged = recalibration.judge(result, prior, raw[fit], raw[held], currents[fit], currents[held], drifted,
                                             seconds_fit=(stamps[fit] - stamps[0]) / 1e9, temperatures=warm)
                seen.update(verdict=judged, prior=prior)
                return judged.problem, judged.result or result

            fallback = self._running_intensity() if self._reference()[0] is None else None
            pushed, message = self._calibrate(window.take(fit), check, fallback)
            if pushed:
                judged = seen["verdict"]
                kept = f" ({', '.join(judged.kept)} kept as running)" if judged.kept else ""
                kept += f" ({judged.scope})" if judged.scope else ""
                message = (f"recalibrated {self._target_name()} during the mission from {int(fit.sum())} sets (its "
                           f"calibration health said: {health}): "
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
        stamps, raw, currents, _ = window
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

    # -- calibrating ----------------------------------------------------------------
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
            return prior, f"the running calibration of {target}"
        path = os.path.expanduser(setting)
        prior = calfile.read(path, self._target_name().lstrip("/"))
        return prior, f"the calibration file {path}"

    def _collected(self) -> tuple[Recording, list[str]]:
        """The collected sets with their currents, temperatures and IMU (lock held)."""
        self._flush_pending(force=True)
        stamps, raw, currents, temperatures, imu = self._buffer.collected()
        return collected_recording(self._geometry.names, self._inputs.channels, stamps, raw, currents, temperatures,
                                   imu, self._imu.frame_id)

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
                collected = Recording(self._geometry.names, window.stamps, window.raw, self._inputs.channels,
                                      window.currents, window.temperatures)
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
        params.update(_channel_parameters(job.inputs, cal.channels))  # no channels: the node's earlier ones go too
        for name in cal.geometry.names:  # replace any covariance the node holds from an earlier calibration
            params[name].setdefault("covariance", list(common.UNKNOWN_COVARIANCE))
            params[name].setdefault("time_offset", 0.0)  # and any time offset
        params.update(_neutral_terms(params, cal.geometry.names))  # nor temperature terms or a rotation
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

    def _calibration_path(self) -> str:
        text = str(self.get_parameter("calibration_file").value).strip()
        return os.path.expanduser(text) if text else ""

    def _target(self) -> str:
        return str(self.get_parameter("correction_node").value).strip()

    def _target_name(self) -> str:
        """The correction node's fully qualified name (relative names in this node's namespace)."""
        return self.resolve_service_name(self._target())

    def _service_clients(self) -> tuple[Any, Any]:
        target = self._target()
        if target not in self._target_clients:
            self._target_clients[target] = (
                self.create_client(SetParametersAtomically, f"{target}/set_parameters_atomically"),
                self.create_client(GetParameters, f"{target}/get_parameters"),
            )
        return self._target_clients[target]

    def _wait(self, ready: Any, timeout: float) -> bool:
        """Wait up to ``timeout`` s for ``ready(slice)``; :class:`Stopping` if the node shuts down."""
        deadline = time.monotonic() + timeout
        while True:
            self._check_stop()
            left = deadline - time.monotonic()
            if left <= 0:
                return False
            if ready(min(left, 0.1)):
                return True

    def _call(self, client: Any, request: Any) -> Any:
        """Call a service from the worker thread; the executor thread delivers the answer."""
        timeout = float(self.get_parameter("service_timeout").value)
        if not self._wait(lambda t: client.wait_for_service(timeout_sec=t), timeout):
            raise CallFailed(
                f"the correction node is not reachable ({client.srv_name} not available after {timeout:g} s); "
                f"start it (ros2 run magcal_ros correction_node) or set correction_node"
            )
        done = threading.Event()
        future = client.call_async(request)
        future.add_done_callback(lambda _: done.set())
        if not self._wait(done.wait, timeout) or future.result() is None:
            future.cancel()
            raise CallFailed(f"{client.srv_name} did not answer within {timeout:g} s", unknown_outcome=True)
        return future.result()

    @staticmethod
    def _wanted(names: Sequence[str]) -> list[str]:
        """The correction node's parameters that make up its calibration for sensors ``names``."""
        per_sensor = [f"{n}.{s}" for n in names
                      for s in ("matrix", "offset", "covariance", "interference", "noise", *common.TEMPERATURE_SUFFIXES)]
        return ["sensor_names", "positions", *common.INTERFERENCE_PARAMETERS[:3], *common.CALIBRATION_FRAME_PARAMETERS,
                "frame_id", "calibration_intensity"] + per_sensor

    def _fetch(self, names: Sequence[str]) -> dict[str, Any]:
        """ParameterValue messages of the correction node's parameters ``names`` that are set.

        rclpy answers a request naming an unset parameter with no values at all: then each
        name is asked on its own.
        """
        _, getter = self._service_clients()
        reply = self._call(getter, GetParameters.Request(names=list(names)))
        if len(reply.values) != len(names):
            values = []
            for name in names:
                one = self._call(getter, GetParameters.Request(names=[name])).values
                values.append(one[0] if one else None)
        else:
            values = list(reply.values)
        return {n: v for n, v in zip(names, values) if v is not None and v.type != ParameterType.PARAMETER_NOT_SET}

    def _get_target_parameters(self, names: Sequence[str]) -> list[ParameterMsg]:
        """The correction node's current calibration parameters, to restore if needed."""
        found = self._fetch(self._wanted(names))
        out = [ParameterMsg(name=n, value=v) for n, v in found.items()]
        for name in common.INTERFERENCE_PARAMETERS[:3]:  # none before: none again on restore
            if name not in found:
                out.append(common.parameter_message(name, []))
        neutral = _neutral_terms({}, names)  # no temperature terms or rotation before: none again
        for name, value in common.flatten_parameters(neutral).items():
            if name not in found:
                out.append(common.parameter_message(name, value))
        return out

    def _target_values(self, names: Sequence[str]) -> dict[str, Any]:
        """The correction node's calibration parameters for ``names`` as Python values (unset ones left out)."""
        found = self._fetch(self._wanted(names) + ["uncorrected_sensors"])
        return {n: parameter_value_to_python(v) for n, v in found.items()}

    def _push(self, params: Any, raw_messages: bool = False) -> None:
        """Set the calibration on the correction node, all parameters at once."""
        setter, _ = self._service_clients()
        if raw_messages:
            msgs = list(params)
        else:
            msgs = [common.parameter_message(k, v) for k, v in common.flatten_parameters(params).items()]
        reply = self._call(setter, SetParametersAtomically.Request(parameters=msgs))
        if not reply.result.successful:
            raise CallFailed(f"{self._target_name()} rejected the calibration: {reply.result.reason}")


def _unset(param: Parameter) -> bool:
    """True for a parameter that says "not set": never given, or an empty list of any type."""
    if param.type_ == Parameter.Type.NOT_SET:
        return True
    return param.type_.name.endswith("_ARRAY") and len(param.value) == 0


def _neutral_terms(params: dict[str, Any], names: Sequence[str]) -> dict[str, Any]:
    """Zero temperature terms, no calibration temperatures and an identity output rotation where ``params``
    (nested) has none: pushed with a calibration, so terms of an earlier one never outlive it on the correction
    node."""
    out: dict[str, Any] = {}
    for name in names:
        block = dict(params.get(name) or {})
        block.setdefault("offset_per_kelvin", [0.0] * 3)
        block.setdefault("matrix_per_kelvin", [0.0] * 9)
        block.setdefault("calibration_temperatures", [])  # unknown: nor an earlier calibration's span
        out[name] = block
    if "output_rotation" not in params:
        out["output_rotation"] = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
    return out


def _channel_parameters(inputs: common.CurrentInputs, solved: Sequence[str]) -> dict[str, list[str]]:
    """The channels of a calibration with the topics and types they were read from (the correction node
    is to read the same currents; channels a calibration left unsolved are left out)."""
    keep = [inputs.channels.index(c) for c in solved]
    return {"interference_channels": list(solved), "interference_topics": [inputs.topics[j] for j in keep],
            "interference_types": [inputs.types[j] for j in keep]}


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


def _envelope_text(assessed: progress.Assessment | None) -> str:
    """The envelope of an assessment in words ('' before the first one)."""
    if assessed is None:
        return ""
    return assessed.envelope_text()


def main(args: Sequence[str] | None = None, stop: StopFlag | None = None) -> int:
    """Run the node (``ros2 run magcal_ros calibration_node`` goes through :mod:`magcal_ros.nodes.entry`)."""
    return common.run_node(lambda argv: CalibrationNode(), SingleThreadedExecutor, args, stop)


if __name__ == "__main__":
    raise SystemExit(main())
