"""The IMU in the calibration pipeline: its blocks' inputs, their analysis in words, the output frame.

The blocks themselves are part of the one forward model (:mod:`magcal_ros.core.attitude_blocks`,
fitted by :func:`~magcal_ros.core.array_fit.fit_array`); this module prepares their inputs from
the IMU at each set, reports what they found (the mounting as roll, pitch and yaw with their
1-sigma, the field direction, the site gradient) and turns a calibration made with an IMU into
the IMU's frame: ``output_rotation`` is the fitted array-to-IMU rotation, ``frame_id`` the IMU's.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from magcal_ros.core import attitude_blocks as ab
from magcal_ros.core.array_fit import JointSolution
from magcal_ros.core.batched import sensor_means
from magcal_ros.core.calibration import ArrayCalibration
from magcal_ros.core.geometry import ArrayGeometry
from magcal_ros.core.imu import NED_TO_ENU
from magcal_ros.core.recording import ImuSamples
from magcal_ros.core.uncertainty import centre_gauge_constraints, covariance
from magcal_ros.errors import InputError

Array = NDArray[np.float64]


def attitude_for(imu: ImuSamples | None, stamps: Any, geometry: ArrayGeometry, count: int,
                 site_field_ned: Array | None = None) -> ab.AttitudeInputs | None:
    """The global blocks' inputs from the IMU at each of ``count`` sets (None without a usable IMU).

    Orientations switch on the mounting, the world field direction (held at the site's model
    ``site_field_ned`` (3,) T, NED, when given) and the site gradient (two or more sensors);
    a gyro alone the mounting and one field direction per continuous segment (``stamps`` (N,)
    int ns needed).
    """
    if imu is None:
        return None
    if len(imu) != count:
        raise InputError(f"the IMU has {len(imu)} sets, the readings {count}")
    if not imu.has_orientation and stamps is None:
        if imu.has_angular_velocity:
            raise InputError("the gyro needs the sets' stamps (to integrate the angular velocity between sets)")
        return None
    st = np.arange(count, dtype=np.int64) if stamps is None else np.asarray(stamps).astype(np.int64)
    field = None if site_field_ned is None else NED_TO_ENU @ np.asarray(site_field_ned, dtype=float)
    return ab.attitude_inputs(imu.orientation, imu.angular_velocity, st, geometry.positions, geometry.size > 1,
                              field if imu.has_orientation else None, imu.frame_id)


MAX_ATTITUDE_ERROR_DEG: float = 10.0
"""Largest attitude error (deg, 1-sigma per axis, as the fit sees it) of an IMU that follows the array: an
AHRS is good to a degree or two; tens of degrees is an IMU that does not describe these readings."""
OUTLYING_WEIGHT: float = 0.25
"""A set whose attitude residual the fit weights below this (beyond about 8 sigma: an IMU glitch) is
counted as left out."""
IMU_STILL_FRACTION: float = 0.1
"""An IMU whose orientation turns by less than this fraction of the readings' turn does not follow the array."""
MIN_READINGS_TURN_DEG: float = 10.0
"""Readings that turn less than this (deg) say nothing about whether the IMU follows them."""
LAG_SIGMAS: float = 3.0
"""The array's lag behind the IMU is applied when it is beyond this many of its 1-sigma ..."""
MAX_LAG_SIGMA: float = 2e-3
"""... and its 1-sigma (s) is at most this: a manoeuvre that turns too slowly leaves it undetermined (held at
zero and said so)."""


def check_follows(imu: ImuSamples | None, raw: Array) -> None:
    """:class:`InputError` when the IMU's orientation stays (nearly) still while the readings ``raw``
    (N, S, 3) T turn: a frozen orientation or another vehicle's topic, which no calibration can use."""
    if imu is None or not imu.has_orientation:
        return
    q = imu.orientation[np.all(np.isfinite(imu.orientation), axis=1)]
    imu_turn = float(np.degrees(2.0 * np.arccos(np.clip(np.abs(q @ q[0]), 0.0, 1.0))).max())
    centre = sensor_means(raw)
    d = centre / np.maximum(np.linalg.norm(centre, axis=1, keepdims=True), 1e-300)
    readings_turn = float(np.degrees(np.arccos(np.clip(d @ d[0], -1.0, 1.0))).max())
    if readings_turn >= MIN_READINGS_TURN_DEG and imu_turn < IMU_STILL_FRACTION * readings_turn:
        raise InputError(f"the IMU's orientation turns by {imu_turn:.1f} deg at most while the readings turn by "
                         f"{readings_turn:.0f} deg: the IMU does not follow the array (a frozen orientation, or "
                         "another vehicle's topic?)")


