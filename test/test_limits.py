"""Every documented limit that decides a refusal or a warning, pinned from both sides.

Each test puts a case just inside a limit and one just outside it, built from the limit's
definition in the docs (the effect of a quantity in noise sd, a residual in noise sd, a
fraction of readings, a gain error, a time), never from what the code happens to return.
A limit moved by a few per cent (or doubled, or an inclusive bound made exclusive) fails.
"""

from __future__ import annotations

import numpy as np
import pytest

from magcal_ros.core import identifiability as ident
from magcal_ros.core import quality
from magcal_ros.core.calibration import check_sensor
from magcal_ros.core.interference import (
    MAX_READING_NOISE,
    NOISE_RATIO,
    CurrentSamples,
    match_currents,
    reading_noise,
    undetermined_channels,
)
from magcal_ros.core.observability import excitation
from magcal_ros.core.sync import SetSynchronizer
from magcal_ros.errors import InputError
from magcal_ros.nodes.health import ERROR, OK, WARN, ArrayHealth, HealthLimits

NT = 1e-9
F = 51_500 * NT
MS = 1_000_000
INSIDE, OUTSIDE = 0.98, 1.02
"""A case 2 % inside and 2 % outside a limit."""


# -- identifiability: undetermined above 400 noise sd (or 15 % of F), weak above 30 -----------
def _analysed(effect: float, noise: float, quantity: int = 3, prior_ratio: float | None = None) -> ident.Identifiability:
    """One sensor, identity correction, whose parameter ``quantity`` of W (row-major (3, 4): 3 is
    offset x, 0 is K_xx, i.e. scale x) has a 1-sigma ``effect`` (T) on the field; every other
    parameter known to 1e-9 of its own effect. ``prior_ratio``: a prior whose 1-sigma is
    ``sigma / prior_ratio``."""
    w = np.concatenate([np.eye(3), np.zeros((3, 1))], axis=1)[None]
    sd = np.full(12, 1e-9 * effect / F)
    sd[quantity] = effect / F  # offsets are in units of F, gains are dimensionless (effect = sd x F)
    cov = np.diag(sd**2)
    prior = None if prior_ratio is None else cov / prior_ratio**2
    return ident.analyse(("s",), w, F, cov, np.array([noise]), prior)


@pytest.mark.parametrize("quantity,name", [(3, "offset x"), (0, "scale x")])
def test_a_quantity_is_undetermined_above_400_noise_sd(quantity: int, name: str) -> None:
    assert ident.UNDETERMINED_EFFECT == 400.0  # the documented value (docs/field_calibration.md)
    inside = _analysed(INSIDE * 400 * NT, NT, quantity).by_name("s", name)
    outside = _analysed(OUTSIDE * 400 * NT, NT, quantity).by_name("s", name)
    assert (inside.status, outside.status) == ("weak", "undetermined"), (inside, outside)


def test_a_quantity_is_undetermined_above_15_percent_of_f_whatever_the_noise() -> None:
    """A consumer sensor (0.3 % of F noise): 400 sd would be 1.2 F, so the fraction of F decides."""
    noise = 0.003 * F
    inside = _analysed(INSIDE * 0.15 * F, noise).by_name("s", "offset x")
    outside = _analysed(OUTSIDE * 0.15 * F, noise).by_name("s", "offset x")
    assert (inside.status, outside.status) == ("weak", "undetermined")


def test_a_quantity_is_weak_above_30_noise_sd() -> None:
    inside = _analysed(INSIDE * 30 * NT, NT).by_name("s", "offset x")
    outside = _analysed(OUTSIDE * 30 * NT, NT).by_name("s", "offset x")
    assert (inside.status, outside.status) == ("determined", "weak")


def test_with_a_prior_a_quantity_is_kept_unless_the_data_halved_its_uncertainty() -> None:
    updated = _analysed(100 * NT, NT, prior_ratio=0.5 * INSIDE).by_name("s", "offset x")  # sigma / prior's
    kept = _analysed(100 * NT, NT, prior_ratio=0.5 * OUTSIDE).by_name("s", "offset x")
    assert (updated.status, kept.status) == ("updated", "kept")


