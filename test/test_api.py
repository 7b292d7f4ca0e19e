"""The Python face (magcal_ros.api) is a thin front: the same numbers as the package's own functions,
against the simulation's truth, and one clear error for bad input."""

from __future__ import annotations

import numpy as np
import pytest

import magcal_ros as mc
from magcal_ros.core.geometry import ArrayGeometry
from magcal_ros.errors import InputError
from magcal_ros.methods.pipeline import calibrate_array
from magcal_ros.sim.spec import SimulationSpec, run


@pytest.fixture(scope="module")
def cross() -> tuple:
    return run(SimulationSpec(count=600, seed=11))


def test_calibrate_is_the_pipeline_itself(cross: tuple) -> None:
    """The same calibration, to the last bit, as calibrate_array on the cross with the same inputs (planted:
    the reference not passed on fails), and float-second stamps give what integer nanoseconds give."""
    rec, _, _ = cross
    ours = mc.calibrate(rec.vectors, reference_field=55e-6, stamps=rec.stamps)
    theirs = calibrate_array(rec.vectors, ArrayGeometry.cross(), 55e-6, stamps=rec.stamps)
    np.testing.assert_array_equal(ours.calibration.matrices, theirs.calibration.matrices)
    np.testing.assert_array_equal(ours.calibration.offsets, theirs.calibration.offsets)
    seconds = mc.calibrate(rec.vectors, reference_field=55e-6, stamps=rec.stamps / 1e9)
    np.testing.assert_array_equal(seconds.calibration.matrices, ours.calibration.matrices)


def test_correct_gives_the_truth_to_the_noise_for_any_array() -> None:
    """Three sensors on a 0.6 m circle: the tensor (least squares, chosen by the geometry) within 10 % of
    the array's noise floor of the truth's gradient, the vectors' TMI within 10 % of the noise."""
    spec = SimulationSpec(count=800, seed=12, sensors=3, baseline=0.6)
    rec, _, sim = run(spec)
    positions = sim.geometry.positions
    result = mc.calibrate(rec.vectors, positions, 55e-6, stamps=rec.stamps)
    fresh, truth, _ = run(SimulationSpec(count=800, seed=12, sensors=3, baseline=0.6, schedule="tumble"))
    out = mc.correct(fresh.vectors, result.calibration)
    floor = mc.array_geometry(3, positions)  # the same geometry, by the public name
    from magcal_ros.core.metrics import gradient_floor

    error = out.tensor[:, :2] - truth.gradient[:, :2]
    assert np.sqrt(np.mean(error**2)) < 1.1 * gradient_floor(1e-9, floor)
    tmi = np.linalg.norm(out.vectors, axis=2) - 55e-6
    assert np.sqrt(np.mean(tmi**2)) < 1.1e-9


@pytest.mark.parametrize(("call", "message"), [
    (lambda raw: mc.calibrate(raw[:, :3]), "give their positions"),
    (lambda raw: mc.calibrate(raw[:, 0]), r"shape \(N, S, 3\)"),
    (lambda raw: mc.calibrate(raw, names=["a", "b"]), "2 names for 4 sensors"),
    (lambda raw: mc.check_health(raw, None, np.arange(3)), "one stamp per set"),  # type: ignore[arg-type]
])
def test_bad_input_is_one_clear_error(cross: tuple, call, message: str) -> None:  # type: ignore[no-untyped-def]
    with pytest.raises(InputError, match=message):
        call(cross[0].vectors)
