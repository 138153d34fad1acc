"""Errors of the capture station, each with a plain-language message for the operator."""

from __future__ import annotations


class CaptureError(Exception):
    """A scan or capture step failed.

    Attributes
    ----------
    operator_message : str
        What the person at the bench should read: what happened and what to do next.
    """

    def __init__(self, message: str, operator_message: str | None = None):
        super().__init__(message)
        self.operator_message = operator_message or message


class NoFragmentError(CaptureError):
    """The pre-scan shows no fragment on the glass."""


class MultipleFragmentsError(CaptureError):
    """The pre-scan shows more than one object on the glass."""


class ScannerError(CaptureError):
    """The scanner refused or failed a scan (cover open, jammed, busy, I/O error, ...).

    Attributes
    ----------
    status : str
        The backend's status name (e.g. ``SANE_STATUS_COVER_OPEN``) or ``"unknown"``.
    """

    def __init__(self, message: str, operator_message: str | None = None, status: str = "unknown"):
        super().__init__(message, operator_message)
        self.status = status


class RegistrationError(Exception):
    """A scan could not be registered to the target scan; solving would emboss the normals."""


class CalibrationError(Exception):
    """No usable calibration, or calibration data that cannot be fitted."""
