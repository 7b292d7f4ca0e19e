"""Integer-nanosecond time end to end: ``magcal correct`` writes exactly the input stamps.

At today's epoch a float second resolves only ~0.24 us, so a stamp that went through a
float comes back off by up to ~120 ns; these stamps carry odd nanoseconds to catch that.
"""

from __future__ import annotations

import csv
import re
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from rosbags.rosbag2 import Reader
from test_offline import magcal, ok

from magcal_ros.core.recording import Recording
from magcal_ros.core.stamps import (MAX_SECONDS, _digit_seconds, _plain_seconds, format_seconds,
                                    format_seconds_column, join_stamp, ns_to_seconds, parse_seconds,
                                    parse_seconds_column, seconds_to_ns, split_stamp)
from magcal_ros.errors import InputError
from magcal_ros.io import calibration_file as calfile
from magcal_ros.io import cdr
from magcal_ros.io.bag_writer import write_recording_bag
from magcal_ros.io.csv_recording import write_csv
from magcal_ros.sim import scenarios
from magcal_ros.sim.attitudes import uniform_random

NS = 1_000_000_000


def odd_recording(n: int = 200) -> Recording:
    """Sets 10 ms apart plus odd nanoseconds, from a simulated array (any readings would do)."""
    rng = np.random.default_rng(2)
    sim = scenarios.coaxial2022_simulation()
    rec, _ = sim.run(uniform_random(n, rng), rng)
    stamps = 1_763_900_000 * NS + np.arange(n, dtype=np.int64) * 10_000_000 + rng.integers(1, 999, n) * 1_000_003
    return Recording(rec.names, np.sort(stamps) + 7, rec.vectors)


