"""A current channel whose interference the calibration does not know: watched, and named once it varies.

The rule (:class:`~magcal_ros.core.interference.CurrentWatch`): over its latest readings a channel is named when
its current varies by at least ``WATCH_MIN_VARIATION`` RMS and ``NOISE_RATIO`` times its reading noise; a
reading that is only noise is never named, whatever its level and noise. The calibration health then says so
(:func:`~magcal_ros.core.calibration_health.with_unknown_currents`), and the calibration node's push watches the
channels a calibration leaves unsolved (``watch_*``). Through both nodes: ``test_mission_soak.py``.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from magcal_ros.core.calibration_health import OK, WARN, DriftReport, with_unknown_currents
from magcal_ros.core.interference import NOISE_RATIO, WATCH_MIN_VARIATION, CurrentWatch

SETTINGS = settings(max_examples=60, deadline=None, derandomize=True)


def _watch(values: np.ndarray) -> tuple[CurrentWatch, list[str]]:
    watch = CurrentWatch(["payload/battery"])
    for k, v in enumerate(values):
        watch.add(0, k, float(v))
    return watch, watch.judge()


@SETTINGS
@given(level=st.floats(-50.0, 50.0), noise=st.floats(1e-4, 0.5), n=st.integers(20, 400), seed=st.integers(0, 2**16))
def test_a_current_that_is_only_noise_is_never_named(level: float, noise: float, n: int, seed: int) -> None:
    u = level + np.random.default_rng(seed).normal(0.0, noise, n)
    _, named = _watch(u)
    assert named == []


@SETTINGS
@given(level=st.floats(0.0, 5.0), noise=st.floats(1e-4, 0.05), n=st.integers(40, 400), at=st.floats(0.05, 0.95),
       seed=st.integers(0, 2**16))
def test_a_step_well_beyond_the_noise_is_named_at_once(level: float, noise: float, n: int, at: float,
                                                        seed: int) -> None:
    """A payload switched on: a step of height h after a fraction p of the readings varies by h sqrt(p (1 - p))
    RMS; twice the threshold (the noise as drawn) is named by the first judgement that sees it."""
    k = max(1, int(at * n))
    p = (n - k) / n
    height = 2.0 * max(WATCH_MIN_VARIATION, NOISE_RATIO * noise) / np.sqrt(p * (1.0 - p))
    u = level + np.random.default_rng(seed).normal(0.0, noise, n)
    u[k:] += height
    watch, named = _watch(u)
    assert named == ["payload/battery"]
    assert "payload/battery varies" in watch.named["payload/battery"]
    assert watch.judge() == []  # named once, and it stays named
    assert list(watch.named) == ["payload/battery"]


def test_a_smooth_change_is_named_and_a_small_one_is_not() -> None:
    t = np.arange(400) / 10.0
    rng = np.random.default_rng(3)
    _, named = _watch(2.0 + np.sin(2 * np.pi * t / 97.0) + rng.normal(0, 0.01, 400))
    assert named == ["payload/battery"]
    _, named = _watch(2.0 + 0.02 * np.sin(2 * np.pi * t / 97.0))  # 14 mA RMS, noise-free: below 50 mA
    assert named == []


def test_readings_that_are_not_currents_are_ignored() -> None:
    watch = CurrentWatch(["a", "b"])
    for k in range(100):
        watch.add(0, k, 1.0 + 1e-3 * (k % 2))
        watch.add(1, k, float("nan") if k % 2 else 1e30)  # never a value
    watch.add(0, 100, 1e30)  # one broken reading does not make channel a vary
    assert watch.judge() == []


def test_the_health_names_the_channels_and_keeps_what_it_judged() -> None:
    fits = DriftReport(OK, "calibration fits: TMI residual 1 nT", False, values={"drifted": "false"})
    same = with_unknown_currents(fits, {})
    assert same.level == OK and not same.drifted and same.values["unknown_interference"] == ""
    named = with_unknown_currents(fits, {"payload/battery": "payload/battery varies (0 .. 3 A)"})
    assert named.level == WARN and named.drifted and named.values["drifted"] == "true"
    assert named.message == "payload/battery varies, interference unknown: recalibrate" and len(named.message) <= 128
    assert named.values["unknown_interference"] == "payload/battery"
    assert named.values["unknown_interference_detail"] == "payload/battery varies (0 .. 3 A)"
    drifted = DriftReport(2, "mag2 calibration drifted: TMI residual 40 nT: recalibrate", True,
                          values={"drifted": "true"})
    both = with_unknown_currents(drifted, {"a": "a varies", "b": "b varies"})
    assert both.level == 2 and both.message.startswith("a, b vary, interference unknown")
    assert both.values["sensor_health"] == drifted.message


@pytest.mark.parametrize("solved", [(), ("pump",), ("pump", "payload")])
def test_a_push_watches_the_channels_a_calibration_left_unsolved(solved: tuple[str, ...]) -> None:
    from magcal_ros.nodes import common
    from magcal_ros.nodes.correction_link import channel_parameters

    inputs = common.current_inputs({"interference_channels": ["pump", "payload"],
                                    "interference_topics": ["/pump/battery", "/payload/current"],
                                    "interference_types": [common.BATTERY_STATE, common.FLOAT64]})
    params = channel_parameters(inputs, solved)
    unsolved = [c for c in ("pump", "payload") if c not in solved]
    assert params["interference_channels"] == list(solved) and params["watch_channels"] == unsolved
    topic = {"pump": "/pump/battery", "payload": "/payload/current"}
    assert params["watch_topics"] == [topic[c] for c in unsolved]
    assert params["interference_topics"] == [topic[c] for c in solved]
    assert len(params["watch_types"]) == len(unsolved)


def test_the_correction_node_refuses_a_channel_both_applied_and_watched() -> None:
    from magcal_ros.errors import InputError
    from magcal_ros.nodes.correction_node import build_state

    values = {"sensor_names": ["mag1"], "positions": [0.0, 0.0, 0.0], "gradient_method": "difference",
              "frame_id": "magcal_array", "sync_tolerance": 0.002, "sync_mode": "auto", "max_gap": 0.0,
              "temperature_tolerance": 10.0, "mag1.matrix": [1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0],
              "mag1.offset": [0.0, 0.0, 0.0], "interference_channels": ["pump"], "mag1.interference": [0.0] * 3}
    state = build_state({**values, "watch_channels": ["payload"]})
    assert state.watched.channels == ("payload",) and state.watched.topics == ("payload",)
    with pytest.raises(InputError, match="pump in both interference_channels and watch_channels"):
        build_state({**values, "watch_channels": ["pump"]})
    with pytest.raises(InputError, match="watch_topics needs one entry per watch channel"):
        build_state({**values, "watch_channels": ["payload"], "watch_topics": ["/a", "/b"]})
