"""The simulation behind ``magcal simulate``: everything it varies (a spec), and the run.

Sensor errors depend only on the seed and the error spreads, so two recordings made with
the same ``seed`` share the same sensors: calibrate one, correct the other.

Thrusters (``thrusters``, platform-fixed dipoles per ampere) run on a current schedule
(:func:`current_schedule`): ``random:IMAX`` draws each thruster's current uniformly in
``0..IMAX`` A (``IMAX >= 0``) at every set; ``steps:L1,L2,...`` holds levels (A) for ``step_sets`` sets
each, the thrusters stepping like an odometer (thruster 1 changes level every
``step_sets`` sets, thruster 2 every ``step_sets * L`` sets, ...) so that no two move in
lockstep. Thruster ``j`` (from 1) is channel ``thrusterj/battery``: in a bag its current is
the ``sensor_msgs/msg/BatteryState`` topic ``/thrusterj/battery``.

Temperature (:mod:`magcal_ros.sim.temperature`): a profile (``temperatures`` steps,
``temperature_ramp`` or ``thermocline``) and the sensors' tempcos, drawn per sensor and axis
from their spreads and the seed alone (the same sensors with and without them). IMU
(:mod:`magcal_ros.sim.imu`): ``imu`` with its mounting (roll, pitch, yaw in deg: the rotation
``Rz(yaw) Ry(pitch) Rx(roll)`` from the array frame to the IMU frame), noise, bias and rate; a
gyro only for schedules flown in time (:data:`~magcal_ros.sim.attitudes.CONTINUOUS_SCHEDULES`).
``world_gradient``: a constant gradient over the array in the world frame (NED).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from magcal_ros.core.field import Dipole, earth_field
from magcal_ros.core.geometry import ArrayGeometry, default_names
from magcal_ros.core.recording import Recording
from magcal_ros.core.stamps import ROS_MAX_SECONDS
from magcal_ros.core.units import MAX_READING, NS_PER_S, NT
from magcal_ros.errors import InputError
from magcal_ros.sim import attitudes
from magcal_ros.sim.imu import DEFAULT_IMU_FRAME_ID, ImuModel
from magcal_ros.sim.simulator import (
    ArraySimulation,
    Thruster,
    Truth,
    random_sensor_errors,
)
from magcal_ros.sim.temperature import draw_tempcos, temperature_profile

SCHEDULE_NAMES: tuple[str, ...] = ("single-axis", "li2018", "coaxial2022", "three-axes", "random", "sea", "tumble")
SCHEDULE_ALIASES: dict[str, str] = {"paper000": "li2018", "paper004": "coaxial2022"}
"""Schedule names of the first release, still accepted."""
CURRENT_SCHEDULES: tuple[str, ...] = ("random", "steps")
MAX_MESSAGES: int = 10_000_000
"""Most messages ``magcal simulate`` writes per sensor (sets, one sensor's stream, the IMU's): 10
million sets take about 6 GB of memory and of bag."""
MAX_SENSORS: int = 64
"""Most sensors ``magcal simulate`` puts in one array."""
MAX_ARM: float = 100.0
"""Largest distance (m) of a simulated sensor from the platform's origin along any axis."""
NOISE_SIGMAS: float = 6.0
"""Standard deviations of noise on each axis a simulated reading may carry and stay within
:data:`~magcal_ros.core.units.MAX_READING` (a Gaussian draw beyond 6 sigma: 2e-9)."""


def schedule_name(name: str) -> str:
    """The schedule called ``name`` (an alias resolved); :class:`InputError` when there is none."""
    name = SCHEDULE_ALIASES.get(name, name)
    if name not in SCHEDULE_NAMES:
        raise InputError(f"unknown schedule {name!r}; choose one of {', '.join(SCHEDULE_NAMES)}")
    return name


def thruster_channel(index: int) -> str:
    """Channel name of thruster ``index`` (from 1): ``thruster<index>/battery``."""
    return f"thruster{index}/battery"


