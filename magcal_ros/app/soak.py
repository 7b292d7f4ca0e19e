"""A mission soak over DDS: both nodes through a long simulated mission with the faults of a real one.

The correction node starts with the true calibration (temperature terms and a payload's current
interference included), the calibration node with ``auto_recalibrate`` on. A 4-sensor cross turns
(yaw at ``YAW_RATE`` with pitch and roll wobble) while it dives through a thermocline; each sensor
samples on its own clock and its driver stamps each message on receipt (a delay plus jitter, as
:mod:`magcal_ros.sim.streams` models). On the way (times as fractions of the mission, see
:class:`SoakPlan`): one sensor's driver restarts (its stamps jump back), another sensor is silent for
minutes, a payload current is switched on (a channel of its own, varying), the hull's hard iron jumps
(:func:`~magcal_ros.sim.simulator.hard_iron_moved`): the health must name it and the calibration node
recalibrate.

The mission is generated ``chunk`` seconds at a time and published in arrival order at ``speed``
times real time; the outputs received are folded into per-block sums and forgotten, so the driver's
memory stays bounded whatever the duration. Measured against the simulator's truth: per block the
tensor RMS error over the floor ``sqrt(2) noise / baseline`` (from the simulation's noise and
geometry), the TMI error of the centre field over the noise, the node processes' RSS; every change
of the correction node's statuses on ``/diagnostics``, every recalibration pushed with its latency
from the hull change, and whether a node hung (its outputs or statuses stopped).

With an IMU (:attr:`SoakPlan.imu`, off by default) the vehicle's IMU, mounted a few degrees off the array
(:attr:`SoakPlan.imu_mounting`), publishes ``sensor_msgs/Imu`` at ``IMU_RATE``: its true orientation (IMU frame
to world ENU, as :mod:`magcal_ros.sim.imu` writes it) and angular velocity (rad/s, IMU frame), stamped on
receipt as the sensors are. The calibration node subscribes it (``imu_topic``): ``auto_recalibrate``'s mission
window keeps the IMU's attitude at each set, so a push during the mission fits the IMU's blocks again (the
``output_rotation`` among them) with the running calibration as the prior. The correction node has no IMU
input: it starts with the true calibration, whose ``output_rotation`` is the mounting (or, with
:attr:`SoakPlan.running_frame_error`, turned off it), and publishes every output in the IMU's frame (``frame_id`` ``imu_link``). Measured besides: per block the RMS per axis of
the centre field's error in the IMU frame against the truth (the mounting times the true platform-frame
field at the set's sample instant: the first sensor's, whose receipt stamps the synchroniser's sample clock
puts on its sampling grid plus the mean receipt delay) over the floor ``noise / 2`` of four sensors' mean, and
the angle of the rotation that best takes the true field onto the published one (the output frame's error).
The tensor is compared in the array frame (the published ``R G R^T`` turned back by the mounting).
"""

from __future__ import annotations

import math
import re
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from magcal_ros.core.field import earth_field
from magcal_ros.core.geometry import ArrayGeometry
from magcal_ros.core.imu import matrix_to_quat, quat_log
from magcal_ros.core.stamps import parse_seconds
from magcal_ros.core.sync import DEFAULT_LAG
from magcal_ros.core.units import NS_PER_S, NT
from magcal_ros.methods.attitude import MOUNTING_KEYS
from magcal_ros.sim.attitudes import yaw_pitch_roll
from magcal_ros.sim.imu import DEFAULT_IMU_FRAME_ID, ImuModel
from magcal_ros.sim.simulator import (
    ArraySimulation,
    Thruster,
    hard_iron_moved,
    random_sensor_errors,
)
from magcal_ros.sim.temperature import draw_tempcos, temperature_profile

Array = NDArray[np.float64]

INTENSITY = 51_500 * NT
NOISE = 1.0 * NT
BASELINE = 0.4
"""m: the cross's sensor spacing."""
YAW_RATE = 6.0
"""deg/s of the yaw turns (the demo's mission)."""
CLOCK_LAG = DEFAULT_LAG
"""s: how far the watch's mission clock (the newest published set's stamp) may run behind the streams (sets wait for
every sensor up to the synchroniser's lag): a status that names a change may read up to this much before it."""
CHANNEL = "payload/battery"
CURRENT_RATE = 10.0
"""Hz of the payload's current messages."""
CURRENT_PERIOD = 97.0
"""s: period of the payload current's variation."""
TEMPERATURE_RATE = 1.0
"""Hz of each sensor's temperature messages."""
CLOCK_PPM = (0.0, 30.0, -20.0, 10.0)
"""The sensors' clock errors (ppm)."""
RECEIPT_DELAY = 0.001
"""s: mean delay from a sample to its receipt stamp."""
RECEIPT_JITTER = 0.0005
"""s: 1-sigma jitter of the receipt stamps."""
LOSSLESS = {"raw_reliability": "reliable", "qos_depth": 10000}
"""Node parameters that deliver every message on a busy machine (reliable, deep queues)."""
CORRECTION = "/magcal_correction"
CALIBRATION = "/magcal_calibration"
MAX_EVENTS = 80
"""Status changes printed at most (the first and last halves)."""
IMU_RATE = 50.0
"""Hz of the IMU's messages (with :attr:`SoakPlan.imu`)."""
IMU_TOPIC = "imu"
"""The IMU's topic (relative, as the nodes' default ``imu_topic``)."""
IMU_PHASE = 0.37
"""Of an IMU period: where its samples fall after the first sensor's (its own clock: none on a set)."""


def field_floor() -> float:
    """Noise floor (T) per axis of the centre field, the mean of the cross's four sensors: sigma / 2."""
    return NOISE / 2.0


INCLINATION = 60.0
"""deg: the field's inclination (declination 5 deg)."""


