"""Is the field uniform over the array where it is calibrated? The array measures it.

A calibration assumes one field at every sensor. Near a ship, a pier or a magnetised object
the field changes across the array by ``G p_i`` (``G`` the gradient, ``p_i`` a sensor's
position), fixed in the world and so turning with the array: no sensor calibration can
absorb it, and it biases every parameter. After the fit the corrected sets show it.

**Model per set** (corrected vectors ``b_i`` of the ``S`` sensors, 3S numbers ``y``): a
uniform field and a source-free linear gradient, ``b_i = B0 + G^T p_i`` with ``G``
symmetric and trace-free (8 unknowns ``theta``: 3 + 5), by least squares ``theta = A^+ y``.
Needs three or more sensors not on one line (then ``A`` has full rank); ``nu = 3S - 8``
numbers per set are left over.

- **Noise.** The residuals ``(I - H) y`` hold noise only (the gradient is in the model),
  so the per-sensor noise variances ``sigma_i^2`` (T^2 per axis) follow from the mean
  squared residuals, ``E r_j^2 = sum_m (I - H)_jm^2 sigma_m^2``, by non-negative least
  squares; unlike the calibration's residual they do not grow with the gradient.
- **Statistic.** ``Q_k = ||G_k||_F^2`` of each set's estimate ``G_k = P y_k`` (``P`` the
  rows of ``A^+`` giving ``G``). ``E Q_k = ||G||_F^2 + t1`` with ``t1 = tr(P Sigma P^T)``,
  the noise's share; for the 0.4 m cross ``t1`` is about ``8 (sqrt(2) sigma / d)^2``.
  The excess ``D = mean_k Q_k - t1`` estimates ``||G||_F^2``; with no gradient its
  standard error is ``sqrt(2 tr((P Sigma P^T)^2) / N + t1^2 2 / (N nu))`` (``N`` sets; the
  second term: ``t1`` is itself estimated), or the batch-means error of ``Q_k`` when the
  noise is correlated in time and that is larger.
- **Coherent statistic.** The gradient is fixed in the world while the array turns, so
  the gradient along the field, ``c = u^T G u`` (``u`` the unit field direction, ``B0``
  of each set), is the same in every set however the array is oriented: its mean over the
  sets has a standard error ``sd(c_k) / sqrt(N)`` (or the batch-means one), far below the
  per-set noise floor, which finds gradients below that floor that ``D`` cannot.
  ``|c| <= ||G||_F``.
- The field is **not uniform** when ``D`` or the mean of ``c`` exceeds
  :data:`DETECT_SIGMAS` standard errors; the gradient reported is ``max(sqrt(D), |c|)``.
- **Limit.** ``d = 2 x`` the RMS distance of the sensors from the array centre (the
  baseline: 0.4 m for the cross), ``sqrt(2) sigma / d`` the noise floor of one gradient
  component. A calibration is refused when the non-uniformity changes the field at a
  sensor by more than the noise of one reading, ``||G||_F d / 2 > sigma``, i.e.
  ``||G||_F > sqrt(2) x`` the floor (:data:`LIMIT_OVER_FLOOR`): 5 nT/m for the cross with
  1 nT noise. Below it the gradient is said and the calibration kept.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from magcal_ros.core.units import NT

Array = NDArray[np.float64]

DETECT_SIGMAS: float = 5.0
"""A gradient energy this many standard errors above what the noise explains is a finding."""
LIMIT_OVER_FLOOR: float = float(np.sqrt(2.0))
"""Refusal limit of ``||G||_F`` over the noise floor ``sqrt(2) sigma / d``: the field's change
across the array (``||G||_F d / 2``) reaches the noise of one reading."""
BATCHES: int = 20
"""Contiguous batches of sets for the batch-means standard error (time-correlated noise)."""
MIN_SETS: int = 2 * BATCHES
PRECISION: float = 1e-9
"""No reading is known better than this fraction of the field (0.05 pT in 50 uT): the least noise
assumed, so that noise-free data are not judged on rounding errors."""


@dataclass(frozen=True)
class Uniformity:
    """What the corrected sets say about the field's uniformity over the array."""

    gradient: float
    """Estimated ``||G||_F`` (T/m) beyond the noise (0 when the excess is negative)."""
    z: float
    """Excess gradient energy in standard errors."""
    noise: float
    """RMS noise per axis of the sensors (T), from the model's residuals."""
    floor: float
    """``sqrt(2) sigma / d`` (T/m)."""
    baseline: float
    """``d`` (m)."""
    sets: int

    @property
    def limit(self) -> float:
        """Largest ``||G||_F`` (T/m) a calibration is accepted with."""
        return LIMIT_OVER_FLOOR * self.floor

    @property
    def detected(self) -> bool:
        """The field is not uniform beyond what the noise explains."""
        return self.z > DETECT_SIGMAS

    @property
    def refused(self) -> bool:
        """The non-uniformity is above :attr:`limit`."""
        return self.detected and self.gradient > self.limit

    def describe(self) -> str:
        """The finding in words (for the summary, the file and the service answer)."""
        return (f"the field is not uniform where you calibrate: {self.gradient / NT:.3g} nT/m across the array "
                f"(||G||, {self.z:.0f} standard errors beyond the noise; noise floor {self.floor / NT:.3g} nT/m, "
                f"limit {self.limit / NT:.3g} nT/m); move away from the ship or pier, or other iron (currents near the "
                "array whose interference is not solved do the same)")

    def provenance(self) -> dict[str, float]:
        """Calibration-file provenance keys (T/m)."""
        return {"field_gradient": self.gradient if self.detected else 0.0, "field_gradient_limit": self.limit,
                "field_gradient_floor": self.floor}