def test_the_envelope_ends_where_the_predicted_tmi_error_reaches_1_5x_the_noise() -> None:
    """An offset uncertainty the same in every direction adds ``sigma_o`` to the TMI error at every
    attitude: ``sqrt(1 + sigma_o^2 / sigma^2)`` is 1.5 for ``sigma_o^2 = 1.25 sigma^2``."""
    w = np.concatenate([np.eye(3), np.zeros((3, 1))], axis=1)[None]
    for factor, whole in ((INSIDE, True), (OUTSIDE, False)):
        sigma_o = factor * np.sqrt(1.25) * NT
        var = np.zeros(12)
        var[[3, 7, 11]] = (sigma_o / F) ** 2
        env = ident.envelope(w, np.diag(var), np.array([NT]), F, np.radians(60.0))
        assert env.whole_sphere is whole and env.empty is (not whole), (factor, env)
        assert env.ratio_sphere == pytest.approx(np.sqrt(1 + (sigma_o / NT) ** 2), rel=1e-6)


# -- quality gates ------------------------------------------------------------------------------
N = 4000


def _white(rng: np.random.Generator, sigma: float, s: int = 1) -> np.ndarray:
    return rng.normal(0.0, sigma, (N, s, 3))


def _slow(rms: float, s: int = 1) -> np.ndarray:
    """A slow residual (period N / 3 sets) of RMS ``rms`` per axis: invisible to second differences."""
    t = np.arange(N) / N
    wave = np.sqrt(2.0) * np.sin(2 * np.pi * 3 * t + np.arange(3)[:, None] * 2.0).T  # (N, 3), RMS 1
    return np.repeat((rms * wave)[:, None, :], s, axis=1)


def _circle(step_deg: float, n: int = N) -> np.ndarray:
    """Unit field directions turning about z by ``step_deg`` per set."""
    a = np.radians(step_deg) * np.arange(n)
    return np.stack([np.cos(a), np.sin(a), np.zeros(n)], axis=1)


def _judge(residuals: np.ndarray, directions: np.ndarray | None = None, tmi: np.ndarray | None = None,
           weights: np.ndarray | None = None, raw: np.ndarray | None = None, **kw: object) -> quality.Verdict:
    n, s, _ = residuals.shape
    return quality.judge(tuple(f"mag{k + 1}" for k in range(s)), residuals,
                         np.ones((n, s)) if weights is None else weights,
                         np.zeros((n, s)) if tmi is None else tmi,
                         np.full((n, s, 3), 3e-5) if raw is None else raw,
                         directions=directions, **kw)  # type: ignore[arg-type]


def _scaled_residual(rng: np.random.Generator, ratio: float) -> np.ndarray:
    """White noise of 1 nT plus a slow part, RMS per axis exactly ``ratio`` x the white noise
    the data show (read from second differences, as the docs define it)."""
    white = _white(rng, NT)
    noise = float(np.mean(quality.white_noise(white[:, 0])))
    total = ratio * noise
    slow_rms = np.sqrt(total**2 - float(np.mean(white**2)))
    return white + _slow(slow_rms)


def test_in_time_order_the_residual_may_be_17x_the_noise_the_data_show() -> None:
    rng = np.random.default_rng(1)
    smooth = _circle(1.0)
    assert _judge(_scaled_residual(rng, INSIDE * 17), smooth).cause is None
    cause = _judge(_scaled_residual(rng, OUTSIDE * 17), smooth).cause
    assert cause is not None and "17x the sensor noise the data show" in cause


def test_a_residual_beyond_3_5x_the_noise_is_a_warning() -> None:
    rng = np.random.default_rng(2)
    smooth = _circle(1.0)
    assert not [w for w in _judge(_scaled_residual(rng, INSIDE * 3.5), smooth).warnings if "white noise" in w]
    verdict = _judge(_scaled_residual(rng, OUTSIDE * 3.5), smooth)
    assert verdict.cause is None and any("x the white noise the data show" in w for w in verdict.warnings)


