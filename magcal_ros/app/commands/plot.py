"""``magcal plot``: draw a corrected recording (or a raw one with its calibration) into a PNG."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

import numpy as np

from magcal_ros.app.commands.common import (
    _read_calibration,
    _report_sync,
    _sensors,
    _subcommand,
    add_common_options,
    add_window_options,
)
from magcal_ros.core.calibration import ArrayCalibration
from magcal_ros.core.units import EARTH_FIELD_RANGE, NT, check_tesla
from magcal_ros.errors import InputError
from magcal_ros.io.recordings import open_recording


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


def add_parser(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    """Add ``magcal plot`` to the subcommands ``sub``."""
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
