"""The stages' errors: a fit the data cannot support, a calibration that cannot be used."""

from __future__ import annotations

from imupipe.readers.errors import ImupipeError


class FitError(ImupipeError):
    """The data cannot support the requested fit (too short, too few poses, planar, ...)."""


class CalibrationError(ImupipeError):
    """A calibration document is malformed, or cannot be applied to this log."""
