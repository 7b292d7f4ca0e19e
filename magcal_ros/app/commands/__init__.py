"""The ``magcal`` commands, one module each: :mod:`.simulate`, :mod:`.calibrate`, :mod:`.correct`,
:mod:`.plot` and :mod:`.batch`, each with ``add_parser(sub)`` (its options, examples and the function it
runs); :mod:`.common` holds what they share (option groups, notes, the reference intensity, calibration
files, a bag's side streams). :mod:`magcal_ros.app.cli` assembles the parser from them and runs ``main``."""

from __future__ import annotations

__all__ = ["batch", "calibrate", "common", "correct", "plot", "simulate"]
