"""A previous calibration as a prior for the next one, and how much each quantity may drift.

At sea the hull's hard iron moves most (a new payload, a magnetised hull: hundreds of nT);
scale factors, non-orthogonality and the mounting drift little (tens of ppm, arc seconds);
current interference changes with wiring. The drift model states that as 1-sigma changes
of the quantities the joint fit estimates (:mod:`magcal_ros.core.array_fit`): each sensor's
offset (T), each entry of its forward matrix ``K = M^-1`` (dimensionless: ``2e-5`` moves
the field by about 1 nT at 50 uT), and each interference gain (T/A). A yaw circle with this
prior determines all three offsets (x and y from the circle, z from the known intensity)
and leaves the matrix where it was.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from magcal_ros.core.array_fit import ParameterPrior
from magcal_ros.core.calibration import ArrayCalibration
from magcal_ros.core.forward_model import ForwardModel
from magcal_ros.core.geometry import ArrayGeometry
from magcal_ros.core.units import NT
from magcal_ros.errors import InputError

Array = NDArray[np.float64]


@dataclass(frozen=True)
class DriftModel:
    """1-sigma change of each quantity since the previous calibration (defaults: a UUV between
    two calibrations with a payload change)."""

    offset: float = 2000 * NT
    """Per offset axis (T): hard iron moves by hundreds of nT."""
    gain: float = 2e-5
    """Per entry of the forward matrix (scale, non-orthogonality, mounting, soft iron): ~1 nT at 50 uT
    (fluxgate scale drifts by tens of ppm; the mounting does not move unless struck)."""
    interference: float = 20 * NT
    """Per interference gain (T/A), when the previous calibration has one for the channel."""
    offset_tempco: float = 1 * NT
    """Per offset-per-kelvin axis (T/K): a fluxgate's offset moves by a fraction of a nT per kelvin."""
    gain_tempco: float = 50e-6
    """Per gain-per-kelvin axis (1/K): tens of ppm per kelvin."""
    time_offset: float = 5e-3
    """Per sensor lag (s): a driver or filter change moves it by milliseconds."""

    def check(self) -> None:
        """Raise :class:`InputError` for a non-positive or non-finite sigma."""
        for name in ("offset", "gain", "interference", "offset_tempco", "gain_tempco", "time_offset"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise InputError(f"drift {name} must be a positive number, got {v}")

    def prior(
        self,
        previous: ArrayCalibration,
        geometry: ArrayGeometry,
        intensity: float,
        channels: Sequence[str] = (),
        model: ForwardModel | None = None,
    ) -> ParameterPrior:
        """The prior on the parameters of ``model`` (units of F) centred on ``previous``, for
        sensors ``geometry.names`` (default model: sensor and interference blocks).

        Interference channels the previous calibration does not know get no prior (a wide one);
        temperature and lag terms it does not have are centred on zero with this drift.
        """
        self.check()
        missing = [n for n in geometry.names if n not in previous.geometry.names]
        if missing:
            raise InputError(f"the prior calibration has no sensor {', '.join(missing)} "
                             f"(it has {', '.join(previous.geometry.names)})")
        idx = [previous.geometry.names.index(n) for n in geometry.names]
        k = np.linalg.inv(previous.matrices[idx])
        m = len(channels)
        e = np.zeros((len(idx), 3, m))
        sig_e = np.full((len(idx), 3, m), np.inf)
        for c, name in enumerate(channels):
            if name in previous.channels:
                j = previous.channels.index(name)
                e[:, :, c] = np.einsum("sab,sb->sa", k, previous.interference[idx][:, :, j])
                sig_e[:, :, c] = self.interference / intensity
        mean = np.concatenate([k, (previous.offsets[idx] / intensity)[:, :, None], e / intensity], axis=2)
        sigma = np.concatenate([
            np.full((len(idx), 3, 3), self.gain), np.full((len(idx), 3, 1), self.offset / intensity), sig_e,
        ], axis=2)
        model = model or ForwardModel(len(idx), m)
        g_mean = tau_mean = None
        if model.temperature:
            has = previous.has_temperature_terms
            c = previous.offset_tempco[idx] if has else np.zeros((len(idx), 3))  # type: ignore[index]
            mean = np.concatenate([mean, (c / intensity)[:, :, None]], axis=2)
            sigma = np.concatenate([sigma, np.full((len(idx), 3, 1), self.offset_tempco / intensity)], axis=2)
            # matrix_tempco = -M diag(g) (the forward gain 1 / (1 - g dT)): g = diag(-K matrix_tempco)
            g_mean = (-np.einsum("sab,sbc->sac", k, previous.matrix_tempco[idx]).diagonal(axis1=1, axis2=2)  # type: ignore[index]
                      if has else np.zeros((len(idx), 3)))
        if model.lag:
            tau_mean = previous.time_offsets[idx] if previous.time_offsets is not None else np.zeros(len(idx))
        flat_mean = model.join(mean, g_mean, tau_mean)
        flat_sigma = model.join(sigma, np.full((len(idx), 3), self.gain_tempco) if model.temperature else None,
                                np.full(len(idx), self.time_offset) if model.lag else None)
        return ParameterPrior(flat_mean, flat_sigma)