@pytest.fixture(scope="module")
def calibration(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("cal") / "identity.yaml"
    from magcal_ros.core.calibration import ArrayCalibration

    path.write_text(calfile.dumps(ArrayCalibration.identity(scenarios.coaxial2022_simulation().geometry)))
    return path


def test_format_and_parse_are_exact_inverses() -> None:
    for ns in (0, 1, 999_999_999, 1_763_900_000_123_456_789, -1, -1_500_000_000):
        assert parse_seconds(format_seconds(ns)) == ns
    assert format_seconds(1_763_900_000_000_000_007) == "1763900000.000000007"
    assert parse_seconds("1763900000.1234567891") == 1_763_900_000_123_456_789
    assert parse_seconds("1.7e9") == 1_700_000_000 * NS and parse_seconds(" 0.02 ") == 20_000_000


def test_a_column_of_stamps_parses_as_each_stamp_alone() -> None:
    """The column parser's fast paths (plain ``digits.digits`` of any 1-9 decimals) give each text's own
    nanoseconds; anything else goes one by one; a stamp out of range is refused, never wrapped around."""
    rng = np.random.default_rng(8)
    plain = [f"{w}.{str(f).zfill(k)}" for w, f, k in zip(rng.integers(0, 9 * 10**9, 500), rng.integers(0, 10**9, 500),
                                                         rng.integers(1, 10, 500))]
    plain = [t if len(t.split(".")[1]) <= 9 else t[: t.index(".") + 10] for t in plain]
    assert parse_seconds_column(plain).tolist() == [parse_seconds(t) for t in plain]
    mixed = plain[:5] + ["1.7e9", " 0.02", "5", "1.", ".5", "1.1234567891"]
    assert parse_seconds_column(mixed).tolist() == [parse_seconds(t) for t in mixed]
    with pytest.raises(InputError, match="1.2.3"):  # two points beside none: as many points as texts
        parse_seconds_column(["0.5", "1.2.3", "4", "5.5"])
    for bad in (["999999999999.5", "1.0"], ["9000000000.0", "1.0"]):
        with pytest.raises(InputError, match="out of range"):
            parse_seconds_column(bad)


def test_stamps_to_and_from_seconds_at_the_edges(monkeypatch: pytest.MonkeyPatch) -> None:
    """Zero is written without a sign; float seconds go to the nearest nanosecond either side of zero; an empty
    column is an empty array; a column of plain texts never goes to the one-by-one parse (a CSV of a million
    rows)."""
    assert format_seconds(0) == "0.000000000" and format_seconds(-1) == "-0.000000001"
    assert format_seconds_column(np.array([0, 1_500_000_000])) == ["0.000000000", "1.500000000"]
    assert seconds_to_ns(np.array([1.5, -0.25, 2.0000000004, 1e-9])).tolist() == [1_500_000_000, -250_000_000,
                                                                                 2_000_000_000, 1]
    sec, nsec = split_stamp(np.array([-1, 1_700_000_000_999_999_999]))
    assert sec.tolist() == [-1, 1_700_000_000] and nsec.tolist() == [999_999_999, 999_999_999]
    assert sec.dtype == np.int64 and join_stamp(sec, nsec).tolist() == [-1, 1_700_000_000_999_999_999]
    assert parse_seconds_column([]).dtype == np.int64 and not len(parse_seconds_column([]))
    assert ns_to_seconds(np.array([1_500_000_000, -1, 1_700_000_000_000_000_001])).tolist() == \
        pytest.approx([1.5, -1e-9, 1.7e9], rel=1e-15, abs=1e-15)
    import magcal_ros.core.stamps as stamps_module

    def refused(text: str) -> int:
        raise AssertionError(f"{text!r} parsed one by one")
    monkeypatch.setattr(stamps_module, "parse_seconds", refused)
    assert parse_seconds_column(["1.5", "2.25"]).tolist() == [1_500_000_000, 2_250_000_000]
    assert parse_seconds_column(["1", "2.25"]).tolist() == [1_000_000_000, 2_250_000_000]


def _each(texts: list[str]) -> list[int] | None:
    """The oracle: every text parsed alone (None: one of them is refused)."""
    try:
        return [parse_seconds(t) for t in texts]
    except InputError:
        return None


_PLAIN = re.compile(r"[0-9]{1,12}\.[0-9]{1,9}")
_DIGITS = re.compile(r"\d{1,12}(\.\d{1,9})?")  # numpy takes any decimal digit (Decimal too)
_TEXTS = st.lists(st.one_of(
    st.text(alphabet=st.sampled_from(list("0123456789.,-+e ") + ["\u00b2", "\u0661", "x"]), max_size=16),
    st.builds(lambda w, f: f"{w}.{f}", st.integers(0, 10**13), st.text("0123456789", min_size=0, max_size=11)),
    st.integers(0, 10**13).map(str)), min_size=1, max_size=6)


@settings(max_examples=1500, derandomize=True, database=None, deadline=None)
@given(_TEXTS)
def test_a_generated_column_parses_as_each_text_alone_and_plain_ones_take_the_fast_paths(texts: list[str]) -> None:
    """Any column: the same stamps as each text parsed alone, or the same refusal (a superscript digit, a
    decimal comma: a traceback and a wrong time before). Columns of plain ``digits.digits`` (1-12 and 1-9
    digits, below the range's end) take the joined-string path; ``digits[.digits]`` the numpy one; any other
    text sends the column to the parse one by one."""
    want = _each(texts)
    if want is None:
        with pytest.raises(InputError):
            parse_seconds_column(texts)
    else:
        assert parse_seconds_column(texts).tolist() == want
    in_range = want is not None and all(abs(v) < MAX_SECONDS * NS for v in want) and \
        all(int(t.split(".")[0]) < MAX_SECONDS for t in texts if _DIGITS.fullmatch(t))
    plain, digits = _plain_seconds(texts), _digit_seconds(texts)
    assert (plain is not None) == (in_range and all(_PLAIN.fullmatch(t) for t in texts)), texts
    assert (digits is not None) == (in_range and all(_DIGITS.fullmatch(t) for t in texts)), texts
    for fast in (plain, digits):
        if fast is not None:
            assert fast.dtype == np.int64 and fast.tolist() == want


@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
def test_correct_keeps_bag_stamps_to_the_nanosecond(tmp_path: Path, calibration: Path, storage: str) -> None:
    rec = odd_recording()
    raw = tmp_path / "raw"
    write_recording_bag(raw, rec, storage)  # type: ignore[arg-type]
    out = tmp_path / "out"
    ok(magcal("correct", raw, "-c", calibration, "-o", out))
    ts = cdr.typestore()
    with Reader(out) as reader:
        msgs = [(c.topic, t, ts.deserialize_cdr(d, c.msgtype)) for c, t, d in reader.messages()]
    fields = [(t, m.header.stamp.sec * NS + m.header.stamp.nanosec) for topic, t, m in msgs if topic == "/field"]
    assert [f[0] for f in fields] == rec.stamps.tolist(), "bag times"
    assert [f[1] for f in fields] == rec.stamps.tolist(), "header stamps"
    gradient_times = [t for topic, t, _ in msgs if topic == "/gradient"]
    assert gradient_times == rec.stamps.tolist()


def test_correct_keeps_csv_stamps_to_the_nanosecond(tmp_path: Path, calibration: Path) -> None:
    rec = odd_recording()
    raw = tmp_path / "raw.csv"
    write_csv(raw, rec)
    with open(raw, newline="") as fh:
        written = [row[0] for row in list(csv.reader(fh))[1:]]
    assert written == [format_seconds(t) for t in rec.stamps] and all(len(s.split(".")[1]) == 9 for s in written)
    out = tmp_path / "out.csv"
    ok(magcal("correct", raw, "-c", calibration, "-o", out))
    with open(out, newline="") as fh:
        assert [row[0] for row in list(csv.reader(fh))[1:]] == written
    # Bag in, CSV out, and CSV in, bag out: the same nanoseconds.
    bag = tmp_path / "bag"
    ok(magcal("correct", raw, "-c", calibration, "-o", bag))
    with Reader(bag) as reader:
        assert [t for c, t, _ in reader.messages() if c.topic == "/field"] == rec.stamps.tolist()
