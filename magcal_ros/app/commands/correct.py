"""``magcal correct``: apply a calibration to a recording: corrected vectors, centre field and
gradient (a bag with the live node's topics, or CSV)."""

from __future__ import annotations

import argparse

import numpy as np

from magcal_ros.app.commands.common import (
    UNITS_NOTE,
    _current_topics,
    _name_list,
    _note,
    _progress,
    _read_calibration,
    _report_sync,
    _sensors,
    _subcommand,
    _temperature_topics,
    _with_side_streams,
    add_common_options,
    add_current_options,
    add_sync_options,
    add_temperature_options,
    add_window_options,
)
from magcal_ros.core.calibration import ArrayCalibration
from magcal_ros.core.units import check_tesla
from magcal_ros.errors import InputError
from magcal_ros.io import topics
from magcal_ros.io.recordings import is_csv, open_recording, recording_sensors


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


def add_parser(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    """Add ``magcal correct`` to the subcommands ``sub``."""
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
    for note in [] if report.span is None else report.span.notes():
        _note(note)
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
    """A CSV input or a CSV output: the recording read (with its side streams), corrected and written."""
    from magcal_ros.app.correct import time_offsets_of

    with _progress(args, "read") as bar:
        rec, stats = open_recording(
            args.input, cal.geometry.names, args.start, args.end, args.sync_tolerance,
            "drop" if args.drop_nonfinite else "error", bar, args.sync_mode, args.max_gap, time_offsets_of(cal),
        )
    _report_sync(stats)
    check_tesla(rec.vectors, rec.names, args.input)
    rec = _with_side_streams(args, rec, temperatures=cal.has_temperature_terms, imu=False, needed=True)
    from magcal_ros.app.correct import temperature_span_notes

    for note in temperature_span_notes(cal, rec, None if is_csv(args.input) else args.input, _temperature_topics(args),
                                       args.temperature_tolerance):
        _note(note)
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
