"""Interference from a still run: a rotation calibration held, the current interference added.

The vehicle does not move while the thrusters (or pumps, payload) step through their
currents; with the previous calibration's matrices and offsets held, every channel's
gains are a linear least-squares fit (:func:`~magcal_ros.core.interference.estimate_interference`).
Channels the run cannot determine (a current that never varies, currents in lockstep)
are not solved: they are left out of the calibration and named in a warning.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from magcal_ros.core.calibration import ArrayCalibration
from magcal_ros.core.interference import (
    InterferenceEstimate,
    describe_undetermined,
    estimate_interference,
)
from magcal_ros.core.units import NT
from magcal_ros.errors import CalibrationFailed, InputError
from magcal_ros.methods.pipeline import check_raw, provenance_key

STILL_RESIDUAL_RATIO: float = 3.0
"""A still run whose residual exceeds this many times the held calibration's noise is suspect."""


@dataclass(frozen=True)
class InterferenceResult:
    """The held calibration with the estimated interference, and how it was estimated."""

    calibration: ArrayCalibration
    estimate: InterferenceEstimate
    channels: tuple[str, ...]
    """All channels of the run (solved or not), the order of ``estimate``."""
    samples: int
    warnings: list[str]

    @property
    def solved(self) -> tuple[str, ...]:
        """Channels whose interference the calibration now subtracts."""
        return self.calibration.channels

    def summary(self) -> str:
        """One line: sets, channels solved, the largest gain and its 1-sigma, the residual."""
        est = self.estimate
        parts = [f"interference of {len(self.solved)} channel{'s' if len(self.solved) != 1 else ''} from a still run "
                 f"of {self.samples} sets (calibration held)"]
        for c in self.solved:
            j = self.channels.index(c)
            norms = np.linalg.norm(est.gains[:, :, j], axis=1)
            worst = int(np.argmax(norms))
            sig = float(np.max(est.sigma[:, :, j]))
            parts.append(f"{c}: up to {norms[worst] / NT:.3g} nT/A ({self.calibration.geometry.names[worst]}) "
                         f"+- {sig / NT:.2g} nT/A")
        parts.append(f"residual {np.max(est.residual) / NT:.3g} nT")
        return ", ".join(parts)


def calibrate_interference(
    raw: ArrayLike, currents: ArrayLike, channels: Sequence[str], held: ArrayCalibration,
    temperatures: ArrayLike | None = None,
) -> InterferenceResult:
    """``held`` plus the interference of ``channels`` from a still run.

    ``raw`` (N, S, 3) T of ``held``'s sensors, ``currents`` (N, m) A. The result subtracts
    the solved channels only (the held calibration's own interference is replaced; its
    temperature terms and output frame are kept, ``temperatures`` (N, S) deg C are needed
    with temperature terms); its provenance is the held one's plus what this run gave. Raises :class:`InputError` for
    bad input or when the held calibration subtracts a channel the run does not record,
    and :class:`CalibrationFailed` when no channel can be determined.
    """
    r = check_raw(raw, held.geometry)
    channels = tuple(channels)
    u = np.asarray(currents, dtype=float)
    if not channels or u.shape != (len(r), len(channels)):
        raise InputError(f"need the currents (N, {len(channels)}) of at least one channel, got {u.shape}")
    missing = [c for c in held.channels if c not in channels]
    if missing:
        raise InputError(f"the calibration subtracts {', '.join(missing)}, which this run does not record: "
                         "give its current too")
    est = estimate_interference(r, u, held, temperatures)
    warnings = []
    if np.any(est.undetermined):
        warnings.append(f"interference not solved (undetermined): {describe_undetermined(channels, u, est.undetermined)}")
    if np.all(est.undetermined):
        raise CalibrationFailed(f"{warnings[0]}; step each current on its own while the vehicle is still")
    noise = np.asarray(held.metadata.get("noise") or [], dtype=float)
    if noise.shape == (held.geometry.size,) and np.any(est.residual > STILL_RESIDUAL_RATIO * noise):
        i = int(np.argmax(est.residual / noise))
        warnings.append(f"{held.geometry.names[i]} residual {est.residual[i] / NT:.3g} nT is "
                        f"{est.residual[i] / noise[i]:.1f}x the calibration's noise: was the vehicle still, and "
                        "are all the currents given?")
    solved = [j for j in range(len(channels)) if not est.undetermined[j]]
    cal = replace(held, metadata={}, channels=tuple(channels[j] for j in solved), interference=est.gains[:, :, solved])
    result = InterferenceResult(cal, est, channels, len(r), warnings)
    object.__setattr__(cal, "metadata", _provenance(held.metadata, result))
    return result


def _provenance(held: dict[str, Any], result: InterferenceResult) -> dict[str, Any]:
    """The held provenance plus the interference run: ``interference_uncertainty`` (1-sigma per
    sensor, keys as the joint fit's ``uncertainty``), ``interference_samples``, ...; ROS
    parameter names and types only."""
    meta = dict(held)
    est = result.estimate
    names = result.calibration.geometry.names
    uncertainty: dict[str, dict[str, float]] = {}
    for i, sensor in enumerate(names):
        for c in result.solved:
            j = result.channels.index(c)
            for a, axis in enumerate("xyz"):
                key = f"{provenance_key(f'interference {c} {axis}')}_nT_per_A"
                uncertainty.setdefault(sensor, {})[key] = float(est.sigma[i, a, j] / NT)
    meta["interference_uncertainty"] = uncertainty
    meta["interference_source"] = "still run, calibration held, linear least squares"
    meta["interference_samples"] = result.samples
    meta["interference_residual_rms"] = [float(x) for x in est.residual]
    meta["interference_summary"] = result.summary()
    if np.any(est.undetermined):
        meta["interference_undetermined"] = [c for c, bad in zip(result.channels, est.undetermined) if bad]
    if result.warnings:
        meta["warnings"] = [*(meta.get("warnings") or []), *result.warnings]
    return meta
