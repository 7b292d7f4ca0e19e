"""The ``magcal`` command: offline calibration tools over CSV and rosbag2 recordings."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

import numpy as np

from magcal_ros import calfile
from magcal_ros.calibrate import DEFAULT_METHOD, METHODS, SolveOptions, calibrate_array
from magcal_ros.errors import InputError, MagcalError
from magcal_ros.geometry import ArrayGeometry
from magcal_ros.scalar import LOSSES
from magcal_ros.sources import read_recording
from magcal_ros.units import NT

EPILOG_CALIBRATE = """examples:
  magcal calibrate rotation.csv -o calibration.yaml --reference-field 5.15e-5
  magcal calibrate rotation_bag/ -o cal.yaml                 # relative (no reference)
  magcal calibrate rotation.csv -o cal.yaml --method linear --reference-field 6e-5

methods:
""" + "\n".join(f"  {m.name:<11} {m.source}: {m.description}" for m in METHODS.values())


def _positions(text: str | None, names: tuple[str, ...]) -> ArrayGeometry:
    if text is None:
        if len(names) != 4:
            raise InputError(f"{len(names)} sensors in the recording: give --positions (3 numbers per sensor, m)")
        return ArrayGeometry.cross(names=names)
    try:
        values = [float(v) for v in text.replace(",", " ").split()]
    except ValueError:
        raise InputError("--positions must be numbers (m), 3 per sensor") from None
    return ArrayGeometry(names, np.asarray(values))


def add_input_options(p: argparse.ArgumentParser) -> None:
    """Options shared by commands that read a recording."""
    p.add_argument("input", help="recording: rosbag2 directory (sqlite3 or mcap) or .csv file")
    p.add_argument("--sensors", help="comma-separated sensor names (default: all in the recording)")
    p.add_argument("--start", type=float, help="ignore sets stamped before this time (s)")
    p.add_argument("--end", type=float, help="ignore sets stamped after this time (s)")
    p.add_argument("--positions", help="sensor positions, 3 per sensor in m (default: 0.4 m planar cross)")


def cmd_calibrate(args: argparse.Namespace) -> int:
    """Solve a calibration from a recording and write the calibration file."""
    names = tuple(args.sensors.split(",")) if args.sensors else None
    rec = read_recording(args.input, names, args.start, args.end)
    geometry = _positions(args.positions, rec.names)
    opts = SolveOptions(loss=args.loss, gradient_method=args.gradient_method, seed=args.seed)
    result = calibrate_array(rec.vectors, geometry, args.reference_field, args.method, opts)
    calfile.write(args.output, result.calibration)
    print(result.summary())
    for name, before, after in zip(geometry.names, result.tmi_before, result.tmi_after):
        print(f"  {name}: TMI RMS {before / NT:10.2f} -> {after / NT:8.3f} nT")
    print(f"  solve time {result.seconds * 1e3:.1f} ms; written {args.output}")
    if getattr(args, "plot", None):
        from magcal_ros.plots import plot_calibration

        plot_calibration(args.plot, rec, result)
        print(f"  plot {args.plot}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    """The ``magcal`` argument parser."""
    parser = argparse.ArgumentParser(
        prog="magcal",
        description="Calibrate, correct and inspect recordings of a magnetic gradient tensor array "
        "(four fluxgates, Tesla on every topic and in every file).",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    p = sub.add_parser(
        "calibrate",
        help="solve a calibration from a rotation recording",
        description="Solve the array calibration from a recording of the vehicle turning in a uniform field, "
        "write it as a ROS 2 parameters file the correction node loads, and print a summary.",
        epilog=EPILOG_CALIBRATE,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add_input_options(p)
    p.add_argument("-o", "--output", required=True, help="calibration file to write (YAML)")
    p.add_argument("--reference-field", type=float, default=None, metavar="TESLA",
                   help="total field intensity F in T (e.g. 5.15e-5); omit for a relative calibration")
    p.add_argument("--method", default=DEFAULT_METHOD, choices=list(METHODS), help=f"default {DEFAULT_METHOD}")
    p.add_argument("--loss", default="linear", choices=list(LOSSES), help="robust loss for method ml")
    p.add_argument("--gradient-method", default="difference", choices=["difference", "least_squares"])
    p.add_argument("--seed", type=int, default=0, help="random seed of stochastic methods (pso)")
    p.add_argument("--plot", metavar="FILE.png", help="draw TMI and tensor residuals before/after")
    p.set_defaults(func=cmd_calibrate)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point: one clear line on stderr and exit 2 for any bad input."""
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except MagcalError as exc:
        print(f"magcal {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"magcal {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
