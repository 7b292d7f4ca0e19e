"""A bag's side topics (currents, temperatures, the IMU) read in one pass: the same recording, counts and
errors as the three readers one after the other, the bag opened once."""

from __future__ import annotations

import contextlib
from pathlib import Path

import numpy as np
import pytest
from test_offline import magcal, ok

from magcal_ros.errors import InputError
from magcal_ros.io import bag_reader
from magcal_ros.io.recordings import (
    CURRENTS,
    IMU_TOPIC,
    TEMPERATURES,
    SideTopics,
    open_recording,
    with_bag_currents,
    with_bag_imu,
    with_bag_side_streams,
    with_bag_temperatures,
)

CURRENT_TOPICS = ("/thruster1/battery", "/thruster2/battery")


@pytest.fixture(scope="module", params=["sqlite3", "mcap"])
def side_bag(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A tumble with two thrusters' currents, a warming and an IMU at its own 100 Hz."""
    out = tmp_path_factory.mktemp("side") / f"side_{request.param}_bag"
    ok(magcal("simulate", out, "--storage", request.param, "--schedule", "tumble", "--count", 300, "--seed", 3,
              "--temperature-ramp", "5,25", "--imu", "--imu-rate", 100,
              "--thruster=-0.7,0.25,0.1,0.06,0,0.04", "--thruster=-0.7,-0.25,0.1,0,-0.06,0.04",
              "--thruster-current", "random:20"))
    return out


def _assert_same(a, b) -> None:  # noqa: ANN001 - two Recordings
    assert a.names == b.names and a.channels == b.channels
    np.testing.assert_array_equal(a.stamps, b.stamps)
    np.testing.assert_array_equal(a.vectors, b.vectors)
    np.testing.assert_array_equal(a.currents, b.currents)
    np.testing.assert_array_equal(a.temperatures, b.temperatures)
    np.testing.assert_array_equal(a.imu.orientation, b.imu.orientation)
    np.testing.assert_array_equal(a.imu.angular_velocity, b.imu.angular_velocity)
    assert a.imu.frame_id == b.imu.frame_id


@contextlib.contextmanager
def counted_opens(monkeypatch: pytest.MonkeyPatch):  # noqa: ANN201
    """Count the bag opens (and the message passes) while inside."""
    opened: list[Path] = []
    passes: list[int] = []
    real_open, real_rows = bag_reader.open_bag, bag_reader.message_rows

    def open_bag(path):  # noqa: ANN001, ANN202
        opened.append(Path(path))
        return real_open(path)

    def message_rows(reader, connections):  # noqa: ANN001, ANN202
        passes.append(len(connections))
        return real_rows(reader, connections)

    monkeypatch.setattr(bag_reader, "open_bag", open_bag)
    monkeypatch.setattr(bag_reader, "message_rows", message_rows)
    yield opened, passes
    monkeypatch.setattr(bag_reader, "open_bag", real_open)
    monkeypatch.setattr(bag_reader, "message_rows", real_rows)


@pytest.mark.parametrize("tolerances", [(0.5, 5.0, 0.05), (0.004, 5.0, 0.0099)], ids=["wide", "tight"])
def test_one_pass_gives_the_recording_of_the_three_readers_and_opens_the_bag_once(
        side_bag: Path, tolerances: tuple[float, float, float], monkeypatch: pytest.MonkeyPatch) -> None:
    rec, _ = open_recording(side_bag)
    current_tol, temperature_tol, imu_tol = tolerances
    one, cstats = with_bag_currents(side_bag, rec, CURRENT_TOPICS, current_tol)
    two, tstats = with_bag_temperatures(side_bag, one, None, temperature_tol)
    three, istats = with_bag_imu(side_bag, two, "/imu", imu_tol)
    assert len(three) > 0 and three.channels == ("thruster1/battery", "thruster2/battery")
    requests = [SideTopics(CURRENTS, CURRENT_TOPICS, current_tol), SideTopics(TEMPERATURES, None, temperature_tol),
                SideTopics(IMU_TOPIC, ("/imu",), imu_tol)]
    seen = []
    with counted_opens(monkeypatch) as (opened, passes):
        got, stats = with_bag_side_streams(side_bag, rec, requests, lambda r, s, m: seen.append((r.kind.what, len(m))))
    assert opened == [side_bag] and len(passes) == 1 and passes[0] >= 4  # two currents, four temperatures, the IMU
    _assert_same(got, three)
    assert [vars(s) for s in stats] == [vars(cstats), vars(tstats), vars(istats)]
    assert [s.note() for s in stats] == [cstats.note(), tstats.note(), istats.note()]
    assert seen == [("current", len(one)), ("temperature", len(two)), ("IMU", len(three))]
    if tolerances[0] < 0.01:
        assert cstats.dropped or istats.dropped  # the tight case drops sets: the counts are compared, too


def test_the_wrappers_open_the_bag_once_each(side_bag: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    rec, _ = open_recording(side_bag)
    with counted_opens(monkeypatch) as (opened, passes):
        with_bag_currents(side_bag, rec, CURRENT_TOPICS)
        with_bag_temperatures(side_bag, rec)
        with_bag_imu(side_bag, rec, "/imu")
    assert opened == [side_bag] * 3 and len(passes) == 3


def test_one_pass_errors_are_the_readers(side_bag: Path) -> None:
    rec, _ = open_recording(side_bag)
    with pytest.raises(InputError, match="no IMU topic /gyro"):
        with_bag_side_streams(side_bag, rec, [SideTopics(CURRENTS, CURRENT_TOPICS, 0.5),
                                              SideTopics(IMU_TOPIC, ("/gyro",), 0.05)])
    with pytest.raises(InputError, match="the IMU tolerance must be a finite number"):
        with_bag_side_streams(side_bag, rec, [SideTopics(IMU_TOPIC, ("/imu",), -1.0)])
    with pytest.raises(InputError, match="IMU orientation frame must be"):
        with_bag_side_streams(side_bag, rec, [SideTopics(IMU_TOPIC, ("/imu",), 0.05, "nwu")])
    with pytest.raises(InputError, match="no set left; check the topic's stamps") as exc:
        with_bag_side_streams(side_bag, _shifted(rec),
                              [SideTopics(IMU_TOPIC, ("/imu",), 0.05)])
    with pytest.raises(InputError, match=str(exc.value).split(": ", 1)[1][:40]):
        with_bag_imu(side_bag, _shifted(rec), "/imu", 0.05)


def _shifted(rec):  # noqa: ANN001, ANN202
    """The recording's sets an hour before the bag: no side sample near any of them."""
    from dataclasses import replace

    return replace(rec, stamps=rec.stamps - 3600 * 10**9)


def test_a_set_waits_for_its_due_sample_through_a_stall_of_the_node() -> None:
    """WaitingSets: a set nothing is due for goes at once; one whose sample is due waits MAX_WAIT of the node's
    awake time for it (released at the first look after 0.5 s of regular 20 ms looks); a stall of the process
    (its clock jumps 1 s between two looks: the node was not scheduled, its timers run before the messages
    queued meanwhile) counts as AWAKE_STEP only, so the set is still there when its sample is taken in."""
    from magcal_ros.core.side_streams import AWAKE_STEP, MAX_WAIT, WaitingSets

    ms = 1_000_000
    waiting = WaitingSets()
    waiting.add(10, 0, "free")
    assert waiting.release(0, lambda stamp: False) == ["free"]
    waiting.add(20, 0, "due")
    looks = [t * 20 * ms for t in range(1, 40)]
    released_at = next(t for t in looks if waiting.release(t, lambda stamp: True))
    assert MAX_WAIT < released_at <= MAX_WAIT + 20 * ms
    stalled = WaitingSets()
    stalled.add(30, 5 * ms, "set")
    assert stalled.release(5 * ms + 1000 * ms, lambda stamp: True) == []  # woke from a 1 s stall: still waiting
    assert AWAKE_STEP < MAX_WAIT
    assert stalled.release(5 * ms + 1001 * ms, lambda stamp: False) == ["set"]  # its sample came: it goes