def test_in_no_time_order_the_residual_may_be_5_percent_of_f() -> None:
    rng = np.random.default_rng(3)
    shuffled = rng.normal(size=(N, 3))
    shuffled /= np.linalg.norm(shuffled, axis=1, keepdims=True)
    white = _white(rng, 1.0)
    white /= np.sqrt(np.mean(white**2))  # RMS per axis exactly 1
    assert _judge(INSIDE * 0.05 * F * white, shuffled, intensity=F).cause is None
    cause = _judge(OUTSIDE * 0.05 * F * white, shuffled, intensity=F).cause
    assert cause is not None and "5.0% of F" in cause


def test_max_residual_replaces_the_noise_rule() -> None:
    rng = np.random.default_rng(4)
    white = _white(rng, 1.0)
    white /= np.sqrt(np.mean(white**2))
    limit = 40 * NT
    assert _judge(INSIDE * limit * white, _circle(1.0), max_residual=limit).cause is None
    cause = _judge(OUTSIDE * limit * white, _circle(1.0), max_residual=limit).cause
    assert cause is not None and "max residual 40 nT" in cause


def test_sets_are_in_time_order_when_consecutive_directions_are_within_0_3_of_the_typical_angle() -> None:
    """On a circle the typical angle between two directions is 90 deg: steps of 27 deg are the limit.
    The typical angle is the median of 2,000 random pairs, good to about +-1.5 deg here: 25 and 28.5 deg."""
    assert quality.in_time_order(_circle(25.0))
    assert not quality.in_time_order(_circle(28.5))


@pytest.mark.parametrize("runs", [False, True])
def test_a_quarter_of_a_sensors_readings_may_be_excluded(runs: bool) -> None:
    """Up to 25 % excluded: accepted with a count; beyond: refused, as spikes when scattered, as a
    field that changed when the excluded readings come in runs of 10 or more."""
    rng = np.random.default_rng(5)
    e = _white(rng, NT)
    raw = 3e-5 + _white(rng, 1e-5)  # readings that vary (a constant axis would read as clipped)
    for fraction, refused in ((0.24, False), (0.26, True)):
        w = np.ones((N, 1))
        k = int(fraction * N)
        if runs:
            w[: k, 0] = 0.0  # one run
        else:
            w[rng.choice(N, k, replace=False), 0] = 0.0
        verdict = _judge(e, weights=w, raw=raw)
        if not refused:
            assert verdict.cause is None and f"{k} outlying readings of mag1 excluded" in verdict.warnings, verdict
        else:
            assert verdict.cause is not None
            assert ("field was not constant" in verdict.cause) is runs
            assert ("too many outliers" in verdict.cause) is not runs


def test_excluded_readings_count_as_a_run_from_10_consecutive_sets() -> None:
    mask = np.zeros(200, bool)
    mask[10:20] = True  # a run of 10
    mask[50:59] = True  # a run of 9
    assert quality.longest_runs(mask) == pytest.approx(10 / 19)


