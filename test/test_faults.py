"""Nothing silent, offline: every fault of ``magcal`` is refused with one line or counted, and no
output is ever half-written (signals, killed runs, replacing an output, units, CSV faults,
file size limits, sensor mismatches).

Commands run as subprocesses, as a user would. Faults that need a precise moment (a signal
while the output is being written, SIGKILL between two renames) are injected by a small
driver that patches one function and then runs ``magcal``'s ``main``.
"""

from __future__ import annotations

import os
import resource
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from rosbags.rosbag2 import Reader, StoragePlugin, Writer
from test_offline import NAMES, NOISE, ROOT, SEED, SETS, F, magcal, ok, read_corrected

from magcal_ros.core.recording import Recording
from magcal_ros.core.stamps import format_seconds
from magcal_ros.core.units import EARTH_FIELD_RANGE, check_tesla
from magcal_ros.errors import InputError
from magcal_ros.io import bag_reader, cdr
from magcal_ros.io.atomic import public_path, recover
from magcal_ros.io.bag_writer import write_recording_bag
from magcal_ros.io.csv_recording import write_csv
from magcal_ros.io.recordings import read_recording

DRIVER = r"""
import os, signal, sys, time
from pathlib import Path

mode, arg, argv = sys.argv[1], sys.argv[2], sys.argv[3:]
if mode == "stall":  # after the first batch of output is written, say so in file ARG and wait
    from magcal_ros.io import bag_writer, csv_recording

    def stalling(original):
        def wrapper(*a, **k):
            out = original(*a, **k)
            Path(arg).write_text(str(os.getpid()))
            time.sleep(600)
            return out
        return wrapper

    bag_writer.BagSink.write_sets = stalling(bag_writer.BagSink.write_sets)
    csv_recording.format_rows = stalling(csv_recording.format_rows)
elif mode in ("kill-before-swap-in", "kill-after-swap-in"):  # SIGKILL around the rename onto output ARG
    target, real = os.path.abspath(arg), os.replace

    def replace(src, dst, *a, **k):
        hit = os.path.abspath(dst) == target
        if hit and mode == "kill-before-swap-in":
            os.kill(os.getpid(), signal.SIGKILL)
        real(src, dst, *a, **k)
        if hit and mode == "kill-after-swap-in":
            os.kill(os.getpid(), signal.SIGKILL)

    os.replace = replace
from magcal_ros.app.cli import main
sys.exit(main(argv))
"""


def _env() -> dict[str, str]:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    return env


def driver(mode: str, arg: object, *args: object) -> subprocess.Popen[str]:
    """Start ``magcal ARGS`` under the fault-injecting driver."""
    return subprocess.Popen([sys.executable, "-c", DRIVER, mode, str(arg), *map(str, args)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=_env())


def wait_for(path: Path, proc: subprocess.Popen[str], timeout: float = 240.0) -> None:
    """Wait until the driver has written ``path`` (it is then stalled inside the output)."""
    deadline = time.monotonic() + timeout
    while not path.exists():
        if proc.poll() is not None:
            raise AssertionError(f"driver exited early: {proc.returncode} {proc.communicate()}")
        assert time.monotonic() < deadline, "driver never reached the output"
        time.sleep(0.05)


def finish(proc: subprocess.Popen[str]) -> tuple[int, str]:
    """Exit code and stderr of a driver (killed if it hangs)."""
    try:
        _, err = proc.communicate(timeout=240)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    return proc.returncode, err


def magcal_limited(limit: int, *args: object) -> subprocess.CompletedProcess[str]:
    """``magcal ARGS`` with a file size limit (``ulimit -f``) of ``limit`` bytes."""
    def preexec() -> None:
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))

    return subprocess.run([sys.executable, "-m", "magcal_ros.app.cli", *map(str, args)], capture_output=True,
                          text=True, env=_env(), timeout=300, preexec_fn=preexec)


def error_line(proc: subprocess.CompletedProcess[str] | tuple[int, str], command: str = "correct") -> str:
    """The one stderr line of a refused command (notes allowed before it)."""
    rc, err = (proc.returncode, proc.stderr) if isinstance(proc, subprocess.CompletedProcess) else proc
    assert rc == 2, err
    lines = [line for line in err.splitlines() if line.strip() and not line.startswith("  note: ")]
    assert len(lines) == 1, err
    assert lines[0].startswith(f"magcal {command}: error: "), err
    return lines[0]


