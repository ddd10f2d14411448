"""Typed errors of the calibration mathematics.

:class:`InputError` and :class:`ParameterError` are also ``ValueError``. (Forward
kinematics raises ``numpy.linalg.LinAlgError``, not one of these, for parameters or readings
that describe no mechanism.)
"""

from __future__ import annotations


class CalibrationError(Exception):
    """Base class of every error raised by :mod:`loopcal.calibration`.

    Parameters
    ----------
    message : str
        What went wrong, in words for the person who ran the calibration.
    """


class InputError(CalibrationError, ValueError):
    """Input data are malformed: wrong shape, NaN, readings outside the stroke, too few poses.

    Parameters
    ----------
    message : str
        What is wrong with the input, naming the first offending pose or sensor where there
        is one.
    """


class ParameterError(CalibrationError, ValueError):
    """A parameter name, value or free/tied/fixed split is invalid.

    Parameters
    ----------
    message : str
        Which parameter (or tie) is wrong, and why.
    """


class UnobservableError(CalibrationError):
    """The chosen free parameters cannot be identified from the given poses.

    Parameters
    ----------
    message : str
        What cannot be identified, for people.
    combinations : list of dict, optional
        The parameter combinations the data cannot see; default none.

    Attributes
    ----------
    combinations : list of dict of str to float
        The parameter combinations (name -> weight, in scaled units) that the data cannot
        see; empty when none were given.
    """

    def __init__(self, message: str, combinations: list[dict[str, float]] | None = None):
        super().__init__(message)
        self.combinations = combinations or []


class ConvergenceError(CalibrationError):
    """The least-squares iteration diverged or failed to converge.

    Parameters
    ----------
    message : str
        What diverged (the free parameters that moved too far from the start), and what to
        check.
    """