def floor() -> float:
    """Tensor noise floor (T/m) of the cross's difference formula, from the simulation: sqrt(2) sigma / d."""
    return math.sqrt(2.0) * NOISE / BASELINE


@dataclass(frozen=True)
class SoakPlan:
    """The mission: duration (s), speed (x real time), sample rate (Hz per sensor) and when things happen
    (fractions of the duration; ``silent_for`` s)."""

    duration: float = 7200.0
    speed: float = 10.0
    rate: float = 20.0
    block: float = 600.0
    """s of mission per row of the table."""
    chunk: float = 20.0
    """s of mission generated at once."""
    restart_at: float = 0.15
    restart_jump: float = 30.0
    """s the restarted sensor's stamps jump back."""
    restart_sensor: int = 2
    silent_at: float = 0.25
    silent_for: float = 180.0
    silent_sensor: int = 3
    current_at: float = 0.40
    hull_at: float = 0.60
    dive_minutes: float = 40.0
    """Minutes of one dive and climb through the thermocline."""
    surface_c: float = 22.0
    deep_c: float = 6.0
    health_window: float = 60.0
    recalibrate_window: float = 60.0
    seed: int = 7
    hang: float = 30.0
    """s of wall time without a status of a node, or without outputs beyond the silent sensor's minutes (at
    ``speed``), that count as a hang."""
    offset_at: float | None = None
    """When set: at this fraction of the mission the soak sets ``mag2.time_offset`` on the correction node (as a
    recalibration that fitted time offsets pushes it), which restarts its set synchroniser."""
    payload_known: bool = True
    """The correction node starts knowing the payload's interference; without, it starts without (the manoeuvre
    was flown with the payload off) and watches its current (``watch_channels``): the health must name it when
    it is switched on and the calibration node learn it."""
    tempco: bool = False
    """The sensors follow their temperature and the calibration carries temperature terms (the correction
    node then takes ``<name>/temperature``); without, the temperatures are published for the calibration
    node only (it takes them always)."""
    imu: bool = False
    """The vehicle's IMU on ``IMU_TOPIC`` at ``IMU_RATE`` (see the module docstring); the outputs are then in its
    frame and the table gets the centre field's error in it."""
    imu_mounting: tuple[float, float, float] = (2.0, -1.5, 3.0)
    """deg roll, pitch, yaw of the rotation ``Rz(yaw) Ry(pitch) Rx(roll)`` from the array (platform) frame to the
    IMU frame (``v_imu = M v_array``, as ``magcal simulate --imu-mounting``)."""
    running_frame_error: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """deg roll, pitch, yaw of the rotation (as :attr:`imu_mounting`'s) by which the correction node's starting
    calibration turns the outputs beyond the mounting (with :attr:`imu`): its ``output_rotation`` is this rotation
    times the mounting, the rest true, so only a recalibration that fits the output rotation puts it right."""
    start_mounting_sigma: float = 0.1
    """mdeg: the 1-sigma of the array-to-IMU rotation the starting calibration stores (with :attr:`imu`, its
    ``imu.sigma``), as a calibration with the IMU before the mission gives it (a tumble: about 0.06 mdeg); a
    recalibration then keeps the mount (rigid) within it. 0, or a :attr:`running_frame_error`: none stored, a
    recalibration fits the rotation from its window alone."""

    def at(self, fraction: float) -> float:
        """Mission time (s) of a fraction of the duration."""
        return fraction * self.duration

    @property
    def change_at(self) -> float:
        """Fraction of the mission at which the running calibration stops fitting: the hull change, or the
        payload switched on when its interference is unknown."""
        return self.hull_at if self.payload_known else min(self.hull_at, self.current_at)


@dataclass
class Block:
    """What one block of the mission gave (sums; T, T/m)."""

    sent: int = 0
    """Sets offered: messages of the first sensor."""
    outputs: int = 0
    tensor_ss: float = 0.0
    tmi_ss: float = 0.0
    field_ss: float = 0.0
    """T^2: sum over the outputs of the squared centre-field error vector, IMU frame (with an IMU only)."""
    field_cross: Array = field(default_factory=lambda: np.zeros((3, 3)))
    """T^2: sum over the outputs of ``published truth^T`` (3, 3), IMU frame (with an IMU only)."""
    rss: dict[str, list[float]] = field(default_factory=dict)
    """MiB per process: [min, max]."""

    def tensor(self) -> float:
        """Tensor RMS error (T/m) over the six measured components."""
        return math.sqrt(self.tensor_ss / (6 * self.outputs)) if self.outputs else float("nan")

    def tmi(self) -> float:
        """RMS of |B| - F of the centre field (T)."""
        return math.sqrt(self.tmi_ss / self.outputs) if self.outputs else float("nan")

    def field_error(self) -> float:
        """RMS per axis (T) of the centre field's error in the IMU frame."""
        return math.sqrt(self.field_ss / (3 * self.outputs)) if self.outputs else float("nan")

    def frame_error(self) -> float:
        """deg: angle of the rotation ``R`` that best takes the true IMU-frame centre fields onto the published
        ones (least squares, ``published ~ R truth``: Kabsch): how far the output frame is off the IMU's."""
        if not self.outputs:
            return float("nan")
        u, _, vt = np.linalg.svd(self.field_cross)
        r = u @ np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))]) @ vt
        return math.degrees(math.acos(min(max((np.trace(r) - 1.0) / 2.0, -1.0), 1.0)))


@dataclass
class Event:
    """A status change or a push seen on /diagnostics (mission s, wall s since the start)."""

    mission: float
    wall: float
    name: str
    level: int
    message: str


