"""The ``magcal`` command: offline calibration tools over CSV and rosbag2 recordings."""

from __future__ import annotations

import argparse
import os
import re
import signal
import sys
import threading
from collections.abc import Sequence
from pathlib import Path
from types import FrameType
from typing import TYPE_CHECKING, Any

import numpy as np

from magcal_ros.app.progress import ProgressBar
from magcal_ros.core.calibration import ArrayCalibration
from magcal_ros.core.geometry import ArrayGeometry
from magcal_ros.core.imu import DEFAULT_IMU_TOLERANCE, IMU_FRAMES
from magcal_ros.core.interference import DEFAULT_CURRENT_TOLERANCE, tolerance_of
from magcal_ros.core.recording import Recording
from magcal_ros.core.scalar_fit import LOSSES
from magcal_ros.core.set_reduction import solve_budget
from magcal_ros.core.stamps import parse_seconds
from magcal_ros.core.sync import (
    DEFAULT_MAX_GAP,
    DEFAULT_SYNC_MODE,
    DEFAULT_SYNC_TOLERANCE,
    SYNC_MODES,
    SyncStats,
    max_gap_ns,
    tolerance_ns,
)
from magcal_ros.core.temperature import DEFAULT_TEMPERATURE_TOLERANCE
from magcal_ros.core.units import EARTH_FIELD_RANGE, NT, check_tesla
from magcal_ros.errors import InputError, MagcalError, Stopped
from magcal_ros.io import calibration_file as calfile
from magcal_ros.io import topics
from magcal_ros.io.atomic import STOP_SIGNALS, recover
from magcal_ros.io.recordings import (
    CURRENTS,
    IMU_TOPIC,
    TEMPERATURES,
    SideTopics,
    is_csv,
    open_recording,
    recording_sensors,
    with_bag_side_streams,
)
from magcal_ros.methods.strategies import DEFAULT_METHOD, METHODS

if TYPE_CHECKING:
    from magcal_ros.core.geomagnetic import SiteField

UNITS_NOTE = (
    f"Readings must be in Tesla: a sensor whose median |B| is outside {EARTH_FIELD_RANGE[0]:g} .. "
    f"{EARTH_FIELD_RANGE[1]:g} T is refused."
)
EXIT_CODES = """exit codes: 0 done; 2 refused (one line on stderr, nothing written); 130, 143, 129 stopped
by SIGINT, SIGTERM, SIGHUP (the unfinished output is removed). An output is replaced only when
the new one is complete; what a killed run leaves beside it is cleaned up by the next run."""

EPILOG_CALIBRATE = """examples:
  magcal calibrate rotation.csv -o calibration.yaml --reference-field 5.15e-5
  magcal calibrate rotation_bag/ -o cal.yaml                 # relative (no reference)
  magcal calibrate rotation.csv -o cal.yaml --site 43.2,5.4 --date 2026-11-23   # F from the WMM
  magcal calibrate rotation.csv -o cal.yaml --site -33.87,151.21,-20   # 33.87 S, 20 m under water, today
  magcal calibrate rotation.csv -o cal.yaml --method linear --reference-field 6e-5
  magcal calibrate rotation_bag/ -o cal.yaml --sensors mag1,mag2,mag3,mag4 \\
      --start 1700000010 --end 1700000100 --plot calibration.png
  magcal calibrate compass.csv -o compass.yaml --reference-field 5.15e-5      # one sensor
  magcal calibrate gradiometer.csv -o g.yaml --positions 0,0,0,0.5,0,0        # two sensors
  magcal calibrate yaw_circle_bag -o new.yaml --prior old.yaml                # at sea, after a hard-iron change
  magcal calibrate rotation_bag/ -o cal.yaml --reference-field 5.15e-5 \\
      --currents /thruster1/battery,/thruster2/battery     # interference estimated jointly
  magcal calibrate steps_bag/ -o cal_thrusters.yaml --interference-only cal.yaml \\
      --currents /thruster1/battery,/thruster2/battery     # still vehicle, thrusters stepped

input: a rosbag2 directory (sqlite3 or mcap) with /<name>/raw sensor_msgs/MagneticField
topics (grouped into sets by --sync-mode: stamps that coincide within --sync-tolerance, or
the sensors interpolated at the first sensor's sample instants when they are sampled apart
or stamped on receipt), or a CSV file with header stamp,mag1.x,mag1.y,mag1.z,mag2.x,...
(seconds, Tesla, one set per row).
""" + UNITS_NOTE + """

arrays: one sensor needs no positions (no gradient); four default to the 0.4 m cross; any
other count needs --positions. Two sensors (or any collinear array) give the gradient along
their line, three or more spread in a plane or in space the full tensor. Every method works
for any count (one sensor: the method's scalar fit alone).

what is refused: a manoeuvre that leaves a quantity undetermined (the answer names it and
the rotation to fly, or use --prior), a residual beyond the noise the data show (a field
that changed or is not uniform: named), too many outliers, a reference intensity the
sensor gains cannot explain.

current interference (thrusters, pumps, payload): corrected = matrix (raw - offset)
- interference @ u, u the channels' currents (A), interference 3 x m per sensor (T/A).
Currents come from --currents bag topics (sensor_msgs/msg/BatteryState 'current' at its
header stamp, or std_msgs/msg/Float64 'data' at its bag time; each set takes each
channel's latest value at most --current-tolerance before it, other sets are dropped;
channel = topic without its leading '/'), or from CSV columns current.<channel> after the
sensor columns. They must vary during the manoeuvre, each on its own: a channel whose
current never varies or varies in lockstep with another is not solved (a warning says
so). The file gains interference_channels: [...] and <name>.interference (3 x m, T/A).

temperature and IMU: a bag's /<name>/temperature topics (sensor_msgs/msg/Temperature, deg C)
are read with the sets when the bag has them (--temperature-topics names others), the IMU
with --imu TOPIC (sensor_msgs/msg/Imu: orientation IMU frame -> world ENU, or NED with
--imu-frame ned; angular velocity rad/s; an orientation_covariance[0] of -1 means no
orientation). A CSV gives them as temperature.<name> (or one temperature) columns and
imu.qx,imu.qy,imu.qz,imu.qw / imu.wx,imu.wy,imu.wz columns after the sensor columns. Each
set takes each sensor's latest temperature within --temperature-tolerance before it, and
the IMU interpolated to its instant (sets without them are dropped, with a note).

methods:
""" + "\n".join(f"  {m.name:<11} {m.source}: {m.description}" for m in METHODS.values())

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