@dataclass(frozen=True)
class ImuReport:
    """What the global blocks found: the quantities with their 1-sigma, and how the IMU was used."""

    quantities: list[ab.GlobalQuantity]
    covariance: Array
    """(G, G) covariance of the global parameters (model layout; rad, unit tangent, 1/m in units of F)."""
    source: str
    """``orientation`` or ``gyro``."""
    sets: int
    """Sets with an attitude."""
    segments: int
    """Gyro segments (1 for orientations)."""
    attitude_sigma_deg: float
    """The IMU's attitude error as the fit saw it (deg, 1-sigma per axis)."""
    frame_id: str
    excluded: int = 0
    """Sets whose attitude lay far off the field's (beyond :data:`OUTLYING_SIGMAS` of the attitude error):
    an IMU glitch, left out of the fit."""

    def by_name(self, name: str) -> ab.GlobalQuantity:
        """The quantity called ``name`` (e.g. ``array to IMU roll``)."""
        return next(q for q in self.quantities if q.name == name)

    def notes(self) -> list[str]:
        """Summary lines: ``array to IMU: roll 2.00 +- 0.01 deg, ...``, the field, the gradient."""
        out = []
        mount = [q for q in self.quantities if q.block == "mounting"]
        if mount:
            where = f"outputs in the IMU frame {self.frame_id}" if self.frame_id else "outputs in the IMU frame"
            out.append("array to IMU: " + ", ".join(f"{q.name.split()[-1]} {q.value:.2f} +- "
                                                  f"{float(f'{q.sigma:.2g}'):g} deg" for q in mount)
                       + f" ({where}; IMU {self.source} at {self.sets} sets"
                       + (f" in {self.segments} segments" if self.source == "gyro" else "")
                       + f", attitude error {self.attitude_sigma_deg:.3g} deg"
                       + (f"; {self.excluded} {'attitude' if self.excluded == 1 else 'attitudes'} far off the field "
                          "left out" if self.excluded else "") + ")")
        field = [q for q in self.quantities if q.block == "field direction"]
        if field:
            out.append("field in the IMU's world frame: " + ", ".join(
                f"{q.name.split()[-1]} {q.value:.2f} +- {float(f'{q.sigma:.2g}'):g} deg" for q in field))
        grad = [q for q in self.quantities if q.block == "site gradient"]
        if grad:
            out.append("site gradient (world ENU, modelled, not calibration error): " + ", ".join(
                f"{q.name.split()[-1]} {q.value:.1f} +- {float(f'{q.sigma:.2g}'):g} nT/m" for q in grad))
        out += self._lag_notes()
        return out

    def _lag_notes(self) -> list[str]:
        lag = [q for q in self.quantities if q.block == "array lag"]
        if not lag:
            return []
        q = lag[0]
        figure = f"{q.value:.3f} +- {float(f'{q.sigma:.2g}'):g} ms"
        if self.array_lag:
            return [f"{ab.ARRAY_LAG}: {figure} (its stamps late on the IMU's clock; added to every sensor's time "
                    "offset, so the outputs are stamped at the IMU's instants)"]
        if q.sigma * 1e-3 > MAX_LAG_SIGMA:
            return [f"{ab.ARRAY_LAG}: undetermined ({figure}: the manoeuvre turns too slowly to tell); none applied"]
        return [f"{ab.ARRAY_LAG}: {figure}, not significant; none applied"]

    @property
    def array_lag(self) -> float:
        """s the array's stamps are late on the IMU's clock, as applied: the fitted lag where determined and
        significant (:data:`MAX_LAG_SIGMA`, :data:`LAG_SIGMAS`), else 0."""
        lag = [q for q in self.quantities if q.block == "array lag"]
        if not lag:
            return 0.0
        value, sigma = lag[0].value * 1e-3, lag[0].sigma * 1e-3
        return value if sigma <= MAX_LAG_SIGMA and abs(value) > LAG_SIGMAS * sigma else 0.0

    def provenance(self) -> dict[str, Any]:
        """Calibration-file provenance keys (``imu``: the blocks' values and 1-sigma)."""
        values = {quantity_key(q.name): q.value for q in self.quantities}
        sigmas = {quantity_key(q.name): q.sigma for q in self.quantities}
        return {"imu": {"source": self.source, "sets": self.sets, "segments": self.segments,
                        "attitude_sigma_deg": self.attitude_sigma_deg, "frame_id": self.frame_id,
                        "attitudes_excluded": self.excluded,
                        "values": values, "sigma": sigmas}}


