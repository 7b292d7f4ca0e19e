"""Sensor streams as real drivers produce them: each sensor on its own clock, stamped on receipt.

The vehicle turns continuously: its attitude at any time ``t`` is the attitude schedule
(``attitudes[k]`` at ``start + k / rate``) interpolated along the shortest rotation
(spherical linear interpolation), so a schedule of small steps is a smooth turn (e.g.
:func:`turn`: a constant rate about one platform axis).

Sensor ``i`` samples at its own instants ``start + phase_i + n * (1 + ppm_i 1e-6) / rate_i``
(its clock ``ppm_i`` parts per million slow), reads the field at ``instant - lag_i`` (a
reading that lags its instant, e.g. a filter delay; the true ``time_offset`` of the
sensor) through its errors and noise (:meth:`~magcal_ros.sim.simulator.ArraySimulation.readings`),
and its message is stamped on receipt: ``instant + delay_i + jitter``, the jitter drawn
per message (``gaussian`` with standard deviation ``jitter``, or ``uniform`` with the same
standard deviation). A fraction ``loss`` of the messages is lost at random. The bag time of
a message (the recorder's receipt) is its undisturbed stamp plus ``bag_delay``; then:

- a glitch ``(sensor, time, shift)``: the message of that sensor nearest ``time`` (s after
  ``start``) is stamped ``shift`` seconds off;
- a restart ``(time, jump, sensors)``: from ``time`` on, the stamps of those sensors (all
  when empty) are ``jump`` seconds behind (a driver restarted with a clock that starts
  over), while bag time moves on.

Stamps are integer nanoseconds. The truth of every message: its sample instant, the
platform-frame field it read, and the true calibration with each sensor's lag as its
``time_offset`` (for ``magcal correct`` on the result).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation, Slerp

from magcal_ros.core.calibration import ArrayCalibration
from magcal_ros.core.stamps import ROS_MAX_SECONDS, seconds_to_ns
from magcal_ros.core.units import NS_PER_S
from magcal_ros.errors import InputError
from magcal_ros.sim.attitudes import _about
from magcal_ros.sim.simulator import ArraySimulation
from magcal_ros.sim.spec import MAX_MESSAGES

Array = NDArray[np.float64]
JitterKind = Literal["gaussian", "uniform"]


MAX_CLOCK_PPM: float = 1e5
"""Largest sensor clock error (ppm): a clock 10 % off is not a clock error any more."""
MAX_SECONDS_OFF: float = 1e6
"""Largest magnitude (s, 11.6 days) of a phase, receipt delay or jitter, lag, glitch time or shift,
restart time or jump."""


def _text(values: Array) -> str:
    """Per-sensor values as the option gives them: one number when they are all equal."""
    return f"{values[0]:g}" if np.all(values == values[0]) else ",".join(f"{v:g}" for v in values)


def _check_stamps(name: str, stamps: NDArray[np.int64], cause: str) -> None:
    """Refuse stamps (ns) of sensor ``name`` that a ROS stamp cannot hold, naming their ``cause``."""
    if len(stamps) and (stamps.min() <= 0 or stamps.max() > ROS_MAX_SECONDS * NS_PER_S + NS_PER_S - 1):
        worst = int(stamps.min() if stamps.min() <= 0 else stamps.max())
        raise InputError(f"{cause} puts a stamp of {name} at {worst / NS_PER_S:.10g} s: a ROS stamp holds 0 .. "
                         f"{ROS_MAX_SECONDS} s (builtin_interfaces/Time.sec is int32)")


def sample_instants(phase: float, period: float, lag: float, duration: float) -> Array:
    """A sensor's sample instants after the start (s): from ``phase`` every ``period`` within
    ``duration``, those whose reading (``lag`` earlier) is of a time after the start."""
    n = int(np.floor((duration - phase) / period))
    rel = phase + np.arange(max(n, 0)) * period
    return rel[rel - lag >= 0.0]  # a reading of the field before the attitudes start: none


@dataclass(frozen=True)
class StreamSpec:
    """How each sensor samples and is stamped (seconds, Hz, ppm; a number applies to every sensor,
    a tuple gives one value per sensor)."""

    rate: float | tuple[float, ...] = 100.0
    """Sample rate (Hz)."""
    phases: float | tuple[float, ...] = 0.0
    """First sample instant after ``start`` (s): 0, 0.0025, 0.005, 0.0075 for sensors 2.5 ms apart."""
    delay: float | tuple[float, ...] = 0.0
    """Mean receipt delay (s) added to each stamp."""
    jitter: float = 0.0
    """Standard deviation of the receipt jitter (s)."""
    jitter_kind: JitterKind = "gaussian"
    clock_ppm: float | tuple[float, ...] = 0.0
    """Sensor clock error (parts per million; positive: the sensor samples slower)."""
    loss: float = 0.0
    """Fraction of the messages lost at random."""
    lags: float | tuple[float, ...] = 0.0
    """Lag of each reading behind its sample instant (s): the sensor's true time offset."""
    glitches: tuple[tuple[int, float, float], ...] = ()
    """(sensor index, time after start s, shift s): one message stamped that far off."""
    restarts: tuple[tuple[float, float, tuple[int, ...]], ...] = ()
    """(time after start s, jump back s, sensor indices or () for all)."""
    bag_delay: float = 0.0002
    """Recorder receipt delay (s) after the undisturbed stamp: the bag time."""

    def check(self, names: tuple[str, ...], duration: float) -> None:
        """Raise :class:`InputError` for values no stream of ``names`` over ``duration`` s can use (the
        options of ``magcal simulate`` named), or that leave a sensor without messages (which and why)."""
        size = len(names)
        if not (0.0 <= self.loss < 1.0):  # False for NaN
            raise InputError(f"--loss must be a fraction in [0, 1), got {self.loss:g}")
        if not (0.0 <= self.jitter <= MAX_SECONDS_OFF) or self.jitter_kind not in ("gaussian", "uniform"):
            raise InputError(f"--receipt-jitter must be a standard deviation of 0 .. {MAX_SECONDS_OFF:g} s "
                             f"(gaussian or uniform), got {self.jitter:g}")
        rates = self.per_sensor(self.rate, size, "--sensor-rate")
        if not np.all((rates > 0) & (rates <= NS_PER_S)):
            raise InputError(f"--sensor-rate must be positive, at most {NS_PER_S:.0e} Hz (a sample period of at least "
                             f"1 ns), got {_text(rates)}")
        ppm = self.per_sensor(self.clock_ppm, size, "--clock-ppm")
        if not np.all(np.abs(ppm) <= MAX_CLOCK_PPM):
            raise InputError(f"--clock-ppm must be within +-{MAX_CLOCK_PPM:g} ppm (a clock off by more is not a clock "
                             f"error), got {_text(ppm)}")
        phases = self.per_sensor(self.phases, size, "--phases")
        lags = self.per_sensor(self.lags, size, "--lags")
        for option, values in (("--phases", phases), ("--receipt-delay", self.per_sensor(self.delay, size, "--receipt-delay")),
                               ("--lags", lags)):
            if not np.all(np.abs(values) <= MAX_SECONDS_OFF):
                raise InputError(f"{option} must be finite seconds within +-{MAX_SECONDS_OFF:g}, got {_text(values)}")
        self._check_events(size)
        if not (0.0 < duration < np.inf):
            raise InputError(f"the streams last {duration:g} s (the attitudes' span less the largest lead of --lags): "
                             "no sensor has messages")
        self._check_messages(names, duration, rates, ppm, phases, lags)

    def _check_events(self, size: int) -> None:
        """Raise :class:`InputError` for a glitch or restart off any time scale or naming no sensor of ``size``."""
        for option, events in (("--glitch TIME,SHIFT", [(w, x, (k,)) for k, w, x in self.glitches]),
                               ("--restart TIME,JUMP", self.restarts)):
            for when, shift, which in events:
                if not (abs(when) <= MAX_SECONDS_OFF and abs(shift) <= MAX_SECONDS_OFF):
                    raise InputError(f"{option} must be finite seconds within +-{MAX_SECONDS_OFF:g}, got "
                                     f"{when:g},{shift:g}")
                if not all(0 <= k < size for k in which):
                    raise InputError(f"{option}: a sensor index must be 0 .. {size - 1}, got {which}")

    @staticmethod
    def _check_messages(names: tuple[str, ...], duration: float, rates: Array, ppm: Array, phases: Array,
                        lags: Array) -> None:
        """Raise :class:`InputError` for a sensor that would sample too often or not at all over ``duration`` s."""
        for i, name in enumerate(names):
            period = (1.0 + ppm[i] * 1e-6) / rates[i]
            samples = (duration - phases[i]) / period
            if samples > MAX_MESSAGES:
                raise InputError(f"{name} would sample {samples:.3g} times (--sensor-rate {rates[i]:g} Hz from --phases "
                                 f"{phases[i]:g} s over {duration:g} s): more messages than magcal simulates, at most "
                                 f"{MAX_MESSAGES}")
            if len(sample_instants(phases[i], period, lags[i], duration)):
                continue
            if phases[i] >= duration:
                why = f"its first sample (--phases {phases[i]:g} s) is after the {duration:g} s of the streams"
            elif samples < 1:
                why = (f"it samples every {period:g} s (--sensor-rate {rates[i]:g} Hz, --clock-ppm {ppm[i]:g}), longer "
                       f"than the {duration - phases[i]:g} s it records")
            else:
                why = f"its readings lag their instants by {lags[i]:g} s (--lags), beyond the {duration:g} s of the streams"
            raise InputError(f"{name} has no messages: {why}")

    def per_sensor(self, value: float | tuple[float, ...], sensors: int, what: str) -> Array:
        """``value`` for each of ``sensors`` sensors (:class:`InputError` for a tuple of another length)."""
        v = np.atleast_1d(np.asarray(value, dtype=float))
        if v.size == 1:
            return np.full(sensors, float(v[0]))
        if v.size != sensors:
            raise InputError(f"{what} needs 1 or {sensors} values, got {v.size}")
        return v


