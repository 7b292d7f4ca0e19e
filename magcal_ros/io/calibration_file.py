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
``--params-file`` loads the file unchanged. Written atomically; the previous file is kept
as a timestamped backup ``<file>.<UTC time>.bak`` (the last :data:`DEFAULT_BACKUPS`).

Every float is written so that every ROS reader reads a float: rcl's parser
(``--params-file``), PyYAML and rclpy's ``parameter_dict_from_yaml_file`` (``ros2 param
load``), which re-parses ``str(value)`` and so reads a float whose ``repr`` has no
decimal point (``5e-08``) as a string. Such a value is written as its neighbour one unit
in the last place away (``5.000000000000001e-08``), a change far below any measurement.
"""

from __future__ import annotations

import contextlib
import errno
import math
import os
import re
import stat
from collections.abc import Iterator, Sequence
from datetime import datetime, timedelta, timezone
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from magcal_ros.core.calibration import ArrayCalibration
from magcal_ros.core.calibration_health import noise_and_intensity
from magcal_ros.errors import InputError
from magcal_ros.io.atomic import atomic_path, write_target
from magcal_ros.io.input_files import MAX_CALIBRATION_BYTES, regular_file

CORRECTION_NODE: str = "magcal_correction"
PROVENANCE_NODE: str = "magcal_provenance"
DEFAULT_BACKUPS: int = 5
"""Backups (previous files) kept beside a calibration file."""
_BACKUP_TIME = "%Y%m%dT%H%M%S.%fZ"


def ros_float(value: float) -> float:
    """``value``, or its neighbour 1 ulp away if ``repr`` has no decimal point (see the module docstring)."""
    x = float(value)
    while math.isfinite(x) and "." not in repr(x):
        x = math.nextafter(x, math.inf)
    return x


def _reads_back(text: str) -> bool:
    """Whether YAML reads ``text`` as itself: what rclpy does to every string of a params file."""
    try:
        return yaml.safe_load(text) == text
    except (yaml.YAMLError, RecursionError):
        return False


_NBSP = "\u00a0"


def ros_text(text: str) -> str:
    """``text``, changed as little as needed for every ROS reader to read it as this text.

    ``ros2 param load`` (rclpy) reads each string of a params file a second time as YAML: a
    time (``2026-11-25T22:13:04+00:00``) becomes a datetime and ``a: b`` a mapping, and
    either stops the command. In that order, until the text reads back as itself: line
    breaks become spaces, the space after ``:`` and before ``#`` a no-break space (the text
    looks the same);
    a trailing UTC offset is written without its colon (``+0000``, still ISO 8601, Python
    reads it); anything else is put in parentheses.
    """
    if _reads_back(text):
        return text
    fixed = " ".join(text.split("\n")).replace(": ", ":" + _NBSP).replace(" #", _NBSP + "#")
    if _reads_back(fixed):
        return fixed
    timed = re.sub(r"([+-]\d\d):(\d\d)$", r"\1\2", fixed)
    if _reads_back(timed):
        return timed
    return f"({fixed})" if _reads_back(f"({fixed})") else "(text not representable)"


def _ros_value(value: Any) -> Any:
    """A YAML value ROS parameters accept: scalars, strings, homogeneous lists, floats and strings ROS-safe."""
    if isinstance(value, str):
        return ros_text(value)
    if isinstance(value, (bool, int)):
        return value
    if isinstance(value, (float, np.floating)):
        return ros_float(value) if math.isfinite(value) else str(float(value))
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, dict):
        return {str(k): _ros_value(v) for k, v in value.items()}
    if isinstance(value, (list, tuple, np.ndarray)):
        items = [_ros_value(v) for v in np.asarray(value).reshape(-1).tolist()]
        if items and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in items):
            return [ros_float(v) for v in items]
        return [str(v) for v in items]  # rclpy reads a list as Python writes it: its strings quoted
    if value is None:
        return ""
    return ros_text(str(value))


def parameters(calibration: ArrayCalibration) -> dict[str, Any]:
    """The correction node's parameters for ``calibration`` (nested), exactly as the file holds them.

    Besides the correction, what the calibration health compares with, from the provenance
    when it has them: ``calibration_intensity`` (T) and per sensor ``noise`` (T per axis)."""
    params = _ros_value(calibration.to_parameters())
    noise, intensity = noise_and_intensity(calibration.metadata, calibration.geometry.names)
    if intensity is not None:
        params["calibration_intensity"] = ros_float(intensity)
    if noise is not None:
        for name, sigma in zip(calibration.geometry.names, noise.tolist()):
            if math.isfinite(sigma) and sigma > 0:
                params[name]["noise"] = ros_float(sigma)
    return params


def dumps(calibration: ArrayCalibration, node_name: str = CORRECTION_NODE) -> str:
    """YAML text of ``calibration`` for ``node_name``, with a provenance block."""
    doc: dict[str, Any] = {node_name: {"ros__parameters": parameters(calibration)}}
    meta = {k: _ros_value(v) for k, v in calibration.metadata.items() if isinstance(k, str)}
    if meta:
        doc[PROVENANCE_NODE] = {"ros__parameters": meta}
    header = "# magcal_ros calibration: B = matrix (raw - offset); Tesla, platform frame.\n"
    header = _temperature_and_frame_header(calibration) or header
    header += "# Load with: correction_node --ros-args --params-file <this file>\n"
    text = header + yaml.safe_dump(doc, sort_keys=False, default_flow_style=None, width=1000, allow_unicode=True)
    _check_readable(text, node_name, calibration)
    return text


def _check_readable(text: str, node_name: str, calibration: ArrayCalibration) -> None:
    """What is written must read back: the calibration it holds, equal to ``calibration`` to the
    last place ROS-safe floats allow (:class:`InputError` otherwise, so nothing unreadable is written)."""
    try:
        back = loads(text, node_name.lstrip("/"))
    except InputError as exc:
        raise InputError(f"the calibration cannot be written: it would not read back ({exc})") from None
    if back.geometry.names != calibration.geometry.names or not (
            np.allclose(back.matrices, calibration.matrices, rtol=1e-15, atol=0)
            and np.allclose(back.offsets, calibration.offsets, rtol=1e-15, atol=0)):
        raise InputError("the calibration cannot be written: it would not read back as it is")


def _temperature_and_frame_header(calibration: ArrayCalibration) -> str:
    """The formula line of a calibration with temperature terms or an output frame ('' otherwise)."""
    if not (calibration.has_temperature_terms or calibration.rotated or calibration.frame_id):
        return ""
    formula = "matrix (raw - offset)"
    if calibration.has_temperature_terms:
        formula = ("(matrix + dT matrix_per_kelvin) (raw - offset - dT offset_per_kelvin), "
                   "dT = T - temperature_reference (deg C)")
    frame = "platform frame"
    if calibration.rotated or calibration.frame_id:
        frame = f"output frame {calibration.frame_id or '(frame_id)'}: output_rotation @ B"
    return f"# magcal_ros calibration: B = {formula}; Tesla, {frame}.\n"


def backups(path: str | os.PathLike[str]) -> list[Path]:
    """The timestamped backups ``<file>.<UTC time>.bak`` of ``path``, oldest first."""
    target = Path(path)
    pattern = re.compile(re.escape(target.name) + r"\.\d{8}T\d{6}\.\d{6}Z\.bak")
    folder = target.parent if str(target.parent) else Path(".")
    if not folder.is_dir():
        return []
    return sorted(p for p in folder.iterdir() if pattern.fullmatch(p.name))


def _backup_path(target: Path) -> Path:
    """A new backup name for ``target``: the current UTC time, and later than every existing backup."""
    existing = backups(target)
    when = datetime.now(timezone.utc).replace(tzinfo=None)
    if existing:
        last = datetime.strptime(existing[-1].name[len(target.name) + 1 : -len(".bak")], _BACKUP_TIME)
        when = max(when, last + timedelta(microseconds=1))
    return target.with_name(f"{target.name}.{when.strftime(_BACKUP_TIME)}.bak")


@contextlib.contextmanager
def replace(
    path: str | os.PathLike[str],
    calibration: ArrayCalibration,
    node_name: str = CORRECTION_NODE,
    keep: int = DEFAULT_BACKUPS,
) -> Iterator[Path]:
    """Write ``calibration`` to ``path``; undo it if the ``with`` block raises.

    The previous file (if any) is first copied to a new timestamped backup; the new file
    is written atomically. If the block raises, the previous file is put back atomically
    (or the new one removed when there was none) and the new backup dropped, so the
    file is as before. On success only the ``keep`` newest backups are kept. OSError if
    the file cannot be written (then nothing changed).
    """
    target = write_target(path)  # through a symbolic link: its target is the calibration file
    text = dumps(calibration, node_name)
    for folder in (target.parent, *target.parent.parents):
        if folder.exists():
            if not folder.is_dir():
                raise NotADirectoryError(errno.ENOTDIR, os.strerror(errno.ENOTDIR), str(folder))
            break
    previous = target.read_bytes() if target.is_file() else None
    mode = stat.S_IMODE(target.stat().st_mode) if previous is not None else None
    backup = _backup_path(target) if previous is not None and keep > 0 else None
    if backup is not None:
        with atomic_path(backup, mode=mode) as tmp:  # a backup is as private as the file
            tmp.write_bytes(previous)  # type: ignore[arg-type]
    try:
        with atomic_path(target) as tmp:
            tmp.write_text(text)
    except BaseException:
        if backup is not None:
            backup.unlink(missing_ok=True)
        raise
    try:
        yield target
    except BaseException:
        if previous is None:
            target.unlink(missing_ok=True)
        else:
            with atomic_path(target) as tmp:
                tmp.write_bytes(previous)
        if backup is not None:
            backup.unlink(missing_ok=True)
        raise
    old = backups(target)
    for stale in old[: max(len(old) - keep, 0)]:
        stale.unlink(missing_ok=True)


def write(
    path: str | os.PathLike[str],
    calibration: ArrayCalibration,
    node_name: str = CORRECTION_NODE,
    keep: int = DEFAULT_BACKUPS,
) -> None:
    """Write ``calibration`` atomically to ``path``, keeping the previous files as timestamped backups."""
    with replace(path, calibration, node_name, keep):
        pass


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
    except RecursionError:
        raise InputError("calibration file is nested too deeply to be a calibration (not a ROS parameters file)") from None
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
    regular_file(path, "calibration", MAX_CALIBRATION_BYTES)
    try:
        with open(path, encoding="utf-8") as fh:
            text = fh.read()
    except OSError as exc:
        raise InputError(f"cannot read calibration file {path}: {exc.strerror}") from None
    except UnicodeDecodeError:
        raise InputError(f"calibration file {path} is not text") from None
    return loads(text, node_name, uncorrected)