EPILOG_CORRECT = """examples:
  magcal correct survey_bag --calibration cal.yaml -o corrected_bag
  magcal correct survey_bag -c cal.yaml -o corrected_bag --storage mcap --copy-topics /imu,/gps/fix
  magcal correct survey_bag -c cal.yaml -o corrected_bag --copy-all
  magcal correct survey.csv -c cal.yaml -o corrected.csv
  magcal correct survey_bag -c cal.yaml -o corrected.csv     # bag in, CSV out

bag output (same topics and types as the live correction node; bag time = set stamp;
/gradient for three or more sensors, /baseline_gradient for a line of sensors, neither
for one sensor):
  /<name>/corrected  sensor_msgs/MagneticField  matrix (raw - offset), T, frame --frame-id,
                     header stamp of that sensor's raw message
  /field             sensor_msgs/MagneticField  centre field (mean of the sensors), T,
                     stamped with the set's stamp (the first sensor's)
  /gradient          std_msgs/Float64MultiArray  3x3 row-major G[i][j] = dB_j/dx_i, T/m,
                     layout dims row (size 3, stride 9), col (size 3, stride 3); written
                     right after /field of the same set
  /baseline_gradient geometry_msgs/Vector3Stamped  dB/ds along the sensors' line, T/m,
                     s from the first sensor towards the last, stamped like /field
CSV output header (gradient.* or baseline_gradient.x,y,z as above):
  stamp,<name>.x,<name>.y,<name>.z,...,field.x,field.y,field.z,
  gradient.xx,gradient.xy,gradient.xz,gradient.yx,gradient.yy,gradient.yz,
  gradient.zx,gradient.zy,gradient.zz
Sets are formed by --sync-mode (auto: from the stamps). A calibration with <name>.time_offset
(s; the sensor's reading stamped t is the field at t - time_offset) shifts that sensor's
stamps and interpolates it to the first sensor's sample instants (bag or CSV input); every
output of a set is then stamped with the set's instant.
The sensors are the calibration file's sensor_names; their /<name>/raw topics (or CSV columns)
must exist, and each needs its block in the calibration file unless listed in --uncorrected
(its raw readings are then written as they are, and /field and the gradient are withheld:
with a raw sensor in them they would be wrong by its errors).
A calibration with interference_channels subtracts their interference: give the currents
(--currents TOPIC,... for a bag, the topics named as the channels with a leading '/'; a
CSV's current.<channel> columns); sets without a current of every channel within
--current-tolerance before them are dropped and counted. E.g.
  magcal correct survey_bag -c cal.yaml -o corrected_bag --currents /thruster1/battery,/thruster2/battery
A calibration with temperature terms (temperature_reference, <name>.offset_per_kelvin,
<name>.matrix_per_kelvin) needs each sensor's temperature: a bag's /<name>/temperature
topics (sensor_msgs/msg/Temperature, deg C; --temperature-topics names others, one per sensor
or one for all) or a CSV's temperature.<name> (or temperature) columns; each set takes the
latest within --temperature-tolerance before it, other sets are dropped. A calibration with
an output frame (output_rotation, frame_id: e.g. the IMU's) writes every output in it.
""" + UNITS_NOTE


def _name_list(text: str | None) -> tuple[str, ...]:
    """Comma-separated names (an option's value) as a tuple, blanks dropped."""
    return tuple(n.strip() for n in (text or "").split(",") if n.strip())


def _sensors(count: int) -> str:
    """``1 sensor``, ``4 sensors``."""
    return f"{count} sensor" if count == 1 else f"{count} sensors"


def _note(text: str) -> None:
    """One note line on stderr (what was dropped, left out or cleaned up)."""
    print(f"  note: {text}", file=sys.stderr)


def _positions(text: str | None, names: tuple[str, ...], prior: ArrayCalibration | None = None) -> ArrayGeometry:
    """The array geometry: --positions, else the prior's, else one sensor or the default cross."""
    if text is None:
        if prior is not None and set(names) <= set(prior.geometry.names):
            idx = [prior.geometry.names.index(n) for n in names]
            return ArrayGeometry(names, prior.geometry.positions[idx])
        if len(names) == 1:
            return ArrayGeometry.single(names[0])
        if len(names) != 4:
            raise InputError(f"{len(names)} sensors in the recording: give --positions (3 numbers per sensor, m)")
        return ArrayGeometry.cross(names=names)
    try:
        values = [float(v) for v in text.replace(",", " ").split()]
    except ValueError:
        raise InputError("--positions must be numbers (m), 3 per sensor") from None
    return ArrayGeometry(names, np.asarray(values))


def _numbers(text: str, count: int, option: str) -> tuple[float, ...]:
    try:
        values = tuple(float(v) for v in text.replace(",", " ").split())
    except ValueError:
        raise InputError(f"{option} must be {count} numbers separated by commas, got {text!r}") from None
    if len(values) != count or not np.all(np.isfinite(values)):
        raise InputError(f"{option} must be {count} finite numbers separated by commas, got {text!r}")
    return values


def _progress(args: argparse.Namespace, label: str) -> ProgressBar:
    """A progress bar on stderr unless --quiet (drawn only on a terminal; the bag sets its total)."""
    return ProgressBar(None, label, enabled=False if args.quiet else None)


def add_common_options(p: argparse.ArgumentParser) -> None:
    """Options every command has."""
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar (it is only drawn on a terminal anyway)")


def add_input_options(p: argparse.ArgumentParser) -> None:
    """Options shared by commands that read a recording."""
    p.add_argument("input", help="recording: rosbag2 directory (sqlite3 or mcap) or .csv file")
    p.add_argument("--sensors", help="comma-separated sensor names, topics /<name>/raw (default: all in the recording)")
    add_window_options(p)
    p.add_argument("--positions", help="sensor positions, 3 per sensor in m (default: 0.4 m planar cross)")
    add_sync_options(p)


def _stamp(text: str) -> int:
    """An argparse type: decimal seconds to exact integer nanoseconds."""
    try:
        return parse_seconds(text)
    except InputError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _tolerance(text: str) -> float:
    """An argparse type: a synchronisation tolerance in seconds, 0 <= t < 1."""
    try:
        tolerance_ns(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc) if "tolerance" in str(exc) else f"not a number: {text!r}") from None
    return float(text)


