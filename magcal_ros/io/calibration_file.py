"""The calibration file: a ROS 2 parameters YAML the correction node loads as is.

Layout (docs/interfaces.md)::

    magcal_correction:
      ros__parameters:
        sensor_names: [...]
        positions: [...]
        mag1: {matrix: [...9], offset: [...3]}
    magcal_provenance:
      ros__parameters: {method: ..., created: ..., samples: ..., ...}

The provenance block is a parameter block of a node that does not exist, so
``--params-file`` loads the file unchanged. Written atomically; the previous file is
kept as ``<file>.bak``.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from typing import Any

import numpy as np
import yaml

from magcal_ros.core.calibration import ArrayCalibration
from magcal_ros.errors import InputError
from magcal_ros.io.atomic import atomic_path

CORRECTION_NODE: str = "magcal_correction"
PROVENANCE_NODE: str = "magcal_provenance"


def _ros_value(value: Any) -> Any:
    """A YAML value ROS parameters accept: scalars, strings, homogeneous lists."""
    if isinstance(value, (bool, int, str)):
        return value
    if isinstance(value, (float, np.floating)):
        return float(value)
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, (list, tuple, np.ndarray)):
        items = [_ros_value(v) for v in np.asarray(value).reshape(-1).tolist()]
        if items and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in items):
            return [float(v) for v in items]
        return [str(v) for v in items]
    if value is None:
        return ""
    return str(value)


def dumps(calibration: ArrayCalibration, node_name: str = CORRECTION_NODE) -> str:
    """YAML text of ``calibration`` for ``node_name``, with a provenance block."""
    doc: dict[str, Any] = {node_name: {"ros__parameters": calibration.to_parameters()}}
    meta = {k: _ros_value(v) for k, v in calibration.metadata.items() if isinstance(k, str)}
    if meta:
        doc[PROVENANCE_NODE] = {"ros__parameters": meta}
    header = "# magcal_ros calibration: B = matrix (raw - offset); Tesla, platform frame.\n"
    header += "# Load with: correction_node --ros-args --params-file <this file>\n"
    return header + yaml.safe_dump(doc, sort_keys=False, default_flow_style=None, width=1000)


def write(path: str | os.PathLike[str], calibration: ArrayCalibration, node_name: str = CORRECTION_NODE) -> None:
    """Write ``calibration`` atomically to ``path``, keeping the previous file as ``.bak``."""
    text = dumps(calibration, node_name)
    with atomic_path(path, backup=True) as tmp:
        tmp.write_text(text)


def _node_blocks(doc: Any) -> dict[str, dict[str, Any]]:
    if not isinstance(doc, dict):
        raise InputError("calibration file must be a YAML mapping of node names")
    out = {}
    for key, value in doc.items():
        if isinstance(value, dict) and isinstance(value.get("ros__parameters"), dict):
            out[str(key).lstrip("/")] = value["ros__parameters"]
    return out


def loads(text: str, node_name: str = CORRECTION_NODE, uncorrected: Sequence[str] = ()) -> ArrayCalibration:
    """Parse calibration YAML text (see :func:`dumps`).

    Every sensor in ``sensor_names`` needs its block; a missing one is an
    :class:`InputError` naming the sensor, unless it is listed in ``uncorrected`` (its raw
    readings are then used as they are, on purpose).
    """
    try:
        doc = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise InputError(f"calibration file is not valid YAML: {str(exc).splitlines()[0]}") from None
    blocks = _node_blocks(doc)
    params = blocks.get(node_name)
    if params is None:
        candidates = [b for b in blocks.values() if "sensor_names" in b]
        if len(candidates) != 1:
            raise InputError(f"calibration file has no '{node_name}: ros__parameters:' block with sensor_names")
        params = candidates[0]
    return ArrayCalibration.from_parameters(params, blocks.get(PROVENANCE_NODE, {}), uncorrected)


def read(path: str | os.PathLike[str], node_name: str = CORRECTION_NODE, uncorrected: Sequence[str] = ()) -> ArrayCalibration:
    """Read a calibration file; :class:`InputError` with one clear line if unusable (see :func:`loads`)."""
    try:
        with open(path, encoding="utf-8") as fh:
            text = fh.read()
    except OSError as exc:
        raise InputError(f"cannot read calibration file {path}: {exc.strerror}") from None
    except UnicodeDecodeError:
        raise InputError(f"calibration file {path} is not text") from None
    return loads(text, node_name, uncorrected)
