"""The boundaries of the stream rules an independent mutation pass found unguarded, each pinned on both
sides: a hole of two lost samples is bridged and one of three is not; a glitch 3-4 periods ahead costs
one message; temperatures in kelvin are refused (CSV and bag) where one out-of-range value is dropped;
the offline temperature tolerance is 10 s by default; an IMU gap in mid-stream drops exactly the sets
it leaves bare, live as offline."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from magcal_ros.core.imu import ImuStream, LatestImu, match_imu
from magcal_ros.core.matching import match_latest
from magcal_ros.core.sync import SetSynchronizer, synchronise_streams
from magcal_ros.core.temperature import TemperatureSamples, check_temperatures
from magcal_ros.errors import InputError
from magcal_ros.io.csv_recording import read_csv

NS = 1_000_000_000
MS = 1_000_000
T0 = 1_700_000_000 * NS
PERIOD = 10 * MS


def _stream(n: int, phase: int = 0, drop: tuple[int, ...] = ()) -> tuple[np.ndarray, np.ndarray]:
    k = np.array([i for i in range(n) if i not in drop])
    stamps = T0 + phase + k * PERIOD
    return stamps.astype(np.int64), np.column_stack([1e-5 + 1e-6 * k, np.zeros(len(k)), np.zeros(len(k))])


@pytest.mark.parametrize("lost, bridged", [(1, True), (2, True), (3, False), (4, False)])
def test_two_lost_samples_are_bridged_and_three_are_not(lost: int, bridged: bool) -> None:
    """Interpolation bridges a hole of at most 3.5 periods: two lost samples in a row (3 periods) are
    bridged, three (4 periods) are not, and the reference samples inside the hole are counted as ``gap``."""
    ref = _stream(200)
    other = _stream(200, phase=3 * MS, drop=tuple(range(100, 100 + lost)))
    batch, stats, _ = synchronise_streams([ref, other], mode="interpolate", names=["a", "b"])
    inside = [t for t in ref[0] if other[0][99] < t < other[0][100]]
    assert len(inside) == lost + 1
    assert (stats.gap == 0) == bridged and (bridged or stats.gap == len(inside))


@pytest.mark.parametrize("ahead", [3.0, 3.5, 4.0])
def test_a_glitch_three_to_four_periods_ahead_costs_one_set(ahead: float) -> None:
    """One stamp 3-4 periods ahead of its sequence (the sequence going on below it) is a glitch: that message
    is dropped and its partner finds no set; nothing else is lost."""
    a, b = _stream(100), _stream(100)
    b[0][50] += int(ahead * PERIOD)
    sync = SetSynchronizer(2, MS)
    for k, (s, v) in enumerate((a, b)):
        sync.add_batch(k, s, v)
    batch = sync.pop(final=True)
    assert (sync.stats.glitch, sync.stats.unmatched, len(batch)) == (1, 1, 99)


def test_temperatures_in_kelvin_are_refused_and_one_out_of_range_is_dropped(tmp_path: Path) -> None:
    """A temperature column in kelvin (about 290) is a units error, refused naming the file; one value of
    -300 deg C among deg C is no value: its row is dropped and counted (it refused the whole recording)."""
    rows = ["stamp,a.x,a.y,a.z,temperature.a"] + [f"{k + 1}.0,1e-5,2e-5,{3e-5 + k * 1e-9},{290.0 + k * 0.01}"
                                                   for k in range(50)]
    path = tmp_path / "kelvin.csv"
    path.write_text("\n".join(rows) + "\n")
    with pytest.raises(InputError, match="kelvin.csv.*temperatures must be in deg C"):
        read_csv(path)
    with pytest.raises(InputError, match="temperatures must be in deg C"):
        check_temperatures(np.full(20, 291.0), "bag: /a/temperature")
    rows = ["stamp,a.x,a.y,a.z,temperature.a"] + [f"{k + 1}.0,1e-5,2e-5,{3e-5 + k * 1e-9},{12.0 if k != 20 else -300.0}"
                                                   for k in range(50)]
    path = tmp_path / "one.csv"
    path.write_text("\n".join(rows) + "\n")
    rec, stats = read_csv(path)
    assert len(rec) == 49 and stats.side_value == 1 and np.all(rec.temperatures == 12.0)


def test_the_offline_temperature_tolerance_is_ten_seconds_by_default() -> None:
    """Offline a set takes a temperature stamped up to 10 s before it (the default), not 10 s and 1 ns."""
    from magcal_ros.core.temperature import DEFAULT_TEMPERATURE_TOLERANCE
    from magcal_ros.io.recordings import tolerance_of

    tol = tolerance_of(DEFAULT_TEMPERATURE_TOLERANCE, "temperature")
    assert tol == 10 * NS
    samples = [TemperatureSamples("a", np.array([T0], np.int64), np.array([12.0]))]
    _, fresh = match_latest(np.array([T0 + tol, T0 + tol + 1]), samples, tol)
    assert fresh[:, 0].tolist() == [True, False]


def test_an_imu_gap_in_mid_stream_drops_the_sets_it_leaves_bare_live_as_offline() -> None:
    """A 100 Hz IMU silent for half a second: the sets more than the tolerance (0.1 s) after its last sample
    before the gap have no IMU sample (offline and live alike: the gap is not bridged by interpolation);
    the others keep theirs."""
    tol = 100 * MS
    t = T0 + np.arange(300) * PERIOD
    keep = (t < T0 + 1 * NS) | (t >= T0 + 1 * NS + 500 * MS)
    q = np.tile([0.0, 0.0, 0.0, 1.0], (int(keep.sum()), 1))
    w = np.tile([0.0, 0.0, 0.1], (int(keep.sum()), 1))
    stream = ImuStream(t[keep], q, w)
    sets = T0 + 5 * MS + np.arange(290) * PERIOD
    _, fresh = match_imu(sets, stream, tol)
    last_before = t[keep][t[keep] < T0 + 1 * NS].max()
    expected = ~((sets - last_before > tol) & (sets < T0 + 1 * NS + 500 * MS))
    assert np.array_equal(fresh, expected) and (~fresh).sum() == 41  # 1.095 .. 1.495 s
    live = LatestImu(tol, keep_ns=10 * NS)
    for stamp, qq, ww in zip(t[keep].tolist(), q, w):
        live.add(stamp, qq, ww)
    assert [live.at(int(s))[2] for s in sets] == fresh.tolist()


@pytest.mark.parametrize(("last", "kept"), [
    (100_000, True),  # crowded (a backlog's stamp 0.1 ms after the previous): kept
    (-5 * MS, False), (-2 * NS, False),  # behind its sequence: a glitch
    (30 * MS, True), (NS, True),  # ahead, up to the restart jump (1 s): kept
    (NS + 1, False), (3 * NS // 2, False),  # further ahead and never confirmed: a glitch
])
def test_a_suspect_stamp_held_when_its_stream_ends_is_kept_or_a_glitch_by_its_kind(last: int, kept: bool) -> None:
    """A stream whose last stamp is held as a suspect when it ends: crowded or ahead within ``restart_ns`` it is
    kept (and, its partner's sample missing, counted unmatched), behind or further ahead a glitch."""
    a = T0 + np.arange(100, dtype=np.int64) * PERIOD
    b = np.concatenate([a[:99], [a[98] + last]]).astype(np.int64)
    sync = SetSynchronizer(2, MS)
    for k, s in enumerate((a, b)):
        sync.add_batch(k, s, np.tile([1e-5, 0.0, 0.0], (len(s), 1)))
    batch = sync.pop(final=True)
    assert len(batch) == 99 and sync.stats.used == 198
    assert (sync.stats.glitch, sync.stats.unmatched) == ((0, 2) if kept else (1, 1))


@pytest.mark.parametrize(("stall", "count", "burst", "faster"), [
    (51, 20, 20, 0),  # a 0.52 s stall's backlog of 20 messages: every one dropped as stamped on delivery
    (10, 15, 15, 0), (10, 16, 15, 1),  # after 0.11 s, no more than 1.25 times the gap and two periods held ...
    (10, 40, 15, 25),  # ... then the rest is a faster rate, taken
])
def test_a_backlog_stamped_on_delivery_after_a_stall_is_dropped_up_to_what_the_gap_could_hold(
        stall: int, count: int, burst: int, faster: int) -> None:
    """A driver that stalled for ``stall`` + 1 periods and then stamped its backlog of ``count`` messages as it
    delivered them (0.1 ms apart): those stamps are no sample instants; the backlog's are dropped (``burst``)
    while their number fits the gap, more are a rate gone up (taken, unmatched). The regular stamps after it
    form every set, the first one included."""
    a = T0 + np.arange(300, dtype=np.int64) * PERIOD
    backlog = a[100 + stall] + 100_000 * np.arange(count)
    b = np.concatenate([a[:100], backlog, a[100 + stall + 2 :]]).astype(np.int64)
    sync = SetSynchronizer(2, MS)
    for k, s in enumerate((a, b)):
        sync.add_batch(k, s, np.tile([1e-5, 0.0, 0.0], (len(s), 1)))
    batch = sync.pop(final=True)
    after = len(a) - (100 + stall + 2)
    assert len(batch) == 100 + after and set(batch.stamps[100:, 1].tolist()) == set(a[100 + stall + 2 :].tolist())
    assert (sync.stats.burst, sync.stats.unmatched) == (burst, stall + 2 + faster)