@dataclass
class SoakOutcome:
    """What the soak measured."""

    plan: SoakPlan
    blocks: dict[int, Block] = field(default_factory=dict)
    events: list[Event] = field(default_factory=list)
    pushes: list[Event] = field(default_factory=list)
    named_at: float | None = None
    """Mission s at which the health first named a drift after the change (its newest set judged; the hull
    change, or the payload switched on when unknown: :attr:`SoakPlan.change_at`)."""
    current_named_at: float | None = None
    """Mission s at which the health first named the payload's current (its interference unknown)."""
    pushed_at: float | None = None
    """Mission s at which the first recalibration after the change was seen pushed."""
    after_push_ss: float = 0.0
    after_push_sets: int = 0
    before_hull_ss: float = 0.0
    before_hull_sets: int = 0
    longest_output_gap: float = 0.0
    """Wall s between two outputs received, longest."""
    longest_status_gap: dict[str, float] = field(default_factory=dict)
    hung: list[str] = field(default_factory=list)
    wall: float = 0.0
    exit_codes: dict[str, int] = field(default_factory=dict)
    counters: dict[str, str] = field(default_factory=dict)
    """The correction node's last stream status values."""

    def tensor_after_push(self) -> float:
        """Tensor RMS (T/m) of the sets a minute after the first push after the hull change on."""
        return math.sqrt(self.after_push_ss / (6 * self.after_push_sets)) if self.after_push_sets else float("nan")

    def tensor_before_hull(self) -> float:
        """Tensor RMS (T/m) of the sets before the change (:attr:`SoakPlan.change_at`: the hull change, or the
        payload switched on when unknown)."""
        return math.sqrt(self.before_hull_ss / (6 * self.before_hull_sets)) if self.before_hull_sets else float("nan")

    def rss_growth(self, process: str) -> float:
        """MiB: the largest RSS of the last block less the smallest of the second (the first warms up)."""
        rows = [b.rss[process] for _, b in sorted(self.blocks.items()) if process in b.rss]
        if len(rows) < 2:
            return float("nan")
        return rows[-1][1] - rows[min(1, len(rows) - 2)][0]


# -- the simulated mission -----------------------------------------------------------------------


