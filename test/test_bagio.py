"""rosbag2 I/O: byte-exact CDR batches, synchronisation, bag round trips, correct_bag."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from rosbags.rosbag2 import Reader, StoragePlugin, Writer

from magcal_ros.app.correct import correct_bag
from magcal_ros.core import stamps as stamp_units
from magcal_ros.core.calibration import ArrayCalibration
from magcal_ros.core.geometry import ArrayGeometry
from magcal_ros.core.recording import Recording
from magcal_ros.core.sync import SetSynchronizer
from magcal_ros.errors import InputError
from magcal_ros.io import bag_reader as bagsource
from magcal_ros.io import cdr
from magcal_ros.io.bag_reader import open_bag, read_bag_recording, read_bag_sets
from magcal_ros.io.bag_writer import BagSink, write_recording_bag, write_stream_bag

NAMES = ("mag1", "mag2", "mag3", "mag4")
NS = 1_000_000_000


def ts():  # type: ignore[no-untyped-def]
    return cdr.typestore()


def read_all(path: Path) -> list[tuple[str, str, int, object]]:
    """(topic, type, bag time, message) of every message of a bag, in bag order."""
    out = []
    with Reader(path) as reader:
        for conn, t, data in reader.messages():
            out.append((conn.topic, conn.msgtype, t, ts().deserialize_cdr(data, conn.msgtype)))
    return out


def stamp_ns(msg: object) -> int:
    return msg.header.stamp.sec * NS + msg.header.stamp.nanosec  # type: ignore[attr-defined]


def random_recording(n: int = 300, seed: int = 0, start_ns: int = 1_700_000_000 * NS) -> Recording:
    rng = np.random.default_rng(seed)
    return Recording(NAMES, start_ns + np.arange(n) * 10_000_000, rng.normal(0, 4e-5, (n, 4, 3)))


def random_calibration(seed: int = 1) -> ArrayCalibration:
    rng = np.random.default_rng(seed)
    geo = ArrayGeometry.cross()
    mats = np.eye(3) + rng.normal(0, 0.02, (4, 3, 3))
    return ArrayCalibration(geo, mats, rng.normal(0, 2e-7, (4, 3)), {})


# --------------------------------------------------------------------------- CDR


@pytest.mark.parametrize("frame_id", ["", "m", "mag1", "magcal_array", "a/very/long/frame_id_with_17"])
def test_magnetic_field_encoding_is_byte_exact(frame_id: str) -> None:
    rng = np.random.default_rng(len(frame_id))
    stamps = rng.integers(0, 2**31 - 1, 50) * NS + rng.integers(0, NS, 50)
    vecs = rng.normal(0, 5e-5, (50, 3))
    enc = cdr.magnetic_field_template(frame_id).encode(stamps, vecs)
    for row, s, v in zip(enc, stamps, vecs):
        msg = cdr.magnetic_field_message(int(s // NS), int(s % NS), frame_id, v)
        assert bytes(row) == bytes(ts().serialize_cdr(msg, cdr.MAGNETIC_FIELD, little_endian=True))


def test_gradient_encoding_is_byte_exact() -> None:
    g = np.random.default_rng(3).normal(0, 1e-6, (20, 3, 3))
    enc = cdr.gradient_template().encode(g)
    for row, gi in zip(enc, g):
        expected = ts().serialize_cdr(cdr.gradient_message(gi), cdr.FLOAT64_MULTI_ARRAY, little_endian=True)
        assert bytes(row) == bytes(expected)
        back = ts().deserialize_cdr(bytes(row), cdr.FLOAT64_MULTI_ARRAY)
        assert [(d.label, d.size, d.stride) for d in back.layout.dim] == [("row", 3, 9), ("col", 3, 3)]
        np.testing.assert_array_equal(back.data.reshape(3, 3), gi)


def test_decode_mixed_frames_and_endianness_matches_rosbags() -> None:
    rng = np.random.default_rng(4)
    frames = ["", "x", "mag1", "mag12", "sensor_frame_long", "mag1"]
    msgs, expected = [], []
    for i in range(120):
        frame = frames[i % len(frames)]
        s, ns_ = int(rng.integers(0, 2**31 - 1)), int(rng.integers(0, NS))
        v = rng.normal(0, 5e-5, 3)
        m = cdr.magnetic_field_message(s, ns_, frame, v, covariance=rng.normal(size=9))
        msgs.append(bytes(ts().serialize_cdr(m, cdr.MAGNETIC_FIELD, little_endian=bool(i % 3))))
        expected.append((s * NS + ns_, v))
    stamps, vecs = cdr.decode_magnetic_fields(msgs)
    assert stamps.tolist() == [e[0] for e in expected]
    np.testing.assert_array_equal(vecs, np.array([e[1] for e in expected]))
    # One group only (the common case) takes the reshape path.
    same = [m for m in msgs[2::6]]
    s2, v2 = cdr.decode_magnetic_fields(same)
    np.testing.assert_array_equal(s2, stamps[2::6])


def test_an_empty_batch_encodes_and_writes(tmp_path: Path) -> None:
    """A stream with no messages is valid data: the encoders give (0, size) bytes and a stream bag
    with one empty sensor is written, the other sensor's messages intact."""
    template = cdr.magnetic_field_template("mag2")
    assert template.encode(np.zeros(0, np.int64), np.zeros((0, 3))).shape == (0, template.size)
    assert cdr.gradient_template().encode(np.zeros((0, 3, 3))).shape == (0, cdr.gradient_template().size)
    bag = tmp_path / "empty_bag"
    write_stream_bag(bag, ("mag1", "mag2"), [np.array([5 * NS]), np.zeros(0, np.int64)],
                     [np.full((1, 3), 1e-5), np.zeros((0, 3))], [np.array([5 * NS]), np.zeros(0, np.int64)])
    with Reader(bag) as reader:
        assert sorted(c.topic for c in reader.connections) == ["/mag1/raw", "/mag2/raw"]
    assert [(topic, stamp_ns(m)) for topic, _, _, m in read_all(bag)] == [("/mag1/raw", 5 * NS)]


