"""Exceptions raised by magcal_ros. Every message is one line a user can act on."""


class MagcalError(Exception):
    """Base class: anything magcal_ros refuses, with the reason and what to do."""


class InputError(MagcalError):
    """Malformed input: wrong shapes, non-finite values, unreadable files."""


class ObservabilityError(MagcalError):
    """The collected attitudes cannot determine the calibration (e.g. one rotation axis)."""


class CalibrationFailed(MagcalError):
    """The solver did not converge or produced a calibration that fails its own checks."""