def current_schedule(text: str, count: int, thrusters: int, step_sets: int, rng: np.random.Generator) -> np.ndarray:
    """(count, thrusters) currents in A from ``random:IMAX`` or ``steps:L1,L2,...`` (module docstring)."""
    kind, _, values = text.partition(":")
    try:
        numbers = [float(v) for v in values.split(",") if v.strip()]
    except ValueError:
        numbers = []
    if kind not in CURRENT_SCHEDULES or not numbers or not np.all(np.isfinite(numbers)) or \
            (kind == "random" and (len(numbers) != 1 or numbers[0] < 0)):
        raise InputError(f"--thruster-current must be random:IMAX (IMAX >= 0) or steps:L1,L2,... (finite amperes), "
                         f"got {text!r}")
    if kind == "random":
        return rng.uniform(0.0, numbers[0], (count, thrusters))
    if step_sets < 1:
        raise InputError("--step-sets must be at least 1")
    levels = np.asarray(numbers)
    k = np.arange(count)
    return np.stack([levels[(k // (step_sets * len(levels) ** j)) % len(levels)] for j in range(thrusters)], axis=1)


@dataclass(frozen=True)
class SimulationSpec:
    """Everything ``magcal simulate`` varies (SI units, angles in degrees)."""

    schedule: str = "random"
    count: int = 1000
    axis: str = "z"
    pitch: float = 5.0
    """Sea manoeuvre: pitch swing +- (deg)."""
    roll: float = 2.0
    """Sea manoeuvre: roll swing +- (deg)."""
    wobble: float = 0.0
    """Sea manoeuvre: smooth random wobble on top (deg)."""
    turns: float = 2.0
    """Sea manoeuvre: full yaw turns."""
    intensity: float = 5.5e-5
    inclination: float = 60.0
    declination: float = 5.0
    scale_sd: float = 0.02
    angle_sd: float = 1.0
    offset_sd: float = 200 * NT
    misalignment_sd: float = 2.0
    hard_iron_sd: float = 0.0
    soft_iron_sd: float = 0.0
    noise: float = 1.0 * NT
    noise_kind: str = "gaussian"
    noise_domain: str = "raw"
    dipoles: tuple[tuple[float, ...], ...] = ()
    """Each ``(x, y, z, mx, my, mz)``: world position (m, NED) and moment (A m^2)."""
    position: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """Array centre in the world frame (m)."""
    rate: float = 10.0
    start_time: float = 1.7e9
    seed: int = 0
    baseline: float = 0.4
    """Diameter (m) of the circle the sensors sit on when ``positions`` is not given (the cross's baseline)."""
    sensors: int = 4
    """Number of sensors when ``positions`` is not given: one at the centre, two or more equally spaced on a
    circle of diameter ``baseline`` in the platform's x-y plane from +x (four: the planar cross)."""
    positions: tuple[float, ...] = ()
    """Sensor positions (m, platform frame), 3 numbers per sensor; empty: ``sensors`` on the circle."""
    names: tuple[str, ...] = ()
    """Sensor names; empty: ``mag1``, ``mag2``, ... one per sensor."""
    thrusters: tuple[tuple[float, ...], ...] = ()
    """Each ``(x, y, z, mx, my, mz)``: platform position (m) and moment per ampere (A m^2 / A)."""
    thruster_current: str = "random:20"
    """Current schedule of the thrusters: ``random:IMAX`` or ``steps:L1,L2,...`` (A)."""
    step_sets: int = 25
    """Sets each level of ``steps:`` is held."""
    still: bool = False
    """The vehicle does not move: every set takes the schedule's first attitude."""
    # -- temperature -------------------------------------------------------------------------------
    temperatures: tuple[float, ...] = ()
    """Profile ``steps``: equal consecutive blocks of sets at these temperatures (deg C)."""
    temperature_ramp: tuple[float, ...] = ()
    """Profile ``ramp``: from T0 to T1 (deg C) over the recording."""
    thermocline: tuple[float, ...] = ()
    """Profile ``thermocline``: surface and deep temperatures (deg C) and optionally the dives."""
    temperature_reference: float = 20.0
    """Temperature (deg C) at which the sensors have their drawn errors."""
    tempco_offset: float = 0.0
    """Spread (1-sigma, T/K) of the offset tempcos, per sensor and axis."""
    tempco_gain: float = 0.0
    """Spread (1-sigma, 1/K) of the gain tempcos, per sensor and axis."""
    temperature_noise: float = 0.0
    """1-sigma (K) of the recorded temperatures' noise."""
    # -- IMU and site --------------------------------------------------------------------------------
    imu: bool = False
    """Simulate the vehicle's IMU (orientation; gyro for schedules flown in time)."""
    imu_mounting: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """Roll, pitch, yaw (deg) of the rotation array frame -> IMU frame."""
    imu_orientation_noise: float = 0.0
    """1-sigma per axis (deg) of the measured orientation."""
    imu_gyro_noise: float = 0.0
    """1-sigma per axis (rad/s) of the gyro's white noise."""
    imu_gyro_bias: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """The gyro's constant bias (rad/s, IMU frame)."""
    imu_rate: float = 0.0
    """Samples per second of the IMU's own topic in a bag (0: one at each set's stamp)."""
    imu_frame_id: str = DEFAULT_IMU_FRAME_ID
    imu_array_lag: float = 0.0
    """s the array's stamps are late on the IMU's clock (magnetometer drivers that stamp on receipt)."""
    world_gradient: tuple[float, ...] = ()
    """A constant gradient over the array (T/m, world frame NED): 5 numbers xx, xy, xz, yy, yz
    (symmetric and traceless) or all 9 row-major."""

    def __post_init__(self) -> None:
        if not self.names:
            count = len(self.positions) // 3 if self.positions else self.sensors
            object.__setattr__(self, "names", default_names(count if isinstance(count, (int, np.integer)) else 0))

    def geometry(self) -> ArrayGeometry:
        """The simulated array: ``positions`` when given, else ``sensors`` on a circle of ``baseline``."""
        if self.positions:
            return ArrayGeometry(self.names, np.asarray(self.positions, dtype=float))
        return ArrayGeometry.ring(len(self.names), self.baseline, self.names)

    def check_array(self) -> None:
        """Raise :class:`InputError` for an array no simulation can use (count, positions, names)."""
        if isinstance(self.sensors, bool) or not isinstance(self.sensors, (int, np.integer)) or \
                not 1 <= self.sensors <= MAX_SENSORS:
            raise InputError(f"--sensors must be a whole number of sensors, 1 .. {MAX_SENSORS}, got {self.sensors}")
        if not (self.baseline > 0 and np.isfinite(self.baseline)):
            raise InputError("--baseline must be positive and finite (m)")
        if self.positions:
            values = np.asarray(self.positions, dtype=float)
            if values.size % 3 or not 1 <= values.size // 3 <= MAX_SENSORS or not np.all(np.isfinite(values)):
                raise InputError(f"--positions must be finite numbers, 3 per sensor (x,y,z in m, platform frame; "
                                 f"1 .. {MAX_SENSORS} sensors), got {values.size}")
            if not np.all(np.abs(values) <= MAX_ARM):
                raise InputError(f"--positions must lie within {MAX_ARM:g} m of the platform's origin")
        self.geometry()  # names: unique, valid ROS names, one per sensor

    @property
    def channels(self) -> tuple[str, ...]:
        """Current channels of the thrusters."""
        return tuple(thruster_channel(j + 1) for j in range(len(self.thrusters)))

    def check(self) -> None:
        """Raise :class:`InputError` for values no simulation can use."""
        schedule_name(self.schedule)
        if self.axis not in ("x", "y", "z"):
            raise InputError("--axis must be x, y or z")
        if self.count < 1:
            raise InputError("--count must be at least 1")
        if isinstance(self.seed, bool) or not isinstance(self.seed, (int, np.integer)) or self.seed < 0:
            raise InputError(f"--seed must be an integer >= 0, got {self.seed}")
        if self.count > MAX_MESSAGES:
            raise InputError(f"--count {self.count} is more sets than magcal simulates: at most {MAX_MESSAGES}")
        if not (0 < self.rate <= NS_PER_S):  # False for NaN
            raise InputError(f"--rate must be a positive number of sets per second, at most {NS_PER_S:.0e} (stamps are "
                             f"integer nanoseconds: a set period of at least 1 ns), got {self.rate:g}")
        if not (0 < self.start_time <= ROS_MAX_SECONDS):  # False for NaN
            raise InputError(f"--start-time {self.start_time:g} s is not a ROS stamp: 0 < SECONDS <= {ROS_MAX_SECONDS} "
                             "(builtin_interfaces/Time.sec is int32)")
        self._check_span_and_field()
        self.check_array()
        self._check_errors_and_sources()
        self._check_temperature_and_imu()
        self.check_reach()

    def _check_span_and_field(self) -> None:
        """The recording's end a ROS stamp; the field's intensity and the manoeuvre's angles."""
        end = self.start_time + (self.count - 1) / self.rate
        if not end < ROS_MAX_SECONDS + 1:
            raise InputError(f"--count {self.count} sets at --rate {self.rate:g} Hz from --start-time {self.start_time:.10g} s "
                             f"end at {end:.4g} s, beyond a ROS stamp (at most {ROS_MAX_SECONDS} s: "
                             "builtin_interfaces/Time.sec is int32)")
        if not (0 < self.intensity < 1e-2):
            raise InputError(f"--intensity {self.intensity} T is not a magnetic field intensity in Tesla")
        for option, value in (("--inclination", self.inclination), ("--declination", self.declination),
                              ("--pitch", self.pitch), ("--roll", self.roll), ("--wobble", self.wobble),
                              ("--turns", self.turns)):
            if not np.isfinite(value):
                raise InputError(f"{option} must be a finite number ({'turns' if option == '--turns' else 'deg'}), "
                                 f"got {value}")

    def _check_errors_and_sources(self) -> None:
        """Error spreads and noise; dipoles, thrusters and their current schedule."""
        spreads = (self.scale_sd, self.angle_sd, self.offset_sd, self.misalignment_sd, self.hard_iron_sd, self.soft_iron_sd, self.noise)
        if any(not (np.isfinite(v) and v >= 0) for v in spreads):
            raise InputError("error spreads and noise must be finite and >= 0")
        for d in self.dipoles:
            if len(d) != 6 or not np.all(np.isfinite(d)):
                raise InputError("--dipole needs 6 numbers: x,y,z (m) and mx,my,mz (A m^2)")
        for d in self.thrusters:
            if len(d) != 6 or not np.all(np.isfinite(d)):
                raise InputError("--thruster needs 6 numbers: x,y,z (m) and mx,my,mz (A m^2 per A), platform frame")
        current_schedule(self.thruster_current, 1, 1, self.step_sets, np.random.default_rng(0))

    def _check_temperature_and_imu(self) -> None:
        """The temperature profile and tempcos; the IMU's options."""
        self.temperature_profile()
        draw_tempcos(np.random.default_rng(0), 1, self.tempco_offset, self.tempco_gain)
        if (self.tempco_offset or self.tempco_gain) and self.temperature_profile() is None:
            raise InputError("--tempco-offset/--tempco-gain need a temperature profile: --temperatures, "
                             "--temperature-ramp or --thermocline")
        if not (np.isfinite(self.temperature_reference) and np.isfinite(self.temperature_noise)
                and self.temperature_noise >= 0):
            raise InputError("--temperature-reference must be finite and --temperature-noise finite and >= 0")
        if not self.imu and (any(self.imu_mounting) or self.imu_orientation_noise or self.imu_gyro_noise
                             or any(self.imu_gyro_bias) or self.imu_rate or self.imu_array_lag):
            raise InputError("the --imu-* options need --imu")
        if len(self.imu_mounting) != 3 or len(self.imu_gyro_bias) != 3:
            raise InputError("--imu-mounting needs ROLL,PITCH,YAW (deg) and --imu-gyro-bias 3 numbers (rad/s)")
        if self.imu:
            self.imu_model()
            seconds = (self.count - 1) / self.rate
            if self.imu_rate > NS_PER_S or self.imu_rate * seconds > MAX_MESSAGES:
                raise InputError(f"--imu-rate {self.imu_rate:g} Hz over the {seconds:g} s recording is more IMU messages "
                                 f"than magcal simulates: at most {MAX_MESSAGES} (and {NS_PER_S:.0e} Hz)")
            if self.imu_rate and not self.continuous:
                raise InputError("--imu-rate needs a schedule flown in time: "
                                 + ", ".join(attitudes.CONTINUOUS_SCHEDULES) + " (or --still)")

    def check_reach(self) -> None:
        """Refuse a world gradient or noise that puts readings beyond any magnetometer's range
        (:data:`~magcal_ros.core.units.MAX_READING`, the limit the tools drop readings at): the
        gradient's field over the array's arms added to the Earth's, plus :data:`NOISE_SIGMAS`
        standard deviations of the noise on each axis."""
        reach = self.intensity
        g = self.world_gradient_matrix()
        if g is not None:
            arm = float(np.max(np.linalg.norm(self.geometry().positions, axis=1)))  # from the rotation centre
            reach += float(np.linalg.norm(g, 2)) * arm
            if not reach <= MAX_READING:
                raise InputError(f"--world-gradient reaches {reach:.3g} T at a sensor {arm:g} m from the array's centre: "
                                 f"beyond a magnetometer's range ({MAX_READING:g} T)")
        worst = NOISE_SIGMAS * np.sqrt(3.0) * self.noise
        if not reach + worst <= MAX_READING:
            raise InputError(f"--noise {self.noise:g} T (1-sigma per axis) puts readings beyond a magnetometer's range "
                             f"({MAX_READING:g} T): at most {(MAX_READING - reach) / (NOISE_SIGMAS * np.sqrt(3.0)):.3g} T")

    def temperature_profile(self) -> tuple[str, tuple[float, ...]] | None:
        """The temperature profile ``(kind, values)``, None without one; :class:`InputError` for two."""
        given = [(k, v) for k, v in (("steps", self.temperatures), ("ramp", self.temperature_ramp),
                                     ("thermocline", self.thermocline)) if v]
        if len(given) > 1:
            raise InputError("give one temperature profile: --temperatures, --temperature-ramp or --thermocline")
        if given:
            temperature_profile(given[0][0], given[0][1], 1)  # checks the values
        return given[0] if given else None

    @property
    def continuous(self) -> bool:
        """The attitudes are a path flown in time (or the vehicle is still): a gyro sees them."""
        return self.still or schedule_name(self.schedule) in attitudes.CONTINUOUS_SCHEDULES

    def imu_model(self) -> ImuModel:
        """The simulated IMU of this spec."""
        roll, pitch, yaw = self.imu_mounting
        mounting = attitudes.yaw_pitch_roll(np.array([yaw]), np.array([pitch]), np.array([roll]))[0]
        return ImuModel(mounting, np.radians(self.imu_orientation_noise), self.imu_gyro_noise,
                        np.asarray(self.imu_gyro_bias, dtype=float), self.imu_rate, self.imu_frame_id,
                        self.imu_array_lag)

    def world_gradient_matrix(self) -> np.ndarray | None:
        """The world gradient (3, 3) T/m (NED), None without one."""
        g = np.asarray(self.world_gradient, dtype=float)
        if not g.size:
            return None
        if g.size == 5:
            xx, xy, xz, yy, yz = g
            g = np.array([[xx, xy, xz], [xy, yy, yz], [xz, yz, -xx - yy]])
        elif g.size != 9:
            raise InputError("--world-gradient needs 5 numbers XX,XY,XZ,YY,YZ or 9 (T/m, world frame NED)")
        g = g.reshape(3, 3)
        if not np.all(np.isfinite(g)) or np.max(np.abs(g - g.T)) > 1e-9 * np.max(np.abs(g)) or \
                abs(np.trace(g)) > 1e-9 * np.max(np.abs(g)):
            raise InputError("--world-gradient must be symmetric and traceless (T/m)")
        return g


def build(spec: SimulationSpec) -> tuple[ArraySimulation, np.ndarray]:
    """The simulated array and its attitude schedule (N, 3, 3)."""
    spec.check()
    geometry = spec.geometry()
    err_rng = np.random.default_rng([spec.seed, 0])
    sensors = tuple(
        random_sensor_errors(err_rng, spec.scale_sd, spec.angle_sd, spec.offset_sd, spec.misalignment_sd,
                             spec.hard_iron_sd, spec.soft_iron_sd)
        for _ in geometry.names
    )
    offset_tempco = gain_tempco = None
    if spec.tempco_offset or spec.tempco_gain:
        offset_tempco, gain_tempco = draw_tempcos(np.random.default_rng([spec.seed, 4]), geometry.size,
                                                  spec.tempco_offset, spec.tempco_gain)
    sim = ArraySimulation(
        geometry=geometry,
        sensors=sensors,
        earth=earth_field(spec.intensity, spec.inclination, spec.declination),
        noise=spec.noise,
        noise_kind=spec.noise_kind,  # type: ignore[arg-type]
        noise_domain=spec.noise_domain,  # type: ignore[arg-type]
        dipoles=tuple(Dipole(np.asarray(d[:3], float), np.asarray(d[3:], float)) for d in spec.dipoles),
        position=np.asarray(spec.position, dtype=float),
        thrusters=tuple(Thruster(c, np.asarray(d[:3], float), np.asarray(d[3:], float))
                        for c, d in zip(spec.channels, spec.thrusters)),
        world_gradient=spec.world_gradient_matrix(),
        temperature_reference=spec.temperature_reference,
        offset_tempco=offset_tempco,
        gain_tempco=gain_tempco,
        temperature_noise=spec.temperature_noise,
        imu=spec.imu_model() if spec.imu else None,
    )
    att_rng = np.random.default_rng([spec.seed, 1])
    if spec.schedule == "single-axis":
        rot = attitudes.single_axis(spec.axis, spec.count)
    elif spec.schedule == "sea":
        rot = attitudes.sea_manoeuvre(spec.count, spec.pitch, spec.roll, spec.turns, spec.wobble, att_rng)
    else:
        rot = attitudes.SCHEDULES[schedule_name(spec.schedule)](spec.count, att_rng)
    if spec.still:
        rot = np.repeat(rot[:1], len(rot), axis=0)
    for d in sim.dipoles:
        if np.min(np.linalg.norm(sim.position + np.einsum("nij,sj->nsi", rot, geometry.positions) - d.position, axis=-1)) < 1e-3:
            raise InputError("a dipole lies on a sensor position: move it away (--dipole x,y,z in m)")
    return sim, rot


def run(spec: SimulationSpec) -> tuple[Recording, Truth, ArraySimulation]:
    """Simulate: ``(recording, truth, simulation)``."""
    sim, rot = build(spec)
    currents = current_schedule(spec.thruster_current, len(rot), len(sim.thrusters), spec.step_sets,
                                np.random.default_rng([spec.seed, 3]))
    profile = spec.temperature_profile()
    temperatures = None if profile is None else temperature_profile(profile[0], profile[1], len(rot))
    rec, truth = sim.run(rot, np.random.default_rng([spec.seed, 2]), rate=spec.rate, start=spec.start_time,
                         currents=currents, temperatures=temperatures, continuous=spec.continuous)
    return rec, truth, sim
