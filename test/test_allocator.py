"""The allocator setting of the solving processes: freed arrays' memory is reused, not faulted in anew."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from magcal_ros import allocator

ROOT = Path(__file__).resolve().parents[1]

# Rounds of several 4 MB arrays alive at once, all freed at the end of each round (as a solve's stages
# build and drop their arrays): the pages the last round faults in.
ROUNDS = """
import json, resource, sys
import numpy as np
from magcal_ros.allocator import keep_freed_memory
took = keep_freed_memory() if sys.argv[1] == "kept" else None
faults = []
for _ in range(4):
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    arrays = [np.ones(512 * 1024) for _ in range(8)]
    del arrays
    faults.append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
print(json.dumps({"took": took, "faults": faults}))
"""

def _rounds(mode: str) -> dict:
    out = subprocess.run([sys.executable, "-c", ROUNDS, mode], capture_output=True, text=True, check=True,
                         cwd=ROOT, timeout=120)
    return json.loads(out.stdout)


@pytest.mark.skipif(allocator._glibc() is None, reason="the setting applies to glibc only")
def test_kept_memory_is_reused_where_the_default_faults_every_round_in_again() -> None:
    kept, default = _rounds("kept"), _rounds("default")
    assert kept["took"] is True
    # the default hands the freed 32 MB back each round (beyond its trim threshold) and faults it in again
    # (4 KB pages, or fewer where the kernel backs some with huge pages: some thousands)
    assert min(default["faults"][1:]) > 1000
    assert max(kept["faults"][1:]) < min(default["faults"][1:]) / 20


def test_keeping_again_is_harmless_repeated() -> None:
    for _ in range(2):
        allocator.keep_freed_memory()