def add_window_options(p: argparse.ArgumentParser) -> None:
    """--start/--end: a window of header stamps (decimal seconds, exact to the nanosecond)."""
    p.add_argument("--start", type=_stamp, metavar="SECONDS", help="ignore sets stamped before this time (s, header stamp)")
    p.add_argument("--end", type=_stamp, metavar="SECONDS", help="ignore sets stamped after this time (s, header stamp)")


def _max_gap(text: str) -> float:
    """An argparse type: the largest gap (s) interpolation bridges, 0 <= g < 60 (0: automatic)."""
    try:
        max_gap_ns(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    return float(text)


def add_sync_options(p: argparse.ArgumentParser) -> None:
    """Bag synchronisation options."""
    p.add_argument("--sync-mode", choices=list(SYNC_MODES), default=DEFAULT_SYNC_MODE,
                   help="how sets are formed from the sensors' messages (docs/synchronisation.md): exact (stamps "
                   "that coincide within --sync-tolerance: sensors sampled together and stamped alike), "
                   "interpolate (at each sample of the first sensor, the others interpolated between their "
                   "samples; sensors sampled apart or stamped on receipt), auto (chosen from the first stamps; "
                   f"default {DEFAULT_SYNC_MODE})")
    p.add_argument("--sync-tolerance", type=_tolerance, default=DEFAULT_SYNC_TOLERANCE, metavar="SECONDS",
                   help=f"exact matching: largest header stamp difference within a set (default {DEFAULT_SYNC_TOLERANCE} s)")
    p.add_argument("--max-gap", type=_max_gap, default=DEFAULT_MAX_GAP, metavar="SECONDS",
                   help="interpolation: a set whose neighbouring samples of a sensor are further apart is dropped "
                   "and counted (default 0: 3.5 sample periods of that sensor, i.e. two lost samples in a row "
                   "are bridged)")
    p.add_argument("--drop-nonfinite", action="store_true",
                   help="skip bag sets with NaN/inf readings instead of refusing the input")


def add_current_options(p: argparse.ArgumentParser) -> None:
    """Current interference channels of a bag (CSV recordings carry current.<channel> columns)."""
    p.add_argument("--currents", metavar="TOPIC[,TOPIC...]",
                   help="bag topics of the current interference channels, sensor_msgs/msg/BatteryState "
                   "(current, A) or std_msgs/msg/Float64 (A); channel name = topic without its leading '/' "
                   "(/thruster1/battery -> thruster1/battery). CSV: current.<channel> columns instead")
    p.add_argument("--current-tolerance", type=float, default=DEFAULT_CURRENT_TOLERANCE, metavar="SECONDS",
                   help="a set takes each channel's latest value stamped at most this long before it "
                   f"(BatteryState: header stamp, Float64: bag time); sets without one are dropped "
                   f"(default {DEFAULT_CURRENT_TOLERANCE} s)")


def add_temperature_options(p: argparse.ArgumentParser) -> None:
    """The sensors' temperatures in a bag (CSV recordings carry temperature.<name> columns)."""
    p.add_argument("--temperature-topics", metavar="TOPIC[,TOPIC...]",
                   help="bag topics of the sensors' temperatures, sensor_msgs/msg/Temperature (deg C), one per sensor "
                   "in sensor order or one for all (default: /<name>/temperature when the bag has them). CSV: "
                   "temperature.<name> columns, or one temperature column for all")
    p.add_argument("--temperature-tolerance", type=float, default=DEFAULT_TEMPERATURE_TOLERANCE, metavar="SECONDS",
                   help="a set takes each sensor's latest temperature stamped at most this long before it; sets "
                   f"without one are dropped (default {DEFAULT_TEMPERATURE_TOLERANCE:g} s: temperatures change slowly)")


def add_imu_options(p: argparse.ArgumentParser) -> None:
    """The vehicle's IMU: a bag topic (CSV recordings carry imu.* columns)."""
    p.add_argument("--imu", metavar="TOPIC",
                   help="bag topic of the vehicle's IMU, sensor_msgs/msg/Imu (orientation IMU -> world, angular "
                   "velocity rad/s); interpolated to each set's instant. CSV: imu.qx,imu.qy,imu.qz,imu.qw and "
                   "imu.wx,imu.wy,imu.wz columns instead")
    p.add_argument("--imu-tolerance", type=float, default=DEFAULT_IMU_TOLERANCE, metavar="SECONDS",
                   help="a set needs an IMU sample stamped at most this long before it (and uses one at most this "
                   f"long after it to interpolate); sets without one are dropped (default {DEFAULT_IMU_TOLERANCE:g} s)")
    p.add_argument("--imu-frame", default="enu", choices=list(IMU_FRAMES),
                   help="world frame of the IMU's orientation: enu (sensor_msgs/Imu, REP 103/145; default) or ned "
                   "(turned into ENU on reading; the IMU's own axes are kept)")


def _temperature_topics(args: argparse.Namespace) -> list[str] | None:
    """The --temperature-topics (absolute), or None; :class:`InputError` for a CSV input or a bad tolerance."""
    tolerance_of(args.temperature_tolerance, "temperature")
    found = [topics.absolute(t.strip()) for t in (args.temperature_topics or "").split(",") if t.strip()]
    if found and is_csv(args.input):
        raise InputError("--temperature-topics names bag topics; a CSV recording gives its temperatures as "
                         "temperature.<name> columns")
    return found or None


def _current_topics(args: argparse.Namespace) -> list[str]:
    """The --currents topics (absolute), or []; :class:`InputError` for a CSV input or a bad tolerance."""
    tolerance_of(args.current_tolerance)
    found = [topics.absolute(t.strip()) for t in (args.currents or "").split(",") if t.strip()]
    if found and is_csv(args.input):
        raise InputError("--currents names bag topics; a CSV recording gives its currents as current.<channel> columns")
    return found


def _with_side_streams(args: argparse.Namespace, rec: Recording, currents: bool = True,
                       temperatures: bool = True, imu: bool = True, needed: bool = False) -> Recording:
    """``rec`` with the side topics of its bag matched to its sets, read in one pass
    (:func:`~magcal_ros.io.recordings.with_bag_side_streams`): the --currents, the temperatures (the given
    topics, or /<name>/temperature when the bag has them) and the --imu, in that order, each with a note
    when sets were dropped. ``needed``: a bag without temperatures is refused. A CSV's come with its sets."""
    wanted = _current_topics(args) if currents else []
    temps = _temperature_topics(args) if temperatures else None
    if imu:
        tolerance_of(args.imu_tolerance, "IMU")
        if args.imu and is_csv(args.input):
            raise InputError("--imu names a bag topic; a CSV recording gives the IMU as imu.qx,...,imu.wz columns")
    if is_csv(args.input):
        return rec
    requests = []
    if wanted:
        requests.append(SideTopics(CURRENTS, tuple(wanted), args.current_tolerance))
    if temperatures:
        requests.append(SideTopics(TEMPERATURES, tuple(temps) if temps else None, args.temperature_tolerance))
    if imu and args.imu:
        requests.append(SideTopics(IMU_TOPIC, (args.imu,), args.imu_tolerance, args.imu_frame))
    if not requests:
        return rec

    def noted(request: SideTopics, stats: Any, matched: Recording) -> None:
        if stats is None and needed:
            raise InputError(f"{args.input}: the calibration corrects for temperature, but the bag has no "
                             f"{', '.join(topics.absolute(topics.temperature(n)) for n in matched.names)} "
                             "(sensor_msgs/msg/Temperature): name the temperature topics with --temperature-topics")
        if stats is not None and stats.note():
            _note(stats.note())

    return with_bag_side_streams(args.input, rec, requests, noted)[0]


def _report_sync(stats: SyncStats | None) -> None:
    """One note on stderr when synchronisation dropped anything or a source's stamps stepped."""
    if stats is not None and (stats.dropped() or stats.restarts):
        _note(stats.describe())


def _reference(args: argparse.Namespace) -> tuple[float | None, SiteField | None]:
    """The reference intensity F (T): --reference-field, the WMM at --site/--date, or None (relative)."""
    if args.site is None:
        if args.date is not None:
            raise InputError("--date needs --site (the date is when the magnetic model is evaluated)")
        return args.reference_field, None
    if args.reference_field is not None:
        raise InputError("give either --reference-field or --site, not both")
    from magcal_ros.core.geomagnetic import parse_date, parse_site, site_field

    given = f"--site {args.site}" + (f" --date {args.date}" if args.date is not None else "")
    try:
        values = [float(v) for v in args.site.split(",")]
    except ValueError:
        raise InputError(f"{given}: the site must be LAT,LON[,ALT_M] in deg, deg, m (e.g. 43.2,5.4,0)") from None
    try:
        site = site_field(*parse_site(values), parse_date(args.date))
    except InputError as exc:
        raise InputError(f"{given}: {exc}") from None
    return site.intensity, site


def _report_site(site: SiteField) -> None:
    """The model's field and what its own error means for the calibration."""
    print(
        f"  reference {site.describe()}: F {site.intensity / NT:.1f} nT, inclination "
        f"{site.inclination_deg:.2f} deg, declination {site.declination_deg:.2f} deg"
    )
    print(
        f"  the model's own error (~{site.intensity_error / NT:.0f} nT in F, 1-sigma; WMM/IGRF 100-200 nT) sets the "
        f"absolute scale only: a common factor (~{site.intensity_error / site.intensity:.1%}) on every corrected "
        "vector and the tensor, not the residuals"
    )


def _report_quantities(result: Any) -> None:
    """The least determined quantities (or, with a prior, what was kept), one line each."""
    ana = result.identifiability
    if result.prior:
        from magcal_ros.core.identifiability import by_sensor

        names = result.calibration.geometry.names
        print(f"  updated from this manoeuvre: {by_sensor(ana.updated(), names)}")
        print(f"  kept from the prior (this manoeuvre does not determine them better): {by_sensor(ana.kept(), names)}")
        return
    worst = sorted(ana.quantities, key=lambda q: -q.effect / max(ana.noise[0], 1e-30))[:3]
    print("  least determined: " + "; ".join(f"{q.describe()} ({float(f'{q.effect / NT:.2g}'):g} nT effect)" for q in worst))
    if result.inflation > 1.5:
        print(f"  uncertainties widened {np.sqrt(result.inflation):.1f}x for time-correlated residuals")


def cmd_calibrate(args: argparse.Namespace) -> int:
    """Solve a calibration from a recording and write the calibration file."""
    reference_field, site = _reference(args)
    _current_topics(args)  # refuse bad current, temperature and IMU options before reading
    _temperature_topics(args)
    if args.imu and is_csv(args.input):
        raise InputError("--imu names a bag topic; a CSV recording gives the IMU as imu.qx,...,imu.wz columns")
    names = _name_list(args.sensors) or None
    with _progress(args, "read") as bar:
        rec, stats = open_recording(
            args.input, names, args.start, args.end, args.sync_tolerance,
            "drop" if args.drop_nonfinite else "error", bar, args.sync_mode, args.max_gap,
            imu_orientation_frame=args.imu_frame,
        )
    _report_sync(stats)
    check_tesla(rec.vectors, rec.names, args.input)
    rec = _with_side_streams(args, rec)
    if args.interference_only:
        return _calibrate_interference(args, rec)
    prior = _read_calibration(args.prior) if args.prior else None
    geometry = _positions(args.positions, rec.names, prior)
    mounting = None
    if args.mounting:
        from magcal_ros.sim.attitudes import yaw_pitch_roll

        roll, pitch, yaw = _numbers(args.mounting, 3, "--mounting")
        mounting = yaw_pitch_roll(np.array([yaw]), np.array([pitch]), np.array([roll]))[0]
    if args.max_residual is not None and not (np.isfinite(args.max_residual) and args.max_residual > 0):
        raise InputError("--max-residual must be a positive number of Tesla")
    from magcal_ros.methods.pipeline import SolveOptions, calibrate_array  # scipy: only when calibrating

    if args.max_solve_sets is not None and args.max_solve_sets < 0:
        raise InputError("--max-solve-sets must be 0 (every set) or a positive number of sets")
    with _progress(args, "solve") as bar:
        bar.unit = "stages"
        bar.set_total(4 if len(rec) > solve_budget(len(rec.names), args.max_solve_sets) > 0 else 3)

        def stage(name: str) -> None:
            bar.label = f"solve ({name})"
            bar(1)

        opts = SolveOptions(
            loss=args.loss, gradient_method=args.gradient_method or "difference", seed=args.seed,
            max_residual=args.max_residual,
            mounting=mounting, inclination_deg=site.inclination_deg if site is not None else None,
            site_field=site.vector if site is not None else None,
            max_solve_sets=args.max_solve_sets, progress=stage,
        )
        result = calibrate_array(rec.vectors, geometry, reference_field, args.method, opts, prior=prior,
                                 stamps=rec.stamps, currents=rec.currents if rec.channels else None,
                                 channels=rec.channels, temperatures=rec.temperatures, imu=rec.imu)
    if site is not None:
        result.calibration.metadata.update(site.provenance())
    if args.plot:
        from magcal_ros.app.plots import plot_calibration

        plot_calibration(args.plot, rec, result)
    calfile.write(args.output, result.calibration)
    print(result.summary())
    if site is not None:
        _report_site(site)
    for i, name in enumerate(geometry.names):
        print(f"  {name}: TMI RMS {result.tmi_before[i] / NT:10.2f} -> {result.tmi_after[i] / NT:8.3f} nT, "
              f"noise {result.noise[i] / NT:.3g} nT" + (f", {int(result.outliers[i])} outliers excluded"
                                                       if result.outliers[i] else ""))
    _report_quantities(result)
    frame = result.calibration.frame_id or topics.DEFAULT_FRAME_ID
    print(f"  frame {frame}: {result.frame_note()}")
    if result.calibration.channels:
        print(f"  interference of {', '.join(result.calibration.channels)} estimated (subtracted by 'magcal correct' "
              "given their currents)")
    for warning in result.warnings:
        print(f"  warning: {warning}")
    print(f"  solve time {result.seconds * 1e3:.1f} ms; written {args.output}")
    if args.plot:
        print(f"  plot {args.plot}")
    return 0


def _calibrate_interference(args: argparse.Namespace, rec: Recording) -> int:
    """--interference-only: hold a calibration, add the interference a still run shows."""
    from magcal_ros.methods.interference import calibrate_interference

    given = [o for o, v in (("--reference-field", args.reference_field), ("--site", args.site), ("--plot", args.plot),
                            ("--positions", args.positions)) if v is not None]
    if given:
        raise InputError(f"--interference-only holds {args.interference_only}: {', '.join(given)} does not apply")
    if not rec.channels:
        raise InputError("--interference-only needs the currents: --currents TOPIC,... (bag) or current.<channel> "
                         "columns (CSV)")
    held = _read_calibration(args.interference_only)
    rec = rec.select(held.geometry.names)
    result = calibrate_interference(rec.vectors, rec.currents, rec.channels, held, rec.temperatures)
    calfile.write(args.output, result.calibration)
    print(result.summary())
    for c in result.solved:
        j = result.channels.index(c)
        gains = ", ".join(f"{n} {np.linalg.norm(g) / NT:.3g}" for n, g in zip(held.geometry.names, result.estimate.gains[:, :, j]))
        print(f"  {c}: |gain| nT/A {gains}")
    for warning in result.warnings:
        print(f"  warning: {warning}")
    print(f"  written {args.output} ({args.interference_only} with the interference of {', '.join(result.solved)})")
    return 0


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
        "imu_frame_id": args.imu_frame_id, "world_gradient": numbers(args.world_gradient, "--world-gradient"),
    }


