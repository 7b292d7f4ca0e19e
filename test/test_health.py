"""Stream health behind /diagnostics (no middleware): losses from stamp gaps, silence, levels."""

from __future__ import annotations

import numpy as np

from magcal_ros.core.sync import SetSynchronizer, stream_synchronizer
from magcal_ros.nodes.health import ERROR, OK, WARN, ArrayHealth, HealthLimits

MS = 1_000_000
LIMITS = HealthLimits(silent_after_ns=1000 * MS, stale_after_ns=3000 * MS, max_drop_fraction=0.01)


def _feed(stamps_by_sensor: list[list[int]]) -> tuple[ArrayHealth, SetSynchronizer]:
    """Offer each sensor's stamps, interleaved by time, as a node does."""
    sync = SetSynchronizer(len(stamps_by_sensor))
    health = ArrayHealth(tuple(f"mag{k + 1}" for k in range(len(stamps_by_sensor))), sync, LIMITS, 0)
    events = sorted((t, k) for k, stamps in enumerate(stamps_by_sensor) for t in stamps)
    for t, k in events:
        health.seen(k, t)
        sync.add(k, t, 1e-5, 2e-5, 3e-5)
    return health, sync


def test_gaps_count_lost_messages_also_when_every_other_one_is_lost() -> None:
    period = 5 * MS
    full = [1000 * MS + k * period for k in range(400)]
    sparse = [t for k, t in enumerate(full) if k not in (50, 120, 121, 122)]
    dense = [t for k, t in enumerate(full) if not (200 <= k < 300 and k % 2)]  # 50 lost, every other one
    health, _ = _feed([full, sparse, dense])
    assert health.lost == [0, 4, 50] and health.gaps == [0, 2, 50]


def test_a_pause_is_not_a_loss_and_a_new_rate_is_learnt() -> None:
    first = [1000 * MS + k * 5 * MS for k in range(100)]
    after = [first[-1] + 3000 * MS + k * 20 * MS for k in range(100)]  # 3 s pause, then 50 Hz
    lossy = [t for k, t in enumerate(after) if k != 60]
    health, _ = _feed([first + after, first + lossy])
    assert health.lost == [0, 1] and health.gaps == [0, 1]


def test_levels_name_a_silent_sensor_and_no_output_is_an_error() -> None:
    sync = SetSynchronizer(2)
    health = ArrayHealth(("mag1", "mag2"), sync, LIMITS, 0)
    for k in range(1, 11):
        for i in (0, 1):
            health.seen(i, k * 10 * MS)
            sync.add(i, k * 10 * MS, 1e-5, 2e-5, 3e-5)
    health.output(10, 100 * MS)
    ok = health.assess(200 * MS, sync.stats.as_dict(), "sets published")
    assert ok.level == OK and ok.message == "ok"
    health.seen(0, 110 * MS)  # mag2 stops
    warn = health.assess(1300 * MS, sync.stats.as_dict(), "sets published")
    assert warn.level == WARN and "silent: mag2 (1.1 s)" in warn.message and "mag1 (" not in warn.message
    error = health.assess(3200 * MS, sync.stats.as_dict(), "sets published")
    assert error.level == ERROR and error.message.startswith("no sets published for 3.1 s")
    assert np.isclose(float(error.values["mag1.period_ms"]), 10.0)


def test_a_sensor_restarted_and_placed_is_not_called_late() -> None:
    """mag2's driver restarts 2 s in, its stamps 30 s back: placed on the common time line it keeps up with
    mag1, and the report does not call it 30 s behind (its stamps are, its samples are not)."""
    sync = stream_synchronizer(["mag1", "mag2"])
    health = ArrayHealth(("mag1", "mag2"), sync, LIMITS, 0)
    start = 100_000 * MS
    for k in range(400):
        for i in (0, 1):
            stamp = start + k * 10 * MS - (30_000 * MS if i == 1 and k >= 200 else 0)
            health.seen(i, stamp)
            sync.add(i, stamp, 1e-5, 2e-5, 3e-5, start + k * 10 * MS + MS)
    health.output(300, start + 4000 * MS)
    report = health.assess(start + 4000 * MS, sync.stats.as_dict(), "sets published")
    assert sync.stats.restarts == 1, sync.stats.describe()
    assert "behind" not in report.message and report.level == OK, report.message


def test_drops_above_the_fraction_are_a_warning_with_the_losses_named() -> None:
    period = 10 * MS
    stamps = [1000 * MS + k * period for k in range(200)]
    lossy = [t for k, t in enumerate(stamps) if k % 10 != 5]  # 20 lost of 200 (the first within the first intervals, once missed)
    health, sync = _feed([stamps, lossy])
    health.output(sync.stats.sets, 3000 * MS)
    report = health.assess(3000 * MS, sync.stats.as_dict(), "sets published")
    assert report.level == WARN and "dropping" in report.message and "mag2 20" in report.message
    assert report.values["lost"] == "20" and report.values["mag2.gaps"] == "20"
    quiet = health.assess(3100 * MS, sync.stats.as_dict(), "sets published")  # nothing new: no drops
    assert quiet.level == OK


def test_stale_currents_are_counted_per_channel_and_warned_once_per_period() -> None:
    from magcal_ros.core import side_streams as side
    from magcal_ros.core.interference import LatestCurrents
    from magcal_ros.nodes.health import CurrentHealth

    health = CurrentHealth(("t1/battery", "t2/battery"), ("/t1/battery", "/ns/t2/battery"), 500 * MS)
    store = LatestCurrents(2, 500 * MS, check=side.CURRENT.check)
    for k in range(9):
        store.add(0, 1000 * MS + 100 * MS * k, 10.0 + k)
    store.add(0, 1900 * MS, 1e30)  # out of range: no value, counted
    store.add(0, 2000 * MS, 12.5)
    assert health.count([True, True]) and not health.count([True, False]) and not health.count([False, False])
    text, values = health.assess(store, "withheld")
    assert text == ("stale current (no value within 500 ms before the set), sets withheld: t1/battery on "
                    "/t1/battery: 1 sets, t2/battery on /ns/t2/battery (none received yet): 2 sets; current samples "
                    "dropped: 1 of t1/battery on /t1/battery (1 out of range)")
    drops = {f"{n}.current_{c}": "1" if (n, c) == ("t1/battery", "out_of_range") else "0"
             for n in ("t1/battery", "t2/battery") for c in ("out_of_range", "glitch", "nonfinite")}
    assert values == {"t1/battery.stale_current": "1", "t1/battery.current_received": "10", "t1/battery.current_A": "12.5",
                      "t2/battery.stale_current": "2", "t2/battery.current_received": "0", "t2/battery.current_A": "",
                      **drops}
    store.add(0, 2100 * MS, 12.0)
    again, values = health.assess(store, "withheld")  # nothing new: no warning, counts kept
    assert again is None and values["t2/battery.stale_current"] == "2" and values["t1/battery.current_received"] == "11"
    assert CurrentHealth((), (), 0).assess(LatestCurrents(0, 0), "withheld") == (None, {})
