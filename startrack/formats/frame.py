"""Frame documents (``startrack.frame/1``): read, validate and write.

A frame document is one JSON object per image.  Many frames travel as JSON
Lines.  :func:`read_frames` accepts a single (possibly pretty-printed) object, a
JSON array of objects, or JSON Lines, from a file or from standard input
(``"-"``), and yields one :class:`FrameRecord` per frame, so a batch can go on
past a frame that cannot be parsed.
"""
from __future__ import annotations

import io
import json
import math
import os
import sys
from dataclasses import dataclass

import numpy as np

from startrack.errors import BadInputError
from startrack.formats.atomic import atomic_path, check_writable

__all__ = [
    "FRAME_FORMAT",
    "FrameRecord",
    "FrameWriter",
    "check_format_tag",
    "dumps_frame",
    "read_frames",
    "read_json_file",
    "validate_frame",
    "validate_stars",
]

FRAME_FORMAT = "startrack.frame/1"


def check_format_tag(doc: dict, expected: str, source: str) -> None:
    """Refuse a document whose ``format`` is missing, another family or major version."""
    tag = doc.get("format") if isinstance(doc, dict) else None
    if tag is None:
        raise BadInputError(source, "format", f"is missing (expected {expected!r})")
    if not isinstance(tag, str):
        raise BadInputError(source, "format", f"must be a string, got {type(tag).__name__}")
    family, _, major = expected.partition("/")
    tag_family, _, tag_major = tag.partition("/")
    if tag_family != family:
        raise BadInputError(source, "format", f"is {tag!r}, expected {expected!r}")
    if tag_major.split(".")[0] != major:
        raise BadInputError(source, "format", f"major version {tag!r} is not supported (expected {expected!r})")


def _require_number(value, source, field, positive=False, allow_none=False):
    if value is None and allow_none:
        return None
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise BadInputError(source, field, f"must be a number, got {json.dumps(value)[:40]}")
    if not math.isfinite(value):
        raise BadInputError(source, field, f"must be a finite number, got {value}")
    if positive and value <= 0:
        raise BadInputError(source, field, f"must be positive, got {value:g}")
    return float(value)


def validate_stars(doc: dict, source: str) -> None:
    """Check the ``stars`` section: a list of objects with finite ``x``, ``y``, ``flux``."""
    stars = doc.get("stars")
    if stars is None:
        raise BadInputError(source, "stars", "is missing")
    if not isinstance(stars, list):
        raise BadInputError(source, "stars", "must be a list")
    for i, star in enumerate(stars):
        if not isinstance(star, dict):
            raise BadInputError(source, f"stars[{i}]", "must be an object")
        for name in ("x", "y"):
            if name not in star:
                raise BadInputError(source, f"stars[{i}].{name}", "is missing")
            _require_number(star[name], source, f"stars[{i}].{name}")
        if "flux" in star:
            _require_number(star["flux"], source, f"stars[{i}].flux")


def validate_frame(doc, source: str, need: tuple[str, ...] = ()) -> dict:
    """Validate a frame document and the sections a stage needs.

    Parameters
    ----------
    doc : object
        The parsed JSON value.
    source : str
        Where it came from (``file:line``), for messages.
    need : tuple of str
        Sections that must be present and valid: any of ``"image"``,
        ``"camera"``, ``"stars"``, ``"truth"``, ``"identification"``.

    Returns
    -------
    dict
        ``doc`` itself.

    Raises
    ------
    BadInputError
        Naming the source, the field and the problem.
    """
    if not isinstance(doc, dict):
        raise BadInputError(source, None, "a frame document must be a JSON object")
    check_format_tag(doc, FRAME_FORMAT, source)
    if "camera" in need:
        from startrack.camera import Camera

        if "camera" not in doc:
            raise BadInputError(source, "camera", "is missing (give --camera camera.json or a frame with a camera section)")
        Camera.from_dict(doc["camera"], source)
    if "image" in need:
        image = doc.get("image")
        if not isinstance(image, dict):
            raise BadInputError(source, "image", "is missing")
        for name in ("width", "height"):
            _require_number(image.get(name), source, f"image.{name}", positive=True)
    if "stars" in need:
        validate_stars(doc, source)
    if "truth" in need:
        truth = doc.get("truth")
        if not isinstance(truth, dict):
            raise BadInputError(source, "truth", "is missing")
        q = truth.get("quaternion")
        if not isinstance(q, list) or len(q) != 4:
            raise BadInputError(source, "truth.quaternion", "must be a list of 4 numbers")
        for i, v in enumerate(q):
            _require_number(v, source, f"truth.quaternion[{i}]")
    if "identification" in need:
        ident = doc.get("identification")
        if not isinstance(ident, dict):
            raise BadInputError(source, "identification", "is missing")
        if ident.get("status") not in ("ok", "failed"):
            raise BadInputError(source, "identification.status", "must be 'ok' or 'failed'")
        matches = ident.get("matches", [])
        if not isinstance(matches, list):
            raise BadInputError(source, "identification.matches", "must be a list")
        n_stars = len(doc.get("stars") or [])
        for i, m in enumerate(matches):
            if not isinstance(m, dict) or "star" not in m or "id" not in m:
                raise BadInputError(source, f"identification.matches[{i}]", "needs 'star' and 'id'")
            s = m["star"]
            if isinstance(s, bool) or not isinstance(s, int) or not 0 <= s < n_stars:
                raise BadInputError(source, f"identification.matches[{i}].star",
                                    f"must index into stars (0..{n_stars - 1}), got {s!r}")
    return doc