def _read_calibration(path: str, uncorrected: tuple[str, ...] = ()) -> ArrayCalibration:
    """The calibration file, every error naming the file; ``uncorrected`` sensors may lack a block."""
    try:
        cal = calfile.read(path, uncorrected=uncorrected)
    except InputError as exc:
        raise (exc if path in str(exc) else InputError(f"{path}: {exc}")) from None
    unknown = [n for n in uncorrected if n not in cal.geometry.names]
    if unknown:
        raise InputError(f"--uncorrected {','.join(unknown)}: not a sensor of {path} (it has {', '.join(cal.geometry.names)})")
    for name in uncorrected:
        k = cal.geometry.names.index(name)
        if np.array_equal(cal.matrices[k], np.eye(3)) and not np.any(cal.offsets[k]):
            _note(f"{name} is not corrected (--uncorrected): its raw readings are used as they are")
    return cal


def cmd_correct(args: argparse.Namespace) -> int:
    """Apply a calibration to a recording: corrected vectors, centre field and tensor."""
    from magcal_ros.app.correct import check_sensors

    cal = _read_calibration(args.calibration, _name_list(args.uncorrected))
    raw = _raw_sensors(cal, _name_list(args.uncorrected))
    if raw:
        from magcal_ros.app.correct import withheld_note

        _note(withheld_note(raw))
    if cal.geometry.size > 1 and cal.geometry.gradient_kind == "none":
        _note(f"the positions of {', '.join(cal.geometry.names)} in {args.calibration} coincide: no gradient, "
              "the field only")
    out_csv = is_csv(args.output)
    if args.gradient_method is None and (is_csv(args.input) or out_csv):
        # Auto: the difference formula for the cross, least squares for any other array, unless the
        # recording holds sensors the calibration lacks (then the cross is refused, naming them).
        # Bag to bag, correct_bag decides the same with the bag it has open.
        from magcal_ros.core.tensor import method_for

        extra = set(recording_sensors(args.input)) - set(cal.geometry.names)
        args.gradient_method = "difference" if extra else method_for(cal.geometry)
    copy = "all" if args.copy_all else _name_list(args.copy_topics)
    from magcal_ros.app.correct import check_temperature_topics

    check_temperature_topics(cal, _temperature_topics(args))
    if not is_csv(args.input):
        from magcal_ros.app.correct import check_channels

        check_channels(cal, [topics.current_channel(t) for t in _current_topics(args)], "topics")
    if is_csv(args.input) or out_csv:
        if copy:
            raise InputError("--copy-topics/--copy-all need a bag input and a bag output")
        for note in check_sensors(cal, recording_sensors(args.input), args.input, args.calibration, args.gradient_method):
            _note(note)
        return _correct_via_recording(args, cal, out_csv, raw)
    from magcal_ros.app.correct import correct_bag

    with _progress(args, "correct") as bar:
        report = correct_bag(
            args.input, cal, args.output, storage=args.storage, copy_topics=copy, progress=bar,
            frame_id=args.frame_id, gradient_method=args.gradient_method, tolerance=args.sync_tolerance,
            nonfinite="drop" if args.drop_nonfinite else "error", start_ns=args.start, end_ns=args.end,
            calibration_name=args.calibration,
            currents=_current_topics(args), current_tolerance=args.current_tolerance,
            sync_mode=args.sync_mode, max_gap=args.max_gap,
            temperature_topics=_temperature_topics(args), temperature_tolerance=args.temperature_tolerance,
            raw_sensors=raw,
        )
    for note in report.notes:
        _note(note)
    _report_sync(report.stats)
    for side in (report.currents, report.temperatures):
        if side is not None and side.note():
            _note(side.note())
    extra = f", {report.copied_messages} messages copied" if report.copied_messages else ""
    print(
        f"corrected {report.input_messages} sets of {_sensors(len(cal.geometry.names))} -> {args.output} "
        f"({report.storage}: /<name>/corrected"
        + (" only, /field and the gradient withheld" if raw else ", /field"
           + {"tensor": ", /gradient", "baseline": ", /baseline_gradient"}.get(cal.geometry.gradient_kind, ""))
        + f"{extra})"
    )
    return 0