def test_a_stamp_beyond_a_ros_stamp_is_refused_not_wrapped() -> None:
    """``sec`` is int32: a stamp after 2038-01-19 was written wrapped to a negative second (a CSV stamped
    in 2065 corrected into a bag). The last second that fits is written and read back exactly."""
    template = cdr.magnetic_field_template("mag1")
    last = (2**31 - 1) * NS + 999_999_999
    got, _ = cdr.decode_magnetic_fields([bytes(template.encode(np.array([last]), np.ones((1, 3)))[0])])
    assert got.tolist() == [last]
    with pytest.raises(InputError, match=r"stamp 3000000000 s does not fit a ROS stamp"):
        template.encode(np.array([5 * NS, 3_000_000_000 * NS]), np.ones((2, 3)))


def test_decode_rejects_other_types() -> None:
    grad = bytes(cdr.gradient_template().template)
    with pytest.raises(InputError, match="MagneticField"):
        cdr.decode_magnetic_fields([grad, grad])
    with pytest.raises(InputError):
        cdr.decode_magnetic_fields([b"\x00\x01\x00\x00" + b"\x00" * 10])


def test_decode_edges_empty_input_nanosecond_range_and_trailing_padding() -> None:
    """Empty input gives empty arrays; an encapsulation other than plain CDR (little or big
    endian) is refused; nanosec 999999999 is a stamp, 1000000000 is malformed; up to 3 bytes of
    trailing padding are accepted (as rosbags does), 4 are not. Batch and single-message
    decoders alike."""
    stamps, vecs = cdr.decode_magnetic_fields([])
    assert stamps.shape == (0,) and vecs.shape == (0, 3)
    stamps, vecs = cdr.decode_magnetic_field_rows(np.empty((0, 132), np.uint8))
    assert stamps.shape == (0,) and vecs.shape == (0, 3)
    msg = bytes(ts().serialize_cdr(cdr.magnetic_field_message(7, 999_999_999, "mag1", (1e-5, 2e-5, 3e-5)),
                                   cdr.MAGNETIC_FIELD, little_endian=True))
    for pad in (0, 1, 3):
        data = msg + b"\x00" * pad
        assert cdr.decode_magnetic_fields([data, data])[0].tolist() == [7_999_999_999] * 2
        assert cdr.decode_magnetic_field(data) == (7_999_999_999, 1e-5, 2e-5, 3e-5)
    for kind in (2, 3, 7):  # PL_CDR and XCDR2 encapsulations are not plain CDR
        other = msg[:1] + bytes([kind]) + msg[2:]
        for decode in (lambda m: cdr.decode_magnetic_fields([m]), cdr.decode_magnetic_field):
            with pytest.raises(InputError, match="not plain CDR|not a plain CDR"):
                decode(other)
    bad_ns = msg[:8] + (1_000_000_000).to_bytes(4, "little") + msg[12:]
    for bad in (msg + b"\x00" * 4, bad_ns):
        with pytest.raises(InputError, match="malformed"):
            cdr.decode_magnetic_fields([bad])
        with pytest.raises(InputError, match="malformed"):
            cdr.decode_magnetic_field(bad)


