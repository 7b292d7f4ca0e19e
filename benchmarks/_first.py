"""Imported first by the benchmarks: this checkout's ``magcal_ros`` on the path, loaded before
numpy so that its process settings (one BLAS thread unless set) hold as they do for the ``magcal``
command and the nodes."""

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

import magcal_ros  # noqa: E402,F401
