"""Input files read in bounded memory: what every reader checks before it reads a byte.

A recording or a calibration is a regular file; a device, a pipe or a link to one (``/dev/zero``,
``/dev/urandom``, a FIFO) never ends, and reading it whole exhausts memory before any check says
what is wrong. :func:`regular_file` refuses them in one line, and text files that cannot be what they
claim (a calibration larger than :data:`MAX_CALIBRATION_BYTES`).
"""

from __future__ import annotations

import os
import stat
from pathlib import Path

from magcal_ros.errors import InputError

MAX_CALIBRATION_BYTES: int = 64 * 1024 * 1024
"""Largest calibration file read (a file of many sensors with their provenance is kilobytes)."""
MAX_HEADER_BYTES: int = 1024 * 1024
"""Longest first line of a CSV recording read in search of its header."""


def regular_file(path: str | os.PathLike[str], what: str, max_bytes: int | None = None) -> Path:
    """``path`` when it names a regular file (following links) of at most ``max_bytes``;
    :class:`InputError` naming ``what`` (``recording``, ``calibration``) otherwise."""
    p = Path(path)
    try:
        st = p.stat()
    except FileNotFoundError:
        raise InputError(f"{p} does not exist") from None
    except OSError as exc:
        raise InputError(f"cannot read {p}: {exc.strerror}") from None
    if stat.S_ISDIR(st.st_mode):
        raise InputError(f"{p} is a directory, not a {what} file")
    if not stat.S_ISREG(st.st_mode):
        raise InputError(f"{p} is not a regular file (a device, pipe or socket never ends): give a {what} file")
    if max_bytes is not None and st.st_size > max_bytes:
        raise InputError(f"{p} is {st.st_size} bytes: no {what} is larger than {max_bytes} bytes")
    return p