def _raw_sensors(cal: ArrayCalibration, uncorrected: tuple[str, ...]) -> tuple[str, ...]:
    """The ``--uncorrected`` sensors the calibration leaves raw (identity matrix, zero offset)."""
    k = cal.geometry.names.index
    return tuple(n for n in uncorrected if np.array_equal(cal.matrices[k(n)], np.eye(3)) and not np.any(cal.offsets[k(n)]))


def _correct_via_recording(args: argparse.Namespace, cal: ArrayCalibration, out_csv: bool, raw: tuple[str, ...]) -> int:
    from magcal_ros.app.correct import time_offsets_of

    with _progress(args, "read") as bar:
        rec, stats = open_recording(
            args.input, cal.geometry.names, args.start, args.end, args.sync_tolerance,
            "drop" if args.drop_nonfinite else "error", bar, args.sync_mode, args.max_gap, time_offsets_of(cal),
        )
    _report_sync(stats)
    check_tesla(rec.vectors, rec.names, args.input)
    rec = _with_side_streams(args, rec, temperatures=cal.has_temperature_terms, imu=False, needed=True)
    if out_csv:
        from magcal_ros.app.correct import correct_recording_csv

        correct_recording_csv(args.output, rec, cal, args.gradient_method, raw)
        kind = "CSV"
    else:
        from magcal_ros.app.correct import write_corrected_bag

        storage = args.storage or "sqlite3"
        write_corrected_bag(args.output, rec, cal, storage, args.frame_id, args.gradient_method, raw)
        kind = storage
    withheld = ": the corrected vectors only, field and gradient withheld" if raw else ""
    print(f"corrected {len(rec)} sets of {_sensors(len(rec.names))} -> {args.output} ({kind}{withheld})")
    return 0


