"""Recalibration during a mission: which sets to fit and which to hold out, whether a window of
the mission determines what changed, and whether the new calibration holds on sets it did not
fit (no ROS).

The calibration node (``auto_recalibrate``) keeps a rolling window of the mission's sets;
when the correction node's calibration health names a drift it fits the sets flown since,
with the running calibration as the prior, exactly as ``~/calibrate`` does
(:func:`~magcal_ros.methods.pipeline.calibrate_array`), and pushes the result only when

1. the window **determines what changed**: a hard-iron change moves the offsets, so every
   sensor's three offsets must be updated by the data (not kept at the prior) to within
   :data:`OFFSET_SIGMA` times the sensor's noise (straight running leaves the offsets across
   the track undetermined: such a window never pushes the whole fit). Where it leaves offsets
   undetermined but a current steps in it (a payload switched on, a thruster's demand changed on a
   straight leg), what it does determine is judged instead: the running calibration with the
   interference gains the steps give (:func:`interference_only`; matrices and offsets kept);
2. the new calibration **holds on held-out sets**: every :data:`HOLD_OUT_EVERY`-th of
   :data:`CHUNKS` stretches of the window in time is left out of the fit, and each sensor is judged
   on them by itself (:func:`judge`). A sensor's TMI residual (``|B| - F``) there, new against
   running, counts as changed only beyond what noise leaves on so few sets
   (:data:`HOLD_OUT_SIGMA` standard errors, ``sigma / sqrt(sets)``): every sensor the calibration
   health named as drifted must improve beyond it, the others must not get worse beyond it, and
   at least one sensor must improve. A sensor that did not improve keeps its running calibration
   (the fit moved it by noise only: pushing that would make every recalibration a random walk of
   the sensors that never moved); one the health did not name must also gain what matters, the
   running calibration leaving an error of :data:`UNNAMED_EXCESS` noise sd that the new removes.
   This holds where the two calibrations have the same form (no temperature terms, the same
   channels, time offsets and output frame); the calibration pushed is the new one
   for the sensors it improved and the running one for the rest. On it, each sensor's TMI residual
   and the sensors' disagreement beyond the gradient must be within :data:`HOLD_OUT_RATIO` of what
   it left on the sets fitted (plus the same noise allowance), and the disagreement within
   :data:`DISAGREEMENT_NOISE` times what the sensors' noise alone leaves there.

The time offsets pushed are the running calibration's (:func:`with_running_timing`): each node places a restarted
driver's samples by its own arrivals, so a lag fitted in one node is not the other's.

Units: T; stamps int64 ns.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from magcal_ros.core.calibration import ArrayCalibration
from magcal_ros.core.calibration_health import DRIFTED_SENSORS, MESSAGE_LIMIT, residual_projector, within
from magcal_ros.core.interference import interference_from_steps
from magcal_ros.core.metrics import rms
from magcal_ros.core.stamps import format_seconds
from magcal_ros.core.units import NT
from magcal_ros.methods.pipeline import CalibrationResult
from magcal_ros.methods.progress import Assessment

Array = NDArray[np.float64]

CHUNKS: int = 10
"""Stretches of the window in time; every :data:`HOLD_OUT_EVERY`-th is held out."""
HOLD_OUT_EVERY: int = 4
"""Chunks 3 and 7 of 10 (0-based): a fifth of the window, between stretches that are fitted."""
HOLD_OUT_RATIO: float = 1.5
"""What the new calibration may leave on the held-out sets, against what it left on its own."""
HOLD_OUT_SIGMA: float = 3.0
"""Standard errors of a held-out TMI RMS (``sigma / sqrt(sets)``) that noise alone may move it by: a sensor
improved (or got worse) only beyond them."""
DISAGREEMENT_NOISE: float = 3.0
"""What the sensors may disagree beyond the gradient on the held-out sets, in units of what their noise
alone leaves there: a calibration that fits every sensor's TMI but turns one sensor against the others
(a rotation the window does not determine) is refused even when it disagrees as much on its own sets."""
UNNAMED_EXCESS: float = 0.25
"""A sensor the calibration health did not name takes the new calibration only where the running one leaves an
error of at least this many noise sd on the held-out sets that the new one removes (:attr:`HeldOut.excess`):
beyond the standard errors, what matters. A refit of a sensor that never moved can line up with the held-out
noise and remove about a tenth of it (0.12 noise sd seen over DDS), which the paired test alone took for an
improvement about one run in fifteen of a recalibration test."""
OFFSET_SIGMA: float = 3.0
"""An offset counts as determined when its 1-sigma is below this many noise sd of its sensor."""
OFFSET_NAMES: tuple[str, ...] = ("offset x", "offset y", "offset z")
"""The offsets (not their temperature coefficients, which a window that barely changes temperature leaves at
the running calibration's)."""


def split(stamps: Sequence[int] | NDArray[np.int64]) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
    """(fit, held out) masks of sets by time: the window cut into :data:`CHUNKS` equal stretches,
    every :data:`HOLD_OUT_EVERY`-th (from the fourth) held out."""
    t = np.asarray(stamps, dtype=np.int64)
    if len(t) == 0:
        return np.zeros(0, bool), np.zeros(0, bool)
    span = max(int(t.max() - t.min()), 1)
    chunk = np.minimum((t - t.min()) * CHUNKS // span, CHUNKS - 1)
    held = chunk % HOLD_OUT_EVERY == HOLD_OUT_EVERY - 1
    return ~held, held


def undetermined_offsets(result: CalibrationResult) -> list[str]:
    """``<sensor> offset <axis> (+- S nT)`` for every offset the window did not determine (see the module
    docstring); empty when it determines them all."""
    out = []
    for i, name in enumerate(result.calibration.geometry.names):
        noise = float(result.noise[i]) / NT
        for q in result.identifiability.quantities:
            if q.sensor == name and q.name in OFFSET_NAMES:
                if q.status == "kept" or q.sigma > OFFSET_SIGMA * max(noise, 1e-3):
                    out.append(f"{name} {q.name} (+- {q.sigma:.3g} nT)")
    return out


@dataclass(frozen=True)
class HeldOut:
    """What the new and the running calibration leave on the held-out sets (T)."""

    sets: int
    tmi_new: Array
    """(S,) RMS of ``|B| - F`` per sensor, new calibration."""
    tmi_old: Array
    """(S,) the same for the running calibration."""
    tmi_fit: Array
    """(S,) what the new calibration leaves on the sets it was fitted to."""
    disagreement_new: float
    """RMS over sets and components of the residual beyond field and gradient (NaN: none)."""
    disagreement_fit: float
    disagreement_noise: float
    """What white noise of the sensors' noise leaves beyond field and gradient (RMS, NaN: no such check)."""
    noise: Array
    """(S,) noise per axis the fit found."""
    names: tuple[str, ...]
    paired: Array | None = None
    """(S,) T: the standard error of ``tmi_old - tmi_new`` from the two calibrations' residuals on the same sets
    (:func:`paired_error`); None: not known (:attr:`slack` stands in)."""

    @property
    def slack(self) -> Array:
        """(S,) T: what noise alone may move each sensor's held-out TMI RMS by (:data:`HOLD_OUT_SIGMA`)."""
        return HOLD_OUT_SIGMA * self.noise / np.sqrt(max(self.sets, 1))

    def improved(self, named: Sequence[str] | None = None) -> NDArray[np.bool_]:
        """(S,) the sensors the new calibration fits better than the running one, beyond noise: by more than
        :data:`HOLD_OUT_SIGMA` standard errors of each RMS alone (:attr:`slack`), or of their difference on the
        same sets (the noise both see cancels: a refinement's few tenths of nT show; a large change varies too
        much from stretch to stretch for that, and shows alone). With ``named`` (the sensors the calibration
        health named), the others must also gain what matters (:data:`UNNAMED_EXCESS`)."""
        slack = self.slack if self.paired is None else np.minimum(self.slack, HOLD_OUT_SIGMA * self.paired)
        better = np.asarray(self.tmi_old - self.tmi_new > slack)
        if named is None:
            return better
        unnamed = np.array([n not in named for n in self.names])
        return better & ~(unnamed & (self.excess < UNNAMED_EXCESS * self.noise))

    @property
    def excess(self) -> Array:
        """(S,) T: the RMS of the error the running calibration leaves on the held-out sets that the new one
        removes, ``sqrt(tmi_old^2 - tmi_new^2)`` (0 where the new leaves more)."""
        return np.sqrt(np.maximum(self.tmi_old**2 - self.tmi_new**2, 0.0))

    def _versus(self, i: int) -> str:
        return f"TMI residual {self.tmi_new[i] / NT:.3g} nT against {self.tmi_old[i] / NT:.3g} nT running"

    def change_problem(self, drifted: Sequence[str], refine: bool = False) -> str | None:
        """Why the new calibration does not fix what drifted without spoiling the rest, or None: each
        sensor in ``drifted`` (named by the calibration health) must improve beyond noise, no other get
        worse beyond it, and at least one improve (not for a ``refine``-ment: see :data:`REFINE_WINDOWS`)."""
        if self.sets < 3:
            return f"only {self.sets} held-out sets to check it on"
        better = self.improved(drifted)
        for i, name in enumerate(self.names):
            if name in drifted and not better[i]:
                return f"on {self.sets} held-out sets drifted {name} is not better ({self._versus(i)})"
        for i, name in enumerate(self.names):
            if self.tmi_new[i] - self.tmi_old[i] > self.slack[i]:
                return f"on {self.sets} held-out sets the new calibration is worse for {name} ({self._versus(i)})"
        if not better.any() and not refine:
            i = int(np.argmax(self.tmi_old - self.tmi_new))
            return f"on {self.sets} held-out sets the new calibration is no better for any sensor ({self.names[i]}: " \
                   f"{self._versus(i)})"
        return None

    def problem(self) -> str | None:
        """Why the calibration judged does not hold on the held-out sets, or None."""
        if self.sets < 3:
            return f"only {self.sets} held-out sets to check it on"
        slack = self.slack
        bad = [i for i in range(len(self.names)) if self.tmi_new[i] > HOLD_OUT_RATIO * self.tmi_fit[i] + slack[i]]
        if bad:
            i = bad[0]
            return (f"on {self.sets} held-out sets {self.names[i]}'s TMI residual is {self.tmi_new[i] / NT:.3g} nT, "
                    f"more than {HOLD_OUT_RATIO:g}x the {self.tmi_fit[i] / NT:.3g} nT on the sets fitted")
        if np.isfinite(self.disagreement_new) and self.disagreement_new > (
                HOLD_OUT_RATIO * self.disagreement_fit + float(np.max(slack))):
            return (f"on {self.sets} held-out sets the sensors disagree by {self.disagreement_new / NT:.3g} nT beyond "
                    f"the gradient, more than {HOLD_OUT_RATIO:g}x the {self.disagreement_fit / NT:.3g} nT on the sets "
                    f"fitted")
        if np.isfinite(self.disagreement_new) and self.disagreement_new > (
                DISAGREEMENT_NOISE * self.disagreement_noise + float(np.max(slack))):
            return (f"on {self.sets} held-out sets the sensors disagree by {self.disagreement_new / NT:.3g} nT beyond "
                    f"the gradient, more than {DISAGREEMENT_NOISE:g}x the {self.disagreement_noise / NT:.3g} nT their "
                    "noise leaves (a sensor turned against the others)")
        return None

    def describe(self) -> str:
        """``held-out sets (400): TMI RMS 312 -> 1.02 nT`` (worst sensor, running -> new)."""
        i = int(np.argmax(self.tmi_old))
        return (f"{self.sets} held-out sets: TMI RMS {self.tmi_old[i] / NT:.3g} -> {self.tmi_new[i] / NT:.3g} nT "
                f"({self.names[i]}, running -> new)")


def _disagreement(vectors: Array, projector: Array | None) -> float:
    if projector is None or len(vectors) == 0:
        return float("nan")
    return float(rms(vectors.reshape(len(vectors), -1) @ projector.T))


def held_out(result: CalibrationResult, running: ArrayCalibration, raw_fit: Array, raw_held: Array,
             currents_fit: Array | None = None, currents_held: Array | None = None,
             temperatures: tuple[Array, Array] | None = None) -> HeldOut:
    """Judge ``result`` (fitted to ``raw_fit``) against ``running`` on ``raw_held`` (N, S, 3) T; ``temperatures``:
    each sensor's (fit, held out; (N, S) deg C), for calibrations with temperature terms."""
    new = result.calibration
    f = result.intensity
    projector = residual_projector(new.geometry)
    use = bool(new.channels)
    t_fit, t_held = temperatures if temperatures is not None else (None, None)

    def warm(cal: ArrayCalibration, t: Array | None) -> Array | None:
        return t if cal.has_temperature_terms else None

    b_new = new.apply(raw_held, currents_held if use else None, warm(new, t_held))
    b_fit = new.apply(raw_fit, currents_fit if use else None, warm(new, t_fit))
    b_old = running.apply(raw_held, currents_held if running.channels else None, warm(running, t_held))
    r_new, r_old = np.linalg.norm(b_new, axis=2) - f, np.linalg.norm(b_old, axis=2) - f
    noise = np.asarray(result.noise, dtype=float)
    return HeldOut(len(raw_held), rms(r_new, axis=0), rms(r_old, axis=0),
                   rms(np.linalg.norm(b_fit, axis=2) - f, axis=0), _disagreement(b_new, projector),
                   _disagreement(b_fit, projector), _noise_disagreement(noise, projector), noise, new.geometry.names,
                   paired_error(r_old, r_new))


PAIRED_BLOCKS: int = 20
"""Stretches in time of the held-out sets whose means give the paired standard error (:func:`paired_error`)."""


def paired_error(r_old: Array, r_new: Array) -> Array | None:
    """(S,) T: the standard error of ``rms(r_old) - rms(r_new)`` for two calibrations' TMI residuals (N, S) T on
    the same sets in time order, from the spread of their squares' difference over :data:`PAIRED_BLOCKS`
    stretches (what the residuals share in time stays within a stretch); None with fewer sets than stretches."""
    if len(r_old) < 2 * PAIRED_BLOCKS:
        return None
    d = r_old**2 - r_new**2
    means = np.array([part.mean(axis=0) for part in np.array_split(d, PAIRED_BLOCKS)])
    se = means.std(axis=0, ddof=1) / np.sqrt(PAIRED_BLOCKS)
    return se / np.maximum(rms(r_old, axis=0) + rms(r_new, axis=0), 1e-30)


def _noise_disagreement(noise: Array, projector: Array | None) -> float:
    """RMS over sets and components of ``P n`` for white noise ``n`` of ``noise`` (S,) T per axis."""
    if projector is None:
        return float("nan")
    variance = np.repeat(noise**2, 3)  # per stacked component
    return float(np.sqrt(np.sum((projector**2) @ variance) / len(variance)))


def same_form(new: ArrayCalibration, running: ArrayCalibration) -> bool:
    """Whether a sensor of ``running`` can stand in for the same sensor of ``new``: the same sensors,
    channels, time offsets and output frame, and neither with temperature terms."""
    names = new.geometry.names
    if set(names) != set(running.geometry.names) or new.channels != running.channels:
        return False
    if new.has_temperature_terms or running.has_temperature_terms:
        return False
    order = [running.geometry.names.index(n) for n in names]
    return bool(np.array_equal(new.output_rotation, running.output_rotation)
                and np.array_equal(new.time_offsets, np.asarray(running.time_offsets)[order]))


def with_running_timing(result: CalibrationResult, running: ArrayCalibration) -> CalibrationResult:
    """``result`` with the running calibration's time offsets (s, per sensor): a recalibration during the mission
    pushes what a drift changes (iron, interference, temperature terms), not the drivers' timing. Where a
    restarted driver's new segment sits is placed by each node from its own arrivals, so a lag the
    calibration node fits across a restart is its own placement's, not the correction node's (a soak pushed
    0.21 ms for a restarted sensor the correction node had placed right: the tensor 1.4x the floor after).
    ``result`` itself where the sensors differ or the offsets agree."""
    cal = result.calibration
    names = cal.geometry.names
    if set(names) != set(running.geometry.names):
        return result
    offsets = np.asarray(running.time_offsets, dtype=float)[[running.geometry.names.index(n) for n in names]]
    if np.array_equal(offsets, cal.time_offsets):
        return result
    return replace(result, calibration=replace(cal, time_offsets=offsets))


def timing_note(fitted: ArrayCalibration, pushed: ArrayCalibration) -> str:
    """`` (time offsets kept as running; the window's: mag3 0.21 ms)`` where the fit's time offsets were not
    pushed (:func:`with_running_timing`), else empty."""
    if fitted.geometry.names != pushed.geometry.names or np.array_equal(fitted.time_offsets, pushed.time_offsets):
        return ""
    moved = [f"{n} {t * 1e3:.2f} ms" for n, t, u in zip(fitted.geometry.names, fitted.time_offsets, pushed.time_offsets)
             if t != u]
    return f" (time offsets kept as running; the window's: {', '.join(moved)})"


def keep_running(new: ArrayCalibration, running: ArrayCalibration, kept: Sequence[str]) -> ArrayCalibration:
    """``new`` with the sensors ``kept`` corrected as ``running`` corrects them (matrix, offset, interference;
    the covariance of the corrected vector too where ``running`` knows it, else the fit's for that sensor, so
    that the calibration gives one for every sensor or none); ``new`` itself when nothing is kept or the two
    differ in form (:func:`same_form`)."""
    if not kept or not same_form(new, running):
        return new
    matrices, offsets = new.matrices.copy(), new.offsets.copy()
    interference = np.array(new.interference, dtype=float)
    covariances = None if new.covariances is None else np.array(new.covariances, dtype=float)
    for name in kept:
        i, j = new.geometry.names.index(name), running.geometry.names.index(name)
        matrices[i], offsets[i] = running.matrices[j], running.offsets[j]
        interference[i] = np.asarray(running.interference)[j]
        known = running.covariances is not None and bool(np.all(np.isfinite(running.covariances[j])))
        if covariances is not None and known:
            covariances[i] = running.covariances[j]  # type: ignore[index]
    return replace(new, matrices=matrices, offsets=offsets, interference=interference, covariances=covariances)


@dataclass(frozen=True)
class Verdict:
    """What :func:`judge` decided: why nothing may be pushed (or None), the held-out figures of what would
    be pushed, and what that is."""

    problem: str | None
    figures: HeldOut | None
    result: CalibrationResult | None
    """The new result with the sensors it did not improve back at the running calibration (None: refused)."""
    kept: tuple[str, ...] = ()
    """The sensors that keep their running calibration."""
    scope: str = ""
    """What was pushed where it is not the whole new calibration, in words (empty: the whole of it)."""


def interference_only(running: ArrayCalibration, raw: Array, currents: Array, channels: Sequence[str],
                      seconds: Array) -> tuple[ArrayCalibration, tuple[str, ...]] | None:
    """``running`` with the interference gains the currents' steps determine in the sets ``raw`` (N, S, 3) T at
    ``seconds`` (N,) s (:func:`~magcal_ros.core.interference.interference_from_steps`; ``currents`` (N, m) A of
    ``channels``), matrices and offsets kept; and the channels learnt. A channel the steps do not determine keeps
    the running gains (none where it has none). None where no channel is determined, or where the running
    calibration has temperature terms (the window keeps no temperatures)."""
    if not channels or running.has_temperature_terms or len(raw) < 3:
        return None
    est = interference_from_steps(raw, currents, running, seconds)
    learnt = tuple(c for c, bad in zip(channels, est.undetermined) if not bad)
    if not learnt:
        return None
    gains = est.gains.copy()
    old = np.asarray(running.interference) if running.channels else np.zeros((running.geometry.size, 3, 0))
    for j, c in enumerate(channels):
        if est.undetermined[j]:
            gains[:, :, j] = old[:, :, running.channels.index(c)] if c in running.channels else 0.0
    return replace(running, channels=tuple(channels), interference=gains), learnt


def judge(result: CalibrationResult, running: ArrayCalibration | None, raw_fit: Array, raw_held: Array,
          currents_fit: Array | None = None, currents_held: Array | None = None,
          drifted: Sequence[str] = (), seconds_fit: Array | None = None,
          temperatures: tuple[Array, Array] | None = None, refine: bool = False) -> Verdict:
    """Whether ``result`` (fitted to ``raw_fit`` from ``running``) may replace ``running``, judged per sensor
    on ``raw_held`` (N, S, 3) T; ``drifted``: the sensors the calibration health named (see the module
    docstring). Where the window leaves offsets undetermined but the currents step in it (``seconds_fit`` (N,)
    s of the sets fitted given), the running calibration with the interference gains the steps determine
    (:func:`interference_only`) is judged instead: what the window determines is pushed, the rest kept.
    ``temperatures``: each sensor's (fit, held out; (N, S) deg C) where a calibration has temperature terms.
    ``refine``: a push's refinement (:data:`REFINE_WINDOWS`), fitted as the push was to every set since its drift
    and so better in expectation, for every sensor: it need not show it on a fifth of the sets (none may be worse,
    and it must hold on them) and no sensor keeps the push's calibration."""
    if running is None:
        return Verdict("there is no running calibration to start from (the prior): recalibrate with ~/calibrate",
                       None, None)
    result = with_running_timing(result, running)
    missing = undetermined_offsets(result)
    if missing:
        shown = ", ".join(missing[:4]) + (f" and {len(missing) - 4} more" if len(missing) > 4 else "")
        why = (f"the sets do not determine what changed ({shown}): turn through a full circle of heading, "
               "with some pitch and roll")
        return _judge_interference(result, running, (raw_fit, raw_held, currents_fit, currents_held), drifted,
                                   seconds_fit, why, refine)
    check = held_out(result, running, raw_fit, raw_held, currents_fit, currents_held, temperatures)
    why = check.change_problem(drifted, refine)
    if why:
        return Verdict(why, check, None)
    better = check.improved(drifted) | refine
    kept = tuple(n for n, b in zip(check.names, better) if not b)
    merged = keep_running(result.calibration, running, kept)
    if merged is not result.calibration:
        result = replace(result, calibration=merged)
        check = held_out(result, running, raw_fit, raw_held, currents_fit, currents_held, temperatures)
    else:
        kept = ()
    why = check.problem()
    return Verdict(why, check, None if why else result, kept)


def _judge_interference(result: CalibrationResult, running: ArrayCalibration,
                        sets: tuple[Array, Array, Array | None, Array | None], drifted: Sequence[str],
                        seconds_fit: Array | None, undetermined: str, refine: bool = False) -> Verdict:
    """The verdict on the running calibration with the interference the currents' steps determine (see
    :func:`judge`); refused with ``undetermined`` (why the whole fit may not be pushed) where there is none."""
    raw_fit, raw_held, currents_fit, currents_held = sets
    channels = result.calibration.channels or running.channels
    candidate = None
    if seconds_fit is not None and currents_fit is not None and currents_held is not None and channels and \
            np.shape(currents_fit)[1:] == (len(channels),):
        candidate = interference_only(running, raw_fit, currents_fit, channels, np.asarray(seconds_fit, float))
    if candidate is None:
        return Verdict(undetermined, None, None)
    calibration, learnt = candidate
    only = replace(result, calibration=calibration)
    check = held_out(only, running, raw_fit, raw_held, currents_fit, currents_held)
    why = check.change_problem(drifted, refine) or check.problem()
    if why:
        return Verdict(f"{undetermined}; with only the interference of {', '.join(learnt)} from the currents' "
                       f"steps: {why}", check, None)
    return Verdict(None, check, only, (), f"interference of {', '.join(learnt)} learnt from the currents' steps, "
                   "matrices and offsets kept as running (the window does not determine them)")


def changes(old: ArrayCalibration, new: ArrayCalibration) -> str:
    """What a recalibration changed, in words: how far each sensor's corrected field moved at zero
    raw reading (the offset change seen through the matrix), nT: ``offsets moved: mag1 612 nT, ...``; the
    largest change of a matrix, ppm; and, when it changed, the angle (deg) between the two output frames (the
    output rotation fitted again from the IMU)."""
    moved = []
    for i, name in enumerate(new.geometry.names):
        j = old.geometry.names.index(name)
        shift = new.matrices[i] @ new.offsets[i] - old.matrices[j] @ old.offsets[j]
        moved.append(f"{name} {np.linalg.norm(shift) / NT:.0f} nT")
    gains = max(float(np.max(np.abs(new.matrices[i] @ np.linalg.inv(old.matrices[old.geometry.names.index(n)])
                                    - np.eye(3)))) for i, n in enumerate(new.geometry.names))
    text = f"offsets moved: {', '.join(moved)}; matrices changed by at most {gains * 1e6:.0f} ppm"
    turn = np.asarray(new.output_rotation) @ np.asarray(old.output_rotation).T
    if not np.array_equal(new.output_rotation, old.output_rotation):
        angle = np.degrees(np.arccos(np.clip((np.trace(turn) - 1.0) / 2.0, -1.0, 1.0)))
        text += f"; output frame turned by {angle:.3f} deg"
    return text


REFINE_WINDOWS: int = 4
"""After a push, the sets flown since the drift was named are fitted once more, as the push was, when they span
this many windows: one window determines what changed only to within its noise (a payload's interference
gains from one minute of its varying current: a few tenths of nT/A, 1.2x the IMU-frame field's floor), this
many to half that. Better in expectation for every sensor, the refinement need not show it on its held-out
fifth (a few hundredths of nT of TMI, which the noise there hides one time in two): it is pushed whole unless
a sensor fits the held-out sets worse or it does not hold on them. It comes a window after the push at the
earliest (a push after several attempts is refined on new sets)."""


@dataclass
class DriftWatch:
    """When the calibration node recalibrates (or advises), in mission time: the stamps (ns) of the sets.

    A drift named by the calibration health starts the clock; the sets flown from then on make the
    window (``window_ns`` of them are needed); an attempt that does not push is retried when half a
    window of new sets came; a push is followed by no other within ``interval_ns``, and drift reports
    are ignored until the health, judging the new calibration afresh, no longer says drifted. A push is
    refined once (:data:`REFINE_WINDOWS`), whatever the interval, unless a drift is named anew before.
    """

    window_ns: int
    interval_ns: int
    since: int | None = None
    """Mission time the drift was first named (None: no drift named)."""
    health: str = ""
    """The latest health message that named it."""
    sensors: tuple[str, ...] = ()
    """Every sensor the health named as drifted since the drift was named (a recalibration must improve them)."""
    last_push: int | None = None
    last_attempt: int | None = None
    settling: bool = False
    """After a push: drift reports are stale until the health says the new calibration is not drifted."""
    refine_from: int | None = None
    """Mission time the drift behind the last push was named, while its refinement is to come (else None)."""

    @property
    def refining(self) -> bool:
        """No drift named, and a push's refinement to come (:data:`REFINE_WINDOWS`)."""
        return self.since is None and self.refine_from is not None

    def report(self, drifted: bool, message: str, now: int, sensors: Sequence[str] = ()) -> bool:
        """A health report at mission time ``now`` (``sensors``: those it names as drifted); True when it
        names a drift anew."""
        if not drifted:
            self.since, self.settling, self.health, self.sensors = None, False, "", ()
            return False
        if self.settling:
            return False
        self.health = message
        anew = self.since is None
        if anew:
            self.since, self.last_attempt, self.sensors, self.refine_from = now, None, (), None
        self.sensors += tuple(n for n in sensors if n not in self.sensors)
        return anew

    def due(self, now: int) -> tuple[bool, str]:
        """(attempt now, else what it waits for) at mission time ``now``."""
        if self.since is None:
            return self.refining and now - self.refine_from >= REFINE_WINDOWS * self.window_ns and \
                now - (self.last_push or now) >= self.window_ns, ""  # type: ignore[operator]
        have = (now - self.since) / 1e9
        need = self.window_ns / 1e9
        if self.last_push is not None and now - self.last_push < self.interval_ns:
            wait = (self.last_push + self.interval_ns - now) / 1e9
            return False, (f"recalibrated {(now - self.last_push) / 1e9:.0f} s ago, next in {wait:.0f} s "
                           "(recalibrate_interval): call ~/calibrate to fix it now")
        if now - self.since < self.window_ns:
            return False, f"collecting sets since the drift was named: {have:.0f} of {need:.0f} s"
        if self.last_attempt is not None and now - self.last_attempt < self.window_ns // 2:
            return False, f"trying again in {(self.last_attempt + self.window_ns // 2 - now) / 1e9:.0f} s"
        return True, ""

    def window_start(self, now: int) -> int:
        """The first stamp (ns) of the window to fit at ``now``: the drift's naming, or a window back; a
        refinement's: the naming of the drift behind the push, or :data:`REFINE_WINDOWS` windows back."""
        if self.refining:
            return max(self.refine_from, now - REFINE_WINDOWS * self.window_ns)  # type: ignore[type-var]
        return max(self.since or now, now - self.window_ns)

    def attempted(self, now: int, pushed: bool) -> None:
        """An attempt at mission time ``now`` ended; ``pushed``: a new calibration is in force. A push after a
        drift is to be refined; a refinement is tried once."""
        self.last_attempt = now
        self.refine_from = self.since if pushed and self.since is not None else None
        if pushed:
            self.last_push = now
            self.since, self.settling, self.sensors = None, True, ()


def advice(assessed: Assessment, with_prior: bool, window_s: float) -> str:
    """What to fly so that ``~/calibrate`` (from the running calibration) fixes a drift, from the
    progress analysis of the sets flown since it was named, in words."""
    if not with_prior:
        return ("there is no running calibration to start from: call ~/start, turn through large angles about at "
                "least two axes, then call ~/calibrate")
    offsets = [q for q in assessed.undetermined if q.startswith("offset ")]
    if assessed.ready and not offsets:
        return (f"what is being flown determines what changed (the offsets): call ~/start, keep flying it for "
                f"{window_s:.0f} s, then call ~/calibrate")
    return (f"the sets flown since do not determine {', '.join(offsets) or 'what changed'}: call ~/start, turn "
            f"through a full circle of heading with some pitch and roll, then call ~/calibrate")


def status(target: str, auto: bool, watch: DriftWatch, now: int, health: str, advice: str,
           record: dict[str, str]) -> tuple[bool, str, dict[str, str]]:
    """The calibration node's ``<node>: recalibration`` status: (WARN, message of at most
    :data:`~magcal_ros.core.calibration_health.MESSAGE_LIMIT` characters ending with what is done or to do,
    values).

    ``health``: the correction node's latest calibration health message; ``advice``: what to fly
    (auto_recalibrate off); ``record``: ``recalibrations``, ``attempts``, ``last_recalibration``,
    ``last_attempt``."""
    _, waiting = watch.due(now)
    since = watch.since
    values = {"auto_recalibrate": str(auto).lower(), "drifted": str(since is not None).lower(),
              DRIFTED_SENSORS: ",".join(watch.sensors),
              "health": watch.health or health, "advice": advice if since is not None else "",
              "since_drift_s": f"{(now - since) / 1e9:.0f}" if since is not None else "",
              "newest_stamp": format_seconds(now) if now else "", **record}
    if since is None:
        judged = health and not health.startswith(("collecting", "not assessed"))
        if not judged:
            return False, within([f"calibration health of {target}: {health or 'none yet'}"]), values
        head = f"calibration of {target} fits"
        last, count = record.get("last_recalibration"), record.get("recalibrations", "0")
        return False, within([f"{head}; last: {last}", f"{head}; recalibrated during the mission: {count}", head]
                             if last else [head]), values
    head = f"calibration of {target} drifted" + (f" ({', '.join(watch.sensors)})" if watch.sensors else "")
    if auto:  # why the last attempt did not push: in the values (last_attempt)
        return True, within([head], "; auto_recalibrate: " + (waiting or "recalibrating")), values
    if not advice:
        return True, within([head], "; analysing the sets flown since the drift was named"), values
    full = f"{head}; to fix it: {advice}"
    return True, full if len(full) <= MESSAGE_LIMIT else within(
        [head], "; to fix it: fly what advice says, call ~/start, then ~/calibrate"), values
