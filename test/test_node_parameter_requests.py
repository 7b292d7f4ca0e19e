"""The nodes' parameters in an unattended mission: what ``ros2 param load``, ``ros2 param set`` and a params file
bring, and a simulated clock that never starts.

The nodes run in this process (as in test_node_parameters.py), reached over a private ROS domain through
rclpy's parameter client (what the ``ros2 param`` commands use) and topics.
"""

from __future__ import annotations

import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from rclpy.parameter import Parameter
from test_node_parameters import NAMES, _make, in_process, load

from magcal_ros.core.calibration import ArrayCalibration
from magcal_ros.core.geometry import ArrayGeometry
from magcal_ros.errors import InputError
from magcal_ros.io import calibration_file as calfile

pytestmark = pytest.mark.dds  # through real nodes over DDS: `scripts/test.sh -m dds` runs them as a group

CORRECTION = "/magcal_correction"
CALIBRATION = "/magcal_calibration"
DEADLINE = 120.0


def _saved_calibration(tmp_path: Path) -> Path:
    """A calibration file as ``magcal calibrate`` writes it (with its provenance block)."""
    from test_offline import magcal, ok

    rec, cal = tmp_path / "rot.csv", tmp_path / "cal.yaml"
    ok(magcal("simulate", rec, "--count", 300, "--seed", 3, "-q"))
    ok(magcal("calibrate", rec, "-o", cal, "--reference-field", 5.15e-5, "-q"))
    return cal


def test_ros2_param_load_of_a_calibration_swaps_it_in_at_once_and_ignores_its_provenance(tmp_path: Path) -> None:
    """``ros2 param load`` sends the whole file in one set_parameters request, which rclpy applies one
    parameter at a time (21 swaps within milliseconds: sets corrected with half a new calibration, and 79
    "failed" lines for the provenance block). The node applies the calibration as one update (one parameter
    event holds every calibration parameter), answers the provenance keys "ignored", and runs the file's
    calibration."""
    from rcl_interfaces.msg import ParameterEvent
    from rclpy.parameter import parameter_dict_from_yaml_file

    cal = _saved_calibration(tmp_path)
    saved = calfile.read(cal)
    offered = parameter_dict_from_yaml_file(str(cal), False)
    ours = {n for n in offered if n in ("sensor_names", "positions", "calibration_intensity")
            or n.split(".")[0] in NAMES}
    with in_process("-p", f"uncorrected_sensors:={NAMES}") as run:
        node = _make("correction", run)
        events: list[set[str]] = []
        lock = threading.Lock()

        def on_event(msg: Any) -> None:
            if msg.node == CORRECTION:
                with lock:
                    events.append({p.name for p in (*msg.new_parameters, *msg.changed_parameters)})

        run.client_node.create_subscription(ParameterEvent, "/parameter_events", on_event, 1000)
        time.sleep(1.0)  # the subscription matched; start-up events are not what is counted
        with lock:
            events.clear()
        results = load(run, CORRECTION, cal)
        failed = [(n, why) for n, good, why in results if not good]
        assert not failed, failed
        ignored = {n for n, _, why in results if why.startswith("ignored")}
        assert ignored == set(offered) - ours and all("magcal_provenance" in why for n, _, why in results
                                                      if n in ignored)
        changed = ours - {"sensor_names", "positions"}  # as they were

        def seen() -> set[str]:
            with lock:
                return set().union(*events) if events else set()

        deadline = time.monotonic() + DEADLINE
        while time.monotonic() < deadline and not changed <= seen():
            time.sleep(0.05)
        with lock:
            touching = [e for e in events if e & ours]
        assert len(touching) == 1 and changed <= touching[0], [sorted(e) for e in touching]
        assert node._state.missing == () and node._state.calibrated == tuple(NAMES)
        np.testing.assert_array_equal(node._state.calibration.matrices, saved.matrices)
        np.testing.assert_array_equal(node._state.calibration.offsets, saved.offsets)
        assert not node.has_parameter("created") and not node.has_parameter("uncertainty.mag1.offset_x_nT")


