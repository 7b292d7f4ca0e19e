"""Files that used to exit 0 but be wrong, or end in a traceback: each is refused with one line, or its
bad readings are dropped and counted, and what is written can always be read back.

Commands run as subprocesses, as a user would (``magcal`` of :mod:`test_offline`).
"""

from __future__ import annotations

import math
import os
import re
import stat
import struct
import zlib
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from test_offline import magcal, ok

from magcal_ros.app.cli import main
from magcal_ros.core.acceptance import reading_fault
from magcal_ros.core.sync import SetSynchronizer, SyncStats
from magcal_ros.core.units import MAX_READING
from magcal_ros.io import calibration_file as calfile

F = 5.15e-5
MS = 1_000_000


@pytest.fixture(scope="module")
def rec(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    d = tmp_path_factory.mktemp("defects")
    csv = d / "rot.csv"
    ok(magcal("simulate", csv, "--count", 300, "--seed", 5, "-q"))
    lines = csv.read_text().splitlines()
    return {"dir": d, "csv": csv, "lines": lines}


def _variant(rec: dict[str, Any], name: str, edit: Any) -> Path:
    lines = list(rec["lines"])
    edit(lines)
    path = rec["dir"] / name
    path.write_text("\n".join(lines) + "\n")
    return path


def _set(lines: list[str], row: int, col: int, value: str) -> None:
    cells = lines[row].split(",")
    cells[col] = value
    lines[row] = ",".join(cells)


def one_line_error(proc: Any) -> str:
    assert proc.returncode == 2, (proc.returncode, proc.stderr)
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr
    return lines[0]


@pytest.mark.parametrize("path", ["live", "batch"])
def test_readings_beyond_a_magnetometer_and_negative_stamps_are_dropped_and_counted(path: str) -> None:
    """The acceptance rule of real data: 1e30 T and a stamp before 1970 are refused and counted, like NaN."""
    sync = SetSynchronizer(2, MS, max_reading=MAX_READING)
    good = (2e-5, -1e-5, 4e-5)
    items = [(0, 10 * MS, good), (1, 10 * MS, (1e30, 0.0, 0.0)),         # out of range: set 10 incomplete
             (0, 20 * MS, good), (1, 20 * MS, good),                      # a set
             (0, -5_000_000_000, good),                                   # sec = -5: a negative stamp
             (0, 30 * MS, (1.9e-3, 0.0, 0.0)), (1, 30 * MS, good),        # within the limit: a set
             (0, 40 * MS, (math.nan, 0.0, 0.0)), (1, 40 * MS, (0.0, 1.5e-3, 1.5e-3))]  # NaN; 2.1e-3 T
    got = []
    if path == "live":
        for k, t, v in items:
            s = sync.add(k, t, *v)
            if s is not None:
                got.append(s.stamp)
    else:
        for k in range(2):
            mine = [(t, v) for j, t, v in items if j == k]
            sync.add_batch(k, np.array([t for t, _ in mine]), np.array([v for _, v in mine]))
        got = sync.pop(final=True).set_stamps.tolist()
    assert got == [20 * MS, 30 * MS]
    st = sync.stats
    assert (st.out_of_range, st.negative_stamp, st.nonfinite, st.zero_stamp) == (2, 1, 1, 0)
    assert st.dropped() == st.out_of_range + st.negative_stamp + st.nonfinite + st.unmatched
    assert "2 readings beyond any magnetometer's range dropped" in st.describe()
    assert "1 negative (before 1970) stamps dropped" in st.describe()


def test_the_reading_limit_is_an_earth_field_plus_the_largest_offset() -> None:
    from magcal_ros.core.calibration import MAX_OFFSET
    from magcal_ros.core.units import EARTH_FIELD_RANGE

    assert MAX_READING == EARTH_FIELD_RANGE[1] + MAX_OFFSET
    assert reading_fault(0.0, 0.0, 0.0) is None  # an offset may cancel the field: no lower bound
    assert reading_fault(1e200, 0.0, 0.0) == "out_of_range" and reading_fault(-math.inf, 0, 0) == "nonfinite"


def test_a_huge_reading_in_a_csv_is_dropped_and_never_reaches_an_output(rec: dict[str, Any]) -> None:
    def corrupt(lines: list[str]) -> None:
        _set(lines, 10, 2, "1e300")
        _set(lines, 40, 7, "-1e30")

    bad = _variant(rec, "huge.csv", corrupt)
    cal = rec["dir"] / "huge.yaml"
    proc = ok(magcal("calibrate", bad, "-o", cal, "--reference-field", F))
    assert "inf" not in proc.stdout and "nan" not in proc.stdout, proc.stdout
    assert "2 readings beyond any magnetometer's range dropped" in proc.stderr
    loaded = calfile.read(cal)  # a written calibration loads
    assert np.all(np.isfinite(loaded.matrices)) and np.all(np.isfinite(loaded.offsets))
    text = cal.read_text()
    assert not re.search(r"\b(inf|nan)\b", text.split("magcal_provenance")[1].lower())
    assert loaded.metadata["samples"] == 298
    out = rec["dir"] / "huge_corrected.csv"
    ok(magcal("correct", bad, "-c", cal, "-o", out))
    values = np.loadtxt(out, delimiter=",", skiprows=1)[:, 1:]
    assert len(values) == 298 and np.all(np.abs(values) < 1e-3)


@pytest.mark.parametrize("name", ["mag 1", "../../evil", "mag1.x", "/abs"])
def test_csv_sensor_names_must_be_ros_names(rec: dict[str, Any], name: str) -> None:
    bad = _variant(rec, "names.csv", lambda lines: lines.__setitem__(0, lines[0].replace("mag1.", f"{name}.")))
    line = one_line_error(magcal("calibrate", bad, "-o", rec["dir"] / "n.yaml", "--reference-field", F))
    assert f"sensor name '{name}' is not a valid relative ROS name" in line
    assert not (rec["dir"] / "n.yaml").exists()
    out = rec["dir"] / "n_bag"
    one_line_error(magcal("correct", bad, "-c", rec["dir"] / "none.yaml", "-o", out))
    assert not out.exists()


def test_cr_only_line_endings_read_like_lf(rec: dict[str, Any]) -> None:
    cr = rec["dir"] / "cr.csv"
    cr.write_bytes(("\r".join(rec["lines"]) + "\r").encode())
    a, b = rec["dir"] / "cr.yaml", rec["dir"] / "lf.yaml"
    ok(magcal("calibrate", cr, "-o", a, "--reference-field", F, "-q"))
    ok(magcal("calibrate", rec["csv"], "-o", b, "--reference-field", F, "-q"))
    np.testing.assert_array_equal(calfile.read(a).matrices, calfile.read(b).matrices)


def test_a_stamp_beyond_int64_nanoseconds_is_one_line(rec: dict[str, Any]) -> None:
    bad = _variant(rec, "stamp.csv", lambda lines: _set(lines, 6, 0, "1e300"))
    line = one_line_error(magcal("calibrate", bad, "-o", rec["dir"] / "s.yaml", "--reference-field", F))
    assert "line 7" in line and "1e300 s is out of range" in line


def test_a_calibration_nested_100000_deep_is_one_line(rec: dict[str, Any]) -> None:
    deep = rec["dir"] / "deep.yaml"
    deep.write_text("[" * 100_000 + "]" * 100_000 + "\n")
    line = one_line_error(magcal("correct", rec["csv"], "-c", deep, "-o", rec["dir"] / "d.csv"))
    assert "nested too deeply" in line


def test_sync_stats_keep_one_vocabulary() -> None:
    """Every counter counts as dropped but sets, restarts (events, not messages) and used (messages in sets)."""
    stats = SyncStats(**{k: 1 for k in SyncStats().as_dict()})
    assert stats.dropped() == len(stats.as_dict()) - 3
    assert "negative_stamp" in SyncStats().as_dict() and "out_of_range" in SyncStats().as_dict()


def _mcap_chunks(path: Path) -> list[tuple[int, bytes]]:
    """(uncompressed_crc, uncompressed records) of every Chunk record of an MCAP file, read by hand
    from the format (magic, then records: opcode u8, length u64, body; Chunk = 0x06, uncompressed)."""
    data = path.read_bytes()
    assert data[:8] == b"\x89MCAP0\r\n"
    chunks, at = [], 8
    while at < len(data) - 8:
        op, length = data[at], struct.unpack_from("<Q", data, at + 1)[0]
        body = data[at + 9 : at + 9 + length]
        if op == 0x06:
            crc = struct.unpack_from("<I", body, 24)[0]
            n = struct.unpack_from("<I", body, 28)[0]
            assert body[32 : 32 + n] == b""  # not compressed
            size = struct.unpack_from("<Q", body, 32 + n)[0]
            chunks.append((crc, body[40 + n : 40 + n + size]))
        at += 9 + length
    return chunks


def test_mcap_chunks_carry_their_crc(rec: dict[str, Any]) -> None:
    bag = rec["dir"] / "crc_bag"
    ok(magcal("simulate", bag, "--storage", "mcap", "--count", 200, "--seed", 2, "-q"))
    out = rec["dir"] / "crc_corrected"
    cal = rec["dir"] / "crc.yaml"
    ok(magcal("calibrate", bag, "-o", cal, "--reference-field", F, "-q"))
    ok(magcal("correct", bag, "-c", cal, "-o", out, "--storage", "mcap"))
    for folder in (bag, out):
        chunks = [c for f in sorted(folder.glob("*.mcap")) for c in _mcap_chunks(f)]
        assert chunks and all(crc == zlib.crc32(records) and crc != 0 for crc, records in chunks)


def test_an_output_inside_the_input_bag_is_refused(rec: dict[str, Any]) -> None:
    bag = rec["dir"] / "in_bag"
    ok(magcal("simulate", bag, "--count", 100, "--seed", 2, "-q"))
    before = sorted(p.name for p in bag.iterdir())
    line = one_line_error(magcal("calibrate", bag, "-o", bag / "x.db3", "--reference-field", F))
    assert "inside the input bag" in line
    cal = rec["dir"] / "in.yaml"
    ok(magcal("calibrate", bag, "-o", cal, "--reference-field", F, "-q"))
    assert "inside the input bag" in one_line_error(magcal("correct", bag, "-c", cal, "-o", bag / "sub" / "out.csv"))
    assert sorted(p.name for p in bag.iterdir()) == before


def test_writing_through_a_symlink_updates_its_target_and_keeps_the_mode(rec: dict[str, Any], tmp_path: Path) -> None:
    real = tmp_path / "store" / "cal.yaml"
    real.parent.mkdir()
    link = tmp_path / "link.yaml"
    link.symlink_to(real)
    ok(magcal("calibrate", rec["csv"], "-o", link, "--reference-field", F, "-q"))
    assert link.is_symlink() and real.is_file()
    os.chmod(real, 0o600)
    first = real.read_text()
    ok(magcal("calibrate", rec["csv"], "-o", link, "--reference-field", 5.0e-5, "-q"))
    assert link.is_symlink() and real.read_text() != first
    assert stat.S_IMODE(real.stat().st_mode) == 0o600
    backups = calfile.backups(real)
    assert len(backups) == 1 and backups[0].read_text() == first
    assert stat.S_IMODE(backups[0].stat().st_mode) == 0o600
    out = tmp_path / "c.csv"
    out.write_text("old\n")
    os.chmod(out, 0o640)
    ok(magcal("correct", rec["csv"], "-c", link, "-o", out))
    assert stat.S_IMODE(out.stat().st_mode) == 0o640 and out.read_text().startswith("stamp,")


def test_list_options_may_start_with_a_minus_sign(rec: dict[str, Any]) -> None:
    """--positions -0.2,... (the cross listed from -x) is a value, not an option."""
    cal = rec["dir"] / "neg.yaml"
    cross = "0.2,0,0,0,0.2,0,-0.2,0,0,0,-0.2,0"
    ok(magcal("calibrate", rec["csv"], "-o", cal, "--reference-field", F, "-q", "--positions", cross))
    assert calfile.read(cal).geometry.positions.reshape(-1).tolist() == [float(v) for v in cross.split(",")]
    mirrored = "-0.2,0,0,0,-0.2,0,0.2,0,0,0,0.2,0"
    proc = magcal("calibrate", rec["csv"], "-o", rec["dir"] / "neg2.yaml", "--reference-field", F, "-q",
                  "--positions", mirrored, "--gradient-method", "least_squares")
    assert "expected one argument" not in proc.stderr, proc.stderr
    ok(proc)
    assert calfile.read(rec["dir"] / "neg2.yaml").geometry.positions[0].tolist() == [-0.2, 0.0, 0.0]


@pytest.mark.parametrize("value", ["1e300", "-25000"])
def test_one_current_beyond_any_vehicle_is_dropped_and_a_column_in_milliamps_refused(rec: dict[str, Any],
                                                                                    value: str) -> None:
    """One current of 1e300 A (it corrected the field to 1e292 T) or -25,000 A in a recording: that row is
    no value, dropped and counted, and the rest calibrates; a column in mA (every value 1000x) is a units
    error, refused in one line with nothing written."""
    d = rec["dir"]
    csv = d / "thr.csv"
    if not csv.exists():
        ok(magcal("simulate", csv, "--count", 200, "--seed", 6, "--thruster", "1.0,0,0,0,0,0.05", "-q"))
    lines = csv.read_text().splitlines()
    col = next(i for i, name in enumerate(lines[0].split(",")) if name.startswith("current."))
    _set(lines, 52, col, value)
    bad = d / "thr_bad.csv"
    bad.write_text("\n".join(lines) + "\n")
    out = d / "thr_out.yaml"
    proc = magcal("calibrate", bad, "-o", out, "--reference-field", F)
    ok(proc)
    assert "4 messages of rows whose current or temperature is out of range dropped" in proc.stderr
    assert out.exists()
    lines = csv.read_text().splitlines()
    for row in range(1, len(lines)):
        cells = lines[row].split(",")
        cells[col] = f"{float(cells[col]) * 1000 + 1e4 + 1:.17g}"
        lines[row] = ",".join(cells)
    milli = d / "thr_milli.csv"
    milli.write_text("\n".join(lines) + "\n")
    out = d / "thr_milli.yaml"
    line = one_line_error(magcal("calibrate", milli, "-o", out, "--reference-field", F))
    assert "and most others are out of range: currents must be in A" in line and "thr_milli.csv" in line
    assert not out.exists()


def test_a_recording_sorted_backwards_is_refused_not_reduced_to_one_set(rec: dict[str, Any]) -> None:
    """Rows newest first: every message but the first of each sensor is behind its predecessor.
    Correcting it wrote 1 set of 300 and exited 0; now both commands say what is wrong."""
    lines = rec["lines"]
    rev = rec["dir"] / "backwards.csv"
    rev.write_text("\n".join([lines[0], *reversed(lines[1:])]) + "\n")
    cal = rec["dir"] / "fwd.yaml"
    ok(magcal("calibrate", rec["csv"], "-o", cal, "--reference-field", F, "-q"))
    for cmd in (["calibrate", rev, "-o", rec["dir"] / "bw.yaml", "--reference-field", F],
                ["correct", rev, "-c", cal, "-o", rec["dir"] / "bw_out.csv"]):
        line = one_line_error(magcal(*cmd))
        assert "against 1 sets formed: the recording is not in time order" in line and "sort it by stamp" in line
        assert not Path(cmd[cmd.index("-o") + 1]).exists()


def test_a_bag_whose_storage_times_run_backwards_is_refused(rec: dict[str, Any]) -> None:
    """The bag's storage timestamps reversed (headers intact): read in storage order, nearly every message
    is behind its predecessor; both commands refuse, and correct (which streams the bag) writes nothing."""
    import sqlite3

    bag = rec["dir"] / "backwards_bag"
    ok(magcal("simulate", bag, "--count", 200, "--seed", 7, "-q"))
    db = sqlite3.connect(next(bag.glob("*.db3")))
    lo, hi = db.execute("SELECT min(timestamp), max(timestamp) FROM messages").fetchone()
    db.execute("UPDATE messages SET timestamp = ? - timestamp", (lo + hi,))
    db.commit()
    db.close()
    cal = rec["dir"] / "fwd_bag.yaml"
    ok(magcal("calibrate", rec["csv"], "-o", cal, "--reference-field", F, "-q"))
    for cmd in (["calibrate", bag, "-o", rec["dir"] / "bwb.yaml", "--reference-field", F],
                ["correct", bag, "-c", cal, "-o", rec["dir"] / "bwb_out"]):
        line = one_line_error(magcal(*cmd))
        assert "the recording is not in time order" in line
        assert not Path(cmd[cmd.index("-o") + 1]).exists()


def test_a_calibration_written_over_a_directory_is_one_line_without_temporary_names(rec: dict[str, Any]) -> None:
    """``-o`` naming an existing directory: the message named the temporary file (".x.magcal123.partial/x")."""
    target = rec["dir"] / "a_directory"
    target.mkdir(exist_ok=True)
    (target / "keep.txt").write_text("mine\n")
    line = one_line_error(magcal("calibrate", rec["csv"], "-o", target, "--reference-field", F))
    assert f"cannot write {target}: it is a directory" in line and ".partial" not in line and "magcal" in line
    assert (target / "keep.txt").read_text() == "mine\n" and not list(rec["dir"].glob(".a_directory*"))


def test_a_one_sensor_calibration_file_holds_no_nan(rec: dict[str, Any]) -> None:
    """One sensor has no gradient tensor: its file wrote ``tensor_rms_before: .nan``; now the keys are left out."""
    csv, out = rec["dir"] / "one.csv", rec["dir"] / "one.yaml"
    ok(magcal("simulate", csv, "--count", 300, "--seed", 9, "-q"))
    ok(magcal("calibrate", csv, "--sensors", "mag1", "-o", out, "--reference-field", 5.5e-5, "-q"))
    text = out.read_text()
    assert ".nan" not in text.lower() and "tmi_rms_after" in text and "tensor_rms" not in text


SIMULATE_REFUSALS: list[tuple[tuple[object, ...], str]] = [
    (("--seed", -1), "--seed must be an integer >= 0, got -1"),
    *[(("--thruster", "0,0,0,1,1,1", "--thruster-current", c), "--thruster-current must be random:IMAX (IMAX >= 0)")
      for c in ("random:-5", "random:nan", "steps:0,inf", "steps:nan")],
    (("--inclination", "nan"), "--inclination must be a finite number (deg), got nan"),
    (("--declination", "inf"), "--declination must be a finite number (deg), got inf"),
    (("--schedule", "sea", "--turns", "nan"), "--turns must be a finite number (turns), got nan"),
    (("--schedule", "sea", "--pitch=-inf"), "--pitch must be a finite number (deg), got -inf"),
    (("--baseline", "inf"), "--baseline must be positive and finite (m)"),
    (("--noise", "1e300"), "--noise 1e+300 T (1-sigma per axis) puts readings beyond a magnetometer's range (0.002 T)"),
    (("--noise", "2e-4"), "--noise 0.0002 T (1-sigma per axis) puts readings beyond a magnetometer's range (0.002 T)"),
    (("--world-gradient", "1e300,0,0,0,0"), "--world-gradient reaches 2e+299 T at a sensor 0.2 m from the array's centre"),
    (("--world-gradient", "0.01,0,0,0,0"), "--world-gradient reaches 0.002"),
    *[(("--start-time", t), f"--start-time {float(t):g} s is not a ROS stamp: 0 < SECONDS <= 2147483647")
      for t in ("9e9", "-1e20", "1e20", "nan", "0", "2147483648")],
    (("--start-time", "2147483647"), ("--count 20 sets at --rate 10 Hz from --start-time 2147483647 s end at 2.147e+09 s, "
                                      "beyond a ROS stamp (at most 2147483647 s")),
    (("--rate", "1e-300"), "--count 20 sets at --rate 1e-300 Hz from --start-time 1700000000 s end at 1.9e+301 s"),
    (("--rate", "1e300"), "--rate must be a positive number of sets per second, at most 1e+09"),
    (("--rate", "nan"), "--rate must be a positive number of sets per second, at most 1e+09"),
    (("--count", 10_000_001), "--count 10000001 is more sets than magcal simulates: at most 10000000"),
    (("--schedule", "sea", "--imu", "--imu-rate", "2e9"), "--imu-rate 2e+09 Hz over the 1.9 s recording is more IMU"),
    (("--schedule", "sea", "--imu", "--imu-rate", "1e7"), "--imu-rate 1e+07 Hz over the 1.9 s recording is more IMU"),
]
"""Options ``magcal simulate`` cannot simulate (with ``--count 20``) and the start of their one-line error."""


def simulate_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str], args: tuple[object, ...], says: str) -> None:
    """``magcal simulate OUT ARGS`` (in this process: an exception would fail the test as its traceback)
    exits 2 with one line starting ``says`` and writes nothing (``tmp_path`` left empty)."""
    code = main(["simulate", str(tmp_path / "sim_bag"), "-q", *map(str, args)])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1 and err.startswith(f"magcal simulate: error: {says}"), err
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize(("args", "says"), SIMULATE_REFUSALS, ids=[" ".join(map(str, a)) for a, _ in SIMULATE_REFUSALS])
def test_simulate_refuses_what_it_cannot_simulate(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                  args: tuple[object, ...], says: str) -> None:
    """Each is one line naming the option, exit 2, nothing written (no traceback, no wrong output)."""
    simulate_refused(tmp_path, capsys, ("--count", 20, *args), says)


