"""The calibration node's collection: raw streams and side streams synchronised into sets, kept for a solve
(while collecting) and in the mission's rolling window (always)."""

from __future__ import annotations

from collections import deque
from typing import Any

from sensor_msgs.msg import MagneticField

from magcal_ros.core import side_streams as side
from magcal_ros.core.geometry import ArrayGeometry
from magcal_ros.core.imu import LatestImu
from magcal_ros.core.interference import LatestCurrents, tolerance_of
from magcal_ros.core.matching import LatestValues
from magcal_ros.core.recording import Recording
from magcal_ros.io import topics
from magcal_ros.nodes import common
from magcal_ros.nodes.buffer import MissionWindow, SetBuffer, collected_recording
from magcal_ros.nodes.health import ArrayHealth, CurrentHealth, ImuHealth, TemperatureHealth


class Collection:
    """The calibration node's part that subscribes and collects (a mixin of
    :class:`~magcal_ros.nodes.calibration_node.CalibrationNode`)."""

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

    def _collected(self) -> tuple[Recording, list[str]]:
        """The collected sets with their currents, temperatures and IMU (lock held)."""
        self._flush_pending(force=True)
        stamps, raw, currents, temperatures, imu = self._buffer.collected()
        return collected_recording(self._geometry.names, self._inputs.channels, stamps, raw, currents, temperatures,
                                   imu, self._imu.frame_id)