def test_stamp_conversion() -> None:
    """To the nanosecond, as the module promises: float seconds go to the integer nanosecond
    nearest their exact binary value (computed here with decimal arithmetic; ties at half a
    nanosecond, below what a float product resolves, are left out), and back to the
    float nearest the stamp wherever a float can hold it."""
    from decimal import ROUND_HALF_EVEN, Decimal

    rng = np.random.default_rng(3)
    t = np.concatenate([[0.0, 1.5, 1.7e9 + 0.123456789, 12.999999999, 0.999999999, 1e-9, 2.4e-9, 3.6e-9,
                         1_763_900_000.999999999], rng.uniform(0, 2e9, 200), rng.uniform(0, 1e3, 200)])
    exact = [int((Decimal(float(x)) * 1_000_000_000).to_integral_value(ROUND_HALF_EVEN)) for x in t]
    ns_ = stamp_units.seconds_to_ns(t)
    assert ns_.dtype == np.int64 and ns_.tolist() == exact
    assert ns_[1] == 1_500_000_000 and ns_[3] == 12_999_999_999 and ns_[4] == 999_999_999
    # Back: sec + nanosec / 1e9 as the nearest float; below 2**53 ns (104 days) that is exact.
    small = rng.integers(0, 2**52, 500, dtype=np.int64)
    assert stamp_units.seconds_to_ns(stamp_units.ns_to_seconds(small)).tolist() == small.tolist()
    big = rng.integers(1_600_000_000 * 10**9, 1_900_000_000 * 10**9, 500, dtype=np.int64)
    back = stamp_units.ns_to_seconds(big)
    nearest = np.array([float(Decimal(int(x)) / 1_000_000_000) for x in big])
    assert np.all(np.abs(back - nearest) <= np.spacing(nearest))  # within one float step (~0.24 us)
    sec, nsec = stamp_units.split_stamp(np.array([-1, 0, 1_999_999_999, -1_500_000_000]))
    assert sec.tolist() == [-1, 0, 1, -2] and nsec.tolist() == [999_999_999, 0, 999_999_999, 500_000_000]
    assert stamp_units.join_stamp(sec, nsec).tolist() == [-1, 0, 1_999_999_999, -1_500_000_000]


# --------------------------------------------------------------------------- sync


