"""The calibration file: every ROS reader gets floats, backups are kept in generations, a failed hand-over is undone."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml
from rcl_interfaces.msg import ParameterType

from magcal_ros.core.calibration import ArrayCalibration
from magcal_ros.core.geometry import ArrayGeometry
from magcal_ros.errors import InputError
from magcal_ros.io import calibration_file as calfile

# Values whose repr has no decimal point (5e-08): YAML 1.1 reads "5e-08" as a string.
AWKWARD = [5e-08, -1e-07, 2e-05, 1e-18, 3e-09]


def _calibration(scale: float = 1.0) -> ArrayCalibration:
    geo = ArrayGeometry.cross()
    matrices = np.tile(np.eye(3), (4, 1, 1)) * scale
    offsets = np.array([[5e-08, -1e-07, 2e-05], [0.0, 1e-06, -3e-07], [4e-08, 0.0, 0.0], [1e-05, 2e-05, 3e-05]])
    covariances = np.stack([np.eye(3) * 1e-18 * (k + 1) for k in range(4)])
    covariances[0, 0, 1] = covariances[0, 1, 0] = 3e-19
    meta = {"method": "ml", "samples": 1000, "reference_field": 5e-05, "tmi_rms_after": [1e-09, 2e-09]}
    return ArrayCalibration(geo, matrices, offsets, meta, covariances)


def _write(tmp_path: Path, cal: ArrayCalibration) -> Path:
    path = tmp_path / "calibration.yaml"
    calfile.write(path, cal, node_name="/magcal_correction")
    return path


def test_rclpy_parameter_file_parser_reads_every_float_as_a_float(tmp_path: Path) -> None:
    """What ``ros2 param load`` does: rclpy.parameter.parameter_dict_from_yaml_file."""
    from rclpy.parameter import parameter_dict_from_yaml_file

    cal = _calibration()
    path = _write(tmp_path, cal)
    params = parameter_dict_from_yaml_file(str(path), target_nodes=["/magcal_correction"])
    assert set(params) == {"sensor_names", "positions"} | {f"mag{i}.{s}" for i in range(1, 5)
                                                            for s in ("matrix", "offset", "covariance")}
    for name, msg in params.items():
        if name != "sensor_names":
            assert msg.value.type == ParameterType.PARAMETER_DOUBLE_ARRAY, (name, msg.value)
    offset = np.array(params["mag1.offset"].value.double_array_value)
    assert np.allclose(offset, cal.offsets[0], rtol=1e-15, atol=0)  # at most one unit in the last place off
    cov = np.array(params["mag1.covariance"].value.double_array_value).reshape(3, 3)
    assert np.allclose(cov, cal.covariances[0], rtol=1e-15, atol=0)
    meta = parameter_dict_from_yaml_file(str(path), target_nodes=["magcal_provenance"])
    assert meta["reference_field"].value.type == ParameterType.PARAMETER_DOUBLE
    assert meta["tmi_rms_after"].value.type == ParameterType.PARAMETER_DOUBLE_ARRAY
    assert meta["samples"].value.type == ParameterType.PARAMETER_INTEGER


def test_rcl_params_file_parser_reads_every_float_as_a_float(tmp_path: Path) -> None:
    """What ``--params-file`` does: rcl's YAML parser, into a node's parameter overrides."""
    import rclpy
    from rclpy.context import Context
    from rclpy.parameter import Parameter

    from magcal_ros.app.ros_driver import pick_domain_id, release_domain_id

    path = _write(tmp_path, _calibration())
    context = Context()
    domain = pick_domain_id()  # a domain nothing uses, never the environment's
    rclpy.init(args=["node", "--ros-args", "--params-file", str(path)], context=context, domain_id=domain)
    try:
        node = rclpy.create_node("magcal_correction", context=context, start_parameter_services=False,
                                 automatically_declare_parameters_from_overrides=True)
        values = {p.name: p for p in node.get_parameters(node.list_parameters([], 0).names)}
        assert values["mag1.offset"].type_ == Parameter.Type.DOUBLE_ARRAY
        assert values["mag4.covariance"].type_ == Parameter.Type.DOUBLE_ARRAY
        assert values["positions"].type_ == Parameter.Type.DOUBLE_ARRAY
        node.destroy_node()
    finally:
        rclpy.try_shutdown(context=context)
        release_domain_id(domain)


def test_ros_float_changes_a_value_by_at_most_one_unit_in_the_last_place() -> None:
    for v in AWKWARD + [1e16, -3e+20, 0.0, 1.5, 123.0]:
        w = calfile.ros_float(v)
        assert "." in repr(w) and abs(w - v) <= np.spacing(abs(v)) and yaml.safe_load(str(w)) == w
    assert calfile.parameters(_calibration())["mag1"]["offset"][0] == calfile.ros_float(5e-08) != 5e-08


def test_backups_keep_the_last_generations_oldest_first(tmp_path: Path) -> None:
    path = tmp_path / "calibration.yaml"
    texts = []
    for k in range(6):
        calfile.write(path, _calibration(1.0 + 0.01 * k), keep=3)
        texts.append(path.read_text())
    backups = calfile.backups(path)
    assert [b.read_text() for b in backups] == texts[2:5]
    assert all(b.name.startswith("calibration.yaml.") and b.name.endswith("Z.bak") for b in backups)
    assert sorted(backups) == backups


def test_replace_undoes_itself_when_the_hand_over_fails(tmp_path: Path) -> None:
    path = tmp_path / "calibration.yaml"
    calfile.write(path, _calibration(), keep=3)
    calfile.write(path, _calibration(1.01), keep=3)
    before, backups = path.read_text(), [b.read_text() for b in calfile.backups(path)]
    with pytest.raises(RuntimeError, match="push failed"):
        with calfile.replace(path, _calibration(1.02), keep=3):
            assert calfile.loads(path.read_text()).matrices[0, 0, 0] == pytest.approx(1.02)  # written first
            raise RuntimeError("push failed")
    assert path.read_text() == before
    assert [b.read_text() for b in calfile.backups(path)] == backups
    fresh = tmp_path / "fresh.yaml"
    with pytest.raises(RuntimeError):
        with calfile.replace(fresh, _calibration()):
            raise RuntimeError("push failed")
    assert not fresh.exists() and sorted(p.name for p in tmp_path.iterdir()) == sorted(
        [path.name] + [b.name for b in calfile.backups(path)])


def test_an_unwritable_destination_changes_nothing(tmp_path: Path) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("x")
    with pytest.raises(NotADirectoryError):
        calfile.write(blocker / "calibration.yaml", _calibration())
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file"]


def test_time_offsets_round_trip_and_an_old_file_reads_as_zeros(tmp_path: Path) -> None:
    """<name>.time_offset (s) is written when a sensor has one, read back exactly, and absent means 0:
    a file without any reads and writes as before."""
    plain = _calibration()
    text = calfile.dumps(plain)
    assert "time_offset" not in text
    assert np.array_equal(calfile.loads(text).time_offsets, np.zeros(4))
    lagging = ArrayCalibration(plain.geometry, plain.matrices, plain.offsets, plain.metadata, plain.covariances,
                               time_offsets=[0.0, 0.0, 0.005, -0.00025])
    path = _write(tmp_path, lagging)
    doc = yaml.safe_load(path.read_text())["/magcal_correction"]["ros__parameters"]
    assert doc["mag3"]["time_offset"] == 0.005 and doc["mag1"]["time_offset"] == 0.0
    assert calfile.read(path).time_offsets.tolist() == [0.0, 0.0, 0.005, -0.00025]


@pytest.mark.parametrize("bad", ["0.7", "abc", "[0.1, 0.2]", ".nan"])
def test_an_unusable_time_offset_is_refused_by_name(bad: str) -> None:
    text = calfile.dumps(_calibration()).replace("      offset: [4.000000000000001e-08", f"      time_offset: {bad}\n"
                                                 "      offset: [4.000000000000001e-08")
    assert "time_offset" in text
    with pytest.raises(InputError, match="mag3.time_offset"):
        calfile.loads(text)


def test_a_non_symmetric_matrix_is_written_row_major_and_read_back_unchanged(tmp_path: Path) -> None:
    """``matrix: [m00, m01, m02, m10, ...]`` is ``B = M (raw - offset)`` row by row: a transposed
    matrix would survive a round trip through the package's own reader, so the file's numbers
    are read with plain YAML and applied with plain numpy (test/truth_tools.py)."""
    from truth_tools import correct

    rng = np.random.default_rng(12)
    geo = ArrayGeometry.cross()
    matrices = np.eye(3)[None] + rng.uniform(-0.05, 0.05, (4, 3, 3))  # far from symmetric
    matrices[:, 0, 1] += 0.03
    assert np.min(np.abs(matrices - matrices.transpose(0, 2, 1))[:, [0, 0, 1], [1, 2, 2]]) > 1e-4
    offsets = rng.normal(0, 300e-9, (4, 3))
    cal = ArrayCalibration(geo, matrices, offsets, {"method": "ml"})
    path = _write(tmp_path, cal)
    block = yaml.safe_load(path.read_text())["/magcal_correction"]["ros__parameters"]
    for i, name in enumerate(geo.names):
        assert block[name]["matrix"] == pytest.approx(matrices[i].reshape(-1).tolist(), rel=1e-15, abs=0)
        assert block[name]["matrix"][1] == pytest.approx(matrices[i][0, 1], rel=1e-15)  # row 0, column 1
        assert block[name]["offset"] == pytest.approx(offsets[i].tolist(), rel=1e-15, abs=0)
    back = calfile.read(path)
    np.testing.assert_allclose(back.matrices, matrices, rtol=1e-15, atol=0)
    np.testing.assert_allclose(back.offsets, offsets, rtol=1e-15, atol=0)
    raw = rng.normal(0, 3e-5, (50, 4, 3))
    from_file = np.stack([np.array(block[n]["matrix"]).reshape(3, 3) for n in geo.names])
    expected = correct(from_file, np.stack([block[n]["offset"] for n in geo.names]), raw)
    np.testing.assert_allclose(back.apply(raw), expected, rtol=1e-12, atol=1e-20)


# -- one validation for every reader -------------------------------------------------------------------
def _with_channel(cal: ArrayCalibration) -> ArrayCalibration:
    from dataclasses import replace

    return replace(cal, channels=("thruster",), interference=np.full((4, 3, 1), 2e-8),
                   temperature_reference=15.0, offset_tempco=np.full((4, 3), 1e-10),
                   matrix_tempco=np.full((4, 3, 3), 1e-6))


BOUNDED = {
    "positions": (lambda p, v: p.__setitem__("positions", [v] + p["positions"][1:]), "positions"),
    "noise": (lambda p, v: p["mag1"].__setitem__("noise", v), "mag1.noise"),
    "intensity": (lambda p, v: p.__setitem__("calibration_intensity", v), "calibration_intensity"),
    "interference": (lambda p, v: p["mag2"].__setitem__("interference", [v, 0.0, 0.0]), "mag2.interference"),
    "offset tempco": (lambda p, v: p["mag3"].__setitem__("offset_per_kelvin", [v, 0.0, 0.0]), "mag3.offset_per_kelvin"),
    "matrix tempco": (lambda p, v: p["mag4"].__setitem__("matrix_per_kelvin", [v] + [0.0] * 8), "mag4.matrix_per_kelvin"),
    "temperature reference": (lambda p, v: p.__setitem__("temperature_reference", v), "temperature_reference"),
    "time offset": (lambda p, v: p["mag1"].__setitem__("time_offset", v), "mag1.time_offset"),
}
"""How to put a value into a file's parameters, and the key the refusal names."""
ABSURD = {"positions": [1e300, -1e3, 51.0], "noise": [-1.0, 1e300, 0.5], "intensity": [-5e-5, 1e300, 0.5],
          "interference": [1e30, -1e-3], "offset tempco": [1e-3, -1e300], "matrix tempco": [0.5, -1e300],
          "temperature reference": [-300.0, 1e30], "time offset": [1e300, -2.0]}
