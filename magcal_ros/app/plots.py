"""Figures: a calibration (``magcal calibrate --plot FILE.png``) and a corrected recording
(``magcal plot RECORDING -o FILE.png``, :func:`plot_survey`).

The calibration's figure:

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
from magcal_ros.io.output_scan import CorrectedOutput
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


def gradient_components(gradient: NDArray[np.float64] | None) -> tuple[NDArray[np.float64] | None, list[str]]:
    """The measured gradient components of an output's gradient rows and their labels: the six tensor
    components ``xx, xy, xz, yx, yy, yz`` of (N, 9) rows, or ``dB/ds`` of (N, 3) rows (T/m)."""
    if gradient is None:
        return None, []
    if gradient.shape[1] == 9:
        return gradient[:, :6], [f"G{c}" for c in TENSOR_COMPONENTS]
    return gradient, ["dBx/ds", "dBy/ds", "dBz/ds"]


def set_to_set_noise(values: NDArray[np.float64] | None) -> float | None:
    """RMS of the differences between consecutive rows over sqrt(2) (the white part of a slowly varying
    series: a survey's gradient changes little from one set to the next), NaN rows skipped; None for none."""
    from magcal_ros.core.streaming_stats import StepNoise

    if values is None:
        return None
    steps = StepNoise()
    steps.add(values)
    return steps.value()


def plot_survey(path: str | os.PathLike[str], output: CorrectedOutput, intensity: float | None = None,
                noise: float | None = None, floor: float | None = None, title: str = "") -> None:
    """Time series of a corrected recording into the PNG ``path``: the centre field's components (nT about
    their median), its total intensity (TMI, nT: ``|B| - F`` with the intensity ``F`` when known, else
    about its median; per sensor when the centre field was withheld), and the measured gradient
    components (nT/m). ``noise`` (T per axis) draws the TMI's noise band ``+- noise / sqrt(S)`` and
    ``floor`` (T/m) the gradient's noise floor, dashed, where they are known."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    comps, labels = gradient_components(output.gradient)
    rows = (2 if output.centre is not None else 1) + (comps is not None)
    fig = Figure(figsize=(13, 3.6 * rows + 0.6), layout="constrained")
    FigureCanvasAgg(fig)
    axes = np.atleast_1d(fig.subplots(rows, 1, sharex=True))
    t = ns_to_seconds(output.stamps - output.stamps[0])
    idx = _thin(len(t))
    fig.suptitle(title or f"magcal corrected recording: {len(t)} sets of {len(output.names)} sensor"
                 f"{'s' if len(output.names) != 1 else ''}", fontsize=12)
    row = 0
    if output.centre is not None:
        ax = axes[row]
        median = np.nanmedian(output.centre, axis=0)
        for k, axis in enumerate("xyz"):
            ax.plot(t[idx], (output.centre[idx, k] - median[k]) / NT, lw=0.7, label=f"B{axis} (median {median[k] / 1e-6:.3f} uT)")
        ax.set_title("centre field (the mean of the sensors), each component about its median")
        ax.set_ylabel("nT")
        ax.legend(fontsize=8, loc="upper right")
        row += 1
    ax = axes[row]
    series = [("centre", output.centre)] if output.centre is not None else \
        [(n, output.vectors[:, k]) for k, n in enumerate(output.names)]
    for name, vectors in series:
        tmi = np.linalg.norm(vectors, axis=1)
        ref = intensity if intensity else float(np.nanmedian(tmi))
        ax.plot(t[idx], (tmi[idx] - ref) / NT, lw=0.7, label=f"{name}: median {float(np.nanmedian(tmi - ref)) / NT:+.3g} nT")
    if noise and output.centre is not None:
        band = noise / np.sqrt(len(output.names)) / NT
        for sign in (-1, 1):
            ax.axhline(sign * band, color="k", ls="--", lw=0.8, label="+- noise / sqrt(S)" if sign > 0 else None)
    about = f"F = {intensity / NT:.1f} nT" if intensity else "its median"
    ax.set_title(f"total intensity (TMI) |B| minus {about}" + ("" if output.centre is not None else
                                                              ", per sensor (centre field withheld)"))
    ax.set_ylabel("nT")
    ax.legend(fontsize=8, loc="upper right")
    if comps is not None:
        ax = axes[-1]
        for k, name in enumerate(labels):
            ax.plot(t[idx], comps[idx, k] / NT, lw=0.7, label=name)
        measured = set_to_set_noise(comps)
        text = f"set-to-set noise {measured / NT:.3g} nT/m" if measured is not None else ""
        if floor:
            for sign in (-1, 1):
                ax.axhline(sign * floor / NT, color="k", ls="--", lw=0.8, label="+- noise floor" if sign > 0 else None)
            text += f" against the noise floor {floor / NT:.3g} nT/m"
        ax.set_title(f"measured gradient components: {text}")
        ax.set_ylabel("nT/m")
        ax.legend(fontsize=8, ncols=4, loc="upper right")
    for ax in axes:
        ax.grid(alpha=0.3)
    axes[-1].set_xlabel("time since first set (s)")
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=90)
