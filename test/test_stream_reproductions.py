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


def test_a_csv_whose_stamps_all_jump_back_says_so(tmp_path) -> None:  # type: ignore[no-untyped-def]
    """Every row's stamp 60 s back from the middle of a CSV on: one restart, said in the note (a bag said it, a
    CSV did not), and the rows still form their sets."""
    from test_offline import magcal, ok

    csv = tmp_path / "run.csv"
    ok(magcal("simulate", csv, "--count", 400, "--seed", 2, "-q"))
    lines = csv.read_text().splitlines()
    for k in range(200, len(lines)):
        cells = lines[k].split(",")
        whole, frac = cells[0].split(".")
        cells[0] = f"{int(whole) - 60}.{frac}"
        lines[k] = ",".join(cells)
    csv.write_text("\n".join(lines) + "\n")
    proc = ok(magcal("calibrate", csv, "-o", tmp_path / "c.yaml"))
    assert "note: 400 sets, 1 source restarts or stamp steps" in proc.stderr


def test_four_sensors_at_400_hz_with_jitter_and_loss_give_the_same_sets_live_and_offline() -> None:
    """Four sensors at 400 Hz, 0.45 ms of stamp jitter, 2 % loss: offline chose interpolation for the whole
    recording, the live node exact matching from its first stamps (not one set stamp in common). One rule
    on the same stamps: the same mode and the same sets."""
    spec = StreamSpec(rate=400.0, phases=0.0, delay=0.001, jitter=0.00045, loss=0.02)
    rec = record(spec, 3.0)
    batch, stats, mode, sets, sync = both_paths(rec)
    assert sync.mode == mode
    n = len(sets)
    assert n >= len(batch) - 10 and np.array_equal(batch.stamps[:n], np.array([s.stamps for s in sets]))


def test_a_stalled_driver_delivering_its_backlog_at_once_does_not_change_the_rate() -> None:
    """A driver stalls 4 s, then delivers its 200-message backlog stamped on delivery 0.04 ms apart (25 kHz): the
    node took that for the sample rate (a sync window of 0.019 ms) and warned of 99.8 % losses on a clean 50 Hz
    stream for the rest of the run. The backlog is dropped and counted (its stamps say nothing of its
    samples), the rate stays 50 Hz, nothing later is lost, and the sets go on."""
    ns, t0, period = 1_000_000_000, 1_700_000_000 * 1_000_000_000, 20_000_000
    sync = stream_synchronizer(["mag1", "mag2", "mag3", "mag4"])
    sets = []
    for n in range(1500):  # 30 s at 50 Hz
        t = t0 + n * period
        for k in range(4):
            stamp = receipt = t + 1_000_000 + k * 100_000
            if k == 2 and 10 * ns <= t - t0 < 14 * ns:
                continue  # stalled: delivered at once below
            sets += sync.add(k, stamp, 1e-5 + 1e-9 * n, 2e-5, 3e-5, receipt)
            if k == 1 and t - t0 == 14 * ns:  # mag3's backlog, stamped as it comes
                for j in range(200):
                    sets += sync.add(2, t + j * 40_000, 1e-5 + 1e-9 * (n - 200 + j), 2e-5, 3e-5, t + j * 40_000)
    assert sync.stats.burst >= 199 and sync.lost(2) <= 1
    assert abs(sync.period_ns(2) - period) < 0.01 * period
    late = [s for s in sets if s.stamp > t0 + 16 * ns]
    assert len(late) >= 0.99 * (14 * 50)
    assert sync.effective_tolerance_ns >= 1_000_000 or sync.mode == "interpolate"


