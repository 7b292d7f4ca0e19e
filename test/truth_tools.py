"""Reference computations for the tests, written from the definitions and independent of the package.

The tests compare the package's results with these few lines of numpy, never with the
package's own ``apply``, ``gradient`` or ``tensor_floor`` run on the same data, so a bug
there cannot move the reference together with the result:

- a correction is ``B = M (r - o)`` per sensor (docs/methods.md, section 1);
- on a planar cross, gradient row x is ``(B(+x) - B(-x)) / d`` and row y likewise;
- on a baseline, ``dB/ds = (B_last - B_first) / L``;
- the noise floor of one difference component is ``sqrt(2) sigma / d``; with noise added
  to the raw reading it is ``sigma sqrt(|M_a[j]|^2 + |M_b[j]|^2) / d`` (row ``j`` of each
  true correction carries the noise into the platform frame);
- the relative alignment of sensor ``i`` is the rotation between its corrected frame and
  sensor 1's, ``E_i E_1^-1`` with ``E_i = M_i K_i`` (the true forward matrix ``K_i``):
  the identity for a perfect calibration whatever common frame the method chose.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]


def rms(values: Array, axis: int | tuple[int, ...] | None = None) -> Array:
    """Root mean square."""
    v = np.asarray(values, dtype=float)
    return np.sqrt(np.mean(v * v, axis=axis))


def correct(matrices: Array, offsets: Array, raw: Array) -> Array:
    """``B_i = M_i (r_i - o_i)`` for raw sets (N, S, 3): corrected vectors (N, S, 3)."""
    r = np.asarray(raw, dtype=float)
    out = np.empty_like(r)
    for i in range(r.shape[1]):
        out[:, i] = (r[:, i] - offsets[i]) @ np.asarray(matrices[i], dtype=float).T
    return out


def true_correction(sim: object) -> tuple[Array, Array]:
    """The simulator's true ``(M_i, o_i)`` (S, 3, 3), (S, 3): ``M_i = K_i^-1`` of its error model."""
    pairs = [s.forward() for s in sim.sensors]  # type: ignore[attr-defined]
    return np.stack([np.linalg.inv(k) for k, _ in pairs]), np.stack([o for _, o in pairs])


def true_forward(sim: object) -> Array:
    """The simulator's true forward matrices ``K_i`` (S, 3, 3)."""
    return np.stack([s.forward()[0] for s in sim.sensors])  # type: ignore[attr-defined]


def cross_pairs(positions: Array) -> tuple[tuple[int, int], tuple[int, int], float]:
    """``((+x, -x), (+y, -y), d)`` of a planar cross centred anywhere (found from the positions)."""
    p = np.asarray(positions, dtype=float)
    px, mx = int(np.argmax(p[:, 0])), int(np.argmin(p[:, 0]))
    py, my = int(np.argmax(p[:, 1])), int(np.argmin(p[:, 1]))
    d = float(p[px, 0] - p[mx, 0])
    assert abs(float(p[py, 1] - p[my, 1]) - d) < 1e-12 and len({px, mx, py, my}) == 4, "not a planar cross"
    return (px, mx), (py, my), d


def cross_rows(b: Array, positions: Array) -> Array:
    """Rows x and y of the gradient (N, 2, 3) T/m from vectors (N, 4, 3) on a planar cross."""
    (px, mx), (py, my), d = cross_pairs(positions)
    return np.stack([(b[:, px] - b[:, mx]) / d, (b[:, py] - b[:, my]) / d], axis=1)


def baseline_slope(b: Array, positions: Array) -> Array:
    """``dB/ds`` (N, 3) T/m of a two-sensor baseline, ``s`` from the first sensor to the second."""
    p = np.asarray(positions, dtype=float)
    return (b[:, -1] - b[:, 0]) / float(np.linalg.norm(p[-1] - p[0]))


def difference_floor(sigma: float, d: float) -> float:
    """``sqrt(2) sigma / d`` (T/m): RMS of one difference component with white noise ``sigma`` per axis."""
    return float(np.sqrt(2.0) * sigma / d)


def raw_noise_floor(matrices: Array, pairs: list[tuple[int, int]], sigma: float, d: float) -> float:
    """Expected RMS (T/m) over the components of the difference rows ``pairs`` when white noise
    ``sigma`` is added to the raw readings and carried into the platform frame by ``matrices``."""
    m = np.asarray(matrices, dtype=float)
    var = [np.sum(m[a] ** 2, axis=1) + np.sum(m[b] ** 2, axis=1) for a, b in pairs]  # (3,) per row
    return float(sigma * np.sqrt(np.mean(var)) / d)


def relative_angles(matrices: Array, forward: Array) -> Array:
    """Rotation angle (rad) between each sensor's corrected frame and sensor 1's, (S - 1,).

    ``E_i = M_i K_i`` maps the true platform field into sensor ``i``'s corrected output; the
    orthogonal polar factor of ``E_i E_1^-1`` is the residual rotation between the two.
    """
    e = np.einsum("sij,sjk->sik", np.asarray(matrices, dtype=float), np.asarray(forward, dtype=float))
    out = []
    for i in range(1, len(e)):
        u, _, vt = np.linalg.svd(e[i] @ np.linalg.inv(e[0]))
        q = u @ vt
        out.append(np.arccos(np.clip((np.trace(q) - 1.0) / 2.0, -1.0, 1.0)))
    return np.array(out)


MU0_OVER_4PI = 1e-7  # T m / A


def dipole_field(points: Array, position: Array, moment: Array) -> Array:
    """Field (T) of a point dipole (moment A m^2 at ``position`` m) at ``points`` (..., 3) m."""
    r = np.asarray(points, dtype=float) - np.asarray(position, dtype=float)
    d = np.linalg.norm(r, axis=-1, keepdims=True)
    u = r / d
    return MU0_OVER_4PI * (3.0 * np.sum(u * moment, axis=-1, keepdims=True) * u - moment) / d**3


