"""Exceptions raised by magcal_ros. Every message is one line a user can act on."""


class MagcalError(Exception):
    """Base class: anything magcal_ros refuses, with the reason and what to do."""


class InputError(MagcalError):
    """Malformed input: wrong shapes, non-finite values, unreadable files."""


class ObservabilityError(MagcalError):
    """The collected attitudes cannot determine the calibration (e.g. one rotation axis)."""


class CalibrationFailed(MagcalError):
    """The solver did not converge or produced a calibration that fails its own checks."""


class Stopped(KeyboardInterrupt):
    """SIGINT, SIGTERM or SIGHUP arrived: unwind (partial output is removed on the way) and exit with
    128 + ``signum``. Defined here, not in the CLI, so that it is one class however the CLI was started
    (``python -m magcal_ros.app.cli`` runs a second copy of that module as ``__main__``)."""

    def __init__(self, signum: int) -> None:
        super().__init__(signum)
        self.signum = signum
