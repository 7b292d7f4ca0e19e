"""The staged calibration pipeline gives what the pipeline gave before it was split into stages.

``test/data/pipeline_reference.json`` holds the outcome of every scenario of ``pipeline_scenarios.py``
(matrices, offsets, interference, covariances, the analysis, the summary, warnings and metadata of a
result; the type and message of a refusal; the progress stages announced) as recorded on the pipeline
before the refactoring (``python test/pipeline_scenarios.py`` writes it). Numbers must agree to a
relative 1e-6 (of the number or of the largest in its array: builds of numpy differ by a few 1e-8 in an
ill-conditioned covariance), texts exactly.
"""

from __future__ import annotations

import json

import pipeline_scenarios as ps
import pytest

REFERENCE = json.loads(ps.REFERENCE.read_text())


def test_every_scenario_has_a_reference() -> None:
    assert sorted(REFERENCE) == sorted(ps.SCENARIOS)


@pytest.mark.parametrize("name", list(ps.SCENARIOS))
def test_the_outcome_is_the_recorded_one(name: str) -> None:
    want = REFERENCE[name]
    got = json.loads(json.dumps(ps.record(name)))  # the same plain data the reference was written as
    found = ps.differences(got, want, name)
    assert not found, "\n".join(found[:20])


def test_the_comparison_sees_a_small_change() -> None:
    """The comparison itself: a relative change of 1e-5 in one number, or one character, is a difference."""
    want = REFERENCE["rotation"]
    got = json.loads(json.dumps(want))
    got["offsets"][1][2] *= 1.0 + 1e-5
    assert ps.differences(got, want) == [f".offsets[1][2]: {got['offsets'][1][2]!r} != {want['offsets'][1][2]!r}"]
    got = json.loads(json.dumps(want))
    got["summary"] = got["summary"][:-1]
    assert len(ps.differences(got, want)) == 1
    assert ps.differences(json.loads(json.dumps(want)), want) == []


def test_an_undetermined_channel_of_a_long_recording_is_left_out_of_every_set() -> None:
    """A recording longer than the solve budget (the expensive stages on a subset) with a channel that never
    varies: solved again without it from every set (it passed the subset's currents with every set's
    readings: a reshape error), with the warning naming it and the calibration of the recording without it."""
    import numpy as np
    from magcal_ros.methods.pipeline import SolveOptions, calibrate_array

    (raw, geometry, f), kwargs = ps.SCENARIOS["currents_one_undetermined"]()
    result = calibrate_array(raw, geometry, f, options=SolveOptions(max_solve_sets=300), **kwargs)
    assert result.calibration.metadata["interference_undetermined"] == [ps.CHANNELS[1]]
    whole = calibrate_array(raw, geometry, f, **kwargs)
    assert np.allclose(result.calibration.offsets, whole.calibration.offsets, atol=2e-9)
    assert np.allclose(result.calibration.matrices, whole.calibration.matrices, atol=2e-4)


@pytest.mark.parametrize("name", ["imu", "temperatures", "lag", "currents"])
def test_the_structured_normal_equations_give_the_dense_jacobians_outcome(name: str, monkeypatch) -> None:
    """The normal equations built from the features (with the IMU's global blocks, the temperature's gain
    columns, the lag's) give the outcome the dense Jacobian gives, to the comparison's 1e-9."""
    from magcal_ros.core import array_fit

    structured = json.loads(json.dumps(ps.record(name)))
    monkeypatch.setattr(array_fit, "STRUCTURED", False)
    dense = json.loads(json.dumps(ps.record(name)))
    found = ps.differences(structured, dense, name)
    assert not found, "\n".join(found[:20])