@dataclass(frozen=True)
class SensorStream:
    """One sensor's messages in the order it sent them."""

    name: str
    stamps: NDArray[np.int64]
    """Header stamps (ns)."""
    vectors: Array
    """Raw readings (n, 3) T."""
    receipts: NDArray[np.int64]
    """Bag times (ns): when the recorder received each message."""
    instants: NDArray[np.int64]
    """True sample instants (ns)."""
    field: Array
    """True platform-frame field (n, 3) T each reading saw (at its instant minus the lag)."""

    def __len__(self) -> int:
        return len(self.stamps)


@dataclass(frozen=True)
class StreamRecording:
    """Every sensor's stream, with the true calibration (lags as ``time_offsets``)."""

    streams: tuple[SensorStream, ...]
    calibration: ArrayCalibration
    attitude: Slerp = field(repr=False)
    """Platform-to-world attitude as a function of time (s since the epoch of the stamps)."""

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(s.name for s in self.streams)

    def messages(self) -> list[tuple[int, int, int]]:
        """(bag time ns, sensor index, message index) of every message, in bag time order (how a
        recorder or a live node receives them)."""
        events = [(int(t), k, i) for k, s in enumerate(self.streams) for i, t in enumerate(s.receipts.tolist())]
        events.sort()
        return events