class MissionSource:
    """The mission's messages, generated a stretch at a time in arrival order (see the module docstring)."""

    def __init__(self, plan: SoakPlan, start_ns: int) -> None:
        rng = np.random.default_rng(plan.seed)
        self.plan, self.start_ns, self.rng = plan, start_ns, rng
        geo = ArrayGeometry.cross(BASELINE)
        offset_tc, gain_tc = draw_tempcos(rng, geo.size, 0.5 * NT, 20e-6) if plan.tempco else (None, None)
        payload = Thruster(CHANNEL, np.array([0.0, 0.0, 0.45]), np.array([0.03, -0.02, 0.05]))
        roll, pitch, yaw = plan.imu_mounting
        self.imu = ImuModel(mounting=yaw_pitch_roll(yaw, pitch, roll)[0]) if plan.imu else None
        """The IMU (true orientation and gyro, no noise), or None."""
        self.imu_rng = np.random.default_rng([plan.seed, 1])
        """The IMU's receipt jitter: its own stream, so the sensors' readings are those of the mission without."""
        self.sim = ArraySimulation(geo, tuple(random_sensor_errors(rng) for _ in geo.names),
                                   earth_field(INTENSITY, INCLINATION, 5.0), noise=NOISE, thrusters=(payload,),
                                   offset_tempco=offset_tc, gain_tempco=gain_tc, imu=self.imu)
        self.moved = hard_iron_moved(self.sim, rng)
        self.gains = self.sim.interference()[:, :, 0]  # (S, 3) T/A
        seconds = int(plan.duration) + 2
        dives = max(plan.duration / (plan.dive_minutes * 60.0), 0.5)
        self.temperatures = temperature_profile("thermocline", (plan.surface_c, plan.deep_c, dives), seconds)
        self.current_phase = float(rng.uniform(0.0, 2.0 * np.pi))
        self.yaw0 = float(rng.uniform(0.0, 360.0))
        self.swell = rng.uniform(0.0, 2.0 * np.pi, 4)
        self.phases = np.arange(geo.size) * 0.25 / plan.rate
        self.periods = (1.0 + np.array(CLOCK_PPM) * 1e-6) / plan.rate

    @property
    def names(self) -> tuple[str, ...]:
        return self.sim.geometry.names

    def attitudes(self, t: Array) -> Array:
        """(n, 3, 3) platform-to-world rotations at mission times ``t`` (s)."""
        s = self.swell
        pitch = 3.0 * np.sin(2 * np.pi * t / 13.0 + s[0]) + 2.0 * np.sin(2 * np.pi * t / 7.1 + s[1])
        roll = 3.0 * np.sin(2 * np.pi * t / 9.0 + s[2]) + 2.0 * np.sin(2 * np.pi * t / 17.3 + s[3])
        return yaw_pitch_roll(self.yaw0 + YAW_RATE * t, pitch, roll)

    def temperature(self, t: Array) -> Array:
        """deg C of the water (and the sensors) at mission times ``t`` (s)."""
        return np.interp(t, np.arange(len(self.temperatures)), self.temperatures)

    def current(self, t: Array) -> Array:
        """A of the payload at mission times ``t`` (s): off, then on at 1-3 A, varying smoothly (period
        ``CURRENT_PERIOD``: steps every few seconds put the field's steps between the sensors' phased samples,
        which interpolation smears)."""
        on = t >= self.plan.at(self.plan.current_at)
        return np.where(on, 2.0 + np.sin(2.0 * np.pi * t / CURRENT_PERIOD + self.current_phase), 0.0)

    def platform_rates(self, t: Array, h: float = 1e-3) -> Array:
        """(n, 3) rad/s: the platform's angular velocity in the platform frame (``dR/dt = R [w]x``) at mission
        times ``t`` (s), from the attitudes ``h`` s either side (``R(t-h)^T R(t+h) = exp(2h [w]x)``, to second
        order in ``h``)."""
        before, after = self.attitudes(t - h), self.attitudes(t + h)
        return quat_log(matrix_to_quat(np.einsum("nji,njk->nik", before, after))) / (2.0 * h)

    def imu_instants(self, t0: float, t1: float) -> Array:
        """Sample instants (s) of the IMU in [t0, t1): ``IMU_RATE``, on a clock of its own (``IMU_PHASE``)."""
        phase = IMU_PHASE / IMU_RATE
        k = np.arange(max(math.ceil((t0 - phase) * IMU_RATE), 0), math.ceil((t1 - phase) * IMU_RATE))
        return phase + k / IMU_RATE

    def imu_samples(self, t: Array) -> tuple[Array, Array]:
        """The IMU at mission times ``t`` (s): orientation (n, 4) quaternions x, y, z, w IMU frame -> world ENU
        and angular velocity (n, 3) rad/s IMU frame (true values: :class:`~magcal_ros.sim.imu.ImuModel`)."""
        assert self.imu is not None
        return (self.imu.true_orientation(self.attitudes(t)),
                self.imu.true_angular_velocity(self.platform_rates(t)))

    def instants(self, i: int, t0: float, t1: float) -> Array:
        """Sample instants (s) of sensor ``i`` in [t0, t1), none while it is silent."""
        p = self.plan
        first = math.ceil((t0 - self.phases[i]) / self.periods[i])
        last = math.ceil((t1 - self.phases[i]) / self.periods[i])
        t = self.phases[i] + np.arange(max(first, 0), last) * self.periods[i]
        if i == p.silent_sensor:
            quiet = (t >= p.at(p.silent_at)) & (t < p.at(p.silent_at) + p.silent_for)
            t = t[~quiet]
        return t

    def readings(self, i: int, t: Array) -> Array:
        """(n, 3) T raw readings of sensor ``i`` at instants ``t``: its errors, temperature, the payload's
        field and noise; the moved hull's from the hull change on."""
        b, _, _ = self.sim.platform_field(self.attitudes(t))
        seen = b[:, i] + self.current(t)[:, None] * self.gains[i]
        temp = self.temperature(t)
        after = t >= self.plan.at(self.plan.hull_at)
        out = np.empty((len(t), 3))
        for sim, mask in ((self.sim, ~after), (self.moved, after)):
            if mask.any():
                out[mask] = sim.readings(i, seen[mask], self.rng, temp[mask])
        return out

    def stretch(self, t0: float, t1: float) -> tuple[Array, list[tuple[int, int, int, Any]]]:
        """The messages of [t0, t1) s in arrival order: (arrival s, [(kind, index, stamp ns, value)]) with kind
        0 a reading of sensor ``index``, 1 the current, 2 a temperature of sensor ``index``; and the
        instants (s) of the first sensor's samples (the sets offered); with an IMU kind 3, its sample (value:
        orientation and angular velocity, see :meth:`imu_samples`), stamped on receipt as the sensors are."""
        arrivals: list[Array] = []
        items: list[tuple[int, int, int, Any]] = []
        p = self.plan
        for i in range(len(self.names)):
            t = self.instants(i, t0, t1)
            received = t + RECEIPT_DELAY + self.rng.normal(0.0, RECEIPT_JITTER, len(t))
            stamps = self.start_ns + np.rint(received * NS_PER_S).astype(np.int64)
            if i == p.restart_sensor:
                stamps[t >= p.at(p.restart_at)] -= int(p.restart_jump * NS_PER_S)
            arrivals.append(np.maximum.accumulate(received + 0.0002) if len(t) else received)
            items += [(0, i, s, tuple(v)) for s, v in zip(stamps.tolist(), self.readings(i, t).tolist())]
        tc = np.arange(math.ceil(t0 * CURRENT_RATE), math.ceil(t1 * CURRENT_RATE)) / CURRENT_RATE
        arrivals.append(tc + 0.0003)
        items += [(1, 0, self.start_ns + round(s * NS_PER_S), float(a)) for s, a in zip(tc, self.current(tc))]
        for i in range(len(self.names)):
            tt = (np.arange(math.ceil(t0 * TEMPERATURE_RATE), math.ceil(t1 * TEMPERATURE_RATE)) + 0.1 * i) / \
                TEMPERATURE_RATE
            tt = tt[tt < t1]
            arrivals.append(tt + 0.0004)
            items += [(2, i, self.start_ns + round(s * NS_PER_S), float(c))
                      for s, c in zip(tt, self.temperature(tt))]
        if self.imu is not None:
            ti = self.imu_instants(t0, t1)
            received = ti + RECEIPT_DELAY + self.imu_rng.normal(0.0, RECEIPT_JITTER, len(ti))
            arrivals.append(np.maximum.accumulate(received + 0.0002) if len(ti) else received)
            q, w = self.imu_samples(ti)
            items += [(3, 0, self.start_ns + int(round(s * NS_PER_S)), (tuple(a), tuple(b)))
                      for s, a, b in zip(received.tolist(), q.tolist(), w.tolist())]
        when = np.concatenate(arrivals)
        order = np.argsort(when, kind="stable")
        return when[order], [items[k] for k in order]

    def truth_gradient(self, t: Array) -> Array:
        """(n, 3, 3) T/m true tensor at the array centre at mission times ``t`` (s), platform frame."""
        return self.sim.platform_field(self.attitudes(t))[2]

    def truth_field(self, t: Array) -> Array:
        """(n, 3) T true field at the array centre at mission times ``t`` (s), platform frame."""
        return self.sim.platform_field(self.attitudes(t))[1]

    def sample_instants(self, stamps: NDArray[np.int64]) -> Array:
        """Mission times (s) of the sets' samples (``stamps`` ns): a set is stamped at the first sensor's instant,
        its receipt stamps put on its sample clock (the sample plus about ``RECEIPT_DELAY``, within the receipt
        jitter), and that sensor samples on the grid ``k / rate`` exactly: the nearest grid instant."""
        period = self.periods[0]
        received = (stamps - self.start_ns) / NS_PER_S
        return self.phases[0] + np.rint((received - RECEIPT_DELAY - self.phases[0]) / period) * period


