"""Typed errors of the calibration mathematics."""

from __future__ import annotations


class CalibrationError(Exception):
    """Base class of every error raised by :mod:`loopcal.calibration`."""


class InputError(CalibrationError, ValueError):
    """Input data are malformed: wrong shape, NaN, readings outside the stroke, too few poses."""


class ParameterError(CalibrationError, ValueError):
    """A parameter name, value or free/tied/fixed split is invalid."""


class UnobservableError(CalibrationError):
    """The chosen free parameters cannot be identified from the given poses.

    ``combinations`` lists the parameter combinations (name -> weight, in scaled units) that
    the data cannot see.
    """

    def __init__(self, message: str, combinations: list[dict[str, float]] | None = None):
        super().__init__(message)
        self.combinations = combinations or []


class ConvergenceError(CalibrationError):
    """The least-squares iteration diverged or failed to converge."""