def test_a_busy_node_draining_its_queue_counts_each_lost_sample_and_no_step() -> None:
    """A node busy for a while takes the queued messages faster than they were stamped (here 12 ms a set of
    four against 20 ms): arrivals then look timed (ratio 0.6) while the stamps' lead over them grows all
    along, and a sample lost on the way (one in 20 of mag2) was read as the stamps stepping forward: a
    restart of that sensor's clock, and only 13 of 18 losses in the node's diagnostics. Each is a loss."""
    ns, t0, period = 1_000_000_000, 1_700_000_000 * 1_000_000_000, 20_000_000
    sync = stream_synchronizer(["mag1", "mag2", "mag3", "mag4"])
    receipt = t0 - ns
    rng = np.random.default_rng(3)
    for n in range(400):
        for k in range(4):
            if k == 1 and n >= 40 and n % 20 == 10:
                continue
            receipt += int(3_000_000 * rng.uniform(0.8, 1.2))
            sync.add(k, t0 + n * period, 1e-5 + 1e-9 * n, 2e-5, 3e-5, receipt)
    assert [sync.lost(k) for k in range(4)] == [0, 18, 0, 0]
    assert [sync.gaps(k) for k in range(4)] == [0, 18, 0, 0]
    assert sync.stats.restarts == 0


def test_a_new_synchroniser_for_new_time_offsets_keeps_a_restarted_sensors_placement() -> None:
    """A node's synchroniser is rebuilt when a recalibration sets time offsets; mag3's driver had restarted
    30 s back before that. The new synchroniser knew nothing of the restart: mag3 was paired 30 s off (or
    not at all) for the rest of the mission. It goes on placing each sensor as the old one did."""
    ns, t0, period = 1_000_000_000, 1_700_000_000 * 1_000_000_000, 20_000_000
    names = ["mag1", "mag2", "mag3", "mag4"]

    def feed(sync, first: int, count: int) -> list:  # type: ignore[no-untyped-def,type-arg]
        sets = []
        for n in range(first, first + count):
            for k in range(4):
                stamp = t0 + n * period + (-30 * ns if k == 2 and n >= 300 else 0)  # mag3 restarted at set 300
                sets += sync.add(k, stamp, 1e-5 + 1e-9 * n, 2e-5, 3e-5, t0 + n * period + 3_000_000 + k * 100_000)
        return sets

    old = stream_synchronizer(names, mode="interpolate")
    assert len(feed(old, 0, 600)) > 590 and old.stats.restarts == 1
    new = stream_synchronizer(names, mode="auto", time_offsets={"mag2": 0.001})
    new.keep_placements(old.placements())
    sets = feed(new, 600, 400)
    assert len(sets) >= 390
    common = np.array([s.stamps for s in sets], dtype=np.int64)  # on the common time line
    assert np.max(np.ptp(common[:, [0, 2, 3]], axis=1)) <= 1_000_000  # every set pairs one instant


def test_a_sensor_silent_for_20_s_in_a_replay_five_times_faster_is_a_pause_not_a_step() -> None:
    """A recording replayed five times faster than it was made (its arrivals keep no time: a fifth of the
    stamps' intervals) in which mag3, sampling on its own clock, is silent for 20 s: its next stamp is 20 s
    on, its arrival 4 s on. It was taken for a step (more than 1 s ahead with arrivals that keep no time) and
    placed one period after its last sample: 20 s off the others for the rest of the replay. The arrivals at
    their own pace saw the gap pass: a pause, and every later set pairs one instant."""
    t0, period = 1_700_000_000 * 1_000_000_000, 50_000_000
    phases = (0, 16_000_000, 33_000_000)  # each sensor on its own clock, none in line with another
    sync = stream_synchronizer(["mag1", "mag2", "mag3"], mode="interpolate")
    sets = []
    for n in range(2000):
        for k in range(3):
            if k == 2 and 600 <= n < 1000:  # mag3 silent from 30 s to 50 s
                continue
            t = n * period + phases[k]
            sets += sync.add(k, t0 + t, 1e-6 * t / 1e9, 2e-5, 3e-5, t0 + t // 5 + 200_000)  # x: the true time
    assert sync.stats.restarts == 0
    late = np.array([[v[0] for v in s.values] for s in sets if s.stamps[0] >= t0 + 1000 * period])
    assert len(late) >= 990  # the sets after the silence, every one
    assert np.max(np.abs(late - late[:, :1])) < 1e-9  # interpolated to one instant (1 ms of x)