def _design(positions: Array) -> Array:
    """(3S, 8) model matrix: B0 (3), then G's xx, yy, xy, xz, yz (zz = -xx - yy), ``b_i = B0 + G^T p_i``."""
    rows = []
    for x, y, z in positions:
        for j in range(3):  # component b_j = B0_j + sum_i G[i, j] p_i
            row = np.zeros(8)
            row[j] = 1.0
            g = np.zeros((3, 3))  # coefficient of each G[i, j] in b_j
            g[:, j] = (x, y, z)
            row[3] = g[0, 0] - g[2, 2]
            row[4] = g[1, 1] - g[2, 2]
            row[5] = g[0, 1] + g[1, 0]
            row[6] = g[0, 2] + g[2, 0]
            row[7] = g[1, 2] + g[2, 1]
            rows.append(row)
    return np.array(rows)


def _tensor_map() -> Array:
    """(9, 5) vec(G) (row-major) from (xx, yy, xy, xz, yz)."""
    m = np.zeros((9, 5))
    m[0, 0] = 1.0
    m[4, 1] = 1.0
    m[8, 0] = m[8, 1] = -1.0
    m[1, 2] = m[3, 2] = 1.0
    m[2, 3] = m[6, 3] = 1.0
    m[5, 4] = m[7, 4] = 1.0
    return m


def check(corrected: Array, positions: Array) -> Uniformity | None:
    """The uniformity of the field over the array from corrected sets (N, S, 3) T and sensor
    positions (S, 3) m, in time order if known; None when the array cannot tell (fewer than three
    sensors, all on one line, or fewer than :data:`MIN_SETS` sets)."""
    y = np.asarray(corrected, dtype=float)
    p = np.asarray(positions, dtype=float) - np.mean(positions, axis=0)
    n, s = y.shape[:2]
    a = _design(p)
    if s < 3 or n < MIN_SETS or np.linalg.matrix_rank(a) < 8:
        return None
    pinv = np.linalg.pinv(a)
    proj = _tensor_map() @ pinv[3:]  # (9, 3S): vec(G) from y
    resid_op = np.eye(3 * s) - a @ pinv
    flat = y.reshape(n, 3 * s)
    resid = flat @ resid_op.T
    sensor = np.repeat(np.arange(s), 3)
    # E r_j^2 = sum_m R_jm^2 sigma_m^2, sigma the same for a sensor's three axes
    design = np.stack([np.sum(resid_op[:, sensor == i] ** 2, axis=1) for i in range(s)], axis=1)
    from scipy.optimize import nnls  # here: scipy.optimize takes a second to import

    var_sensor = nnls(design, np.mean(resid**2, axis=0))[0]
    floor2 = (PRECISION * float(np.median(np.linalg.norm(y, axis=2)))) ** 2
    var_sensor = var_sensor + floor2  # a noise-free simulation is not judged on rounding errors
    sigma2 = var_sensor[sensor]  # (3S,)
    cov_g = (proj * sigma2) @ proj.T  # (9, 9) noise covariance of vec(G)
    t1, t2 = float(np.trace(cov_g)), float(np.sum(cov_g * cov_g))
    g = (flat @ proj.T).reshape(n, 3, 3)
    q = np.sum(g * g, axis=(1, 2))
    excess = float(np.mean(q) - t1)
    nu = 3 * s - 8
    se = max(np.sqrt(2.0 * t2 / n + t1 * t1 * 2.0 / (n * nu)), _batch_error(q))
    b0 = flat @ pinv[:3].T
    u = b0 / np.linalg.norm(b0, axis=1, keepdims=True)
    c = np.einsum("ni,nij,nj->n", u, g, u)
    c_mean = float(np.mean(c))
    c_se = max(float(np.std(c, ddof=1) / np.sqrt(n)), _batch_error(c))
    z = max(excess / se if se > 0 else 0.0, abs(c_mean) / c_se if c_se > 0 else 0.0)
    noise = float(np.sqrt(np.mean(var_sensor)))
    baseline = 2.0 * float(np.sqrt(np.mean(np.sum(p * p, axis=1))))
    return Uniformity(
        gradient=max(float(np.sqrt(max(excess, 0.0))), abs(c_mean)), z=float(z), noise=noise,
        floor=float(np.sqrt(2.0) * noise / baseline), baseline=baseline, sets=n,
    )


def _batch_error(series: Array) -> float:
    """Standard error of the mean of ``series`` from :data:`BATCHES` contiguous batch means (valid
    under correlation in time shorter than a batch)."""
    means = np.array([b.mean() for b in np.array_split(np.asarray(series, dtype=float), BATCHES)])
    return float(np.std(means, ddof=1) / np.sqrt(BATCHES))
