"""Imported first by the benchmarks: this checkout's ``magcal_ros`` on the path, loaded before
numpy so that its process settings (one BLAS thread unless set, as for the ``magcal`` command and the
nodes; freed memory kept for reuse, as for the command) hold."""

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

import magcal_ros  # noqa: E402,F401
from magcal_ros.allocator import keep_freed_memory  # noqa: E402

keep_freed_memory()