"""Values no calibration of a vehicle's fluxgate array can hold (units, signs, corruption)."""


@pytest.mark.parametrize("key, value", [(k, v) for k, vs in ABSURD.items() for v in vs])
def test_every_reader_refuses_a_value_no_calibration_can_hold_by_its_key(tmp_path: Path, key: str,
                                                                         value: float) -> None:
    """The same key with the same absurd value is refused by the file reader (magcal correct, batch, --prior,
    the calibration node's prior) and by the correction node's parameters, naming the key; the valid file
    reads. (Before: noise -1, a negative or 1e300 intensity, 1e30 T/A, positions of 1e300 m were accepted by
    correct and batch, some of them by the node, and 7e30 T written in every row.)"""
    from magcal_ros.nodes.correction_node import build_state
    from magcal_ros.nodes.common import flatten_parameters

    cal = _with_channel(_calibration())
    path = _write(tmp_path, cal)
    calfile.read(path, "/magcal_correction")
    doc = yaml.safe_load(path.read_text())
    params = doc["/magcal_correction"]["ros__parameters"]
    put, name = BOUNDED[key]
    put(params, value)
    path.write_text(yaml.safe_dump(doc))
    with pytest.raises(InputError, match=name.replace(".", r"\.")):
        calfile.read(path, "/magcal_correction")
    values = flatten_parameters(params)
    values.update(frame_id="magcal_array", gradient_method="difference", sync_tolerance=1e-3, sync_mode="auto",
                  max_gap=0.0, temperature_tolerance=10.0, current_topics=["/thruster"],
                  current_types=["std_msgs/msg/Float64"], current_tolerance=0.5)
    with pytest.raises(InputError, match=name.replace(".", r"\.")):
        build_state(values)
