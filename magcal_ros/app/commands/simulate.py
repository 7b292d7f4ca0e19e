"""``magcal simulate``: a synthetic recording (sets, or per-sensor streams) and its ground truth."""

from __future__ import annotations

import argparse
from typing import Any

import numpy as np

from magcal_ros.app.commands.common import _numbers, _sensors, _subcommand, add_common_options
from magcal_ros.core.units import NT
from magcal_ros.errors import InputError
from magcal_ros.io import topics
from magcal_ros.io.recordings import is_csv


EPILOG_SIMULATE = """examples:
  magcal simulate rotation_bag                       # 1000 random attitudes, sqlite3 bag
  magcal simulate rotation.mcap_bag --storage mcap --schedule li2018
  magcal simulate rotation.csv --count 2000 --noise 2e-9 --seed 7
  magcal simulate survey_bag --schedule single-axis --axis z --count 360 \\
      --dipole 3,1,0.5,20,0,50 --position 0,0,0   # same --seed: same sensors as rotation_bag

output files (OUT without a trailing slash):
  OUT              the raw recording: rosbag2 directory with /<name>/raw
                   (sensor_msgs/MagneticField, T, frame_id = sensor name, bag time =
                   header stamp), or CSV (stamp,mag1.x,...) when OUT ends in .csv
  OUT.truth.yaml   the true calibration as a calibration file (magcal_correction block,
                   usable with 'magcal correct --calibration') plus a magcal_simulation
                   block with all parameters and each sensor's true errors
  OUT.truth.npz    per set, platform frame: stamps (N,) s, field (N,S,3) T at each sensor,
                   centre (N,3) T, gradient (N,3,3) T/m with G[i,j] = dB_j/dx_i,
                   attitudes (N,3,3) platform to world, names, positions (S,3) m, earth (3,) T

Sensor errors are drawn from --seed and the spreads only: two recordings with the same
--seed share the same sensors (calibrate one, correct the other). World frame NED.
thrusters: --thruster X,Y,Z,MX,MY,MZ (platform frame: position m, dipole moment per ampere
A m^2/A; repeatable) adds a platform-fixed field proportional to its current; thruster j is
channel thrusterj/battery: a sensor_msgs/msg/BatteryState topic /thrusterj/battery in a bag
(current in A, header stamp = the set's), a column current.thrusterj/battery in CSV. The
truth files add the true interference (interference_channels, <name>.interference, T/A)
and the currents per set (OUT.truth.npz: currents (N,m) A, channels (m,)). E.g.
  magcal simulate rotation_bag --count 1500 --thruster=-0.7,0.25,0.1,0.06,0,0.04 \\
      --thruster=-0.7,-0.25,0.1,0,-0.06,0.04 --thruster-current random:20
  magcal simulate steps_bag --count 480 --still --thruster=-0.7,0.25,0.1,0.06,0,0.04 \\
      --thruster=-0.7,-0.25,0.1,0,-0.06,0.04 --thruster-current steps:0,5,10,20 --step-sets 30
sensor streams (rosbag2 only): each sensor samples on its own clock and is stamped on receipt;
the schedule's attitudes at --rate become a continuous turn. Four 100 Hz sensors 2.5 ms apart
with 0.5 ms of receipt jitter, turning at 0.2 rad/s about y (2 pi 100 / 0.2 = 3142 steps):
  magcal simulate streams_bag --schedule single-axis --axis y --count 3142 --rate 100 \\
      --phases 0,0.0025,0.005,0.0075 --receipt-jitter 0.0005
  ... --lags 0,0,0.005,0          # mag3 reads 5 ms late (its time_offset in the truth YAML)
  ... --restart 15,60,mag3        # mag3's driver restarts 15 s in, its stamps 60 s behind
  ... --glitch mag2,10,2 --clock-ppm 0,50,-50,20 --loss 0.02
The truth NPZ then holds per sensor stamps_<name>, instants_<name> (true sample instants,
ns), receipts_<name> (bag times) and field_<name> (N, 3) T.
temperature: --temperatures 5,15,25 (steps), --temperature-ramp 5,25 (warming) or --thermocline
25,4,2 (dives) give each set a temperature; --tempco-offset (T/K) and --tempco-gain (1/K) draw
per sensor and axis how offset and gain follow it about --temperature-reference. A bag gets
/<name>/temperature (sensor_msgs/msg/Temperature, deg C), a CSV temperature.<name> columns; the
truth YAML the exact temperature terms, the truth NPZ the true temperatures (N,S). E.g.
  magcal simulate warm.csv --schedule tumble --count 1500 --temperatures 5,15,25 \\
      --tempco-offset 0.5e-9 --tempco-gain 30e-6
IMU: --imu adds the vehicle's IMU mounted --imu-mounting ROLL,PITCH,YAW deg off the array
(orientation IMU frame -> world ENU; the gyro for schedules flown in time: single-axis, sea,
tumble), with --imu-orientation-noise, --imu-gyro-noise, --imu-gyro-bias, --imu-rate (a bag's
/imu at the IMU's own rate); --world-gradient XX,XY,XZ,YY,YZ (T/m, NED) a site that is not
uniform. The truth NPZ adds imu_orientation, imu_angular_velocity, output_rotation (the
mounting) and world_gradient. E.g.
  magcal simulate imu_bag --schedule sea --pitch 5 --roll 5 --imu --imu-mounting 2,-1.5,3 \\
      --imu-rate 100 --world-gradient 30e-9,0,0,-15e-9,0
schedules: single-axis (one turn about --axis, --count steps), li2018 (Li et al. 2018: 12^3
grid of 30 deg steps, 1728 sets), coaxial2022 (the 2022 coaxial array calibration paper: x
every 60 deg, y every 90, z every 60, 144 sets), three-axes (a turn about each axis,
--count in total), random (--count uniform attitudes), sea (what a vehicle flies: --turns
yaw circles while pitch and roll swing +-PITCH and +-ROLL deg, plus --wobble; in time
order), tumble (a smooth hand-held tumble through all attitudes, in time order)."""