def turn(rate_rad_s: float, duration: float, axis: str = "y", steps_per_second: float = 200.0,
         start_deg: float = 0.0) -> tuple[Array, float]:
    """A constant-rate turn about a platform ``axis``: (attitudes (N, 3, 3), their rate in Hz) for
    :func:`simulate_streams`. About ``y`` with the default NED field the whole field turns
    (dB/dt = rate x F: 0.2 rad/s in 51500 nT is 10300 nT/s)."""
    n = int(np.ceil(duration * steps_per_second)) + 2
    angles = np.radians(start_deg) + rate_rad_s * np.arange(n) / steps_per_second
    return _about(axis, angles), steps_per_second


def simulate_streams(
    sim: ArraySimulation,
    attitudes: ArrayLike,
    attitude_rate: float,
    spec: StreamSpec,
    duration: float,
    rng: np.random.Generator | int | None = None,
    start: float = 1_700_000_000.0,
) -> StreamRecording:
    """Per-sensor streams of ``sim``'s array turning through ``attitudes`` (at ``attitude_rate`` Hz from
    ``start``, s) for ``duration`` seconds (see the module docstring)."""
    gen = np.random.default_rng(rng)
    rot = np.asarray(attitudes, dtype=float).reshape(-1, 3, 3)
    if len(rot) < 2 or attitude_rate <= 0:
        raise InputError("need at least two attitudes and a positive attitude rate")
    names = sim.geometry.names
    size = len(names)
    spec.check(names, duration)
    times = np.arange(len(rot)) / attitude_rate  # relative to start
    slerp = Slerp(times, Rotation.from_matrix(rot))
    rates = spec.per_sensor(spec.rate, size, "rate")
    phases = spec.per_sensor(spec.phases, size, "phases")
    delays = spec.per_sensor(spec.delay, size, "delay")
    ppm = spec.per_sensor(spec.clock_ppm, size, "clock_ppm")
    lags = spec.per_sensor(spec.lags, size, "lags")
    start_ns = int(seconds_to_ns(start))
    streams = []
    for i, name in enumerate(names):
        period = (1.0 + ppm[i] * 1e-6) / rates[i]
        rel = sample_instants(phases[i], period, lags[i], duration)  # instants after start (s)
        reading_time = rel - lags[i]
        if rel.size and reading_time[-1] > times[-1]:
            raise InputError(f"the attitudes cover {times[-1]:.3g} s, the streams need {reading_time[-1]:.3g} s")
        b, _, _ = sim.platform_field(slerp(reading_time).as_matrix())
        truth = b[:, i]
        raw = sim.readings(i, truth, gen)
        if spec.jitter_kind == "gaussian":
            jit = gen.normal(0.0, spec.jitter, len(rel))
        else:
            half = spec.jitter * np.sqrt(3.0)
            jit = gen.uniform(-half, half, len(rel))
        instants = start_ns + np.rint(rel * NS_PER_S).astype(np.int64)
        received = instants + np.rint((delays[i] + jit) * NS_PER_S).astype(np.int64)
        _check_stamps(name, received, f"--start-time {start:.10g} s with --receipt-delay {delays[i]:g} s and "
                                      f"--receipt-jitter {spec.jitter:g} s")
        stamps = received.copy()
        for sensor, when, shift in spec.glitches:
            if sensor == i and len(rel):
                j = int(np.argmin(np.abs(rel - when)))
                stamps[j] += int(round(shift * NS_PER_S))
                _check_stamps(name, stamps[j : j + 1], f"--glitch {name},{when:g},{shift:g}")
        for when, jump, which in spec.restarts:
            if not which or i in which:
                stamps[rel >= when] -= int(round(jump * NS_PER_S))
                _check_stamps(name, stamps, f"--restart {when:g},{jump:g}")
        keep = gen.random(len(rel)) >= spec.loss
        if not keep.any():
            raise InputError(f"{name} has no messages: --loss {spec.loss:g} lost all {len(rel)} of them")
        bag = received + int(round(spec.bag_delay * NS_PER_S))
        bag = np.maximum.accumulate(bag)  # a topic arrives in order
        streams.append(SensorStream(name, stamps[keep], raw[keep], bag[keep], instants[keep], truth[keep]))
    calibration = replace(sim.true_calibration(), time_offsets=lags)
    shifted = Slerp(times + start, Rotation.from_matrix(rot))
    return StreamRecording(tuple(streams), calibration, shifted)



