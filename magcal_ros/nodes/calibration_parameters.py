"""The calibration node's parameters: declared with descriptions, validated together, applied."""

from __future__ import annotations

import os
from typing import Any

from rcl_interfaces.msg import SetParametersResult
from rclpy.parameter import Parameter

from magcal_ros.core import sync
from magcal_ros.core.geomagnetic import SiteField, parse_date, parse_site, site_field
from magcal_ros.core.geometry import ArrayGeometry
from magcal_ros.core.imu import DEFAULT_IMU_TOLERANCE
from magcal_ros.errors import InputError
from magcal_ros.io import calibration_file as calfile
from magcal_ros.io import topics
from magcal_ros.methods.pipeline import (
    DEFAULT_METHOD,
    METHODS,
)
from magcal_ros.nodes import common

DEFAULT_CALIBRATION_FILE = "~/.ros/magcal_calibration.yaml"
PRIORS: tuple[str, ...] = ("running", "none")
RECONNECT: frozenset[str] = frozenset({"sensor_names", "positions", "max_samples", "sync_tolerance", "sync_mode",
                                       "max_gap", *common.INTERFERENCE_PARAMETERS, "temperature_tolerance",
                                       "imu_topic", "imu_tolerance"})


class CalibrationParameters:
    """The calibration node's part that declares, checks and applies its parameters (a mixin of
    :class:`~magcal_ros.nodes.calibration_node.CalibrationNode`)."""

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


def _unset(param: Parameter) -> bool:
    """True for a parameter that says "not set": never given, or an empty list of any type."""
    if param.type_ == Parameter.Type.NOT_SET:
        return True
    return param.type_.name.endswith("_ARRAY") and len(param.value) == 0