def test_a_request_with_one_bad_calibration_value_sets_none_of_them() -> None:
    """One set_parameters request (as ros2 param load sends a file) with a valid matrix and an offset that is not
    in Tesla: neither is applied, each says why, and the node keeps its calibration."""
    with in_process("-p", f"uncorrected_sensors:={NAMES}") as run:
        node = _make("correction", run)
        before = node._state
        request = [Parameter("mag1.matrix", value=[2.0, 0.0, 0.0, 0.0, 2.0, 0.0, 0.0, 0.0, 2.0]),
                   Parameter("mag1.offset", value=[1.0, 0.0, 0.0])]
        results = run.wait(run.client(CORRECTION).set_parameters(request)).results
        assert [r.successful for r in results] == [False, False]
        assert all("Tesla" in r.reason and "none was set" in r.reason for r in results), results
        assert node._state is before and node.get_parameter("mag1.matrix").value == []


def test_an_identity_calibration_given_on_purpose_is_a_calibration(tmp_path: Path) -> None:
    """Identity matrices and zero offsets from a calibration file correct (as ``magcal correct`` does with the
    file): field and gradient are published, the centre field the mean of the raw readings. A sensor whose
    matrix is [] (a dump of a node that never had a calibration) is not calibrated."""
    from sensor_msgs.msg import MagneticField

    identity = tmp_path / "identity.yaml"
    calfile.write(identity, ArrayCalibration.identity(ArrayGeometry.cross()))
    with in_process("--params-file", str(identity)) as run:
        node = _make("correction", run)
        assert node._state.missing == () and node._state.calibrated == tuple(NAMES)
        got: list[tuple[float, float, float]] = []
        run.client_node.create_subscription(MagneticField, "/field", lambda m: got.append(
            (m.magnetic_field.x, m.magnetic_field.y, m.magnetic_field.z)), 100)
        raw = np.array([[1.0e-5, 2.0e-5, 4.0e-5], [1.1e-5, 2.0e-5, 4.0e-5], [1.0e-5, 2.2e-5, 4.0e-5],
                        [1.0e-5, 2.0e-5, 4.4e-5]])
        send = _sender(node)
        deadline = time.monotonic() + DEADLINE
        k = 0
        while time.monotonic() < deadline and not got:
            for i in range(4):
                send(i, 1_700_000_000 * 10**9 + k * 10_000_000, raw[i])
            k += 1
            time.sleep(0.01)
        assert got, "no field published with an identity calibration"
        np.testing.assert_allclose(got[0], raw.mean(axis=0), rtol=1e-12)
        assert node._withheld == 0
    with in_process("-p", "mag2.matrix:=[]") as run:  # not given: not calibrated
        node = _make("correction", run)
        assert node._state.calibrated == () and node._state.missing == tuple(NAMES)


def _sender(node: Any) -> Any:
    """Offer a raw reading to the node's subscription callback as the middleware would (CDR bytes)."""
    from rclpy.serialization import serialize_message
    from sensor_msgs.msg import MagneticField

    callbacks = [node._raw_callback(i) for i in range(len(NAMES))]

    def send(i: int, stamp: int, vector: Any) -> None:
        msg = MagneticField()
        msg.header.stamp.sec, msg.header.stamp.nanosec = divmod(stamp, 10**9)
        msg.magnetic_field.x, msg.magnetic_field.y, msg.magnetic_field.z = (float(x) for x in vector)
        callbacks[i](serialize_message(msg), {"received_timestamp": stamp})

    return send


@pytest.mark.parametrize("kind", ["correction", "calibration"])
def test_a_sensor_named_twice_is_refused_at_start_and_at_param_set(kind: str) -> None:
    """At start-up a clear InputError (the node prints one line and exits 1), not a traceback from declaring the
    sensor's parameters twice; at param set a refusal naming it, the node as it was."""
    with in_process("-p", "sensor_names:=[mag1, mag2, mag1]") as run, \
            pytest.raises(InputError, match="sensor_names lists mag1 more than once"):
        _make(kind, run)
    with in_process("-p", f"uncorrected_sensors:={NAMES}") as run:
        node = _make(kind, run)
        result = run.wait(run.client(node.get_fully_qualified_name()).set_parameters(
            [Parameter("sensor_names", value=["mag1", "mag2", "mag3", "mag3"])])).results[0]
        assert not result.successful and "mag3 more than once" in result.reason, result.reason
        assert node.get_parameter("sensor_names").value == NAMES


