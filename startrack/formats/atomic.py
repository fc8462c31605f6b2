"""Atomic output files: write beside the destination, then rename into place."""
from __future__ import annotations

import contextlib
import os
import tempfile

from startrack.errors import BadInputError

__all__ = ["atomic_path", "atomic_open", "check_writable"]


def check_writable(path: str) -> None:
    """Refuse early (``BadInputError``) an output whose directory cannot be written."""
    directory = os.path.dirname(os.path.abspath(path)) or "."
    if os.path.isdir(path):
        raise BadInputError(path, None, "is a directory, expected a file name")
    if not os.path.isdir(directory):
        raise BadInputError(path, None, f"cannot write: directory {directory} does not exist")
    if not os.access(directory, os.W_OK | os.X_OK):
        raise BadInputError(path, None, f"cannot write: directory {directory} is not writable")


@contextlib.contextmanager
def atomic_path(path: str, suffix: str | None = None):
    """Yield a temporary path beside ``path``; rename it onto ``path`` on success.

    On any exception the temporary file is removed and ``path`` is untouched.
    ``suffix`` (default: ``path``'s own extension) lets writers that choose a
    format by extension (OpenCV, astropy) see the right one.
    """
    check_writable(path)
    directory = os.path.dirname(os.path.abspath(path))
    if suffix is None:
        suffix = os.path.splitext(path)[1]
    fd, tmp = tempfile.mkstemp(prefix="." + os.path.basename(path) + ".", suffix=".part" + suffix,
                               dir=directory)
    os.close(fd)
    try:
        yield tmp
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.remove(tmp)
        raise


@contextlib.contextmanager
def atomic_open(path: str, mode: str = "w", **kwargs):
    """Open a temporary file beside ``path`` and rename it onto ``path`` on success."""
    with atomic_path(path) as tmp:
        with open(tmp, mode, **kwargs) as handle:
            yield handle