MOUNTING_KEYS: tuple[str, ...] = ("array_to_imu_roll_deg", "array_to_imu_pitch_deg", "array_to_imu_yaw_deg")
"""The calibration file's 1-sigma keys (``imu.sigma``) of the array-to-IMU rotation."""


def with_saved_imu(running: ArrayCalibration, saved: ArrayCalibration | None) -> ArrayCalibration:
    """``running`` (a calibration as a correction node runs it: its parameters carry the array-to-IMU rotation, not
    how well it is known) with ``saved``'s IMU report (the file's ``imu``: the rotation's 1-sigma the mounting's
    prior needs, :func:`with_mounting_prior`) when ``saved`` is that calibration's file: the same output frame
    and rotation; ``running`` unchanged otherwise."""
    if saved is None or not running.frame_id or saved.frame_id != running.frame_id:
        return running
    imu = saved.metadata.get("imu")
    same = np.allclose(np.asarray(saved.output_rotation, dtype=float), np.asarray(running.output_rotation, dtype=float),
                       rtol=0.0, atol=1e-12)
    if not isinstance(imu, dict) or "imu" in running.metadata or not same:
        return running
    return replace(running, metadata={**running.metadata, "imu": imu})


def with_mounting_prior(att: ab.AttitudeInputs | None, prior: ArrayCalibration | None) -> ab.AttitudeInputs | None:
    """``att`` with the array-to-IMU rotation of a ``prior`` calibration fitted with this IMU (its output frame
    the IMU's, the file's ``imu.sigma`` giving the rotation's 1-sigma: the largest of roll, pitch and yaw) as the
    mounting's prior; ``att`` unchanged otherwise (the weak prior)."""
    if att is None or prior is None or not prior.frame_id or prior.frame_id != att.frame_id:
        return att
    imu = prior.metadata.get("imu")
    sigma = imu.get("sigma") if isinstance(imu, dict) else None
    if not isinstance(sigma, dict) or not all(isinstance(sigma.get(k), (int, float)) for k in MOUNTING_KEYS):
        return att
    worst = max(float(sigma[k]) for k in MOUNTING_KEYS)
    if not (np.isfinite(worst) and worst > 0):
        return att
    return replace(att, mounting_prior=(np.asarray(prior.output_rotation, dtype=float), float(np.radians(worst))))


def quantity_key(name: str) -> str:
    """A quantity name as a parameter key: ``array to IMU roll`` -> ``array_to_imu_roll_deg``."""
    unit = "nT_per_m" if name.startswith("site gradient") else "ms" if name == ab.ARRAY_LAG else "deg"
    return name.lower().replace(" ", "_") + "_" + unit


