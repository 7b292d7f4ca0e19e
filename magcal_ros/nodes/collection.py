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
from magcal_ros.methods import recalibration
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
        self._mission = MissionWindow((recalibration.REFINE_WINDOWS + 1) * window_ns,
                                      window_ns // int(self.get_parameter("max_samples").value),
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
        self._pending: deque[tuple[int, Any, int, bool]] = deque()
        """Sets waiting for side-stream samples due at them: (stamp, raw values, arrival ns, to be collected); each
        goes into the mission window too when it is due there."""
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
        """Take the sets nothing is due for any more (all of them with ``force``): the IMU's sample after
        them arrived (or they waited its tolerance), and no current or temperature stamped at or before them
        is on its way (or they waited :data:`~magcal_ros.core.side_streams.MAX_WAIT`); each with its side
        streams' values then, into the mission window and (while collecting) the buffer (:meth:`_collect`).
        Lock held."""
        imu, pending = self._imu, self._pending
        now = self._receipt_clock()
        while pending:
            stamp, values, arrival, collect = pending[0]
            waited = now - arrival
            if not force and imu.received and not imu.ready(stamp, self._newest_set, waited):
                break
            if not force and waited <= side.MAX_WAIT and self._side_due(stamp):
                break
            pending.popleft()
            self._collect(stamp, values, collect)

    def _side_due(self, stamp: int) -> bool:
        """Whether a current or temperature stamped at or before ``stamp`` (ns) is due and has not come."""
        return bool((self._inputs.channels and self._currents.due(stamp))
                    or (any(self._temperatures.received) and self._temperatures.due(stamp)))

    def _collect(self, stamp: int, values: Any, collect: bool = True) -> None:
        """One set, with its currents, temperatures and IMU sample (orientation and angular velocity) at it, into
        the mission window (when due there) and, with ``collect``, the buffer. A set without a fresh current of
        every channel, or (once heard) a fresh temperature of every sensor, goes into neither (counted while
        collecting); one without a fresh IMU sample (once heard) goes into the mission window without attitude
        and not into the buffer. Lock held."""
        currents: list[float] = []
        current_fresh: list[bool] = []
        if self._inputs.channels:
            currents, current_fresh = self._currents.at(stamp)
        temperatures, warm = None, []
        if any(self._temperatures.received):  # once heard, every set needs them
            temperatures, warm = self._temperatures.at(stamp)
        attitude, imu_fresh = None, True
        if self._imu.received:
            q, w, imu_fresh = self._imu.at(stamp)
            attitude = [*q.tolist(), *w.tolist()] if imu_fresh else None
        if all(current_fresh) and all(warm):
            self._mission.add(stamp, values, currents, temperatures, attitude)
        if not collect:
            return
        if self._inputs.channels and not self._current_health.count(current_fresh):
            return
        if temperatures is not None and not self._temperature_health.count(warm):
            return
        if not self._imu.received or self._imu_health.count([imu_fresh]):
            self._buffer.add(stamp, values, currents, temperatures, attitude)

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
                self._offer(self._sync.add(index, stamp, f.x, f.y, f.z, arrival))

        return callback

    def _offer(self, sets: list[Any]) -> None:
        """Synchronised sets into the mission's rolling window (for a recalibration at sea) and, while
        collecting, the buffer, once the side streams due at them came (:meth:`_flush_pending`). Lock held."""
        for synced in sets:
            if not self._mission.due(synced.stamp) and not self._collecting:
                continue
            self._newest_set = max(self._newest_set, synced.stamp)
            self._pending.append((synced.stamp, synced.values, self._receipt_clock(), self._collecting))
        self._flush_pending(force=False)

    def _release_quiet(self) -> None:
        """The sets completed by messages held for a sensor that fell quiet (the synchroniser decides them as at
        the end of its stream once it has been quiet for its hold, on the arrivals' clock: at the end of a
        collection no later message comes to decide them)."""
        with self._lock:
            self._offer(self._sync.release_quiet(self._receipt_clock()))

    def _collected(self) -> tuple[Recording, list[str]]:
        """The collected sets with their currents, temperatures and IMU (lock held)."""
        self._flush_pending(force=True)
        stamps, raw, currents, temperatures, imu = self._buffer.collected()
        return collected_recording(self._geometry.names, self._inputs.channels, stamps, raw, currents, temperatures,
                                   imu, self._imu.frame_id)
