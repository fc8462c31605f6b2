"""The exceptions startrack raises.

Library code raises these and never exits or prints.  The command line turns
:class:`BadInputError` into exit status 2 and every other
:class:`StartrackError` into exit status 1, each as a single line.
"""
from __future__ import annotations


class StartrackError(Exception):
    """Base class of every error startrack raises on purpose."""

    exit_code = 1


class BadInputError(StartrackError, ValueError):
    """Input that is not what the operation accepts (file, field or value).

    Parameters
    ----------
    source : str
        What was read: a file path, ``<stdin>`` or an option name.
    field : str or None
        The field or option at fault, e.g. ``camera.focal_length_px``.
    problem : str
        What is wrong with it, in a few words.
    """

    exit_code = 2

    def __init__(self, source: str, field: str | None, problem: str):
        self.source = str(source)
        self.field = field
        self.problem = problem
        where = self.source if field is None else f"{self.source}: {field}"
        super().__init__(f"{where}: {problem}")


class DatabaseMismatchError(BadInputError):
    """A database built for another catalog, field of view or camera."""


class SolveError(StartrackError):
    """A computation that could not produce a result (not a bad input)."""