def write_start_calibration(source: MissionSource, path: Path) -> None:
    """Write the calibration the mission starts with to ``path``: the true one (its noise and intensity in the
    metadata), without the payload when :attr:`SoakPlan.payload_known` is off, its output rotation turned by
    :attr:`SoakPlan.running_frame_error` with an IMU."""
    from magcal_ros.io import calibration_file as calfile

    p = source.plan
    truth = source.sim.true_calibration()
    if not p.payload_known:
        truth = replace(truth, channels=(), interference=None)
    if p.imu and any(p.running_frame_error):
        roll, pitch, yaw = p.running_frame_error
        truth = replace(truth, output_rotation=yaw_pitch_roll(yaw, pitch, roll)[0] @ truth.output_rotation)
    metadata: dict[str, Any] = {"noise": [NOISE] * 4, "intensity": INTENSITY}
    if p.imu and p.start_mounting_sigma > 0 and not any(p.running_frame_error):
        sigma = p.start_mounting_sigma * 1e-3
        metadata["imu"] = {"frame_id": truth.frame_id, "sigma": {k: sigma for k in MOUNTING_KEYS}}
    calfile.write(path, replace(truth, metadata=metadata))


def output_errors(source: MissionSource, stamps: NDArray[np.int64], gradients: Array,
                  fields: Array) -> tuple[Array, Array, Array]:
    """Per output (sets stamped ``stamps`` ns, published ``gradients`` (n, 3, 3) T/m and centre ``fields``
    (n, 3) T, in the output frame): the tensor's squared error summed over its six measured components
    (T^2/m^2, array frame), ``|B| - F`` (T) and, with an IMU, the error (n, 3) T of the centre field in the
    IMU frame, published less true (zeros without)."""
    t = (stamps - source.start_ns) / NS_PER_S
    if source.imu is not None:  # R G R^T published: back into the array frame with the true mounting
        gradients = np.einsum("ji,njk,kl->nil", source.imu.mounting, gradients, source.imu.mounting)
    g = gradients - source.truth_gradient(t)
    tensor_ss = np.sum(g[:, :2, :].reshape(len(g), 6) ** 2, axis=1)
    tmi = np.linalg.norm(fields, axis=1) - INTENSITY
    if source.imu is None:
        return tensor_ss, tmi, np.zeros((len(t), 3))
    truth = source.truth_field(source.sample_instants(stamps)) @ source.imu.mounting.T
    return tensor_ss, tmi, fields - truth


