"""Diagnostic figure of a calibration (``magcal calibrate --plot FILE.png``).

Three rows, before (left) and after (right) the calibration:

1. TMI error ``|b| - F`` per sensor (nT) against time;
2. what the array measures of the gradient (nT/m; zero in the uniform field of a
   calibration manoeuvre): the six tensor components ``xx, xy, xz, yx, yy, yz``, or for
   sensors on a line the three components ``dB/ds`` along it; a single sensor has no row;
3. the vectors of every sensor in 3-D (uT): raw ellipsoids, corrected on the sphere of
   radius F.

Matplotlib's Agg canvas is used directly (no pyplot, no global backend switch), and the
PNG is written atomically.
"""

from __future__ import annotations

import os

import numpy as np
from numpy.typing import NDArray

from magcal_ros.core.metrics import TENSOR_COMPONENTS, rms
from magcal_ros.core.recording import Recording
from magcal_ros.core.stamps import ns_to_seconds
from magcal_ros.core.tensor import baseline_gradient, gradient, method_for
from magcal_ros.core.units import NT
from magcal_ros.io.atomic import atomic_path
from magcal_ros.methods.pipeline import CalibrationResult

MAX_POINTS = 4000
"""Sets drawn per line; longer recordings are thinned evenly."""


def _thin(n: int) -> NDArray[np.int64]:
    return np.arange(n) if n <= MAX_POINTS else np.linspace(0, n - 1, MAX_POINTS).astype(np.int64)


def _sphere(ax, radius: float) -> None:  # type: ignore[no-untyped-def]
    u, v = np.meshgrid(np.linspace(0, 2 * np.pi, 25), np.linspace(0, np.pi, 13))
    ax.plot_wireframe(radius * np.cos(u) * np.sin(v), radius * np.sin(u) * np.sin(v), radius * np.cos(v),
                      color="0.8", linewidth=0.4)


def _gradient_row(axes, t: NDArray[np.float64], idx: NDArray[np.int64], raw: NDArray[np.float64],  # type: ignore[no-untyped-def]
                  corrected: NDArray[np.float64], geometry) -> None:  # type: ignore[no-untyped-def]
    """Row 2: the tensor components, or ``dB/ds`` for sensors on a line, before and after."""
    for ax, (vectors, label) in zip(axes, ((raw, "before (raw)"), (corrected, "after (corrected)"))):
        if geometry.gradient_kind == "tensor":
            method = method_for(geometry)
            g = gradient(vectors, geometry, method)
            comps, names, what = g[:, :2, :].reshape(len(g), 6), [f"G{c}" for c in TENSOR_COMPONENTS], \
                f"tensor components ({method})"
        else:
            comps, names, what = baseline_gradient(vectors, geometry), ["dBx/ds", "dBy/ds", "dBz/ds"], \
                "gradient along the baseline"
        for k, name in enumerate(names):
            ax.plot(t[idx], comps[idx, k] / NT, lw=0.7, label=f"{name}: RMS {rms(comps[:, k]) / NT:.3g}")
        ax.set_title(f"{what}, {label}: RMS {rms(comps) / NT:.3g} nT/m")
        ax.set_xlabel("time since first set (s)")
        ax.set_ylabel("nT/m")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8, ncols=3, loc="upper right")


def plot_calibration(path: str | os.PathLike[str], recording: Recording, result: CalibrationResult) -> None:
    """Draw the before/after figure of ``result`` on ``recording`` into the PNG ``path``."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    cal = result.calibration
    rec = recording.select(cal.geometry.names)
    raw = rec.vectors
    corrected = cal.apply_array(raw, rec.select_channels(cal.channels).currents if cal.channels else None,
                                rec.temperatures)  # the array frame: the gradient is formed there
    f = result.intensity
    kind = cal.geometry.gradient_kind
    idx = _thin(len(rec))
    t = ns_to_seconds(rec.stamps - rec.stamps[0])

    rows = 3 if kind != "none" else 2
    fig = Figure(figsize=(13, 15 if rows == 3 else 10), layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(rows, 2, height_ratios=(1, 1, 1.5) if rows == 3 else (1, 1.5))
    mode = "relative: F taken as" if result.relative else "reference F ="
    fig.suptitle(
        f"magcal calibration, method {result.method}: {result.samples} sets, {mode} {f / NT:.1f} nT, "
        f"coverage {result.excitation.coverage:.0%}",
        fontsize=12,
    )
    for col, (vectors, label) in enumerate(((raw, "before (raw)"), (corrected, "after (corrected)"))):
        ax = axes[0, col]
        err = np.linalg.norm(vectors, axis=-1) - f
        for k, name in enumerate(rec.names):
            ax.plot(t[idx], err[idx, k] / NT, lw=0.7, label=f"{name}: RMS {rms(err[:, k]) / NT:.3g} nT")
        ax.set_title(f"TMI error |b| - F, {label}")
        ax.set_xlabel("time since first set (s)")
        ax.set_ylabel("nT")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8, loc="upper right")
    if kind != "none":
        _gradient_row(axes[1], t, idx, raw, corrected, cal.geometry)
    for col, (vectors, label) in enumerate(((raw, "raw vectors"), (corrected, "corrected vectors"))):
        spec = axes[rows - 1, col].get_subplotspec()
        axes[rows - 1, col].remove()
        ax = fig.add_subplot(spec, projection="3d")
        _sphere(ax, f / 1e-6)
        for k, name in enumerate(rec.names):
            v = vectors[idx, k] / 1e-6
            ax.scatter(v[:, 0], v[:, 1], v[:, 2], s=2, label=name, depthshade=False)
        lim = 1.15 * max(f, np.max(np.abs(vectors))) / 1e-6
        ax.set_xlim(-lim, lim)
        ax.set_ylim(-lim, lim)
        ax.set_zlim(-lim, lim)
        ax.set_box_aspect((1, 1, 1))
        ax.set_xlabel("x (uT)")
        ax.set_ylabel("y (uT)")
        ax.set_zlabel("z (uT)")
        ax.set_title(f"{label} and the sphere |b| = F")
        ax.legend(fontsize=8, loc="upper left", markerscale=4)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=90)
