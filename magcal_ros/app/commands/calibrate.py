"""``magcal calibrate``: solve a calibration from a recording (or, --interference-only, the
current interference alone) and write the calibration file."""

from __future__ import annotations

import argparse
from typing import Any

import numpy as np

from magcal_ros.app.commands.common import (
    UNITS_NOTE,
    _current_topics,
    _name_list,
    _numbers,
    _positions,
    _progress,
    _read_calibration,
    _reference,
    _report_site,
    _report_sync,
    _subcommand,
    _temperature_topics,
    _with_side_streams,
    add_common_options,
    add_current_options,
    add_imu_options,
    add_input_options,
    add_temperature_options,
)
from magcal_ros.core.recording import Recording
from magcal_ros.core.scalar_fit import LOSSES
from magcal_ros.core.set_reduction import solve_budget
from magcal_ros.core.units import NT, check_tesla
from magcal_ros.errors import InputError
from magcal_ros.io import calibration_file as calfile
from magcal_ros.io import topics
from magcal_ros.io.recordings import is_csv, open_recording
from magcal_ros.methods.strategies import DEFAULT_METHOD, METHODS


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


def add_parser(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    """Add ``magcal calibrate`` to the subcommands ``sub``."""
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
