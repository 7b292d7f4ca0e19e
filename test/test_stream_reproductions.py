"""The stream faults an independent check reproduced, each as a test against simulated truth.

The simulator (:mod:`magcal_ros.sim.streams`) samples four sensors on their own clocks during a
turn, stamps them on receipt and records bag times; the field is uniform, so with the true
calibration the tensor is noise only, and its RMS against the floor sqrt(2) sigma / d measures
whether the sets pair readings of one instant. Every fault below went silent before: the tensor
was 2,600-25,000x the floor for the rest of the recording, or thousands of sets paired readings
0.25-0.53 s apart.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from magcal_ros.core.field import earth_field
from magcal_ros.core.geometry import ArrayGeometry
from magcal_ros.core.metrics import tensor_floor
from magcal_ros.core.sync import stream_synchronizer, synchronise_streams
from magcal_ros.core.units import NT
from magcal_ros.sim.simulator import ArraySimulation, random_sensor_errors
from magcal_ros.sim.streams import PHASED, StreamRecording, StreamSpec, simulate_streams, turn

FLOOR = tensor_floor(1 * NT, 0.4)
RATE = 100.0
"""Each sensor's sample rate (Hz)."""


def record(spec: StreamSpec, duration: float, seed: int = 3) -> StreamRecording:
    rng = np.random.default_rng(seed)
    geo = ArrayGeometry.cross(0.4)
    sim = ArraySimulation(geo, tuple(random_sensor_errors(rng) for _ in geo.names),
                          earth_field(51_500 * NT, 60.0, 5.0), noise=1 * NT)
    attitudes, steps = turn(0.2, duration + 1.0)
    return simulate_streams(sim, attitudes, steps, spec, duration, np.random.default_rng(seed + 10))


def blocks(rec: StreamRecording, stamps: np.ndarray, vectors: np.ndarray, seconds: float = 10.0) -> list[float]:
    """Tensor RMS against the floor with the true calibration, per ``seconds`` of set stamps."""
    tensor = rec.calibration.outputs(vectors).tensor
    t = (stamps - stamps[0]) / 1e9
    return [float(np.sqrt(np.mean(tensor[(t >= a) & (t < a + seconds)] ** 2)) / FLOOR)
            for a in np.arange(0.0, t[-1] - seconds / 2, seconds)]


def both_paths(rec: StreamRecording):  # type: ignore[no-untyped-def]
    """The sets offline (batches with bag times) and live (one message at a time in arrival order)."""
    batch, stats, mode = synchronise_streams([(s.stamps, s.vectors) for s in rec.streams], mode="auto",
                                             receipts=[s.receipts for s in rec.streams], names=rec.names)
    sync = stream_synchronizer(rec.names)
    sets = []
    for bag_time, k, i in rec.messages():
        s = rec.streams[k]
        v = s.vectors[i].tolist()
        sets += sync.add(k, int(s.stamps[i]), v[0], v[1], v[2], bag_time)
    return batch, stats, mode, sets, sync


@pytest.mark.parametrize("jump", [20.0, 60.0])
def test_a_restart_of_one_sensor_keeps_its_placement_three_times_the_jump_on(jump: float) -> None:
    """mag3's driver restarts 15 s in, its stamps ``jump`` s behind, and the recording goes on three times the
    jump: the new segment was placed right until its stamps passed the old ones (after exactly the jump),
    then paired with the others ``jump`` s off for the rest (2,600-25,000x the floor). Every 10 s block is at
    the floor, offline and live alike, with one restart counted."""
    spec = StreamSpec(phases=PHASED, delay=0.001, jitter=0.0005, restarts=((15.0, jump, (2,)),))
    rec = record(spec, 15.0 + 3 * jump)
    batch, stats, mode, sets, sync = both_paths(rec)
    assert stats.restarts == sync.stats.restarts == 1
    per_block = blocks(rec, batch.set_stamps, batch.vectors)
    assert max(per_block) < 1.3, per_block
    assert len(batch) >= 0.98 * len(rec.streams[0])
    n = len(sets)
    assert np.array_equal(batch.stamps[:n], np.array([s.stamps for s in sets])) and n >= len(batch) - 40


STEPS = [-0.25, -0.5, -0.53, 0.25, 0.5, 0.53, -0.03, 0.03]
"""Stamp steps of one sensor (s): sub-second back and forward, and three whole sample periods either way."""


@pytest.mark.parametrize("step", STEPS)
def test_a_sub_second_step_of_one_sensor_is_a_step(step: float) -> None:
    """One sensor's stamps step by under a second (or a whole number of periods) and the receipts show it at
    hundreds of times their jitter: it was not seen as a restart, and the ~2,000 later sets paired that
    sensor with readings 0.25-0.53 s away. Now a step, placed by the arrivals: every block at the floor."""
    spec = StreamSpec(phases=PHASED, delay=0.001, jitter=0.0005, restarts=((10.0, -step, (1,)),))
    rec = record(spec, 40.0)
    batch, stats, mode, sets, sync = both_paths(rec)
    assert stats.restarts == 1, stats.describe()
    per_block = blocks(rec, batch.set_stamps, batch.vectors)
    assert max(per_block) < 1.3, per_block
    n = len(sets)
    assert np.array_equal(batch.stamps[:n], np.array([s.stamps for s in sets])) and n >= len(batch) - 40


def test_a_restart_of_every_sensor_three_times_the_jump_on() -> None:
    """The same with every sensor's driver restarting at once (one stamping clock): one restart, the sensors
    placed alike, every block at the floor."""
    spec = StreamSpec(phases=PHASED, delay=0.001, jitter=0.0005, restarts=((15.0, 20.0, ()),))
    rec = record(spec, 75.0)
    batch, stats, _, _, _ = both_paths(rec)
    assert stats.restarts == 1
    assert max(blocks(rec, batch.set_stamps, batch.vectors)) < 1.3


def test_the_measure_sees_a_sensor_a_tenth_of_a_second_off() -> None:
    """Not vacuous: the same recording with mag2's stamps shifted 0.1 s (not a step: from the start) is far
    above the floor."""
    rec = record(StreamSpec(phases=PHASED, delay=0.001, jitter=0.0005), 20.0)
    shifted = replace(rec.streams[1], stamps=rec.streams[1].stamps + 100_000_000)
    rec = replace(rec, streams=(rec.streams[0], shifted, *rec.streams[2:]))
    batch, _, _, _, _ = both_paths(rec)
    assert min(blocks(rec, batch.set_stamps, batch.vectors)) > 20