@pytest.mark.parametrize("chunk", [7, 50, 10_000])
def test_bag_synchronisation_matches_the_rule_in_any_chunking(chunk: int) -> None:
    """Fed in bag-sized chunks, the batch path gives exactly the rule's sets (test_sync.rule_sets)."""
    from test_sync import rule_sets

    rng = np.random.default_rng(5)
    n, tol = 400, 2_000_000  # 100 Hz, 2 ms tolerance
    base = 1_700_000_000 * NS + np.arange(n) * 10_000_000
    streams = []
    for k in range(4):
        jitter = rng.integers(-3_000_000, 3_000_000, n)  # some beyond the tolerance
        keep = rng.random(n) > 0.05  # dropped messages
        streams.append((base + jitter)[keep])
    sync = SetSynchronizer(4, tol)
    got: list[tuple[int, ...]] = []
    # Feed interleaved in chunks, like a bag in bag-time order.
    events = sorted((int(t), k) for k, s in enumerate(streams) for t in s)
    for a in range(0, len(events), chunk):
        part = events[a : a + chunk]
        for k in range(4):
            st = np.array([t for t, kk in part if kk == k], dtype=np.int64)
            sync.add_batch(k, st, np.zeros((len(st), 3)) + k)
        batch = sync.pop()
        got += [tuple(int(x) for x in row) for row in batch.stamps]
        assert np.all(batch.vectors[:, :, 0] == np.arange(4))
    got += [tuple(int(x) for x in row) for row in sync.pop(final=True).stamps]
    assert got == rule_sets([s.tolist() for s in streams], tol)
    total = sum(len(s) for s in streams)
    assert sync.stats.sets == len(got)
    assert sync.stats.unmatched == sync.stats.dropped() == total - 4 * len(got)
    assert sync.pending == 0


# --------------------------------------------------------------------------- bags