def global_covariance(sol: JointSolution, order: NDArray[np.int64], prior_precision: Array | None) -> Array:
    """(G, G) sandwich covariance of the global parameters (time-correlated noise, the frame's gauge
    fixed as for the sensors, held ones at zero; ``prior_precision`` (S P,) of the sensors' prior)."""
    assert sol.full_information is not None and sol.full_scores is not None and sol.attitude is not None
    model = sol.model
    sp, ng = model.sensors * model.size, model.global_size
    prec = np.concatenate([np.zeros(sp) if prior_precision is None else prior_precision,
                           sol.attitude.global_precision(model)])
    rows = []
    if prior_precision is None:
        rows.append(np.concatenate([centre_gauge_constraints(sol.w, model.size), np.zeros((3, ng))], axis=1))
    fixed = np.concatenate([np.zeros(sp, bool) if sol.fixed is None else sol.fixed.reshape(-1),
                            sol.attitude.fixed(model)])
    if fixed.any():
        rows.append(np.eye(sp + ng)[fixed])
    # the global parameters are determined by the attitude residuals: their time correlation (an
    # IMU's slowly wandering error, the gyro's integrated noise) sets the bandwidth
    series = sol.residuals[order].reshape(len(order), -1) if sol.attitude_residuals is None else \
        sol.attitude_residuals[order][sol.attitude.known[order]]
    cov = covariance(sol.full_information, sol.full_scores[order], series, prec,
                     np.concatenate(rows) if rows else None)
    return cov.matrix[sp:, sp:]


def imu_report(sol: JointSolution, order: NDArray[np.int64], prior_precision: Array | None) -> ImuReport | None:
    """The global blocks of a solution in physical words (None without them)."""
    if sol.globals is None or sol.attitude is None:
        return None
    cov = global_covariance(sol, order, prior_precision)
    att = sol.attitude
    quantities = ab.global_quantities(sol.globals, cov, sol.model, sol.intensity, att.world)
    if att.field is not None:  # held at the site's model: no 1-sigma of its own
        quantities = [q if q.block != "field direction" else ab.GlobalQuantity(q.block, q.name, q.unit, q.value, 0.0)
                      for q in quantities]
    sigma_deg = float(np.degrees(sol.attitude_sigma or 0.0))
    if sigma_deg > MAX_ATTITUDE_ERROR_DEG:
        raise InputError(f"the IMU's attitudes disagree with the field throughout (attitude error {sigma_deg:.3g} deg per "
                         f"axis where an IMU is good to {MAX_ATTITUDE_ERROR_DEG:g}): another vehicle's topic, a world "
                         "frame other than the one given (--imu-frame ned?), or a clock far off the readings'; "
                         "calibrate without the IMU")
    weights = sol.attitude_weights
    excluded = 0 if weights is None else int(np.sum(att.known & (weights < OUTLYING_WEIGHT)))
    return ImuReport(quantities, cov, "orientation" if att.world else "gyro", int(att.known.sum()), att.count,
                     sigma_deg, att.frame_id, excluded)


def with_array_lag(offsets: Array | None, report: ImuReport | None, sensors: int) -> Array | None:
    """Every sensor's time offset (s, ``offsets`` relative to the first, None: none) with the array's lag
    behind the IMU added (:attr:`ImuReport.array_lag`): a set stamped ``t`` is then the field at ``t - lag``
    on the IMU's clock, and the outputs are stamped so."""
    lag = 0.0 if report is None else report.array_lag
    if not lag:
        return offsets
    return (np.zeros(sensors) if offsets is None else np.asarray(offsets, dtype=float)) + lag


def output_frame(sol: JointSolution, prior: ArrayCalibration | None = None) -> dict[str, Any]:
    """``ArrayCalibration`` keywords putting the outputs in the IMU frame; without an IMU a
    recalibration from a ``prior`` (whose frame it keeps) keeps the prior's output frame, else {}."""
    if sol.globals is None or sol.attitude is None:
        if prior is not None and (prior.rotated or prior.frame_id):
            return {"output_rotation": prior.output_rotation, "frame_id": prior.frame_id}
        return {}
    return {"output_rotation": sol.globals.mounting, "frame_id": sol.attitude.frame_id or None}


def without_site_field(corrected: Array, sol: JointSolution) -> Array:
    """Corrected vectors (N, S, 3) T, array frame, with the fitted site gradient's field taken off:
    what the quality gates judge (the field the manoeuvre's uniform part would give)."""
    site = sol.site_field()
    return corrected if site is None else corrected - site
