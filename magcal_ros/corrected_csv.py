"""Corrected output as CSV (``magcal correct`` with a CSV input or a ``.csv`` output).

Header: ``stamp``, then ``<name>.x,<name>.y,<name>.z`` per sensor (corrected vectors, T,
platform frame), ``field.x,field.y,field.z`` (centre field, T) and ``gradient.xx,
gradient.xy, ..., gradient.zz`` (the 3x3 tensor row-major, ``gradient.ij = dB_j/dx_i``,
T/m). One synchronized set per row, stamp in seconds, full double precision.
"""

from __future__ import annotations

import os
from collections.abc import Sequence

import numpy as np

from magcal_ros.atomic import atomic_path
from magcal_ros.calibration import ArrayCalibration
from magcal_ros.recording import AXIS_NAMES, Recording, csv_header, format_rows

TENSOR_COLUMNS: tuple[str, ...] = tuple(f"gradient.{i}{j}" for i in AXIS_NAMES for j in AXIS_NAMES)
FIELD_COLUMNS: tuple[str, ...] = tuple(f"field.{a}" for a in AXIS_NAMES)


def corrected_header(names: Sequence[str]) -> list[str]:
    """``stamp, <name>.x.., field.x.., gradient.xx..gradient.zz``."""
    return csv_header(list(names)) + list(FIELD_COLUMNS) + list(TENSOR_COLUMNS)


def write_corrected_csv(
    path: str | os.PathLike[str],
    recording: Recording,
    calibration: ArrayCalibration,
    gradient_method: str = "difference",
) -> int:
    """Correct ``recording`` and write it atomically as CSV; returns the number of sets."""
    rec = recording.select(calibration.geometry.names)
    b, centre, g = calibration.field_and_gradient(rec.vectors, gradient_method)
    columns = np.concatenate([b.reshape(len(rec), -1), centre, g.reshape(len(rec), 9)], axis=1)
    with atomic_path(path) as tmp:
        with open(tmp, "w", encoding="utf-8", newline="") as fh:
            fh.write(",".join(corrected_header(rec.names)) + "\n")
            fh.write(format_rows(rec.stamps, columns))
    return len(rec)