PHASED: tuple[float, ...] = (0.0, 0.0025, 0.005, 0.0075)
"""Four 100 Hz sensors sampled 2.5 ms apart."""
PATTERNS: dict[str, tuple[StreamSpec, float]] = {
    "synchronous": (StreamSpec(), 0.2),
    "phased + 0.5 ms jitter": (StreamSpec(phases=PHASED, delay=0.001, jitter=0.0005), 0.2),
    "synchronous + 1.5 ms jitter": (StreamSpec(delay=0.001, jitter=0.0015), 0.2),
    "clock drift 50 ppm": (StreamSpec(phases=PHASED, delay=0.001, jitter=0.0005, clock_ppm=(0.0, 50.0, -50.0, 20.0)), 0.2),
    "2 % loss": (StreamSpec(phases=PHASED, delay=0.001, jitter=0.0005, loss=0.02), 0.2),
    "glitch 2 s early + late": (StreamSpec(phases=PHASED, delay=0.001, jitter=0.0005,
                                           glitches=((1, 10.0, -2.0), (2, 16.0, 2.0))), 0.2),
    "restart of all": (StreamSpec(phases=PHASED, delay=0.001, jitter=0.0005, restarts=((15.0, 60.0, ()),)), 0.2),
    "restart of one": (StreamSpec(phases=PHASED, delay=0.001, jitter=0.0005, restarts=((15.0, 60.0, (2,)),)), 0.2),
    "5 ms lag at 1 rad/s": (StreamSpec(lags=(0.0, 0.0, 0.005, 0.0)), 1.0),
}
"""The stamp patterns of real arrays (spec, turn rate rad/s): 100 Hz sensors, 0.5 ms of receipt jitter
where there is jitter, turning about y in the default field (0.2 rad/s: ~10,000 nT/s)."""
