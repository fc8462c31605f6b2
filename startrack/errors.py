"""The exceptions startrack raises.

Library code raises these and never exits or prints.  The command line turns
:class:`BadInputError` into exit status 2 and every other
:class:`StartrackError` into exit status 1, each as a single line.

Library code names *parameters* (``fov_deg``), never command-line flags: a
bad argument raises :class:`ParameterError`, whose ``field`` is the parameter's
name, and the command line maps that name to its flag.
"""
from __future__ import annotations

__all__ = ["BadInputError", "DatabaseMismatchError", "ParameterError", "StartrackError"]


class StartrackError(Exception):
    """Base class of every error startrack raises on purpose."""

    exit_code = 1


class BadInputError(StartrackError, ValueError):
    """Input that is not what the operation accepts (file, field or value).

    Parameters
    ----------
    source : str
        What was read: a file path, ``<stdin>``, or the function given a bad argument.
    field : str or None
        The field or parameter at fault, e.g. ``camera.focal_length_px`` or ``fov_deg``.
    problem : str
        What is wrong with it, in a few words.
    """

    exit_code = 2

    def __init__(self, source: str, field: str | None, problem: str):
        self.source = str(source)
        self.field = field
        self.problem = problem
        where = self.source if field is None else (f"{self.source}: {field}" if self.source else field)
        super().__init__(f"{where}: {problem}")


class ParameterError(BadInputError):
    """A bad argument of a library function: ``field`` is the parameter's name.

    Parameters
    ----------
    parameter : str
        The parameter's name as the function spells it (``fov_deg``).
    problem : str
        What is wrong with it, e.g. ``must be positive, got -1``.
    source : str, optional
        The function or object (``Camera.from_fov``); default none.
    """

    def __init__(self, parameter: str, problem: str, source: str = ""):
        super().__init__(source, parameter, problem)

    @property
    def parameter(self) -> str:
        return self.field


class DatabaseMismatchError(BadInputError):
    """A database built for another catalog, field of view or camera."""