def test_a_calibration_whose_positions_coincide_corrects_the_field_and_says_why_no_gradient(rec: dict[str, Any]) -> None:
    """Positions all zero in the file: the gradient columns went missing without a word."""
    import yaml

    cal = rec["dir"] / "zero_pos_src.yaml"
    ok(magcal("calibrate", rec["csv"], "-o", cal, "--reference-field", F, "-q"))
    doc = yaml.safe_load(cal.read_text())
    block = doc["magcal_correction"]["ros__parameters"]
    block["positions"] = [0.0] * len(block["positions"])
    zero = rec["dir"] / "zero_pos.yaml"
    zero.write_text(yaml.safe_dump(doc))
    out = rec["dir"] / "zero_pos_out.csv"
    proc = ok(magcal("correct", rec["csv"], "-c", zero, "-o", out))
    assert "note: the positions of mag1, mag2, mag3, mag4" in proc.stderr and "coincide: no gradient" in proc.stderr
    header = out.read_text().splitlines()[0]
    assert "field.x" in header and "gradient." not in header


def test_an_input_that_never_ends_is_refused_in_one_line(tmp_path: Any) -> None:
    """A "CSV" or a calibration that is a link to /dev/zero was read whole before any check (MemoryError):
    refused as not a regular file, in one line, before a byte is read."""
    (tmp_path / "zero.csv").symlink_to("/dev/zero")
    (tmp_path / "zero.yaml").symlink_to("/dev/zero")
    line = one_line_error(magcal("calibrate", tmp_path / "zero.csv", "-o", tmp_path / "c.yaml", "--reference-field", F))
    assert "zero.csv is not a regular file" in line
    (tmp_path / "ok.csv").write_text("stamp,a.x,a.y,a.z\n1.0,1e-5,2e-5,3e-5\n")
    line = one_line_error(magcal("correct", tmp_path / "ok.csv", "-c", tmp_path / "zero.yaml", "-o", tmp_path / "o.csv"))
    assert "zero.yaml is not a regular file" in line