@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
def test_write_and_read_recording(tmp_path: Path, storage: str) -> None:
    rec = random_recording()
    out = tmp_path / "raw"
    write_recording_bag(out, rec, storage)  # type: ignore[arg-type]
    assert not [p for p in tmp_path.iterdir() if p.name != "raw"], "temporary files left behind"
    with Reader(out) as r:
        assert {c.topic: c.msgtype for c in r.connections} == {f"/{n}/raw": cdr.MAGNETIC_FIELD for n in NAMES}
        assert r.message_count == 4 * len(rec)
        assert r.storage.storages[0].__class__.__name__.lower().startswith(storage[:4])
    msgs = read_all(out)
    expected_ns = rec.stamps
    for i, (topic, _, t, m) in enumerate(msgs):
        k = i % 4
        assert topic == f"/{NAMES[k]}/raw" and m.header.frame_id == NAMES[k]
        assert t == stamp_ns(m) == expected_ns[i // 4]
        assert [m.magnetic_field.x, m.magnetic_field.y, m.magnetic_field.z] == rec.vectors[i // 4, k].tolist()
        assert not np.any(m.magnetic_field_covariance)
    back = read_bag_recording(out)
    assert back.names == NAMES
    np.testing.assert_array_equal(back.vectors, rec.vectors)
    np.testing.assert_array_equal(back.stamps, expected_ns)
    sub = read_bag_recording(out, names=["mag3", "mag1"])
    np.testing.assert_array_equal(sub.vectors, rec.vectors[:, [2, 0]])
    tops = read_bag_recording(out, topics=["/mag2/raw", "/mag4/raw"])
    assert tops.names == ("mag2", "mag4")


def write_messages(path: Path, storage: str, items: list[tuple[str, str, int, bytes]]) -> None:
    """A bag from raw (topic, type, bag time, bytes) items, via plain rosbags."""
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    with Writer(path, version=9, storage_plugin=plugin) as w:
        conns = {}
        for topic, typ, t, data in items:
            if topic not in conns:
                conns[topic] = w.add_connection(topic, typ, typestore=ts())
            w.write(conns[topic], t, data)


def field_bytes(stamp: int, frame: str, v: object) -> bytes:
    m = cdr.magnetic_field_message(stamp // NS, stamp % NS, frame, v)
    return bytes(ts().serialize_cdr(m, cdr.MAGNETIC_FIELD))


@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
def test_read_synchronises_with_jitter_and_drops(tmp_path: Path, storage: str) -> None:
    rng = np.random.default_rng(6)
    n = 200
    base = 1_700_000_000 * NS + np.arange(n) * 100_000_000
    items = []
    vecs = rng.normal(0, 4e-5, (n, 4, 3))
    for i in range(n):
        for k, name in enumerate(NAMES):
            if i == 17 and k == 2:
                continue  # incomplete set
            if i == 40 and k == 1:
                vecs[i, k, 0] = np.nan  # non-finite reading
            s = int(base[i] + (rng.integers(-400_000, 400_000) if k else 0))
            items.append((f"/{name}/raw", cdr.MAGNETIC_FIELD, s + 1_000_000, field_bytes(s, name, vecs[i, k])))
    items.append(("/other", "std_msgs/msg/Float64MultiArray", int(base[5]), bytes(cdr.gradient_template().template)))
    items.sort(key=lambda x: x[2])
    bag = tmp_path / "jitter"
    write_messages(bag, storage, items)
    rec, stats = read_bag_sets(bag, tolerance=1e-3)
    # Set 17 lost a message, set 40 a reading: their other 3 + 3 messages find no set.
    assert stats.unmatched == 6 and stats.nonfinite == 1 and stats.sets == n - 2
    keep = np.setdiff1d(np.arange(n), [17, 40])
    np.testing.assert_array_equal(rec.vectors, vecs[keep])
    # Integer nanoseconds end to end: the set stamps are the first sensor's header stamps, exactly.
    np.testing.assert_array_equal(rec.stamps, base[keep])
    with pytest.raises(InputError, match="NaN"):
        read_bag_sets(bag, tolerance=1e-3, nonfinite="error")
    # Exact matching with a tolerance below the jitter leaves no complete set: a clear error, not an
    # empty recording. Mode auto sees the stamps do not coincide within it and interpolates instead.
    with pytest.raises(InputError, match="no complete synchronized sets.*dropped"):
        read_bag_sets(bag, tolerance=1e-6, sync_mode="exact")
    rec, stats = read_bag_sets(bag, tolerance=1e-6)
    assert stats.sets == len(rec) >= n - 3


def test_missing_and_wrong_topics(tmp_path: Path) -> None:
    bag = tmp_path / "raw"
    write_recording_bag(bag, random_recording(20))
    with pytest.raises(InputError, match="no topic /mag9/raw"):
        read_bag_recording(bag, names=["mag1", "mag9"])
    other = tmp_path / "other"
    write_messages(other, "sqlite3", [("/imu", "std_msgs/msg/Float64MultiArray", 1, bytes(cdr.gradient_template().template))])
    with pytest.raises(InputError, match="no /<name>/raw"):
        read_bag_recording(other)
    wrong = tmp_path / "wrong"
    write_messages(wrong, "sqlite3", [("/mag1/raw", "std_msgs/msg/Float64MultiArray", 1, bytes(cdr.gradient_template().template))])
    with pytest.raises(InputError, match="has type std_msgs/msg/Float64MultiArray"):
        read_bag_recording(wrong, names=["mag1"])


@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
def test_corrupt_bags_give_input_errors(tmp_path: Path, storage: str) -> None:
    bag = tmp_path / "raw"
    write_recording_bag(bag, random_recording(2000), storage)  # type: ignore[arg-type]
    data = next(p for p in bag.iterdir() if p.suffix in (".db3", ".mcap"))
    raw = data.read_bytes()
    data.write_bytes(raw[: len(raw) // 2])
    with pytest.raises(InputError, match="corrupt or unreadable"):
        read_bag_recording(bag)
    data.write_bytes(b"garbage" * 100)
    with pytest.raises(InputError):
        read_bag_recording(bag)
    (bag / "metadata.yaml").unlink()
    with pytest.raises(InputError, match="not a rosbag2 directory"):
        read_bag_recording(bag)
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(InputError):
        read_bag_recording(empty)


@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
def test_correct_bag_matches_rosbags_serialisation(tmp_path: Path, storage: str) -> None:
    rec = random_recording(300)
    cal = random_calibration()
    raw = tmp_path / "raw"
    write_recording_bag(raw, rec, storage)  # type: ignore[arg-type]
    out = tmp_path / "out"
    calls: list[int] = []
    report = correct_bag(raw, cal, out, progress=calls.append)
    assert report.stats.sets == 300 and report.storage == storage and sum(calls) == 1200
    b, centre, g = cal.field_and_gradient(rec.vectors)
    stamps = rec.stamps
    msgs = read_all(out)
    assert len(msgs) == 6 * 300
    with Reader(out) as r:
        types = {c.topic: c.msgtype for c in r.connections}
        files = [p.suffix for p in out.iterdir()]
    assert types == {**{f"/{n}/corrected": cdr.MAGNETIC_FIELD for n in NAMES}, "/field": cdr.MAGNETIC_FIELD,
                     "/gradient": cdr.FLOAT64_MULTI_ARRAY}
    assert (".mcap" if storage == "mcap" else ".db3") in files
    order = [f"/{n}/corrected" for n in NAMES] + ["/field", "/gradient"]
    for i in range(300):
        block = msgs[6 * i : 6 * i + 6]
        assert [m[0] for m in block] == order, "field must precede gradient, per set"
        assert all(m[2] == stamps[i] for m in block)
        for k in range(4):
            m = block[k][3]
            assert m.header.frame_id == "magcal_array" and stamp_ns(m) == stamps[i]
            np.testing.assert_array_equal([m.magnetic_field.x, m.magnetic_field.y, m.magnetic_field.z], b[i, k])
        f = block[4][3]
        np.testing.assert_array_equal([f.magnetic_field.x, f.magnetic_field.y, f.magnetic_field.z], centre[i])
        np.testing.assert_array_equal(block[5][3].data.reshape(3, 3), g[i])
    # Byte-exact against rosbags' serializer.
    with Reader(out) as r:
        for conn, t, data in r.messages():
            obj = ts().deserialize_cdr(data, conn.msgtype)
            assert bytes(ts().serialize_cdr(obj, conn.msgtype, little_endian=True)) == bytes(data)


@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
def test_fast_paths_equal_plain_rosbags_paths(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, storage: str) -> None:
    """Batch reading and writing give the same bag as rosbags' per-message Reader/Writer."""
    rec = random_recording(5000)
    cal = random_calibration()
    raw = tmp_path / "raw"
    write_recording_bag(raw, rec, storage)  # type: ignore[arg-type]
    with open_bag(raw) as reader:
        fast_source = bagsource._plain_sqlite_files(reader) or bagsource._indexed_mcaps(reader, reader.connections)
        assert fast_source, "the fast reader must be used for bags we write"
    correct_bag(raw, cal, tmp_path / "fast")
    monkeypatch.setattr(BagSink, "_detect_fast", lambda self: None)
    monkeypatch.setattr(bagsource, "_plain_sqlite_files", lambda reader: None)
    monkeypatch.setattr(bagsource, "_indexed_mcaps", lambda reader, conns: None)
    correct_bag(raw, cal, tmp_path / "slow")
    with Reader(tmp_path / "fast") as a, Reader(tmp_path / "slow") as b:
        fa = [(c.topic, t, bytes(d)) for c, t, d in a.messages()]
        fb = [(c.topic, t, bytes(d)) for c, t, d in b.messages()]
    assert fa == fb


@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
def test_correct_bag_copies_topics_and_converts_storage(tmp_path: Path, storage: str) -> None:
    rec = random_recording(40)
    raw = tmp_path / "raw"
    items = []
    stamps = rec.stamps
    for i in range(40):
        for k, name in enumerate(NAMES):
            items.append((f"/{name}/raw", cdr.MAGNETIC_FIELD, int(stamps[i]), field_bytes(int(stamps[i]), name, rec.vectors[i, k])))
        items.append(("/imu", cdr.FLOAT64_MULTI_ARRAY, int(stamps[i]) + 7, bytes(cdr.gradient_template().template)))
    write_messages(raw, storage, items)
    cal = random_calibration()
    out = tmp_path / "out"
    other = "sqlite3" if storage == "mcap" else "mcap"
    report = correct_bag(raw, cal, out, storage=other, copy_topics=["/imu"])
    assert report.copied_messages == 40
    msgs = read_all(out)
    imu = [m for m in msgs if m[0] == "/imu"]
    assert [m[2] for m in imu] == [int(s) + 7 for s in stamps]
    assert sum(1 for m in msgs if m[0] == "/gradient") == 40
    assert any(p.suffix == (".mcap" if other == "mcap" else ".db3") for p in out.iterdir())
    imu_bytes = {bytes(cdr.gradient_template().template)}
    with Reader(out) as r:
        assert {bytes(d) for c, _, d in r.messages() if c.topic == "/imu"} == imu_bytes
    out2 = tmp_path / "out2"
    report2 = correct_bag(raw, cal, out2, copy_topics="all")
    topics = {m[0] for m in read_all(out2)}
    assert {"/imu", "/mag1/raw", "/mag1/corrected", "/field", "/gradient"} <= topics
    assert report2.copied_messages == 200
    with pytest.raises(InputError, match="no topic /gps"):
        correct_bag(raw, cal, tmp_path / "out3", copy_topics=["/gps"])
    assert not (tmp_path / "out3").exists()


def test_outputs_are_atomic_and_safe(tmp_path: Path) -> None:
    rec = random_recording(30)
    raw = tmp_path / "raw"
    write_recording_bag(raw, rec)
    precious = tmp_path / "precious"
    precious.mkdir()
    (precious / "notes.txt").write_text("keep me")
    with pytest.raises(InputError, match="not a rosbag2 directory"):
        correct_bag(raw, random_calibration(), precious)
    assert (precious / "notes.txt").read_text() == "keep me"
    with pytest.raises(InputError, match="differ"):
        correct_bag(raw, random_calibration(), raw)
    # A calibration naming a sensor the bag lacks: nothing written.
    geo = ArrayGeometry.cross(names=("mag1", "mag2", "mag3", "mag5"))
    cal = ArrayCalibration(geo, np.tile(np.eye(3), (4, 1, 1)), np.zeros((4, 3)))
    with pytest.raises(InputError, match="has no mag5 .*the calibration covers mag1, mag2, mag3, mag5"):
        correct_bag(raw, cal, tmp_path / "out")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["precious", "raw"]
    # Rewriting an existing bag replaces it.
    write_recording_bag(raw, random_recording(10))
    assert len(read_bag_recording(raw)) == 10
    shutil.rmtree(raw)


def test_write_failures_are_one_line_and_leave_nothing(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import sqlite3

    from magcal_ros.errors import MagcalError

    raw = tmp_path / "raw"
    write_recording_bag(raw, random_recording(30))

    def full_disk(self, *args, **kwargs):  # type: ignore[no-untyped-def]
        raise sqlite3.OperationalError("database or disk is full")

    monkeypatch.setattr(BagSink, "_sqlite_sets", full_disk)
    with pytest.raises(MagcalError, match="cannot write bag .*disk is full"):
        correct_bag(raw, random_calibration(), tmp_path / "out")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["raw"]