@dataclass
class FrameRecord:
    """One frame read from a stream: its parsed document, or why it could not be read."""

    source: str
    doc: dict | None
    error: BadInputError | None = None


def _reject_constant(name):
    raise ValueError(f"{name} is not valid JSON")


def _loads(text: str):
    return json.loads(text, parse_constant=_reject_constant)


def _open_text(path: str):
    if path == "-":
        return sys.stdin, "<stdin>"
    if not os.path.exists(path):
        raise BadInputError(path, None, "no such file")
    if os.path.isdir(path):
        raise BadInputError(path, None, "is a directory")
    try:
        return open(path, encoding="utf-8"), path
    except OSError as exc:
        raise BadInputError(path, None, f"cannot read: {exc.strerror}") from None


def read_json_file(path: str) -> dict:
    """Read one JSON object from a file (e.g. a camera file); one-line errors."""
    handle, name = _open_text(path)
    try:
        text = handle.read()
    except UnicodeDecodeError:
        raise BadInputError(name, None, "is not a UTF-8 text file") from None
    finally:
        if handle is not sys.stdin:
            handle.close()
    try:
        doc = _loads(text)
    except ValueError as exc:
        raise BadInputError(name, None, f"is not valid JSON ({exc})") from None
    if not isinstance(doc, dict):
        raise BadInputError(name, None, "must hold a JSON object")
    return doc


def read_frames(path: str):
    """Yield a :class:`FrameRecord` for every frame in a file or on stdin (``"-"``).

    JSON Lines are read line by line (a stream is processed as it arrives); a
    text whose first line is not a complete JSON value is parsed whole, as one
    object or an array of objects.  A line that is not valid JSON yields a record
    with ``error`` set, and reading goes on.
    """
    handle, name = _open_text(path)
    try:
        first = ""
        first_no = 0
        for first_no, line in enumerate(handle, start=1):
            if line.strip():
                first = line
                break
        if not first:
            return
        try:
            value = _loads(first)
            whole = None
        except ValueError:
            whole = first + handle.read()
        if whole is not None:
            try:
                value = _loads(whole)
            except ValueError as exc:
                yield FrameRecord(name, None, BadInputError(name, None, f"is not valid JSON or JSON Lines ({exc})"))
                return
            items = value if isinstance(value, list) else [value]
            for i, item in enumerate(items):
                src = name if len(items) == 1 else f"{name}[{i}]"
                yield FrameRecord(src, item)
            return
        yield FrameRecord(f"{name}:{first_no}", value)
        for line_no, line in enumerate(handle, start=first_no + 1):
            if not line.strip():
                continue
            src = f"{name}:{line_no}"
            try:
                yield FrameRecord(src, _loads(line))
            except ValueError as exc:
                yield FrameRecord(src, None, BadInputError(src, None, f"is not valid JSON ({exc})"))
    except UnicodeDecodeError:
        yield FrameRecord(name, None, BadInputError(name, None, "is not a UTF-8 text file"))
    finally:
        if handle is not sys.stdin:
            handle.close()


def _to_json(value):
    if isinstance(value, dict):
        return {str(k): _to_json(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_to_json(v) for v in value]
    if isinstance(value, np.ndarray):
        return _to_json(value.tolist())
    if isinstance(value, (np.integer,)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        value = float(value)
        return value if math.isfinite(value) else None
    if isinstance(value, np.bool_):
        return bool(value)
    return value


def dumps_frame(doc: dict) -> str:
    """One compact JSON line; numpy values converted, non-finite floats as ``null``."""
    return json.dumps(_to_json(doc), separators=(",", ":"), allow_nan=False)


class FrameWriter:
    """Write frame documents as JSON Lines to a file (atomically) or stdout (``"-"``).

    Use as a context manager.  On stdout each frame is flushed as it is written,
    so pipelines stream.  A file is written to a temporary name and renamed into
    place only when the ``with`` block ends without an exception.
    """

    def __init__(self, path: str = "-"):
        self.path = path
        self.count = 0
        self._ctx = None
        self._handle: io.TextIOBase | None = None
        if path != "-":
            check_writable(path)

    def __enter__(self):
        if self.path == "-":
            self._handle = sys.stdout
        else:
            self._ctx = atomic_path(self.path)
            tmp = self._ctx.__enter__()
            self._handle = open(tmp, "w", encoding="utf-8")
        return self

    def write(self, doc: dict) -> None:
        self._handle.write(dumps_frame(doc) + "\n")
        if self.path == "-":
            self._handle.flush()
        self.count += 1

    def __exit__(self, exc_type, exc, tb):
        if self.path == "-":
            return False
        self._handle.close()
        return self._ctx.__exit__(exc_type, exc, tb)