def _subcommand(sub: argparse._SubParsersAction, name: str, summary: str, description: str,  # type: ignore[type-arg]
                epilog: str) -> argparse.ArgumentParser:
    """A subcommand parser whose epilog (examples) keeps its line breaks."""
    return sub.add_parser(name, help=summary, description=description, epilog=epilog,
                          formatter_class=argparse.RawDescriptionHelpFormatter)


def _add_calibrate(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = _subcommand(
        sub, "calibrate", "solve a calibration from a rotation recording",
        "Solve the array calibration from a recording of the vehicle turning in a uniform field, "
        "write it as a ROS 2 parameters file the correction node loads, and print a summary.",
        EPILOG_CALIBRATE,
    )
    add_input_options(p)
    p.add_argument("-o", "--output", required=True, help="calibration file to write (YAML)")
    p.add_argument("--reference-field", type=float, default=None, metavar="TESLA",
                   help="total field intensity F in T (e.g. 5.15e-5); omit (and --site) for a relative calibration")
    p.add_argument("--site", metavar="LAT,LON[,ALT_M]",
                   help="take F from the World Magnetic Model (offline) at this site instead: latitude and "
                   "longitude in deg (north, east positive), altitude in m above sea level (default 0, negative "
                   "under water); e.g. 43.2,5.4 or -33.87,151.21,-20")
    p.add_argument("--date", metavar="YYYY-MM-DD",
                   help="date at which --site evaluates the model (default today, UTC; 2015-01-01 .. 2029-12-31)")
    p.add_argument("--method", default=DEFAULT_METHOD, choices=list(METHODS), help=f"default {DEFAULT_METHOD}")
    p.add_argument("--prior", metavar="CAL.yaml",
                   help="the previous calibration: recalibrate what this manoeuvre determines (e.g. the offsets "
                   "from a yaw circle after the hard iron moved) and keep the rest; method ml")
    p.add_argument("--max-solve-sets", type=int, metavar="N", default=None,
                   help="sets the expensive stages use at most (default 1000 per sensor): a longer recording "
                   "is solved on a subset keeping its attitude coverage and time span, then refined in one "
                   "pass over every set (the summary says so; that pass and reading a long CSV use a second core "
                   "when there is one, the same result; MAGCAL_WORKERS=1 keeps one); 0: every set in every stage")
    p.add_argument("--max-residual", type=float, metavar="TESLA",
                   help="accept a residual (per axis) up to this, instead of the noise-aware rule (17x the "
                   "noise the data show, or 5%% of F for sets in no time order)")
    p.add_argument("--mounting", metavar="ROLL,PITCH,YAW",
                   help="one sensor: its mounting in the platform frame (deg, sensor to platform); without it the "
                   "calibrated vector is in the sensor's own axes made orthogonal")
    p.add_argument("--loss", default="linear", choices=list(LOSSES), help="loss of the per-sensor start (method ml)")
    p.add_argument("--gradient-method", default=None, choices=["difference", "least_squares"],
                   help="tensor formula of the summary (default: difference for the cross, least_squares otherwise)")
    p.add_argument("--seed", type=int, default=0, help="random seed of stochastic methods (pso)")
    p.add_argument("--plot", metavar="FILE.png",
                   help="draw TMI per sensor, tensor components and corrected vectors before/after (PNG)")
    add_current_options(p)
    add_temperature_options(p)
    add_imu_options(p)
    p.add_argument("--interference-only", metavar="CAL.yaml",
                   help="hold CAL.yaml's calibration and estimate only the current interference, from a run with "
                   "the vehicle still and the currents stepped (each on its own); writes CAL.yaml plus the "
                   "interference to --output")
    add_common_options(p)
    p.set_defaults(func=cmd_calibrate)


def _schedule_arg(text: str) -> str:
    """``--schedule`` value: a schedule name (a first-release alias is resolved to today's name)."""
    from magcal_ros.sim.spec import schedule_name

    try:
        return schedule_name(text)
    except InputError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _add_simulate(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
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


def _add_correct(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = _subcommand(
        sub, "correct", "apply a calibration: corrected vectors, centre field and gradient tensor",
        "Apply a calibration file to every synchronized set of a recording and write the corrected "
        "vectors, the centre field and the gradient tensor (a bag with the live node's topics, or CSV).",
        EPILOG_CORRECT,
    )
    p.add_argument("input", help="recording: rosbag2 directory (sqlite3 or mcap) or .csv file")
    p.add_argument("-c", "--calibration", required=True, metavar="CALIBRATION.yaml", help="calibration file")
    p.add_argument("--uncorrected", metavar="NAME[,NAME]",
                   help="sensors the calibration file may lack a block for: their raw readings are written as they "
                   "are, and the centre field and the gradient (which would mix them with calibrated sensors) are "
                   "withheld (otherwise a missing block is refused)")
    p.add_argument("-o", "--output", required=True, help="rosbag2 directory to write, or a .csv file")
    copy = p.add_mutually_exclusive_group()
    copy.add_argument("--copy-topics", metavar="T1,T2", help="also copy these input topics unchanged (bag to bag)")
    copy.add_argument("--copy-all", action="store_true", help="also copy every input topic unchanged (bag to bag)")
    p.add_argument("--storage", choices=["sqlite3", "mcap"], help="output storage (default: the input's; sqlite3 for CSV input)")
    p.add_argument("--frame-id", default=None,
                   help="frame of the output (default: the calibration's frame_id, e.g. its IMU's, else "
                   f"{topics.DEFAULT_FRAME_ID})")
    p.add_argument("--gradient-method", default=None, choices=["difference", "least_squares"],
                   help="cross difference formula or constrained least squares (any geometry); default: difference "
                   "for the planar cross, least_squares otherwise")
    add_window_options(p)
    add_sync_options(p)
    add_current_options(p)
    add_temperature_options(p)
    add_common_options(p)
    p.set_defaults(func=cmd_correct)


EPILOG_PLOT = """examples:
  magcal plot corrected_bag -o survey.png                   # a corrected output of magcal correct
  magcal plot corrected.csv -o survey.png -c cal.yaml       # the same, with the noise floor of cal.yaml
  magcal plot survey_bag -c cal.yaml -o survey.png          # a raw recording, corrected on the way

The figure: the centre field's components (nT about their median), its total intensity
(|B| - F, nT; F from --reference-field or the calibration, else about the median) and the
measured gradient components (nT/m: the six of the tensor's x and y rows, or dB/ds along a
line of sensors), against time. With a calibration (-c) the noise it stored draws the TMI's
noise band and the gradient's noise floor (dashed; the floor of the array's own estimator,
sqrt(2) sigma / d for the cross). The line printed says the gradient's set-to-set noise
against that floor: a calibration that holds is at it."""


def _add_plot(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    p = _subcommand(
        sub, "plot", "draw a corrected recording: centre field, TMI and gradient against time (PNG)",
        "Draw a corrected recording (the output of magcal correct: a bag or CSV), or a raw one corrected on "
        "the way with -c, as time series of the centre field, its total intensity and the gradient.",
        EPILOG_PLOT,
    )
    p.add_argument("input", help="a corrected output (bag or .csv of magcal correct), or a raw recording with -c")
    p.add_argument("-o", "--output", required=True, metavar="FILE.png", help="PNG to write")
    p.add_argument("-c", "--calibration", metavar="CALIBRATION.yaml",
                   help="the calibration: needed for a raw recording; gives the noise floor and F for either")
    p.add_argument("--reference-field", type=float, default=None, metavar="TESLA",
                   help="F for the TMI (default: the calibration's intensity, else the TMI about its median)")
    add_window_options(p)
    add_common_options(p)
    p.set_defaults(func=cmd_plot)


def _plotted(args: argparse.Namespace, cal: ArrayCalibration | None) -> Any:
    """The recording to plot as a :class:`~magcal_ros.io.output_scan.CorrectedOutput`: read back, or
    corrected from a raw recording with ``cal``."""
    from magcal_ros.io.output_scan import CorrectedOutput, corrected_names, read_output

    names = corrected_names(args.input)
    if names is None:
        if cal is None:
            raise InputError(f"{args.input} is a raw recording (no corrected outputs): give its calibration with "
                             "-c CALIBRATION.yaml, or plot the output of magcal correct")
        from magcal_ros.app.correct import corrected_input, time_offsets_of
        from magcal_ros.core.tensor import method_for

        rec, stats = open_recording(args.input, cal.geometry.names, args.start, args.end,
                                    time_offsets=time_offsets_of(cal))
        _report_sync(stats)
        check_tesla(rec.vectors, rec.names, args.input)
        rec = corrected_input(rec, cal)
        sets = cal.outputs(rec.vectors, method_for(cal.geometry), rec.currents if rec.channels else None,
                           rec.temperatures)
        rows = sets.tensor.reshape(len(rec), 9) if sets.tensor is not None else sets.baseline
        return CorrectedOutput(rec.names, rec.stamps, sets.vectors, sets.centre, rows)
    out = read_output(args.input, names)
    keep = np.ones(len(out.stamps), bool)
    if args.start is not None:
        keep &= out.stamps >= args.start
    if args.end is not None:
        keep &= out.stamps <= args.end
    if not keep.any():
        raise InputError(f"{args.input}: no sets in the selected time window")
    return CorrectedOutput(out.names, out.stamps[keep], out.vectors[keep],
                           None if out.centre is None else out.centre[keep],
                           None if out.gradient is None else out.gradient[keep])


def cmd_plot(args: argparse.Namespace) -> int:
    """Draw a corrected recording (or a raw one with its calibration) into a PNG."""
    from magcal_ros.app.plots import gradient_components, plot_survey, set_to_set_noise
    from magcal_ros.core.metrics import gradient_floor

    if not str(args.output).lower().endswith(".png"):
        raise InputError(f"-o {args.output}: the figure is a PNG file (name ending in .png)")
    if args.reference_field is not None and not (EARTH_FIELD_RANGE[0] <= args.reference_field <= EARTH_FIELD_RANGE[1]):
        raise InputError(f"--reference-field {args.reference_field:g} T is not an Earth field intensity in Tesla")
    cal = _read_calibration(args.calibration) if args.calibration else None
    out = _plotted(args, cal)
    if cal is not None and tuple(cal.geometry.names) != tuple(out.names):
        raise InputError(f"{args.calibration} covers {', '.join(cal.geometry.names)}, the recording has "
                         f"{', '.join(out.names)}")
    stored = [] if cal is None else [float(v) for v in cal.metadata.get("noise") or [] if float(v) > 0]
    noise = float(np.sqrt(np.mean(np.square(stored)))) if stored else None
    intensity = args.reference_field or (float(cal.metadata.get("intensity") or 0) if cal is not None else 0) or None
    floor = gradient_floor(noise, cal.geometry) if noise and cal is not None and out.gradient is not None else None
    plot_survey(args.output, out, intensity, noise, floor, f"magcal plot {Path(args.input).name}: {len(out.stamps)} "
                f"sets of {_sensors(len(out.names))}")
    parts = [f"plotted {len(out.stamps)} sets of {_sensors(len(out.names))} -> {args.output}"]
    if out.centre is not None:
        tmi = np.linalg.norm(out.centre, axis=1)
        parts.append(f"TMI median {float(np.median(tmi)) / NT:.1f} nT" + (f" (F {intensity / NT:.1f} nT)" if intensity else ""))
    else:
        parts.append("centre field and gradient withheld in this output (a sensor left raw)")
    measured = set_to_set_noise(gradient_components(out.gradient)[0])
    if measured is not None:
        parts.append(f"gradient set-to-set noise {measured / NT:.3g} nT/m"
                     + (f" against the noise floor {floor / NT:.3g} nT/m" if floor else " (no calibration: no floor)"))
    print(", ".join(parts))
    return 0


def build_parser() -> argparse.ArgumentParser:
    """The ``magcal`` argument parser."""
    import magcal_ros  # the package's version

    parser = argparse.ArgumentParser(
        prog="magcal",
        description="Calibrate, correct and inspect recordings of an array of three-axis magnetometers: one\n"
        "sensor, two (a gradiometer), the four-fluxgate cross of a gradient tensor array, or any number\n"
        "anywhere (Tesla on every topic and in every file).",
        epilog="examples:\n"
        "  magcal simulate rotation_bag && magcal calibrate rotation_bag -o cal.yaml --plot cal.png\n"
        "  magcal correct survey_bag -c cal.yaml -o corrected_bag\n"
        "  magcal batch campaign/ -c cal.yaml -o corrected/   # every recording, on Dask, with a report\n"
        "  magcal COMMAND --help      # options and examples of a command\n\n" + EXIT_CODES,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"magcal {magcal_ros.__version__} (magcal_ros)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    _add_simulate(sub)
    _add_calibrate(sub)
    _add_correct(sub)
    _add_plot(sub)
    from magcal_ros.app.batch import add_batch_parser  # Dask itself is imported only when a batch runs

    add_batch_parser(sub, _subcommand)
    return parser


def _value_options(parser: argparse.ArgumentParser) -> frozenset[str]:
    """The option strings (of every subcommand) that take a value."""
    found: set[str] = set()
    stack = [parser]
    while stack:
        p = stack.pop()
        for action in p._actions:  # noqa: SLF001 - argparse keeps its actions here
            if isinstance(action, argparse._SubParsersAction):  # noqa: SLF001
                stack.extend(action.choices.values())
            elif action.option_strings and action.nargs != 0:
                found.update(action.option_strings)
    return frozenset(found)


def _attach_negative_values(argv: Sequence[str], options: frozenset[str]) -> list[str]:
    """``--positions -0.25,0,0,...`` as ``--positions=-0.25,0,0,...`` for every option that takes a
    value (numbers, or lists of them, may start with a minus sign): argparse takes a leading '-'
    followed by anything but a plain number for an option."""
    out: list[str] = []
    for arg in argv:
        if out and out[-1] in options and re.match(r"-\.?\d", arg):
            out[-1] = f"{out[-1]}={arg}"
        else:
            out.append(arg)
    return out


def _stop(signum: int, frame: FrameType | None) -> None:
    """Signal handler: ignore further stop signals while cleaning up, then unwind."""
    for s in STOP_SIGNALS:
        signal.signal(s, signal.SIG_IGN)
    raise Stopped(signum)


def _outputs(args: argparse.Namespace) -> list[str]:
    """Every path the command will write."""
    outs = [args.output]
    if args.command == "simulate":
        from magcal_ros.io.truth_file import truth_paths

        outs += [str(p) for p in truth_paths(args.output)]
    if getattr(args, "plot", None):
        outs.append(args.plot)
    return outs


def _check_paths(args: argparse.Namespace) -> None:
    """Refuse an output that is one of the command's inputs, or two outputs at one path."""
    inputs = [p for p in (getattr(args, "input", None), getattr(args, "calibration", None)) if p]
    seen: dict[Path, str] = {Path(p).resolve(): p for p in inputs}
    folders = [(Path(p).resolve(), p) for p in inputs if Path(p).is_dir()]  # a bag is a directory
    for out in _outputs(args):
        where = Path(out).resolve()
        if where in seen and seen[where] in inputs:
            raise InputError(f"output {out} would overwrite the input {seen[where]}: write to another path")
        inside = next((p for folder, p in folders if folder in where.parents), None)
        if inside is not None:
            raise InputError(f"output {out} is inside the input bag {inside}: write outside it")
        if where in seen:
            raise InputError(f"outputs {seen[where]} and {out} are the same file: give different paths")
        seen[where] = out


def _silence_stdout() -> None:
    """Point stdout at the null device so the interpreter's final flush cannot fail again."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)
    except (OSError, ValueError):
        pass


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point: one clear line on stderr and exit 2 for any bad input.

    SIGINT, SIGTERM and SIGHUP stop a run like Ctrl-C: the partial output is removed, one
    line says so, and the exit code is 128 + the signal number (130, 143, 129).
    """
    parser = build_parser()
    args = parser.parse_args(_attach_negative_values(sys.argv[1:] if argv is None else argv, _value_options(parser)))
    previous: dict[signal.Signals, Any] = {}
    try:
        if threading.current_thread() is threading.main_thread():
            previous = {s: signal.signal(s, _stop) for s in STOP_SIGNALS}
        _check_paths(args)
        for out in _outputs(args):
            for note in recover(out):
                _note(note)
        with np.errstate(all="ignore"):  # a fit's overflow on bad data ends in a clear error, not a numpy warning
            return int(args.func(args) or 0)
    except MagcalError as exc:
        print(f"magcal {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except BrokenPipeError:
        # The reader of stdout went away (``magcal ... | head``): stop quietly as shell tools do.
        _silence_stdout()
        return 128 + int(signal.SIGPIPE)
    except OSError as exc:
        where = f"{exc.filename}: " if getattr(exc, "filename", None) else ""
        print(f"magcal {args.command}: error: {where}{exc.strerror or exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as exc:
        signum = exc.signum if isinstance(exc, Stopped) else signal.SIGINT
        print(f"magcal {args.command}: stopped by {signal.Signals(signum).name}; unfinished output removed", file=sys.stderr)
        return 128 + int(signum)
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)


if __name__ == "__main__":
    sys.exit(main())