@pytest.mark.parametrize("kind", ["correction", "calibration"])
def test_a_number_beyond_its_range_is_refused_whatever_its_type(kind: str) -> None:
    """temperature_tolerance as the integer 2**63 - 1 passed rclpy's range (checked for doubles only) and then
    withheld every set: refused at param set and at start, the reason giving the range."""
    huge = 2**63 - 1
    with in_process("-p", f"uncorrected_sensors:={NAMES}") as run:
        node = _make(kind, run)
        client = run.client(node.get_fully_qualified_name())
        names = ["temperature_tolerance"] + (["imu_tolerance", "service_timeout"] if kind == "calibration" else [])
        for name in names:
            before = node.get_parameter(name).value
            result = run.wait(client.set_parameters([Parameter(name, value=huge)])).results[0]
            assert not result.successful and f"{name} {huge} is out of range" in result.reason, result.reason
            assert node.get_parameter(name).value == before
        assert run.wait(client.set_parameters([Parameter("temperature_tolerance", value=20)])).results[0].successful
    with in_process("-p", f"temperature_tolerance:={huge}") as run, \
            pytest.raises(InputError, match="temperature_tolerance .* is out of range: 0 .. 3600"):
        _make(kind, run)


def test_with_use_sim_time_and_no_clock_both_nodes_still_report_and_say_why(tmp_path: Path) -> None:
    """use_sim_time without a /clock publisher: the node clock stands at 0 and a timer on it never fires, so
    /diagnostics went silent without a word. The reports run on the steady clock: both nodes keep publishing
    /diagnostics, each with a WARN that names the missing /clock (and a line in the log)."""
    from diagnostic_msgs.msg import DiagnosticArray

    args = ("-p", "use_sim_time:=true", "-p", f"uncorrected_sensors:={NAMES}", "-p", "status_period:=0.25",
            "-p", "progress_period:=0.25")
    with in_process(*args) as run:
        _make("correction", run)
        _make("calibration", run)
        seen: dict[str, list[Any]] = {CORRECTION: [], CALIBRATION: []}
        lock = threading.Lock()

        def keep(msg: Any) -> None:
            with lock:
                for status in msg.status:
                    if status.name in seen:
                        seen[status.name].append(status)

        run.client_node.create_subscription(DiagnosticArray, "/diagnostics", keep, 100)

        def warned(name: str) -> bool:
            with lock:
                return any(s.level[0] >= 1 and "no /clock" in s.message for s in seen[name])

        deadline = time.monotonic() + DEADLINE
        while time.monotonic() < deadline and not all(warned(n) for n in seen):
            time.sleep(0.1)
        with lock:
            last = {n: (s[-1].message if s else None) for n, s in seen.items()}
        assert all(warned(n) for n in seen), last
        assert all("use_sim_time is true and no /clock arrived" in m for m in last.values()), last


def test_the_sets_a_calibration_solves_are_the_sets_it_keeps_with_the_imu_pending() -> None:
    """~/calibrate keeps exactly the sets it solved (so that calling it again answers unchanged): those waiting for
    the IMU's next sample go into the solve first, and so into what is kept. (Taken before them, the sets kept
    lacked the waiting ones and a second ~/calibrate solved again.)"""
    with in_process("-p", "prior:=none") as run:
        node = _make("calibration", run)
        rng = np.random.default_rng(2)
        t0 = 1_700_000_000 * 10**9
        with node._lock:
            for k in range(40):
                t = t0 + k * 10_000_000
                node._imu.add(t, [0.0, 0.0, 0.0, 1.0], [0.0, 0.0, 0.0])
                node._buffer.add(t, tuple(map(tuple, rng.normal(size=(4, 3)) * 1e-5)), [], None,
                                 [0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0])
            waiting = t0 + 40 * 10_000_000 + 1_000_000  # after the last IMU sample: waits for the next one
            node._newest_set = waiting
            node._pending.append((waiting, tuple(map(tuple, rng.normal(size=(4, 3)) * 1e-5)), 0, True))
        first = node._take_sets(None)
        assert len(first.collected) == 41 and waiting in first.collected.stamps
        with node._lock:
            node._buffer.restore(*first.snapshot)
        again = node._take_sets(None)
        np.testing.assert_array_equal(again.collected.stamps, first.collected.stamps)
        np.testing.assert_array_equal(again.collected.vectors, first.collected.vectors)