def numerical_gradient(field: Callable[[Array], Array], point: Array, step: float = 1e-4) -> Array:
    """``G[i, j] = dB_j / dx_i`` (T/m) at ``point`` by central differences of ``field`` (4th order)."""
    g = np.empty((3, 3))
    for i in range(3):
        e = np.zeros(3)
        e[i] = step
        g[i] = (8 * (field(point + e) - field(point - e)) - (field(point + 2 * e) - field(point - 2 * e))) / (12 * step)
    return g


def cross_difference(b: Array, positions: Array) -> Array:
    """The full difference tensor (N, 3, 3) of a planar cross: rows x, y measured, row z from
    symmetry and zero trace (Li et al. 2018, eq. 2)."""
    rows = cross_rows(b, positions)
    g = np.empty((len(b), 3, 3))
    g[:, :2] = rows
    g[:, 2, 0], g[:, 2, 1] = rows[:, 0, 2], rows[:, 1, 2]
    g[:, 2, 2] = -(rows[:, 0, 0] + rows[:, 1, 1])
    return g


def least_squares_tensor(b: Array, positions: Array, with_centre: bool = False) -> Array | tuple[Array, Array]:
    """Symmetric traceless ``G`` (N, 3, 3) fitting ``B_i = B0 + G^T (p_i - c)`` by least squares,
    ``c`` the mean position: the 8 unknowns ``B0, Gxx, Gyy, Gxy, Gxz, Gyz`` (``Gzz = -Gxx - Gyy``).
    ``with_centre``: return ``(B0 (N, 3), G)``."""
    rel = np.asarray(positions, dtype=float) - np.mean(positions, axis=0)
    rows = []
    for x, y, z in rel:
        # B_x = B0x + Gxx x + Gxy y + Gxz z ; B_y = B0y + Gxy x + Gyy y + Gyz z ;
        # B_z = B0z + Gxz x + Gyz y - (Gxx + Gyy) z
        rows.append([1, 0, 0, x, 0, y, z, 0])
        rows.append([0, 1, 0, 0, y, x, 0, z])
        rows.append([0, 0, 1, -z, -z, 0, x, y])
    design = np.array(rows, dtype=float)
    sol = np.linalg.lstsq(design, np.asarray(b, dtype=float).reshape(len(b), -1).T, rcond=None)[0].T
    gxx, gyy, gxy, gxz, gyz = sol[:, 3], sol[:, 4], sol[:, 5], sol[:, 6], sol[:, 7]
    g = np.stack([np.stack([gxx, gxy, gxz], 1), np.stack([gxy, gyy, gyz], 1),
                  np.stack([gxz, gyz, -gxx - gyy], 1)], axis=1)
    return (sol[:, :3], g) if with_centre else g


# -- what a user reads ----------------------------------------------------------------------------
SUMMARY = (r"calibrated (?P<sensors>\d+) sensors? from (?P<sets>\d+) sets \(method (?P<method>\w+), "
           r"(?:F|relative: no reference, F taken as) (?P<F>[\d.]+) nT\): "
           r"TMI RMS (?P<tmi_before>[\d.]+) -> (?P<tmi_after>[\d.]+) nT"
           r"(?:, (?:tensor|baseline gradient) RMS (?P<gradient_before>[\d.]+) -> (?P<gradient_after>[\d.]+) nT/m)?")
"""The numbers of a calibration summary line (``magcal calibrate``, ``~/calibrate``'s answer, the
file's ``summary``), with their units as printed: nT and nT/m."""

QUANTITY = (r"(?P<sensor>\S+) (?P<name>offset [xyz]|scale [xyz]|non-orthogonality [xyz]-[xyz]|misalignment about [xyz]"
            r"|interference \S+ [xyz]) (?P<value>-?[\d.e+-]+) \+- (?P<sigma>[\d.e+-]+) (?P<unit>nT/A|nT|ppm|deg)")
"""One quantity as :meth:`Quantity.describe` prints it (a scale's value is the gain, its sigma in ppm)."""


def summary_numbers(text: str) -> dict[str, float | str]:
    """The numbers of the summary line in ``text`` (nT, nT/m, counts); AssertionError if there is none."""
    import re

    found = re.search(SUMMARY, text)
    assert found, f"no calibration summary in {text!r}"
    out: dict[str, float | str] = {}
    for key, value in found.groupdict().items():
        if value is not None:
            out[key] = value if key == "method" else float(value)
    return out


def quantities(text: str) -> list[dict[str, float | str]]:
    """Every quantity printed in ``text`` (see :data:`QUANTITY`): value, sigma (floats), unit, names."""
    import re

    return [{k: (float(v) if k in ("value", "sigma") else v) for k, v in m.groupdict().items()}
            for m in re.finditer(QUANTITY, text)]


def sensor_errors(forward: Array) -> dict[str, Array]:
    """Scale (gains), non-orthogonality angles (rad, order x-z, x-y, y-z) of a forward matrix ``K``
    (raw = K B + o), from its RQ decomposition ``K = U Q`` with a positive diagonal: invariant to
    the platform frame (a rotation of the frame only changes ``Q``)."""
    import scipy.linalg

    upper, _ = scipy.linalg.rq(np.asarray(forward, dtype=float))
    upper = upper * np.sign(np.diag(upper))[None, :]
    scale = np.linalg.norm(upper, axis=1)
    a = upper / scale[:, None]
    return {"scale": scale,
            "angles": np.array([np.arcsin(a[0, 2]), np.arctan2(a[0, 1], a[0, 0]), np.arcsin(a[1, 2])])}