def fold_outputs(blocks: dict[int, Block], block: float, t: Array, centre: Array, tensor_ss: Array, tmi: Array,
                 field_err: Array) -> None:
    """Add outputs at mission times ``t`` (s) to the ``block``-s rows of ``blocks``: their centre fields (n, 3) T
    and the errors of :func:`output_errors`."""
    keys = np.maximum((t // block).astype(int), 0)
    for k in np.unique(keys):
        b = blocks.setdefault(int(k), Block())
        m = keys == k
        b.outputs += int(m.sum())
        b.tensor_ss += float(tensor_ss[m].sum())
        b.tmi_ss += float(np.sum(tmi[m] ** 2))
        b.field_ss += float(np.sum(field_err[m] ** 2))
        b.field_cross += np.einsum("ni,nj->ij", centre[m], centre[m] - field_err[m])


# -- watching the nodes ------------------------------------------------------------------------------


def _level(status: Any) -> int:
    return int(status.level[0]) if isinstance(status.level, bytes) else int(status.level)


class Watch:
    """Every /diagnostics status of the nodes, as it arrives: changes of the correction node's statuses
    (level, or for its calibration health whether it says drifted), pushes of recalibrations, and when each
    node was last heard (wall)."""

    def __init__(self, outcome: SoakOutcome, start_ns: int) -> None:
        self.outcome, self.start_ns = outcome, start_ns
        self.lock = threading.Lock()
        self.mission = 0.0
        """Mission s of the latest message published (set by the publisher)."""
        self.wall0 = time.monotonic()
        self.heard: dict[str, float] = {}
        self.state: dict[str, tuple[int, str, str]] = {}
        self.pushes = 0

    def subscribe(self, node: Any) -> Any:
        """Subscribe ``node`` (the driver's) to /diagnostics."""
        from diagnostic_msgs.msg import DiagnosticArray

        return node.create_subscription(DiagnosticArray, "/diagnostics", self.on_array, 100)

    def on_array(self, msg: Any) -> None:
        """Take one DiagnosticArray."""
        now = time.monotonic() - self.wall0
        with self.lock:
            for status in msg.status:
                self._take(status, now)

    def _take(self, status: Any, now: float) -> None:
        node = status.name.split(":")[0]
        gap = now - self.heard.get(node, now)
        gaps = self.outcome.longest_status_gap
        gaps[node] = max(gaps.get(node, 0.0), gap)
        self.heard[node] = now
        values = {kv.key: kv.value for kv in status.values}
        if status.name == CALIBRATION + ": recalibration":
            self._recalibration(status, values, now)
        elif status.name in (CORRECTION, CORRECTION + ": calibration"):
            self._change(status, values, now)
            if status.name == CORRECTION:
                self.outcome.counters = values

    def _mission_time(self, values: dict[str, str]) -> float:
        newest = values.get("newest_stamp")
        return (parse_seconds(newest) - self.start_ns) / NS_PER_S if newest else self.mission

    def _change(self, status: Any, values: dict[str, str], now: float) -> None:
        """A new level, drift verdict or kind of message (its numbers aside) of a correction node status."""
        key = (_level(status), values.get("drifted", ""), re.sub(r"[-+]?\d[\d.]*", "#", status.message))
        t = self._mission_time(values)
        if values.get("unknown_interference") and self.outcome.current_named_at is None:
            self.outcome.current_named_at = t
        if self.state.get(status.name) == key:
            return
        self.state[status.name] = key
        if len(self.outcome.events) < 10_000:  # bounded, whatever the node says
            self.outcome.events.append(Event(t, now, status.name, key[0], status.message))
        change = self.outcome.plan.at(self.outcome.plan.change_at) - CLOCK_LAG  # (a status naming it may read early)
        if key[1] == "true" and t >= change and self.outcome.named_at is None:
            self.outcome.named_at = t

    def _recalibration(self, status: Any, values: dict[str, str], now: float) -> None:
        count = int(values.get("recalibrations", "0") or 0)
        if count <= self.pushes:
            return
        self.pushes = count
        event = Event(self.mission, now, status.name, _level(status), values.get("last_recalibration", ""))
        self.outcome.pushes.append(event)
        change = self.outcome.plan.at(self.outcome.plan.change_at)
        if self.outcome.pushed_at is None and self.mission >= change:
            self.outcome.pushed_at = self.mission


def rss_mib(pid: int) -> float | None:
    """Resident memory (MiB) of a process, None when it is gone."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        return None
    return None


def children(pid: int) -> list[int]:
    """Child process ids of ``pid`` (Linux)."""
    try:
        return [int(c) for c in Path(f"/proc/{pid}/task/{pid}/children").read_text().split()]
    except OSError:
        return []


# -- the run -------------------------------------------------------------------------------------------


class Soak:
    """Both nodes, a driver, the mission published and measured (see the module docstring)."""

    def __init__(self, plan: SoakPlan, workdir: Path, say: Callable[[str], None]) -> None:
        self.plan, self.workdir, self.say = plan, workdir, say
        self.outcome = SoakOutcome(plan)
        self.nodes: dict[str, Any] = {}
        self.driver: Any = None
        self.domain: int | None = None
        self.last_output = time.monotonic()
        self._start_ns = 0

    # setting up
    def start(self, source: MissionSource) -> None:
        """Write the true calibration, start both nodes and the driver, wait for discovery."""
        from magcal_ros.app.ros_driver import (
            ArrayDriver,
            NodeProcess,
            pick_domain_id,
            ros_args,
            ros_environment,
        )
        p = self.plan
        cal = self.workdir / "calibration.yaml"
        write_start_calibration(source, cal)
        self.domain = pick_domain_id()
        env = ros_environment(self.domain)
        correction = {**LOSSLESS, "health_window": p.health_window}
        if not p.payload_known:
            correction["watch_channels"] = [CHANNEL]
        calibration = {**LOSSLESS, "reference_field": INTENSITY, "calibration_file": str(cal),
                       "auto_recalibrate": True, "recalibrate_window": p.recalibrate_window,
                       "interference_channels": [CHANNEL]}
        if p.imu:  # the correction node has no IMU input: its outputs are in the IMU frame by output_rotation
            calibration["imu_topic"] = IMU_TOPIC
        for name, exe, params, files, ready in (
                ("correction", "correction_node", correction, [cal], "correcting"),
                ("calibration", "calibration_node", calibration, [], "listening to")):
            proc = NodeProcess(exe, ros_args(params=params, params_files=files), env, self.workdir / f"{name}.log")
            self.nodes[name] = proc
            if not proc.wait_for_log(ready, 180.0):
                raise RuntimeError(f"{exe} did not start:\n{proc.log()}")
        self.driver = ArrayDriver(source.names, self.domain, node_name="magcal_soak_driver", collect_corrected=False,
                                  currents=[(CHANNEL, "sensor_msgs/msg/BatteryState")], temperatures=True,
                                  imu_topic=IMU_TOPIC if p.imu else None)
        d = self.driver
        if not (d.wait_for_subscribers(2, 180.0) and d.wait_for_output_publishers(180.0) and self.prime(source, 180.0)):
            raise RuntimeError("the nodes were not discovered")

    def prime(self, source: MissionSource, timeout: float) -> bool:
        """Probe sets stamped as the mission's (each sensor at its phase; with a current and temperatures, which
        the node needs) until outputs come back; then forget them. The node's ``sync_mode: auto`` chooses from
        them as it would from the mission's first stamps. They are stamped now, more than a health window
        before the mission's first set."""
        from magcal_ros.app.ros_driver import RawMessage

        d = self.driver
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            stamp = time.time_ns()
            d.publish_current(0, stamp - 1_000_000, 0.0)
            for i, name in enumerate(d.names):
                d.publish_temperature(i, stamp - 1_000_000, 20.0)
                d.publish(RawMessage(name, stamp + int(source.phases[i] * NS_PER_S), (2.0e-5, 1.0e-6, 4.5e-5)))
            time.sleep(1.0 / self.plan.rate)
            with d._lock:  # the driver's own stores
                ok = bool(d.outputs.field) and bool(d.outputs.stamped)
            if ok:
                time.sleep(0.5)
                d.clear_outputs()
                return True
        return False

    def close(self) -> None:
        """Stop the driver and the nodes; their exit codes into the outcome."""
        from magcal_ros.app.ros_driver import release_domain_id

        if self.driver is not None:
            self.driver.close()
        self.outcome.exit_codes = {name: proc.stop() for name, proc in self.nodes.items()}
        if self.domain is not None:
            release_domain_id(self.domain)

    # measuring
    def sample_memory(self, mission: float) -> None:
        """RSS of each node process (and the calibration node's analysis process) into the block of ``mission`` s."""
        block = self.block(mission)
        procs = {name: proc.pid for name, proc in self.nodes.items()}
        for child in children(self.nodes["calibration"].pid)[:1]:
            procs["analysis"] = child
        for name, pid in procs.items():
            mib = rss_mib(pid)
            if mib is None:
                continue
            lo_hi = block.rss.setdefault(name, [mib, mib])
            lo_hi[0], lo_hi[1] = min(lo_hi[0], mib), max(lo_hi[1], mib)

    def block(self, mission: float) -> Block:
        """The block of mission time ``mission`` (s)."""
        return self.outcome.blocks.setdefault(max(int(mission // self.plan.block), 0), Block())

    def drain(self, source: MissionSource) -> int:
        """Fold the outputs received so far into the blocks and forget them; how many."""
        d = self.driver
        with d._lock:  # the driver's own stores, emptied as read
            stamped, fields = d.outputs.stamped, d.outputs.field
            d.outputs.stamped, d.outputs.field = {}, {}
            d.outputs.gradient.clear()
            d.outputs.latency.clear()
            d.outputs.field_covariance.clear()
        both = sorted(set(stamped) & set(fields))
        if not both:
            return 0
        self.last_output = time.monotonic()
        stamps = np.array(both, dtype=np.int64)
        t = (stamps - self.start_ns) / NS_PER_S
        centre = np.stack([fields[s] for s in both])
        tensor_ss, tmi, field_err = output_errors(source, stamps, np.stack([stamped[s] for s in both]), centre)
        fold_outputs(self.outcome.blocks, self.plan.block, t, centre, tensor_ss, tmi, field_err)
        self._segments(t, tensor_ss)
        return len(both)

    def _segments(self, t: Array, tensor_ss: Array) -> None:
        """The tensor before the hull change, and a minute after the first push after it on."""
        o, p = self.outcome, self.plan
        before = t < p.at(p.change_at)
        o.before_hull_ss += float(tensor_ss[before].sum())
        o.before_hull_sets += int(before.sum())
        if o.pushed_at is not None:
            after = t >= o.pushed_at + 60.0
            o.after_push_ss += float(tensor_ss[after].sum())
            o.after_push_sets += int(after.sum())

    # publishing
    def publish(self, source: MissionSource, watch: Watch) -> None:
        """The mission, a stretch at a time, paced at ``speed`` x real time by the messages' arrivals."""
        p, d = self.plan, self.driver
        wall0 = time.monotonic()
        shown = wall0
        t0 = 0.0
        while t0 < p.duration:
            t1 = min(t0 + p.chunk, p.duration)
            when, items = source.stretch(t0, t1)
            self.block(t0).sent += len(source.instants(0, t0, t1))
            if p.offset_at is not None and t0 <= p.at(p.offset_at) < t1:
                d.set_parameters(CORRECTION, {"mag2.time_offset": 1e-4})
            for k, (kind, index, stamp, value) in enumerate(items):
                delay = wall0 + when[k] / p.speed - time.monotonic()
                if delay > 0.002:
                    time.sleep(delay)
                if kind == 0:
                    d.publish(_raw(source.names[index], stamp, value))
                elif kind == 1:
                    d.publish_current(0, stamp, value)
                elif kind == 3:
                    d.publish_imu(stamp, value[0], value[1], DEFAULT_IMU_FRAME_ID)
                else:
                    d.publish_temperature(index, stamp, value)
                watch.mission = float(when[k])
            self.drain(source)
            self.sample_memory(t1)
            self._check_hang(t1)
            if time.monotonic() - shown >= 20.0 or t1 >= p.duration:
                shown = time.monotonic()
                self.say(self.progress(t1, shown - wall0))
            t0 = t1

    def _check_hang(self, mission: float) -> None:
        """A node that died, stopped its statuses or its outputs (beyond the silent sensor's minutes)."""
        p, o = self.plan, self.outcome
        gap = time.monotonic() - self.last_output
        o.longest_output_gap = max(o.longest_output_gap, gap)
        if gap > p.hang + p.silent_for / p.speed and "outputs" not in " ".join(o.hung):
            o.hung.append(f"no outputs for {gap:.0f} s at {mission:.0f} s of mission")
        for name, proc in self.nodes.items():
            if not proc.alive() and not any(h.startswith(name) for h in o.hung):
                o.hung.append(f"{name} node exited at {mission:.0f} s of mission")

    def progress(self, mission: float, wall: float) -> str:
        """One line: where the mission is, outputs, memory, the latest status."""
        o = self.outcome
        sent = sum(b.sent for b in o.blocks.values())
        got = sum(b.outputs for b in o.blocks.values())
        rss = self.block(mission).rss
        mem = ", ".join(f"{k} {v[1]:.0f} MiB" for k, v in rss.items())
        last = o.events[-1].message[:60] if o.events else ""
        return (f"[{wall:6.0f} s wall] mission {mission / 60:6.1f} min ({mission / max(wall, 1e-9):.1f}x): "
                f"{got}/{sent} sets out; {mem}; pushes {len(o.pushes)}; last change: {last}")

    def finish(self, source: MissionSource, settle: float = 30.0, longest: float = 300.0) -> None:
        """Wait for the outputs still in flight (until none came for ``settle`` s, at most ``longest``)."""
        deadline = time.monotonic() + longest
        quiet_since = time.monotonic()
        while time.monotonic() < deadline and time.monotonic() - quiet_since < settle:
            time.sleep(1.0)
            if self.drain(source):
                quiet_since = time.monotonic()
            self.sample_memory(self.plan.duration - 1e-6)
        for name in self.nodes:
            gap = self.outcome.longest_status_gap.get("/magcal_" + name, float("inf"))
            if gap > self.plan.hang:
                self.outcome.hung.append(f"{name} node: no status for {gap:.0f} s")

    @property
    def start_ns(self) -> int:
        return self._start_ns

    def run(self) -> SoakOutcome:
        """The whole soak; the nodes stopped at the end whatever happened."""
        t0 = time.monotonic()
        self._start_ns = time.time_ns() + int((self.plan.health_window + 5.0) * NS_PER_S)
        source = MissionSource(self.plan, self._start_ns)
        try:
            self.start(source)
            watch = Watch(self.outcome, self._start_ns)
            watch.subscribe(self.driver.node)
            self.say(f"nodes up on domain {self.domain}; mission of {self.plan.duration / 60:.0f} min at "
                     f"{self.plan.speed:g}x, {self.plan.rate:g} Hz per sensor")
            self.publish(source, watch)
            self.finish(source)
        finally:
            self.close()
        self.outcome.wall = time.monotonic() - t0
        return self.outcome


def _raw(name: str, stamp: int, vector: tuple[float, float, float]) -> Any:
    from magcal_ros.app.ros_driver import RawMessage

    return RawMessage(name, stamp, vector)


def run_soak(plan: SoakPlan, say: Callable[[str], None] = print, workdir: Path | None = None) -> SoakOutcome:
    """Run the soak of ``plan`` (node logs in ``workdir``, default a new temporary directory)."""
    work = workdir or Path(tempfile.mkdtemp(prefix="magcal_soak_"))
    return Soak(plan, work, say).run()


# -- the report ----------------------------------------------------------------------------------------


def table(outcome: SoakOutcome) -> list[str]:
    """The per-block table, the events, pushes and the verdicts as lines."""
    p = outcome.plan
    fl = floor()
    procs = sorted({k for b in outcome.blocks.values() for k in b.rss})
    imu = f" {'IMU field/floor':>15} {'IMU frame mdeg':>14}" if p.imu else ""
    head = f"{'block (min)':>12} {'sets':>7} {'out':>7} {'tensor/floor':>12} {'TMI/noise':>9}{imu}  " + \
        "  ".join(f"{k + ' MiB':>17}" for k in procs)
    lines = [head]
    for k, b in sorted(outcome.blocks.items()):
        lo, hi = k * p.block / 60, min((k + 1) * p.block, p.duration) / 60
        if lo >= p.duration / 60:
            continue
        mem = "  ".join(f"{b.rss[n][0]:8.1f}-{b.rss[n][1]:<8.1f}" if n in b.rss else f"{'':>17}" for n in procs)
        imu = f" {b.field_error() / field_floor():15.2f} {b.frame_error() * 1e3:14.2f}" if p.imu else ""
        lines.append(f"{lo:5.0f}-{hi:<6.0f} {b.sent:7d} {b.outputs:7d} {b.tensor() / fl:12.2f} "
                     f"{b.tmi() / NOISE:9.2f}{imu}  {mem}")
    lines.append(f"events (mission min): restart of mag{p.restart_sensor + 1} {p.at(p.restart_at) / 60:.1f}, "
                 f"mag{p.silent_sensor + 1} silent {p.at(p.silent_at) / 60:.1f}-"
                 f"{(p.at(p.silent_at) + p.silent_for) / 60:.1f}, payload current on {p.at(p.current_at) / 60:.1f}, "
                 f"hull change {p.at(p.hull_at) / 60:.1f}")
    if p.imu:
        lines.append(f"IMU field/floor: RMS per axis of the centre field's error in the IMU frame (mounting roll, pitch, "
                     f"yaw {', '.join(f'{a:g}' for a in p.imu_mounting)} deg) over noise / 2 = "
                     f"{field_floor() / NT:.2f} nT; IMU frame mdeg: angle of the rotation that best takes the "
                     f"true IMU-frame field onto the published one (the output frame's error; noise alone gives "
                     f"about 0.02 mdeg)")
    lines.append("status changes of the correction node (mission min, wall s, level, message):")
    shown = outcome.events if len(outcome.events) <= MAX_EVENTS else \
        outcome.events[:MAX_EVENTS // 2] + outcome.events[-MAX_EVENTS // 2:]
    lines += [f"  {e.mission / 60:7.2f} {e.wall:7.1f} {e.level} {e.name}: {e.message}" for e in shown]
    if len(shown) < len(outcome.events):
        lines.append(f"  ({len(outcome.events) - len(shown)} more changes in the middle not shown)")
    what = "hull change" if p.change_at == p.hull_at else "payload switched on (interference unknown)"
    lines.append(f"recalibrations pushed (mission min; latency from the {what}):")
    change = p.at(p.change_at)
    lines += [f"  {e.mission / 60:7.2f} latency {e.mission - change:6.0f} s: {e.message[:200]}"
              for e in outcome.pushes]
    named = f"{outcome.named_at - change:.0f} s" if outcome.named_at is not None else "never"
    if not p.payload_known:
        on = p.at(p.current_at)
        heard = f"{outcome.current_named_at - on:.0f} s" if outcome.current_named_at is not None else "never"
        lines.append(f"payload current named by the health (interference unknown) {heard} after it was switched on")
    lines.append(f"{what} named by the health after {named}; tensor before it "
                 f"{outcome.tensor_before_hull() / fl:.2f}x the floor, from a minute after the push on "
                 f"{outcome.tensor_after_push() / fl:.2f}x ({outcome.after_push_sets} sets)")
    growth = ", ".join(f"{n} {outcome.rss_growth(n):+.1f} MiB" for n in procs)
    lines.append(f"memory, last block's max less the second block's min: {growth}")
    gaps = ", ".join(f"{k} {v:.1f} s" for k, v in sorted(outcome.longest_status_gap.items()))
    lines.append(f"longest wall gaps: outputs {outcome.longest_output_gap:.1f} s; statuses {gaps}")
    lines.append(f"hung: {'; '.join(outcome.hung) if outcome.hung else 'no'}; exit codes {outcome.exit_codes}; "
                 f"wall {outcome.wall:.0f} s for {p.duration / 60:.0f} min of mission "
                 f"({p.duration / max(outcome.wall, 1e-9):.1f}x overall)")
    keys = ("sets", "published", "withheld", "unmatched", "restarts", "gap", "lost")
    lines.append("correction node counters: " + ", ".join(f"{k} {outcome.counters.get(k, '?')}" for k in keys))
    return lines
