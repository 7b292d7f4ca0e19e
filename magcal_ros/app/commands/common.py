"""What the ``magcal`` commands share: option groups (input, window, synchronisation, currents,
temperatures, IMU), the notes on stderr, the reference intensity (--reference-field or the WMM at
--site), calibration files, and a bag's side streams matched to the sets."""

from __future__ import annotations

import argparse
import sys
from typing import TYPE_CHECKING, Any

import numpy as np

from magcal_ros.app.progress import ProgressBar
from magcal_ros.core.calibration import ArrayCalibration
from magcal_ros.core.geometry import ArrayGeometry
from magcal_ros.core.imu import DEFAULT_IMU_TOLERANCE, IMU_FRAMES
from magcal_ros.core.interference import DEFAULT_CURRENT_TOLERANCE, tolerance_of
from magcal_ros.core.recording import Recording
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
from magcal_ros.core.units import EARTH_FIELD_RANGE, NT
from magcal_ros.errors import InputError
from magcal_ros.io import calibration_file as calfile
from magcal_ros.io import topics
from magcal_ros.io.recordings import CURRENTS, IMU_TOPIC, TEMPERATURES, SideTopics, is_csv, with_bag_side_streams

if TYPE_CHECKING:
    from magcal_ros.core.geomagnetic import SiteField


UNITS_NOTE = (
    f"Readings must be in Tesla: a sensor whose median |B| is outside {EARTH_FIELD_RANGE[0]:g} .. "
    f"{EARTH_FIELD_RANGE[1]:g} T is refused."
)


def _name_list(text: str | None) -> tuple[str, ...]:
    """Comma-separated names (an option's value) as a tuple, blanks dropped."""
    return tuple(n.strip() for n in (text or "").split(",") if n.strip())


def _sensors(count: int) -> str:
    """``1 sensor``, ``4 sensors``."""
    return f"{count} sensor" if count == 1 else f"{count} sensors"


def _note(text: str) -> None:
    """One note line on stderr (what was dropped, left out or cleaned up)."""
    print(f"  note: {text}", file=sys.stderr)


def _numbers(text: str, count: int, option: str) -> tuple[float, ...]:
    """``count`` finite numbers separated by commas (an option's value); :class:`InputError` naming ``option``."""
    try:
        values = tuple(float(v) for v in text.replace(",", " ").split())
    except ValueError:
        raise InputError(f"{option} must be {count} numbers separated by commas, got {text!r}") from None
    if len(values) != count or not np.all(np.isfinite(values)):
        raise InputError(f"{option} must be {count} finite numbers separated by commas, got {text!r}")
    return values


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


def _progress(args: argparse.Namespace, label: str) -> ProgressBar:
    """A progress bar on stderr unless --quiet (drawn only on a terminal; the bag sets its total)."""
    return ProgressBar(None, label, enabled=False if args.quiet else None)


def _subcommand(sub: argparse._SubParsersAction, name: str, summary: str, description: str,  # type: ignore[type-arg]
                epilog: str) -> argparse.ArgumentParser:
    """A subcommand parser whose epilog (examples) keeps its line breaks."""
    return sub.add_parser(name, help=summary, description=description, epilog=epilog,
                          formatter_class=argparse.RawDescriptionHelpFormatter)


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
