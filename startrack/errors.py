"""The exceptions startrack raises.

Library code raises these and never exits or prints.  The command line turns
:class:`BadInputError` into exit status 2 and every other
:class:`StartrackError` into exit status 1, each as a single line.

Library code names *parameters* (``fov_deg``), never command-line flags: a
bad argument raises :class:`ParameterError`, whose ``field`` is the parameter's
name, and the command line maps that name to its flag.
"""
from __future__ import annotations

__all__ = ["BadInputError", "DatabaseMismatchError", "ParameterError", "StartrackError", "input_of", "note_input",
           "reading"]


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


# -- where an unexpected exception happened ------------------------------------------------------------------------
#
# "Every internal error names the file and the field": readers and per-frame loops say what input they are reading
# (``with reading(path, field)``) or which one they handed out last (``note_input``); an exception that is no
# StartrackError (a bug, or input no check foresaw) leaving a ``reading`` block is marked with it, and the command
# line's last handler names it (``startrack.cli.options.handle_errors``).  Library code raises as before.

_last_input: list = [None]


class reading:  # noqa: N801 - used as a context manager, like contextlib's
    """Mark what input is read (or processed) in a block; set ``.field`` as reading goes on.

    An unexpected exception (not a :class:`StartrackError`) leaving the block keeps the innermost
    ``(source, field)`` as ``exc.startrack_input`` (:func:`input_of`).  Nothing is caught.

    Example: ``with reading(path) as where: where.field = "ra"; ra = h5["ra"][()]``.
    """

    def __init__(self, source, field: str | None = None):
        self.source, self.field = str(source), field

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb):
        if exc is not None and isinstance(exc, Exception) and not isinstance(exc, StartrackError) \
                and getattr(exc, "startrack_input", None) is None:
            try:
                exc.startrack_input = (self.source, self.field)
            except (AttributeError, TypeError):  # an exception type without a __dict__
                pass
        return False


def note_input(source: str | None) -> None:
    """Say which input (a file, ``FILE:LINE`` of a frame) is being processed now (``None``: none)."""
    _last_input[0] = source


def input_of(exc: BaseException) -> tuple[str, str | None, bool] | None:
    """``(source, field, read)`` of the input an unexpected exception happened on, or None.

    ``read`` is True when the exception left a :class:`reading` block (it happened reading that input), False
    when only :func:`note_input` named what was being processed.  Follows ``__cause__``/``__context__``.
    """
    seen = set()
    e = exc
    while e is not None and id(e) not in seen:
        where = getattr(e, "startrack_input", None)
        if where is not None:
            return where[0], where[1], True
        seen.add(id(e))
        e = e.__cause__ or e.__context__
    if _last_input[0] is not None:
        return _last_input[0], None, False
    return None