def listing(d: Path) -> list[str]:
    return sorted(os.listdir(d))


@pytest.fixture(scope="module")
def base(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """A rotation bag and the same recording as CSV, the calibration solved from the bag."""
    d = tmp_path_factory.mktemp("faults")
    bag, csv_path, cal = d / "rotation", d / "rotation.csv", d / "cal.yaml"
    ok(magcal("simulate", bag, "--count", SETS, "--seed", SEED, "--noise", NOISE))
    ok(magcal("simulate", csv_path, "--count", SETS, "--seed", SEED, "--noise", NOISE))
    ok(magcal("calibrate", bag, "-o", cal, "--reference-field", F))
    rec = read_recording(bag)
    return {"dir": d, "bag": bag, "csv": csv_path, "cal": cal, "rec": rec}


def out_path(d: Path, kind: str) -> tuple[Path, list[str]]:
    """An output path of ``kind`` (sqlite3, mcap, csv) in ``d`` and the options that select it."""
    if kind == "csv":
        return d / "out.csv", []
    return d / "out", ["--storage", kind]


# --------------------------------------------------------------------------- 1: missing block


def _calibration_without(cal: Path, dest: Path, name: str) -> Path:
    doc = yaml.safe_load(cal.read_text())
    del doc["magcal_correction"]["ros__parameters"][name]
    dest.write_text(yaml.safe_dump(doc))
    return dest


@pytest.mark.parametrize("source", ["bag", "csv"])
def test_a_calibration_missing_a_sensor_block_is_refused(tmp_path: Path, base: dict[str, Any], source: str) -> None:
    cal = _calibration_without(base["cal"], base["dir"] / "no_mag3.yaml", "mag3")
    out = tmp_path / ("out.csv" if source == "csv" else "out")
    proc = magcal("correct", base[source], "-c", cal, "-o", out)
    line = error_line(proc)
    assert str(cal) in line and "'mag3'" in line and "no matrix and offset" in line
    assert listing(tmp_path) == [], "no output and no temporary files"


def test_uncorrected_sensors_are_used_raw_only_when_asked(tmp_path: Path, base: dict[str, Any]) -> None:
    """A sensor left raw on purpose is written raw, and the centre field and the gradient, which would mix
    it with the calibrated sensors (thousands of nT/m off), are withheld: nan columns in a CSV, no /field
    and no /gradient in a bag. (Planted: the outputs written as before, with the raw sensor in them.)"""
    cal = _calibration_without(base["cal"], base["dir"] / "no_mag3.yaml", "mag3")
    full, raw = tmp_path / "full.csv", tmp_path / "raw.csv"
    ok(magcal("correct", base["bag"], "-c", base["cal"], "-o", full))
    proc = ok(magcal("correct", base["bag"], "-c", cal, "-o", raw, "--uncorrected", "mag3"))
    assert "note: mag3 is not corrected (--uncorrected): its raw readings are used as they are" in proc.stderr
    assert "note: field and gradient withheld: mag3 is raw (--uncorrected)" in proc.stderr
    a, b = read_corrected(full), read_corrected(raw)
    np.testing.assert_array_equal(b["sensors"][:, 2], base["rec"].vectors[:, 2])  # mag3 exactly raw
    np.testing.assert_array_equal(b["sensors"][:, [0, 1, 3]], a["sensors"][:, [0, 1, 3]])
    assert np.all(np.isnan(b["field"])) and np.all(np.isnan(b["gradient"])) and np.all(np.isfinite(a["gradient"]))
    bag = tmp_path / "raw_bag"
    proc = ok(magcal("correct", base["bag"], "-c", cal, "-o", bag, "--uncorrected", "mag3"))
    assert "/<name>/corrected only, /field and the gradient withheld" in proc.stdout
    from rosbags.rosbag2 import Reader

    with Reader(bag) as reader:
        assert sorted(c.topic for c in reader.connections) == [f"/mag{i}/corrected" for i in range(1, 5)]
    proc = magcal("correct", base["bag"], "-c", base["cal"], "-o", tmp_path / "x", "--uncorrected", "mag9")
    assert "--uncorrected mag9: not a sensor of" in error_line(proc)
    assert listing(tmp_path) == ["full.csv", "raw.csv", "raw_bag"]


# --------------------------------------------------------------------------- 5: signals, killed runs


@pytest.mark.parametrize(("kind", "sig", "existing"), [
    ("sqlite3", signal.SIGTERM, False), ("csv", signal.SIGTERM, False), ("mcap", signal.SIGTERM, True),
    ("sqlite3", signal.SIGINT, True), ("csv", signal.SIGHUP, False),
])
def test_a_stop_signal_removes_the_partial_output(
    tmp_path: Path, base: dict[str, Any], kind: str, sig: signal.Signals, existing: bool
) -> None:
    d = tmp_path / "o"
    d.mkdir()
    out, opts = out_path(d, kind)
    if existing:
        ok(magcal("correct", base["csv"], "-c", base["cal"], "-o", out, *opts))
        before = out.stat().st_mtime_ns, read_corrected(out)["gradient"]
    ready = tmp_path / "ready"
    proc = driver("stall", ready, "correct", base["bag"], "-c", base["cal"], "-o", out, *opts)
    wait_for(ready, proc)
    assert [p for p in listing(d) if p.endswith(".partial")], "the run was writing its output"
    proc.send_signal(sig)
    rc, err = finish(proc)
    assert rc == 128 + sig
    assert err.strip().splitlines() == [f"magcal correct: stopped by {sig.name}; unfinished output removed"]
    if existing:
        assert listing(d) == [out.name]
        assert out.stat().st_mtime_ns == before[0]
        np.testing.assert_array_equal(read_corrected(out)["gradient"], before[1])
    else:
        assert listing(d) == []


def test_partials_of_killed_runs_are_removed_but_never_a_running_one(tmp_path: Path, base: dict[str, Any]) -> None:
    d = tmp_path / "o"
    d.mkdir()
    out = d / "out"
    args = ("correct", base["bag"], "-c", base["cal"], "-o", out)
    killed = driver("stall", tmp_path / "ready_a", *args)
    wait_for(tmp_path / "ready_a", killed)
    killed.send_signal(signal.SIGKILL)
    assert finish(killed)[0] == -signal.SIGKILL
    (stale,) = listing(d)
    assert stale.startswith(".out.magcal") and stale.endswith(".partial"), "SIGKILL leaves its partial output"

    running = driver("stall", tmp_path / "ready_b", *args)  # its start cleans up the killed run
    wait_for(tmp_path / "ready_b", running)
    (mine,) = listing(d)
    assert mine != stale

    proc = ok(magcal(*args))  # a concurrent run to the same output leaves the running one alone
    assert "note:" not in proc.stderr
    assert listing(d) == sorted([mine, "out"])
    assert len(read_corrected(out)["gradient"]) == SETS

    running.send_signal(signal.SIGTERM)
    rc, err = finish(running)
    assert rc == 128 + signal.SIGTERM
    assert f"note: removed {stale}, left by an interrupted run" in err
    assert listing(d) == ["out"]
    assert len(read_corrected(out)["gradient"]) == SETS


def test_recover_touches_only_abandoned_partials_of_its_own_target(tmp_path: Path) -> None:
    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait()  # a pid that no longer runs (reaped)
    host = socket.gethostname()

    def partial(name: str, owner: str | None, aside: bool = False) -> Path:
        p = tmp_path / name
        p.mkdir()
        (p / "out").mkdir()
        if owner is not None:
            (p / "out.owner").write_text(owner)
        if aside:
            (p / "out.replaced").mkdir()
            (p / "out.replaced" / "metadata.yaml").write_text("old")
        return p

    dead = partial(f".out.magcal{gone.pid}.abcd1234.partial", f"{host} {gone.pid}\n", aside=True)
    no_owner = partial(f".out.magcal{gone.pid}.efgh5678.partial", None)
    alive = partial(f".out.magcal{os.getpid()}.ijkl9012.partial", f"{host} {os.getpid()}\n")
    elsewhere = partial(f".out.magcal{gone.pid}.mnop3456.partial", f"another-host {gone.pid}\n")
    other_target = partial(f".out2.magcal{gone.pid}.qrst7890.partial", f"{host} {gone.pid}\n")
    not_ours = partial(".out.partial", None)
    (tmp_path / f".out.magcal{gone.pid}.uvwx1234.partial").write_text("a file, not our directory")

    notes = recover(tmp_path / "out")
    assert (tmp_path / "out" / "metadata.yaml").read_text() == "old", "the set-aside output is restored"
    assert not dead.exists() and not no_owner.exists()
    assert alive.exists() and elsewhere.exists() and other_target.exists() and not_ours.exists()
    assert (tmp_path / f".out.magcal{gone.pid}.uvwx1234.partial").is_file()
    assert notes == [f"restored {tmp_path / 'out'}, set aside by an interrupted run", f"removed {dead.name}, left by an "
                     "interrupted run", f"removed {no_owner.name}, left by an interrupted run"]
    assert public_path(alive / "out") == tmp_path / "out"
    assert public_path(alive / "out" / "x.db3") == alive / "out" / "x.db3"


# --------------------------------------------------------------------------- 6: atomic replacement


@pytest.mark.parametrize("when", ["before", "after"])
@pytest.mark.parametrize("kind", ["sqlite3", "mcap", "csv"])
def test_sigkill_while_replacing_an_output_keeps_old_or_new_complete(
    tmp_path: Path, base: dict[str, Any], kind: str, when: str
) -> None:
    d = tmp_path / "o"
    d.mkdir()
    out, opts = out_path(d, kind)
    ref_old, ref_new = tmp_path / f"old{out.suffix}", tmp_path / f"new{out.suffix}"
    end = format_seconds(int(base["rec"].stamps[99]))
    ok(magcal("correct", base["bag"], "-c", base["cal"], "-o", ref_old, "--end", end, *opts))
    ok(magcal("correct", base["bag"], "-c", base["cal"], "-o", ref_new, *opts))
    old, new = read_corrected(ref_old), read_corrected(ref_new)
    assert len(old["stamps"]) == 100 and len(new["stamps"]) == SETS
    ok(magcal("correct", base["bag"], "-c", base["cal"], "-o", out, "--end", end, *opts))

    proc = driver(f"kill-{when}-swap-in", out, "correct", base["bag"], "-c", base["cal"], "-o", out, *opts)
    assert finish(proc)[0] == -signal.SIGKILL
    expected = new if when == "after" else old

    def same(got: dict[str, np.ndarray]) -> None:
        for key in expected:
            np.testing.assert_array_equal(got[key], expected[key])

    if when == "before" and kind != "csv":
        # Killed between the two renames: the old bag is set aside, complete, beside the target.
        assert not out.exists()
        (aside,) = d.glob(".out.magcal*.partial/out.replaced")
        same(read_corrected(aside))
    else:
        same(read_corrected(out))  # a file is replaced in one rename; after the swap the new bag is in place

    # The next run, even one refused at once, restores or cleans up what the crash left.
    proc = magcal("correct", base["bag"], "-c", d / "missing.yaml", "-o", out)
    error_line(proc)
    assert listing(d) == [out.name], "no partial directory and no set-aside copy left"
    same(read_corrected(out))


# --------------------------------------------------------------------------- 7: units


def test_check_tesla_bounds() -> None:
    lo, hi = EARTH_FIELD_RANGE
    unit = np.array([0.6, 0.0, 0.8])
    for f in (2e-5, 7e-5, 1.01 * lo, 0.99 * hi):
        check_tesla(np.tile(unit * f, (10, 4, 1)), NAMES, "x")
    for f in (0.99 * lo, 1.01 * hi, 5.5e4, 0.55, 55.0, 0.0):
        v = np.tile(unit * 5e-5, (10, 4, 1))
        v[:, 2] = unit * f
        with pytest.raises(InputError, match=r"^x: median \|B\| of mag3 is .*units must be Tesla$"):
            check_tesla(v, NAMES, "x")
    v = np.tile(unit * 5e-5, (10, 4, 1))
    v[:4] *= 1e9  # a few outliers do not move the median
    check_tesla(v, NAMES, "x")


def test_check_tesla_decides_by_the_median_when_half_the_readings_lie_outside() -> None:
    """The check counts the readings beyond each end of the range before it takes a median: with half
    or nearly half of them outside (odd and even counts, at one end or both), it decides as the median does."""
    lo, hi = EARTH_FIELD_RANGE
    unit = np.array([0.6, 0.0, 0.8])
    rng = np.random.default_rng(3)
    for n in (1, 2, 3, 4, 5, 10, 11):
        for _ in range(200):
            f = rng.choice([0.5 * lo, 2 * lo, 0.5 * hi, 2 * hi], n) * rng.uniform(0.9, 1.1, n)
            v = np.tile(unit * 5e-5, (n, 4, 1))
            v[:, 1] = unit * f[:, None]
            inside = lo <= float(np.median(f)) <= hi
            if inside:
                check_tesla(v, NAMES, "x")
            else:
                with pytest.raises(InputError, match=r"median \|B\| of mag2"):
                    check_tesla(v, NAMES, "x")


@pytest.mark.parametrize(("unit", "scale"), [("nT", 1e9), ("uT", 1e6), ("Gauss", 1e4)])
def test_readings_not_in_tesla_are_refused(tmp_path: Path, base: dict[str, Any], unit: str, scale: float) -> None:
    rec = base["rec"]
    scaled = Recording(rec.names, rec.stamps, rec.vectors * scale)
    inputs = tmp_path / "in"
    inputs.mkdir()
    write_csv(inputs / f"{unit}.csv", scaled)
    write_recording_bag(inputs / f"{unit}_bag", scaled)
    d = tmp_path / "o"
    d.mkdir()
    for command, src, out in [
        ("correct", f"{unit}.csv", "out.csv"), ("correct", f"{unit}_bag", "out"), ("correct", f"{unit}_bag", "out.csv"),
        ("calibrate", f"{unit}.csv", "cal.yaml"), ("calibrate", f"{unit}_bag", "cal.yaml"),
    ]:
        args = ["-c", base["cal"]] if command == "correct" else []
        line = error_line(magcal(command, inputs / src, *args, "-o", d / out), command)
        assert line.endswith("units must be Tesla") and "median |B| of mag1" in line, line
        assert listing(d) == []


# --------------------------------------------------------------------------- 8: CSV rows out of order


def _faulty_order() -> list[int]:
    """Set indices in recording order with a repeat, a swap and a late row (stamps within 1 s)."""
    order = list(range(SETS))
    order.insert(101, 100)  # set 100 twice in a row: 4 repeated stamps
    i = order.index(200)
    order[i], order[i + 1] = 201, 200  # 200 after 201: 4 out-of-order stamps
    order.insert(order.index(305) + 1, 300)  # 300 again after 305: 4 more
    return order


def test_out_of_order_and_repeated_rows_are_counted_like_bag_messages(tmp_path: Path, base: dict[str, Any]) -> None:
    rec = base["rec"]
    order = _faulty_order()
    csv_path = tmp_path / "faulty.csv"
    write_csv(csv_path, Recording(rec.names, rec.stamps[order], rec.vectors[order]))
    bag = tmp_path / "faulty_bag"  # the same messages, received in that order (bag time increasing)
    ts = cdr.typestore()
    with Writer(bag, version=9, storage_plugin=StoragePlugin.SQLITE3) as w:
        conns = [w.add_connection(f"/{n}/raw", cdr.MAGNETIC_FIELD, typestore=ts) for n in NAMES]
        for pos, i in enumerate(order):
            t = int(rec.stamps[i])
            for k, (name, conn) in enumerate(zip(NAMES, conns)):
                msg = cdr.magnetic_field_message(t // 1_000_000_000, t % 1_000_000_000, name, rec.vectors[i, k])
                w.write(conn, int(rec.stamps[0]) + pos * 100_000_000 + k, bytes(ts.serialize_cdr(msg, cdr.MAGNETIC_FIELD)))
    note = f"  note: {SETS - 1} sets, 4 repeated stamps dropped, 8 out-of-order stamps dropped"
    outputs = {}
    for name, src in (("csv", csv_path), ("bag", bag)):
        proc = ok(magcal("correct", src, "-c", base["cal"], "-o", tmp_path / f"from_{name}.csv"))
        assert proc.stderr.splitlines() == [note], proc.stderr
        outputs[name] = read_corrected(tmp_path / f"from_{name}.csv")
        proc = ok(magcal("calibrate", src, "-o", tmp_path / f"{name}.yaml"))
        assert proc.stderr.splitlines() == [note], proc.stderr
        assert f"from {SETS - 1} sets" in proc.stdout
    kept = np.delete(np.arange(SETS), 200)
    np.testing.assert_array_equal(outputs["csv"]["stamps"], rec.stamps[kept])
    for key in ("stamps", "sensors", "field", "gradient"):
        np.testing.assert_array_equal(outputs["csv"][key], outputs["bag"][key])


# --------------------------------------------------------------------------- 9: BOM and CRLF


def test_csv_with_byte_order_mark_and_crlf_line_endings(tmp_path: Path, base: dict[str, Any]) -> None:
    text = base["csv"].read_text()
    bom = tmp_path / "bom.csv"
    bom.write_bytes(b"\xef\xbb\xbf" + text.replace("\n", "\r\n").encode())
    assert bom.read_bytes()[:8] == b"\xef\xbb\xbfstamp" and b"\r\n" in bom.read_bytes()
    ok(magcal("correct", base["csv"], "-c", base["cal"], "-o", tmp_path / "plain_out.csv"))
    ok(magcal("correct", bom, "-c", base["cal"], "-o", tmp_path / "bom_out.csv"))
    assert (tmp_path / "bom_out.csv").read_bytes() == (tmp_path / "plain_out.csv").read_bytes()
    proc = ok(magcal("calibrate", bom, "-o", tmp_path / "cal.yaml", "--reference-field", F))
    assert f"from {SETS} sets" in proc.stdout and proc.stderr == ""


# --------------------------------------------------------------------------- 10a: file size limit


@pytest.fixture(scope="module")
def big_bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A healthy bag large enough that SQLite sorts through temporary files while opening it."""
    bag = tmp_path_factory.mktemp("big") / "big"
    ok(magcal("simulate", bag, "--count", 80_000, "--seed", SEED))
    return bag


def test_a_file_size_limit_is_named_not_called_a_corrupt_bag(tmp_path: Path, base: dict[str, Any], big_bag: Path) -> None:
    d = tmp_path / "o"
    d.mkdir()
    limit = 100_000
    line = error_line(magcal_limited(limit, "calibrate", big_bag, "-o", d / "cal.yaml"), "calibrate")
    assert "corrupt" not in line
    assert line.endswith(f"cannot read {big_bag}: SQLite could not write its temporary files: "
                         f"file size limit exceeded (ulimit -f: {limit} bytes)")
    for out, what in (("out", "bag "), ("out.csv", ""), ("out_mcap", "bag ")):
        opts = ["--storage", "mcap"] if out == "out_mcap" else []
        line = error_line(magcal_limited(limit, "correct", base["bag"], "-c", base["cal"], "-o", d / out, *opts))
        assert line.endswith(f"cannot write {what}{d / out}: file size limit exceeded (ulimit -f: {limit} bytes)"), line
    line = error_line(magcal_limited(1000, "calibrate", base["bag"], "-o", d / "cal.yaml"), "calibrate")
    assert line.endswith(f"cannot write {d / 'cal.yaml'}: file size limit exceeded (ulimit -f: 1000 bytes)"), line
    assert listing(d) == []


def test_a_bug_in_our_code_is_not_reported_as_a_corrupt_bag(base: dict[str, Any], monkeypatch: pytest.MonkeyPatch) -> None:
    def broken(*args: object, **kwargs: object) -> None:
        raise AttributeError("'NoneType' object has no attribute 'shape'")

    monkeypatch.setattr(bag_reader, "decode_magnetic_fields", broken)
    with pytest.raises(AttributeError, match="no attribute 'shape'"):
        bag_reader.read_bag_sets(base["bag"])
    # What the storage library raises about the bag is still the bag's; what ours raises is a bug.
    with pytest.raises(AttributeError) as inside_rosbags:
        Reader(None)  # type: ignore[arg-type]
    assert bag_reader.is_read_error(inside_rosbags.value)
    with pytest.raises(TypeError) as inside_ours:
        cdr.decode_magnetic_fields(None)  # type: ignore[arg-type]
    assert not bag_reader.is_read_error(inside_ours.value)


# --------------------------------------------------------------------------- 10b: sensor mismatch


def _three_sensors(cal: Path, dest: Path) -> Path:
    doc = yaml.safe_load(cal.read_text())
    p = doc["magcal_correction"]["ros__parameters"]
    p["sensor_names"], p["positions"] = p["sensor_names"][:3], p["positions"][:9]
    del p["mag4"]
    dest.write_text(yaml.safe_dump(doc))
    return dest


@pytest.mark.parametrize("source", ["bag", "csv"])
def test_a_calibration_and_a_recording_with_different_sensors_name_them(
    tmp_path: Path, base: dict[str, Any], source: str
) -> None:
    three_cal = _three_sensors(base["cal"], base["dir"] / "three.yaml")
    rec = base["rec"]
    three_rec = tmp_path / "in" / ("three.csv" if source == "csv" else "three_bag")
    three_rec.parent.mkdir()
    (write_csv if source == "csv" else write_recording_bag)(three_rec, rec.select(("mag1", "mag2", "mag3")))
    d = tmp_path / "o"
    d.mkdir()

    line = error_line(magcal("correct", base[source], "-c", three_cal, "-o", d / "out"))
    assert line.endswith(f"{base[source]} has sensors mag1, mag2, mag3, mag4 but {three_cal} covers only "
                         "mag1, mag2, mag3: no calibration for mag4 (calibrate all 4 sensors together)"), line
    line = error_line(magcal("correct", three_rec, "-c", base["cal"], "-o", d / "out"))
    assert line.endswith(f"{three_rec} has no mag4 (its sensors: mag1, mag2, mag3); {base['cal']} covers "
                         "mag1, mag2, mag3, mag4"), line
    assert listing(d) == []
    # A tensor the calibrated sensors can give on their own: computed, the extra sensor reported.
    proc = ok(magcal("correct", base[source], "-c", three_cal, "-o", d / "out.csv", "--gradient-method", "least_squares"))
    assert f"note: {base[source]} also has mag4, which {three_cal} does not cover: left out" in proc.stderr
    assert (d / "out.csv").read_text().splitlines()[0].startswith("stamp,mag1.x,mag1.y,mag1.z,mag2.x")
    assert "mag4" not in (d / "out.csv").read_text().splitlines()[0]
    if source == "bag":  # the streaming bag-to-bag path says the same
        proc = ok(magcal("correct", base[source], "-c", three_cal, "-o", d / "out_bag", "--gradient-method", "least_squares"))
        assert f"note: {base[source]} also has mag4, which {three_cal} does not cover: left out" in proc.stderr
        with Reader(d / "out_bag") as reader:
            assert sorted(c.topic for c in reader.connections) == ["/field", "/gradient", "/mag1/corrected",
                                                                   "/mag2/corrected", "/mag3/corrected"]


# --------------------------------------------------------------------------- more of the same spirit


def test_an_output_never_overwrites_an_input_or_another_output(tmp_path: Path, base: dict[str, Any]) -> None:
    rec_csv = tmp_path / "rec.csv"
    write_csv(rec_csv, base["rec"])
    cal = tmp_path / "cal.yaml"
    cal.write_bytes(base["cal"].read_bytes())
    before = {p: p.read_bytes() for p in (rec_csv, cal)}
    cases = [
        ("correct", rec_csv, "-c", cal, "-o", rec_csv, "would overwrite the input"),
        ("correct", rec_csv, "-c", cal, "-o", tmp_path / "." / "rec.csv", "would overwrite the input"),
        ("calibrate", rec_csv, "-o", rec_csv, "would overwrite the input"),
        ("calibrate", rec_csv, "-o", tmp_path / "c.yaml", "--plot", tmp_path / "c.yaml", "are the same file"),
    ]
    for *args, expected in cases:
        line = error_line(magcal(*args), str(args[0]))
        assert expected in line, line
    assert {p: p.read_bytes() for p in (rec_csv, cal)} == before
    assert listing(tmp_path) == ["cal.yaml", "rec.csv"]


@pytest.mark.parametrize("value", ["5", "-0.001", "nan", "x"])
def test_a_bad_sync_tolerance_is_a_usage_error_not_a_traceback(tmp_path: Path, base: dict[str, Any], value: str) -> None:
    proc = magcal("correct", base["bag"], "-c", base["cal"], "-o", tmp_path / "out", "--sync-tolerance", value)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert proc.stderr.strip().splitlines()[-1].startswith("magcal correct: error: argument --sync-tolerance: ")
    assert listing(tmp_path) == []
