"""Exceptions raised for bad input.

Every error raised for something a user passed in is a :class:`NRSfMError`
(and, where the input's *value* is wrong, a :class:`ValueError` too), with a
message that names the field, what was expected, what arrived and how to fix
it. The command line turns these into one line on stderr and exit status 2.
"""

from __future__ import annotations


class NRSfMError(Exception):
    """Base class of every error the toolbox raises for user input."""


class ValidationError(NRSfMError, ValueError):
    """An array or parameter has the wrong shape, type or value."""


class DataFormatError(NRSfMError, ValueError):
    """A file is not in a layout the toolbox can read."""


class SolverError(NRSfMError, ValueError):
    """A solver cannot handle this input (for example missing points)."""


def shape_error(field: str, expected: str, got: object, hint: str = "") -> ValidationError:
    """Build a :class:`ValidationError` in the house style.

    ``points_2d: expected (F, P, 2), got (2, 17, 120); <hint>``
    """
    got_s = tuple(got) if isinstance(got, (tuple, list)) else got
    msg = f"{field}: expected {expected}, got {got_s}"
    if hint:
        msg += f"; {hint}"
    return ValidationError(msg)
