"""How far a manoeuvre being collected has got: the validity envelope so far, what it still
leaves undetermined, and what to fly next, in words (no ROS).

:func:`~magcal_ros.methods.pipeline.calibrate_array`'s analysis without its quality gates,
meant to run every few seconds while a vehicle turns (0.1-2 s of one core): the joint fit
(:func:`~magcal_ros.core.array_fit.fit_array`) from the prior calibration when there is
one, else from the ``ml`` method's closed-form start (or a crude one when the readings do
not determine it yet), on at most :data:`MAX_SETS` sets; then the time-correlated
covariance, the identifiability of each quantity, the envelope and the advice of
:mod:`magcal_ros.core.identifiability`. It decides "ready" by the calibration's own rule
(on up to :data:`MAX_SETS` sets, the same decision): without a prior nothing may be
undetermined (a current channel aside: the calibration leaves it out); with one, the prior
keeps what the data do not determine.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from magcal_ros.core import identifiability as ident
from magcal_ros.core.array_fit import fit_array, fix_rotation_gauge
from magcal_ros.core.calibration import ArrayCalibration
from magcal_ros.core.geometry import ArrayGeometry
from magcal_ros.core.observability import MIN_SAMPLES
from magcal_ros.core.uncertainty import centre_gauge_constraints
from magcal_ros.errors import MagcalError
from magcal_ros.methods.pipeline import (
    SolveOptions,
    _analyse,
    _crude_start,
    _inclination,
    _prior_of,
    _prior_start,
    _start,
    _undetermined_channels,
    check_raw,
)
from magcal_ros.methods.strategies import DEFAULT_METHOD, METHODS

Array = NDArray[np.float64]

MAX_SETS: int = 1000
"""Sets an assessment uses at most (evenly spaced in time): enough to see what a manoeuvre
determines, cheap enough to run every few seconds."""


@dataclass(frozen=True)
class Assessment:
    """What the sets collected so far determine, and what to do next."""

    samples: int
    """Sets assessed."""
    ready: bool
    """A calibration of these sets (with the same prior) would pass the identifiability check."""
    envelope: ident.Envelope | None
    """Where a calibration of these sets would be valid (None: too few sets to tell)."""
    undetermined: tuple[str, ...]
    """Quantities the data do not determine (without a prior: the reason it is not ready; with
    one: those the prior would keep), e.g. ``scale z``, each named once."""
    advice: str
    """What to do next, in words: ``pitch nose down 15 deg and keep turning``,
    ``enough for a calibration: ...``."""

    def envelope_text(self) -> str:
        """``valid within pitch +-P deg, roll +-R deg``, ``valid over the whole sphere``, or why there is none."""
        if self.envelope is None:
            return "no envelope yet (too few sets)"
        if self.envelope.pitch_deg <= 0 and self.envelope.roll_deg <= 0:
            return "not valid at any attitude yet"
        return self.envelope.describe()

    def describe(self) -> str:
        """One line: the envelope, then the advice."""
        return f"{self.envelope_text()}; {self.advice}"


def _names(quantities: list[ident.Quantity]) -> tuple[str, ...]:
    """Quantity names, each once, in the analysis' order."""
    return tuple(dict.fromkeys(q.name for q in quantities))


def _evenly(n: int, most: int) -> NDArray[np.int64]:
    return np.arange(n) if n <= most else np.unique(np.linspace(0, n - 1, most).round().astype(np.int64))


def assess(
    raw: ArrayLike,
    geometry: ArrayGeometry,
    reference_field: float | None = None,
    prior: ArrayCalibration | None = None,
    stamps: ArrayLike | None = None,
    currents: ArrayLike | None = None,
    channels: tuple[str, ...] = (),
    method: str = DEFAULT_METHOD,
    inclination_deg: float | None = None,
) -> Assessment:
    """Assess the raw sets (N, S, 3) T collected so far (see the module docstring).

    ``reference_field`` T (None or 0: relative); ``prior`` the calibration a recalibration
    would start from and keep what the data do not determine; ``stamps`` (N,) int ns put the
    sets in time order; ``currents`` (N, m) A of ``channels`` are fitted too (so that their
    field does not pass for noise); ``inclination_deg`` of the field, for the envelope (None:
    from the data). Raises :class:`~magcal_ros.errors.InputError` for malformed input only.
    """
    r = check_raw(raw, geometry)
    n = len(r)
    if n < MIN_SAMPLES:
        return Assessment(n, False, None, (), f"collect at least {MIN_SAMPLES} sets while turning (have {n})")
    order = np.argsort(np.asarray(stamps), kind="stable") if stamps is not None else np.arange(n)
    keep = order[_evenly(n, MAX_SETS)]
    r = r[keep]
    u = np.zeros((len(r), 0)) if currents is None else np.asarray(currents, dtype=float).reshape(n, -1)[keep]
    f_ref = float(reference_field) if reference_field else None
    opts = SolveOptions(inclination_deg=inclination_deg)
    if prior is not None:
        matrices, offsets, interference, intensity = _prior_start(prior, geometry, r, f_ref, channels)
    else:
        try:
            matrices, offsets, intensity = _start(METHODS[method], r, np.ones(len(r), bool), f_ref, opts)
        except (MagcalError, np.linalg.LinAlgError, ValueError):
            matrices, offsets, intensity = _crude_start(r, f_ref)
        interference = None
    param_prior = _prior_of(prior, geometry, intensity, channels, opts)
    sol = fit_array(r, matrices, offsets, intensity, u, interference, param_prior)
    if prior is None:
        sol = fix_rotation_gauge(sol)
    ana, cov = _analyse(sol, r, geometry, np.arange(len(r)), param_prior, channels, u)
    env = ident.envelope(sol.w, cov.matrix, sol.sigma, sol.intensity, _inclination(opts, sol.directions[:, 2]))
    # What the data alone determine (the prior aside), with the information the time correlation
    # leaves (as the covariance has it): the advice on what to fly.
    data_only = ident.advise(geometry.names, sol.w, sol.intensity, sol.information / cov.inflation, sol.directions,
                             sol.sigma, centre_gauge_constraints(sol.w))
    # Channels whose currents never vary or vary in lockstep: an exact degeneracy the covariance does not show.
    lockstep = tuple(f"interference {channels[j]}" for j in _undetermined_channels(ana, sol.directions, u, channels,
                                                                                     prior))
    if prior is None:
        undetermined = tuple(dict.fromkeys(_names(ana.undetermined()) + lockstep))
        # A channel whose interference is undetermined is left out by the calibration, not refused.
        blocking = [q for q in undetermined if not q.startswith("interference ")]
        advice = data_only.text
        if blocking and advice.startswith("enough"):  # at the threshold: the tilts compared all suffice
            advice = f"keep turning, with more pitch and roll ({', '.join(blocking)} not determined yet)"
        return Assessment(len(r), not blocking, env, undetermined, advice)
    kept = tuple(dict.fromkeys(_names(ana.kept()) + lockstep))
    if not kept:
        advice = "enough for a calibration: call ~/calibrate (it updates every quantity)"
    else:
        fly = data_only.text if not data_only.text.startswith("enough") else "turn through more attitudes"
        advice = (f"enough to recalibrate from the prior: call ~/calibrate (it keeps {', '.join(kept)} from the "
                  f"prior); to determine those too: {fly}")
    return Assessment(len(r), True, env, kept, advice)