def _schedule_arg(text: str) -> str:
    """``--schedule`` value: a schedule name (a first-release alias is resolved to today's name)."""
    from magcal_ros.sim.spec import schedule_name

    try:
        return schedule_name(text)
    except InputError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def add_parser(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    """Add ``magcal simulate`` to the subcommands ``sub``."""
    from magcal_ros.sim.spec import SCHEDULE_NAMES, SimulationSpec

    d = SimulationSpec()
    p = _subcommand(
        sub, "simulate", "write a synthetic rotation recording with ground truth",
        "Simulate an array of three-axis magnetometers on a turning platform in the Earth's field (plus "
        "optional dipoles) with known sensor errors, hull iron and noise; write the raw recording and the truth "
        "beside it. The array: the 0.4 m four-sensor cross by default, --sensors N on a circle of --baseline, or "
        "any layout with --positions.",
        EPILOG_SIMULATE,
    )
    p.add_argument("output", metavar="OUT", help="rosbag2 directory to create, or a .csv file")
    g = p.add_argument_group("attitudes")
    g.add_argument("--schedule", default=d.schedule, type=_schedule_arg,
                   metavar="{" + ",".join(SCHEDULE_NAMES) + "}", help=f"rotation schedule (default {d.schedule})")
    g.add_argument("--count", type=int, default=d.count, help=f"attitudes for single-axis/three-axes/random (default {d.count})")
    g.add_argument("--axis", default=d.axis, choices=["x", "y", "z"], help="rotation axis of single-axis (default z)")
    g.add_argument("--pitch", type=float, default=d.pitch, metavar="DEG",
                   help=f"sea: pitch swings +-DEG while turning (default {d.pitch:g})")
    g.add_argument("--roll", type=float, default=d.roll, metavar="DEG",
                   help=f"sea: roll swings +-DEG while turning (default {d.roll:g})")
    g.add_argument("--wobble", type=float, default=d.wobble, metavar="DEG",
                   help="sea: smooth random wobble on top, e.g. waves or a hand (default 0)")
    g.add_argument("--turns", type=float, default=d.turns, help=f"sea: full yaw turns (default {d.turns:g})")
    g.add_argument("--rate", type=float, default=d.rate, metavar="HZ", help=f"sets per second (default {d.rate:g})")
    g.add_argument("--start-time", type=float, default=d.start_time, metavar="SECONDS",
                   help=f"stamp of the first set (default {d.start_time:.0f})")
    g = p.add_argument_group("field (world frame NED)")
    g.add_argument("--intensity", type=float, default=d.intensity, metavar="TESLA", help=f"total intensity F (default {d.intensity:g} T)")
    g.add_argument("--inclination", type=float, default=d.inclination, metavar="DEG", help=f"default {d.inclination:g} deg")
    g.add_argument("--declination", type=float, default=d.declination, metavar="DEG", help=f"default {d.declination:g} deg")
    g.add_argument("--dipole", action="append", metavar="X,Y,Z,MX,MY,MZ",
                   help="a point dipole: world position (m) and moment (A m^2); repeat for more")
    g.add_argument("--position", default="0,0,0", metavar="X,Y,Z", help="array centre in the world frame (m, default 0,0,0)")
    g = p.add_argument_group("thrusters (current interference, platform frame)")
    g.add_argument("--thruster", action="append", metavar="X,Y,Z,MX,MY,MZ",
                   help="a thruster: platform position (m) and dipole moment per ampere (A m^2 / A); repeat for more. "
                   "Thruster j's current is channel thrusterj/battery (bag topic /thrusterj/battery, BatteryState; "
                   "CSV column current.thrusterj/battery)")
    g.add_argument("--thruster-current", default=d.thruster_current, metavar="random:IMAX|steps:L1,L2,...",
                   help="current schedule (A): random:20 draws 0..20 A per thruster and set; steps:0,5,10,20 holds "
                   "each level --step-sets sets, thrusters stepping one after the other (odometer order) "
                   f"(default {d.thruster_current})")
    g.add_argument("--step-sets", type=int, default=d.step_sets, metavar="K",
                   help=f"sets each level of steps: is held (default {d.step_sets})")
    g.add_argument("--still", action="store_true",
                   help="the vehicle does not move: every set takes the schedule's first attitude (a stepped-thruster run)")
    g = p.add_argument_group("temperature (the sensors' offsets and gains follow it)")
    g.add_argument("--temperatures", metavar="T1,T2,...",
                   help="temperature steps (deg C): the sets in equal consecutive blocks, e.g. 5,15,25")
    g.add_argument("--temperature-ramp", metavar="T0,T1",
                   help="a warming (or cooling) from T0 to T1 deg C over the recording (exponential, levelling off)")
    g.add_argument("--thermocline", metavar="SURFACE,DEEP[,DIVES]",
                   help="a glider's dives through a sharp thermocline: SURFACE and DEEP deg C, DIVES dives (default 1)")
    g.add_argument("--temperature-reference", type=float, default=d.temperature_reference, metavar="DEG_C",
                   help=f"temperature at which the sensors have their drawn errors (default {d.temperature_reference:g})")
    g.add_argument("--tempco-offset", type=float, default=d.tempco_offset, metavar="TESLA_PER_K",
                   help="spread (1-sigma) of each sensor axis' offset change per kelvin, e.g. 0.5e-9 (default 0)")
    g.add_argument("--tempco-gain", type=float, default=d.tempco_gain, metavar="PER_K",
                   help="spread (1-sigma) of each sensor axis' gain change per kelvin, e.g. 30e-6 (default 0)")
    g.add_argument("--temperature-noise", type=float, default=d.temperature_noise, metavar="K",
                   help="noise (1-sigma) of the recorded temperatures (default 0)")
    g = p.add_argument_group("IMU and site")
    g.add_argument("--imu", action="store_true",
                   help="simulate the vehicle's IMU: orientation (IMU frame -> ENU) and, for schedules flown in time "
                   "(single-axis, sea, tumble, --still), the gyro; bag topic /imu (sensor_msgs/msg/Imu), CSV columns "
                   "imu.qx..imu.qw, imu.wx..imu.wz")
    g.add_argument("--imu-mounting", default="0,0,0", metavar="ROLL,PITCH,YAW",
                   help="the IMU's mounting (deg): the rotation Rz(yaw) Ry(pitch) Rx(roll) from the array frame to "
                   "the IMU frame (default 0,0,0)")
    g.add_argument("--imu-orientation-noise", type=float, default=d.imu_orientation_noise, metavar="DEG",
                   help="noise (1-sigma per axis) of the measured orientation (default 0)")
    g.add_argument("--imu-gyro-noise", type=float, default=d.imu_gyro_noise, metavar="RAD_PER_S",
                   help="white noise (1-sigma per axis) of the gyro (default 0)")
    g.add_argument("--imu-gyro-bias", default="0,0,0", metavar="WX,WY,WZ",
                   help="constant bias of the gyro (rad/s, IMU frame; default 0,0,0)")
    g.add_argument("--imu-rate", type=float, default=d.imu_rate, metavar="HZ",
                   help="the IMU's own rate in a bag (its clock offset from the sets'; default 0: one sample at each "
                   "set's stamp)")
    g.add_argument("--imu-frame-id", default=d.imu_frame_id, help=f"the IMU's frame (default {d.imu_frame_id})")
    g.add_argument("--imu-array-lag", type=float, default=d.imu_array_lag, metavar="S",
                   help="how late the array's stamps are on the IMU's clock (s; magnetometer drivers that stamp on "
                   "receipt), for schedules flown in time; the calibration fits it (default 0)")
    g.add_argument("--world-gradient", metavar="XX,XY,XZ,YY,YZ",
                   help="a constant gradient over the array (T/m, world frame NED, symmetric and traceless: 5 "
                   "numbers, or all 9 row-major), e.g. 30e-9,0,0,-15e-9,0")
    g = p.add_argument_group("sensor errors (1-sigma spreads, drawn per sensor from --seed)")
    g.add_argument("--scale-sd", type=float, default=d.scale_sd, help=f"scale factor spread (default {d.scale_sd:g})")
    g.add_argument("--angle-sd", type=float, default=d.angle_sd, metavar="DEG", help=f"non-orthogonality (default {d.angle_sd:g} deg)")
    g.add_argument("--offset-sd", type=float, default=d.offset_sd, metavar="TESLA", help=f"offset (default {d.offset_sd:g} T)")
    g.add_argument("--misalignment-sd", type=float, default=d.misalignment_sd, metavar="DEG",
                   help=f"sensor-to-platform misalignment (default {d.misalignment_sd:g} deg)")
    g.add_argument("--hard-iron-sd", type=float, default=d.hard_iron_sd, metavar="TESLA", help="hull hard iron (default 0 T)")
    g.add_argument("--soft-iron-sd", type=float, default=d.soft_iron_sd, help="hull soft iron matrix entries (default 0)")
    g.add_argument("--noise", type=float, default=d.noise, metavar="TESLA", help=f"noise per axis, 1-sigma (default {d.noise:g} T)")
    g.add_argument("--noise-kind", default=d.noise_kind, choices=["gaussian", "uniform"], help="noise distribution")
    g.add_argument("--noise-domain", default=d.noise_domain, choices=["raw", "sensor"],
                   help="add noise to the reading (raw) or before scale and non-orthogonality (sensor, Li et al. (2018))")
    g = p.add_argument_group(
        "sensor streams (rosbag2 output; any of these simulates each sensor on its own clock, stamped on receipt: "
        "the schedule's attitudes at --rate become a continuous turn; N or N,N,... per sensor)")
    g.add_argument("--sensor-rate", metavar="HZ[,HZ...]", help="sample rate of each sensor (default --rate)")
    g.add_argument("--phases", metavar="S[,S...]",
                   help="first sample instant of each sensor after the start, s (e.g. 0,0.0025,0.005,0.0075)")
    g.add_argument("--receipt-delay", metavar="S[,S...]", help="mean delay of each sensor's stamps after its sample (s)")
    g.add_argument("--receipt-jitter", type=float, metavar="S", help="standard deviation of the stamps' jitter (s)")
    g.add_argument("--jitter-kind", choices=["gaussian", "uniform"], help="distribution of the jitter (default gaussian)")
    g.add_argument("--clock-ppm", metavar="PPM[,PPM...]", help="each sensor's clock error (ppm; positive samples slower)")
    g.add_argument("--loss", type=float, metavar="FRACTION", help="fraction of messages lost at random")
    g.add_argument("--lags", metavar="S[,S...]",
                   help="each sensor's reading lags its sample instant by this (s): its true time_offset (truth YAML)")
    g.add_argument("--glitch", action="append", metavar="NAME,TIME,SHIFT",
                   help="the message of NAME nearest TIME (s after the start) stamped SHIFT s off; repeatable")
    g.add_argument("--restart", action="append", metavar="TIME,JUMP[,NAME...]",
                   help="from TIME (s after the start) the stamps of NAME... (default every sensor) are JUMP s behind "
                   "(a driver restarted), bag time moving on; repeatable")
    g = p.add_argument_group("output")
    g.add_argument("--storage", default="sqlite3", choices=["sqlite3", "mcap"], help="rosbag2 storage (default sqlite3)")
    g.add_argument("--seed", type=int, default=d.seed, help="random seed of errors, attitudes and noise (default 0)")
    g = p.add_argument_group("array (platform frame, m)")
    g.add_argument("--sensors", type=int, default=None, metavar="N",
                   help="number of sensors: one at the centre (no gradient), two on a line along x (the gradient "
                   "along it), three or more equally spaced on a circle of --baseline from +x (four: the cross; "
                   f"default {d.sensors})")
    g.add_argument("--positions", metavar="X,Y,Z,...",
                   help="any layout instead: 3 numbers per sensor (m, platform frame), e.g. 0,0,0,0.5,0,0 for two "
                   "sensors 0.5 m apart; the names are mag1, mag2, ...")
    g.add_argument("--baseline", type=float, default=d.baseline, metavar="METRES",
                   help=f"diameter of the circle of --sensors: the cross's baseline d (default {d.baseline:g} m)")
    add_common_options(p)
    p.set_defaults(func=cmd_simulate)


def cmd_simulate(args: argparse.Namespace) -> int:
    """Write a synthetic rotation recording and its ground truth."""
    from magcal_ros.io.truth_file import write_simulation
    from magcal_ros.sim import spec as synthetic

    dipoles = tuple(_numbers(d, 6, "--dipole") for d in (args.dipole or []))
    thrusters = tuple(_numbers(d, 6, "--thruster") for d in (args.thruster or []))
    spec = synthetic.SimulationSpec(
        schedule=args.schedule, count=args.count, axis=args.axis, pitch=args.pitch, roll=args.roll,
        wobble=args.wobble, turns=args.turns, intensity=args.intensity,
        inclination=args.inclination, declination=args.declination, scale_sd=args.scale_sd,
        angle_sd=args.angle_sd, offset_sd=args.offset_sd, misalignment_sd=args.misalignment_sd,
        hard_iron_sd=args.hard_iron_sd, soft_iron_sd=args.soft_iron_sd, noise=args.noise,
        noise_kind=args.noise_kind, noise_domain=args.noise_domain, dipoles=dipoles,
        position=_numbers(args.position, 3, "--position"),  # type: ignore[arg-type]
        rate=args.rate, start_time=args.start_time, seed=args.seed, baseline=args.baseline,
        **_simulated_array(args),
        thrusters=thrusters, thruster_current=args.thruster_current, step_sets=args.step_sets, still=args.still,
        **_simulate_temperature_and_imu(args),
    )
    if not is_csv(args.output):
        from magcal_ros.io.bag_writer import check_bag_output

        check_bag_output(args.output)
    streams = _stream_spec(args, spec.names)
    if streams is not None:
        return _simulate_streams(args, spec, streams)
    truth, ypath, npath = write_simulation(args.output, spec, args.storage)
    kind = "CSV" if is_csv(args.output) else f"rosbag2 ({args.storage})"
    print(
        f"wrote {args.output}: {kind}, {len(truth.centre)} sets x {_sensors(len(spec.names))} at {spec.rate:g} Hz "
        f"(schedule {spec.schedule}, F {spec.intensity / NT:.1f} nT, noise {spec.noise / NT:g} nT, "
        f"{len(spec.dipoles)} dipoles{', still' if spec.still else ''})"
    )
    profile = spec.temperature_profile()
    if profile is not None:
        temps = truth.temperatures
        where = ("/<name>/temperature (Temperature)" if not is_csv(args.output) else "temperature.<name> columns")
        print(f"  temperature {profile[0]} {','.join(f'{v:g}' for v in profile[1])}: {temps.min():.1f} .. "  # type: ignore[union-attr]
              f"{temps.max():.1f} deg C on {where}; tempco spreads {spec.tempco_offset / NT:g} nT/K, "  # type: ignore[union-attr]
              f"{spec.tempco_gain * 1e6:g} ppm/K about {spec.temperature_reference:g} deg C")
    if spec.imu:
        gyro = "orientation and gyro" if spec.continuous else "orientation only (the schedule is not flown in time)"
        where = f"/imu (Imu, {f'{spec.imu_rate:g} Hz' if spec.imu_rate else 'at each set'})" if not is_csv(args.output) \
            else "imu.* columns"
        print(f"  IMU {spec.imu_frame_id}: {gyro} on {where}; mounted roll,pitch,yaw "
              f"{','.join(f'{v:g}' for v in spec.imu_mounting)} deg off the array")
    if spec.world_gradient:
        print(f"  world gradient (NED, nT/m): {np.round(spec.world_gradient_matrix() / NT, 3).reshape(-1).tolist()}")  # type: ignore[operator]
    if spec.thrusters:
        print(f"  {len(spec.thrusters)} thrusters ({spec.thruster_current} A): currents on "
              + (", ".join(topics.current_topic(c) for c in spec.channels) + " (BatteryState)" if not is_csv(args.output)
                 else ", ".join(f"current.{c}" for c in spec.channels)))
    print(f"  truth {ypath} and {npath}")
    return 0


def _simulated_array(args: argparse.Namespace) -> dict[str, Any]:
    """The simulation spec's array fields from --sensors and --positions (checked by the spec)."""
    if args.positions is None:
        return {} if args.sensors is None else {"sensors": args.sensors}
    try:
        values = tuple(float(v) for v in args.positions.replace(",", " ").split())
    except ValueError:
        raise InputError(f"--positions must be numbers (m), 3 per sensor, got {args.positions!r}") from None
    if not values or len(values) % 3:
        raise InputError(f"--positions must be 3 numbers per sensor (x,y,z in m), got {len(values)}")
    if args.sensors not in (None, len(values) // 3):
        raise InputError(f"--sensors {args.sensors} but --positions gives {_sensors(len(values) // 3)}: give one of them")
    return {"positions": values, "sensors": len(values) // 3}


STREAM_OPTIONS: tuple[str, ...] = ("sensor_rate", "phases", "receipt_delay", "receipt_jitter", "jitter_kind",
                                   "clock_ppm", "loss", "lags", "glitch", "restart")


def _per_sensor(text: str | None, option: str, count: int) -> float | tuple[float, ...]:
    """``N`` or ``N,N,...`` (one per sensor) of a stream option; 0 when not given."""
    if text is None:
        return 0.0
    try:
        values = tuple(float(v) for v in text.replace(",", " ").split())
    except ValueError:
        raise InputError(f"{option} must be a number or {count} numbers separated by commas, got {text!r}") from None
    if len(values) not in (1, count) or not np.all(np.isfinite(values)):
        raise InputError(f"{option} must be a number or {count} finite numbers separated by commas, got {text!r}")
    return values[0] if len(values) == 1 else values


def _stream_spec(args: argparse.Namespace, names: tuple[str, ...]) -> Any:
    """The sensor-stream settings of ``magcal simulate``, or None when none is given."""
    if all(getattr(args, o) is None for o in STREAM_OPTIONS):
        return None
    from magcal_ros.sim.streams import StreamSpec

    glitches = []
    for text in args.glitch or []:
        parts = [v.strip() for v in text.split(",")]
        if len(parts) != 3 or parts[0] not in names:
            raise InputError(f"--glitch must be NAME,TIME,SHIFT with NAME one of {', '.join(names)}, got {text!r}")
        time_, shift = _numbers(",".join(parts[1:]), 2, "--glitch TIME,SHIFT")
        glitches.append((names.index(parts[0]), time_, shift))
    restarts = []
    for text in args.restart or []:
        parts = [v.strip() for v in text.split(",")]
        which = parts[2:]
        if len(parts) < 2 or any(n not in names for n in which):
            raise InputError(f"--restart must be TIME,JUMP[,NAME...] with names among {', '.join(names)}, got {text!r}")
        time_, jump = _numbers(",".join(parts[:2]), 2, "--restart TIME,JUMP")
        restarts.append((time_, jump, tuple(names.index(n) for n in which)))
    rate = _per_sensor(args.sensor_rate, "--sensor-rate", len(names)) if args.sensor_rate else args.rate
    spec = StreamSpec(
        rate=rate, phases=_per_sensor(args.phases, "--phases", len(names)),
        delay=_per_sensor(args.receipt_delay, "--receipt-delay", len(names)),
        jitter=args.receipt_jitter or 0.0, jitter_kind=args.jitter_kind or "gaussian",
        clock_ppm=_per_sensor(args.clock_ppm, "--clock-ppm", len(names)), loss=args.loss or 0.0,
        lags=_per_sensor(args.lags, "--lags", len(names)), glitches=tuple(glitches), restarts=tuple(restarts),
    )
    return spec  # checked where it is used (StreamSpec.check, with the names and duration)


def _simulate_streams(args: argparse.Namespace, spec: Any, streams: Any) -> int:
    """``magcal simulate`` with sensor-stream options: the bag of per-sensor streams and its truth."""
    from magcal_ros.io.truth_file import write_stream_simulation

    rec, ypath, npath = write_stream_simulation(args.output, spec, streams, args.storage)
    counts = ", ".join(f"{s.name} {len(s)}" for s in rec.streams)
    print(f"wrote {args.output}: rosbag2 ({args.storage}), per-sensor streams over {spec.count / spec.rate:g} s "
          f"(schedule {spec.schedule} as a continuous turn): {counts} messages")
    lags = [f"{n} {t * 1e3:g} ms" for n, t in zip(rec.names, rec.calibration.time_offsets) if t]
    if lags:
        print(f"  lags (true time_offset in the truth YAML): {', '.join(lags)}")
    print(f"  truth {ypath} and {npath}")
    return 0


def _simulate_temperature_and_imu(args: argparse.Namespace) -> dict[str, Any]:
    """The simulation spec's temperature, IMU and world gradient fields from the options."""
    def numbers(text: str | None, option: str) -> tuple[float, ...]:
        if not text:
            return ()
        try:
            values = tuple(float(v) for v in text.replace(",", " ").split())
        except ValueError:
            raise InputError(f"{option} must be numbers separated by commas, got {text!r}") from None
        if not values or not np.all(np.isfinite(values)):
            raise InputError(f"{option} must be finite numbers separated by commas, got {text!r}")
        return values

    return {
        "temperatures": numbers(args.temperatures, "--temperatures"),
        "temperature_ramp": numbers(args.temperature_ramp, "--temperature-ramp"),
        "thermocline": numbers(args.thermocline, "--thermocline"),
        "temperature_reference": args.temperature_reference, "tempco_offset": args.tempco_offset,
        "tempco_gain": args.tempco_gain, "temperature_noise": args.temperature_noise,
        "imu": args.imu, "imu_mounting": _numbers(args.imu_mounting, 3, "--imu-mounting"),
        "imu_orientation_noise": args.imu_orientation_noise, "imu_gyro_noise": args.imu_gyro_noise,
        "imu_gyro_bias": _numbers(args.imu_gyro_bias, 3, "--imu-gyro-bias"), "imu_rate": args.imu_rate,
        "imu_frame_id": args.imu_frame_id, "imu_array_lag": args.imu_array_lag, "world_gradient": numbers(args.world_gradient, "--world-gradient"),
    }