def test_a_step_in_the_field_must_exceed_20_white_noise_sd_in_time_order() -> None:
    """A clean step of the TMI residual half way (explains nearly all of it, highly significant):
    refused from 20 sd of the white noise the residuals show."""
    rng = np.random.default_rng(6)
    e = _white(rng, NT)
    noise = float(np.mean(quality.white_noise(e[:, 0])))
    for factor, refused in ((INSIDE, False), (OUTSIDE, True)):
        tmi = np.where(np.arange(N) < N // 2, 0.0, factor * 20 * noise) + rng.normal(0, 0.01 * NT, N)
        cause = _judge(e, _circle(1.0), tmi[:, None]).cause
        assert (cause is not None and "field was not constant" in cause) is refused, (factor, cause)


def test_a_step_must_explain_a_quarter_of_the_tmi_residual() -> None:
    """A 40-sd step with an alternating residual beside it: the step explains ``s^2/4 / (s^2/4 + a^2)``."""
    rng = np.random.default_rng(7)
    e = _white(rng, NT)
    s = 40 * NT
    for explained, refused in ((0.25 * INSIDE, False), (0.25 * OUTSIDE, True)):
        a = s / 2 * np.sqrt(1 / explained - 1)
        tmi = np.where(np.arange(N) < N // 2, 0.0, s) + a * (-1.0) ** np.arange(N)
        assert quality.best_step(tmi).explained == pytest.approx(explained, rel=1e-6)
        cause = _judge(e, _circle(1.0), tmi[:, None]).cause
        assert (cause is not None and "field was not constant" in cause) is refused, (explained, cause)


def test_the_reference_intensity_may_imply_gains_3_percent_off_with_a_warning_20_percent_refused() -> None:
    e = _white(np.random.default_rng(8), NT)
    for gain, warned, refused in ((1 + 0.03 * INSIDE, False, False), (1 + 0.03 * OUTSIDE, True, False),
                                  (1 - 0.03 * OUTSIDE, True, False),
                                  (1 + 0.2 * INSIDE, True, False), (1 + 0.2 * OUTSIDE, True, True),
                                  (1 - 0.2 * OUTSIDE, True, True)):
        verdict = _judge(e, implied_gain=gain, intensity=F)
        assert (verdict.cause is not None) is refused, (gain, verdict.cause)
        if refused:
            assert "disagrees with the data" in verdict.cause  # type: ignore[operator]
        else:
            assert any("makes the sensor gains" in w for w in verdict.warnings) is warned, (gain, verdict.warnings)


def test_a_residual_below_0_43_of_the_quantisation_noise_is_a_collapsed_fit() -> None:
    """Readings on a 100 nT grid (quantisation noise 100 / sqrt(12) nT): a residual below 0.43 of it
    cannot come from such a sensor."""
    rng = np.random.default_rng(9)
    q = 100 * NT
    raw = (rng.integers(0, 60, (N, 1, 3)) * q) + 2e-5
    white = _white(rng, 1.0)
    white /= np.sqrt(np.mean(white**2))
    floor = q / np.sqrt(12.0)
    assert _judge(OUTSIDE * 0.43 * floor * white, raw=raw).cause is None
    cause = _judge(INSIDE * 0.43 * floor * white, raw=raw).cause
    assert cause is not None and "far below its quantisation" in cause


def test_a_sensor_is_refused_as_saturated_when_more_than_a_quarter_of_its_readings_clip() -> None:
    rng = np.random.default_rng(10)
    raw = rng.uniform(-4e-5, 4e-5, (N, 1, 3))
    for fraction, refused in ((0.24, False), (0.26, True)):
        r = raw.copy()
        r[: int(fraction * N), 0, 0] = 8e-5  # an axis stuck at its full-scale value
        mask, cause = quality.saturation(("mag1",), r)
        assert int(mask.sum()) == int(fraction * N)
        assert (cause is not None and "mag1 is saturated" in cause) is refused


# -- what a manoeuvre must at least be -----------------------------------------------------------
def test_the_coverage_counts_the_cells_of_the_directions_visited() -> None:
    """Coverage: the share of the 42 direction cells (each the directions nearest one centre) that hold a
    reading's direction about the readings' centre, against a plain nearest-centre search: random caps
    of every size, every centre itself (all 42), and one direction (one cell)."""
    from magcal_ros.core.observability import SPHERE_CELLS, sphere_cells

    centres = sphere_cells()
    rng = np.random.default_rng(11)
    offset = np.array([3e-6, -2e-6, 1e-6])
    for cap in (0.1, 0.5, 1.0, 1.7, np.pi):
        d = rng.normal(size=(3000, 3))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        d = d[np.arccos(np.clip(d @ centres[5], -1, 1)) <= cap]
        d = np.concatenate([d, -d[:1]])  # (a point opposite: the readings' centre stays near the offset)
        readings = 3e-5 * d + offset
        moved = readings - readings.mean(axis=0)
        expected = len(np.unique(np.argmax(moved @ centres.T, axis=1))) / SPHERE_CELLS
        assert excitation(readings).coverage == pytest.approx(expected), cap
    assert excitation(3e-5 * centres + offset).coverage == 1.0
    line = np.outer(np.linspace(1.0, 2.0, 50), centres[7])  # along one direction from its mean
    assert excitation(3e-5 * line + offset).coverage == pytest.approx(2 / SPHERE_CELLS)  # both ends of the line


def test_a_long_recordings_coverage_and_quadric_ratio_count_every_set() -> None:
    """Over more sets than one of the excitation's chunks, the coverage and the quadric ratio are those of every
    set: a cap of directions whose last few sets (in the last chunk) visit cells no other set does, and a quadric
    ratio against the singular values of the whole design matrix (planted: the last chunk left out)."""
    from magcal_ros.core.observability import EXCITATION_CHUNK, SPHERE_CELLS, centred_quadric_design, sphere_cells

    centres = sphere_cells()
    rng = np.random.default_rng(5)
    n = 2 * EXCITATION_CHUNK + 123
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    d = np.where((d @ centres[5] > 0.3)[:, None], d, centres[5])  # a cap about one centre ...
    d[-3:] = -centres[5]  # ... and the far side in the last sets only
    readings = 3e-5 * d * rng.uniform(0.95, 1.05, size=(n, 1)) + np.array([3e-6, -2e-6, 1e-6])
    moved = readings - readings.mean(axis=0)
    exc = excitation(readings)
    assert exc.coverage == pytest.approx(len(np.unique(np.argmax(moved @ centres.T, axis=1))) / SPHERE_CELLS)
    sv = np.linalg.svd(centred_quadric_design(moved.T, float(np.median(np.linalg.norm(moved, axis=1)))),
                       compute_uv=False)
    assert exc.quadric_ratio == pytest.approx(sv[8] / sv[0], rel=1e-6)


def test_a_calibration_needs_12_sets() -> None:
    from magcal_ros.core.observability import sphere_cells

    for n, refused in ((11, True), (12, False)):
        readings = 3e-5 * sphere_cells(n) + np.array([1e-6, 2e-6, 3e-6])
        problem = excitation(readings).problem()
        assert (problem is not None and f"only {n} synchronized sets" in problem) is refused, problem


def test_readings_must_spread_by_5_percent_of_their_norm() -> None:
    """A small sphere of readings around a large constant field: its widest spread (sd along a
    principal axis, over the mean norm) just under or over 5 %."""
    from magcal_ros.core.observability import sphere_cells

    centre = np.array([3e-5, 1e-5, 4e-5])
    unit = sphere_cells(400)
    for factor, refused in ((INSIDE, True), (OUTSIDE, False)):
        # Solve for the radius whose widest principal sd / mean norm is factor x 0.05 (from the definition).
        lo, hi = 1e-8, 1e-4
        for _ in range(80):
            radius = 0.5 * (lo + hi)
            r = centre + radius * unit
            c = r - r.mean(axis=0)
            widest = np.sqrt(np.linalg.eigvalsh(c.T @ c / len(r))[-1]) / np.mean(np.linalg.norm(r, axis=1))
            lo, hi = (radius, hi) if widest < factor * 0.05 else (lo, radius)
        problem = excitation(centre + radius * unit).problem()
        assert (problem is not None and "barely change" in problem) is refused, (factor, problem)


# -- a correction a sensor can have ---------------------------------------------------------------
def test_a_correction_matrix_has_gains_between_0_1_and_10_and_an_offset_below_1_mT() -> None:
    rot = np.linalg.qr(np.random.default_rng(11).normal(size=(3, 3)))[0]
    ok = np.zeros(3)
    for gains, refused in (((10.0, 1.0, 1.0), False), ((10.0 * 1.001, 1.0, 1.0), True),
                           ((1.0, 1.0, 0.1), False), ((1.0, 1.0, 0.1 / 1.001), True)):
        m = rot @ np.diag(gains) @ rot.T
        if refused:
            with pytest.raises(InputError, match="not a fluxgate correction|ill-conditioned"):
                check_sensor("mag1", m, ok)
        else:
            check_sensor("mag1", m, ok)
    direction = np.array([2.0, -1.0, 2.0]) / 3.0
    check_sensor("mag1", np.eye(3), 1e-3 * INSIDE * direction)
    with pytest.raises(InputError, match="units must be Tesla"):
        check_sensor("mag1", np.eye(3), 1e-3 * OUTSIDE * direction)


# -- current interference ----------------------------------------------------------------------------
def test_a_current_channel_must_vary_by_1_mA() -> None:
    # steps of 25 sets: a current that changes at every set is its monitor's reading noise (next test)
    alternating = (-1.0) ** (np.arange(1000) // 25)
    for amplitude, undetermined in ((INSIDE * 1e-3, True), (OUTSIDE * 1e-3, False)):
        assert bool(undetermined_channels((amplitude * alternating)[:, None])[0]) is undetermined, amplitude


def test_a_current_channel_is_left_out_when_its_gains_effect_would_exceed_30_noise_sd() -> None:
    """A current of mean ``c`` varying by ``v`` (RMS) over ``n`` sets: its gains' 1-sigma effect at
    its RMS current is ``sqrt(c^2 + v^2) / (sqrt(n) v)`` noise sd; above 30 it is left out."""
    n, v = 1000, 0.1
    alternating = v * (-1.0) ** (np.arange(n) // 25)
    for effect, undetermined in ((INSIDE * 30, False), (OUTSIDE * 30, True)):
        c = np.sqrt((effect * np.sqrt(n) * v) ** 2 - v**2)
        assert bool(undetermined_channels((c + alternating)[:, None])[0]) is undetermined, effect


def test_a_current_within_3_times_its_reading_noise_is_undetermined() -> None:
    """Steps of +-a every 25 sets read with noise 10 mA (estimated from the set-to-set differences): RMS
    ``sqrt(a^2 + noise^2)``, undetermined below 3x the noise; a reading noise above 0.1 A is taken for a
    current changing at every set (determined)."""
    n, sigma = 4000, 0.01
    noise = np.random.default_rng(5).normal(0.0, sigma, n)
    steps = (-1.0) ** (np.arange(n) // 25)
    estimated = reading_noise(noise)
    assert estimated == pytest.approx(sigma, rel=0.05)
    for ratio, undetermined in ((0.7 * NOISE_RATIO, True), (1.3 * NOISE_RATIO, False)):
        a = np.sqrt((ratio * estimated) ** 2 - estimated**2)
        assert bool(undetermined_channels((5.0 + a * steps + noise)[:, None])[0]) is undetermined, ratio
    for scale, undetermined in ((INSIDE, True), (OUTSIDE * 1.1, False)):
        louder = MAX_READING_NOISE * scale / estimated * noise  # reading noise MAX_READING_NOISE * scale
        assert bool(undetermined_channels(louder[:, None])[0]) is undetermined, scale


def test_a_current_is_fresh_for_half_a_second_after_its_stamp() -> None:
    tol = 500 * MS
    set_stamp = 10_000 * MS
    for age, fresh in ((tol, True), (tol + 1, False), (0, True), (-1, False)):
        samples = [CurrentSamples("thruster1/battery", np.array([set_stamp - age]), np.array([7.5]))]
        u, ok = match_currents(np.array([set_stamp]), samples, tol)
        assert bool(ok[0, 0]) is fresh and u[0, 0] == (7.5 if fresh else 0.0), age


# -- stream health -----------------------------------------------------------------------------------
LIMITS = HealthLimits(silent_after_ns=1000 * MS, stale_after_ns=3000 * MS, max_drop_fraction=0.01)


def _health(stamps: list[int], now: int = 0) -> ArrayHealth:
    sync = SetSynchronizer(1)
    health = ArrayHealth(("mag1",), sync, LIMITS, now)
    for t in stamps:
        health.seen(0, t)
        sync.add(0, t, 1e-5, 2e-5, 3e-5)
    return health


def test_a_sample_index_the_stamps_skip_is_a_sample_lost() -> None:
    """The sample clock (a line through many stamps) numbers the samples: a stamp one period after the
    last is the next sample, two periods after it skips one (lost, one gap), whatever came before."""
    period = 10 * MS
    stamps = [1000 * MS + k * period for k in range(60)]
    regular = stamps + [stamps[-1] + period + k * period for k in range(10)]
    skipped = stamps + [stamps[-1] + 2 * period + k * period for k in range(10)]
    assert _health(regular).lost == [0] and _health(regular).gaps == [0]
    assert _health(skipped).lost == [1] and _health(skipped).gaps == [1]


def test_a_sensor_is_silent_after_sensor_timeout_and_the_node_in_error_after_output_timeout() -> None:
    health = _health([1000 * MS + k * 10 * MS for k in range(40)])
    health.output(40, 0)
    quiet = health.assess(0, {}, "sets published")
    assert quiet.level == OK, quiet.message
    at_limit = health.assess(LIMITS.silent_after_ns, {}, "sets published")
    assert at_limit.level == OK, at_limit.message
    silent = health.assess(LIMITS.silent_after_ns + 1, {}, "sets published")
    assert silent.level == WARN and "silent: mag1" in silent.message
    assert health.assess(LIMITS.stale_after_ns, {}, "sets published").level == WARN
    stale = health.assess(LIMITS.stale_after_ns + 1, {}, "sets published")
    assert stale.level == ERROR and "no sets published for 3.0 s" in stale.message


def test_more_than_1_percent_of_a_periods_messages_dropped_is_a_warning() -> None:
    health = _health([1000 * MS + k * 10 * MS for k in range(1000)])
    health.output(1, 0)
    assert health.assess(0, {"unmatched": 10}, "sets").level == OK  # 10 of 1000: exactly 1 %
    for k in range(1000, 2000):
        t = 1000 * MS + k * 10 * MS
        health.seen(0, t)
    warned = health.assess(0, {"unmatched": 10 + 11}, "sets")  # 11 more of the next 1000
    assert warned.level == WARN and "dropping 1.1% of messages" in warned.message


@pytest.mark.parametrize("motion", ["tumble", "level yaw circle"])
def test_a_step_is_scored_as_the_best_split_of_offset_and_gain(motion: str) -> None:
    """The step part of the residual's shape is, at each split tried, the variance explained by
    ``[1, h, h d, d]`` (``h``: 1 from the split on) fitted by least squares: checked against that fit,
    with a planted step (explained almost whole) and on noise alone (explained little), also when
    a direction component never varies (a level yaw circle)."""
    rng = np.random.default_rng(8)
    n = 900
    if motion == "tumble":
        d = rng.normal(size=(n, 3))
    else:
        a = np.linspace(0.0, 6 * np.pi, n)
        d = np.column_stack([0.6 * np.cos(a), 0.6 * np.sin(a), np.full(n, 0.8)])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    splits = np.linspace(n * 0.05, n * 0.95, 37).astype(int)
    noise = rng.normal(0.0, 1e-9, n)
    stepped = noise + np.where(np.arange(n) >= splits[16], 40e-9 + 25e-9 * d[:, 0], 0.0)  # at a split tried
    for y, low, high in ((stepped, 0.99, 1.0), (noise, 0.0, 0.05)):
        direct = []
        for k in splits:
            h = (np.arange(n) >= k).astype(float)
            design = np.column_stack([np.ones(n), h, h[:, None] * d, d])
            coef, *_ = np.linalg.lstsq(design, y, rcond=None)
            direct.append(1.0 - np.sum((y - design @ coef) ** 2) / np.sum((y - y.mean()) ** 2))
        got = quality._step_explained(y, d, splits)
        assert got == pytest.approx(max(direct), abs=1e-9)
        assert low <= got <= high
