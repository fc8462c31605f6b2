"""Frame documents (``startrack.frame/1``): read, validate and write.

A frame document is one JSON object per image.  Many frames travel as JSON
Lines.  :func:`read_frames` accepts a single (possibly pretty-printed) object, a
JSON array of objects, or JSON Lines, from a file or from standard input
(``"-"``), and yields one :class:`FrameRecord` per frame, so a batch can go on
past a frame that cannot be parsed.
"""
from __future__ import annotations

import contextlib
import io
import json
import math
import os
import sys
from dataclasses import dataclass

import numpy as np

from startrack.errors import BadInputError, note_input
from startrack.formats.atomic import (
    check_writable,
    is_special,
    output_target,
    register_input,
    write_error,
)
from startrack.records import FRAME_FORMAT  # the tag lives with the record schema (records write frames too)

__all__ = [
    "FRAME_FORMAT",
    "FrameRecord",
    "FrameWriter",
    "validate_attitude",
    "check_format_tag",
    "dumps_frame",
    "frame_key",
    "frame_line",
    "read_finished",
    "read_frames",
    "read_json_file",
    "resolve_path",
    "validate_frame",
    "validate_stars",
]


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


def validate_attitude(doc: dict, source: str) -> np.ndarray:
    """The rotation matrix of a solved ``attitude`` section, checked: its ``quaternion`` a unit quaternion, its
    ``dcm`` a rotation, and the two the same attitude (tolerance 1e-6); ``BadInputError`` names the field."""
    from startrack.rotations import quaternion_to_dcm

    att = doc.get("attitude") if isinstance(doc.get("attitude"), dict) else {}
    q, dcm = att.get("quaternion"), att.get("dcm")
    if q is None and dcm is None:
        raise BadInputError(source, "attitude.quaternion", "is missing")
    out = None
    if q is not None:
        if not isinstance(q, list) or len(q) != 4:
            raise BadInputError(source, "attitude.quaternion", "must be a list of 4 numbers")
        for i, v in enumerate(q):
            _require_number(v, source, f"attitude.quaternion[{i}]")
        norm = math.hypot(*(float(v) for v in q))       # no overflow for huge components
        if abs(norm - 1.0) > 1e-6:
            raise BadInputError(source, "attitude.quaternion", f"is not a unit quaternion (norm {norm:.6g})")
        out = quaternion_to_dcm(np.asarray(q, dtype=float))
    if dcm is not None:
        try:
            m = np.asarray(dcm, dtype=float)
        except (TypeError, ValueError):
            m = np.zeros(0)
        if m.shape != (3, 3) or not np.all(np.isfinite(m)):
            raise BadInputError(source, "attitude.dcm", "must be 3 rows of 3 finite numbers")
        if np.abs(m @ m.T - np.eye(3)).max() > 1e-6 or np.linalg.det(m) < 0:
            raise BadInputError(source, "attitude.dcm", "is not a rotation matrix")
        if out is not None and np.abs(m - out).max() > 1e-6:
            raise BadInputError(source, "attitude.dcm", "and attitude.quaternion are not the same attitude")
        out = m
    return out


#: The frame document's sections (``docs/formats.md``) and their JSON types.
SECTION_TYPES = {"image": dict, "observer": dict, "camera": dict, "truth": dict, "stars": list, "centroid": dict,
                 "identification": dict, "attitude": dict, "track": dict, "solve": dict, "render": dict}


def _json_type(value) -> str:
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "true/false"
    if isinstance(value, (int, float)):
        return "a number"
    return {str: "a string", list: "a list", dict: "an object"}.get(type(value), type(value).__name__)


def read_frame_image(doc: dict, source: str, why: str = "this command needs the image", whole_dn: bool = False):
    """The image a frame document names (``image.path``), read by :func:`startrack.imageio.read_image`
    (``whole_dn``: an 8- or 16-bit file's pixels as decoded, not float32).

    Every problem names the document and the field: ``FILE:LINE: image.path: sky.png: no such file``.
    """
    from startrack.imageio import read_image

    image = doc.get("image") if isinstance(doc, dict) else None
    path = image.get("path") if isinstance(image, dict) else None
    if path is None or path == "":
        raise BadInputError(source, "image.path", f"is missing: {why}")
    if not isinstance(path, str):
        raise BadInputError(source, "image.path", f"must be a file name, got {_json_type(path)}")
    try:
        return read_image(path, whole_dn=whole_dn)
    except BadInputError as exc:
        if exc.source != path:
            raise
        raise BadInputError(source, "image.path", f"{path}: {exc.problem}") from None


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
    # Every section, needed or not, has its JSON type (a stage that passes one on reads it too: `"image": 7` must
    # be named here, not fail as an internal error where some stage first looks inside it).
    for name, value in doc.items():
        kind = SECTION_TYPES.get(name)
        if kind is not None and not isinstance(value, kind):
            expected = "a JSON object" if kind is dict else "a JSON list"
            raise BadInputError(source, name, f"must be {expected}, got {_json_type(value)}")
    if "camera" in need:
        from startrack.camera import Camera

        if "camera" not in doc:
            raise BadInputError(source, "camera", "is missing (give a camera file or a frame with a camera section)")
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
            ident_id = m["id"]
            if isinstance(ident_id, bool) or not isinstance(ident_id, int):
                raise BadInputError(source, f"identification.matches[{i}].id",
                                    f"must be an integer catalog id, got {json.dumps(ident_id)[:40]}")
            s = m["star"]
            if isinstance(s, bool) or not isinstance(s, int) or not 0 <= s < n_stars:
                raise BadInputError(source, f"identification.matches[{i}].star",
                                    f"must index into stars (0..{n_stars - 1}), got {s!r}")
    elif isinstance(doc.get("identification"), dict) and isinstance(doc["identification"].get("matches"), list):
        for i, m in enumerate(doc["identification"]["matches"]):
            if isinstance(m, dict) and "id" in m and (isinstance(m["id"], bool) or not isinstance(m["id"], int)):
                raise BadInputError(source, f"identification.matches[{i}].id",
                                    f"must be an integer catalog id, got {json.dumps(m['id'])[:40]}")
    return doc


@dataclass
class FrameRecord:
    """One frame read from a stream: its parsed document, or why it could not be read.

    ``base_dir`` is the directory relative paths inside the document resolve
    against: the document file's own directory, or ``None`` (the current
    directory) for standard input.
    """

    source: str
    doc: dict | None
    error: BadInputError | None = None
    base_dir: str | None = None


def _reject_constant(name):
    raise ValueError(f"{name} is not valid JSON")


MAX_JSON_DEPTH = 64


def _unique_keys(pairs):
    """A JSON object whose keys are unique: a repeated key (two ``"stars"``) is refused, never last-one-wins."""
    out = dict(pairs)
    if len(out) != len(pairs):
        seen = set()
        for key, _ in pairs:
            if key in seen:
                raise ValueError(f"duplicate key {key!r} in one object")
            seen.add(key)
    return out


def _loads(text: str):
    try:
        value = json.loads(text, parse_constant=_reject_constant, object_pairs_hook=_unique_keys)
    except RecursionError:
        raise ValueError("nested too deeply") from None
    _check_depth(value)
    return value


def _check_depth(value, limit: int = MAX_JSON_DEPTH) -> None:
    """Refuse JSON nested deeper than ``limit`` (no frame document needs more than a few levels)."""
    stack = [(value, 1)]
    while stack:
        item, depth = stack.pop()
        if depth > limit:
            raise ValueError(f"nested more than {limit} levels deep")
        if isinstance(item, dict):
            stack.extend((v, depth + 1) for v in item.values() if isinstance(v, (dict, list)))
        elif isinstance(item, list):
            stack.extend((v, depth + 1) for v in item if isinstance(v, (dict, list)))


def _open_text(path: str):
    if path == "-":
        if sys.stdin is None or sys.stdin.closed:
            raise BadInputError("<stdin>", None, "is closed: give an input file or pipe frame documents in")
        return sys.stdin, "<stdin>"
    if not os.path.exists(path):
        raise BadInputError(path, None, "no such file")
    if os.path.isdir(path):
        raise BadInputError(path, None, "is a directory")
    register_input(path)
    try:
        return open(path, encoding="utf-8"), path
    except OSError as exc:
        raise BadInputError(path, None, f"cannot read: {exc.strerror}") from None


def resolve_path(path: str, base_dir: str | None) -> str:
    """Resolve a path written inside a frame document.

    Absolute paths are used as they are.  A relative path resolves against the
    document's own directory ``base_dir``; if nothing exists there but the path
    exists relative to the current directory (documents written to stdout by
    ``render`` name paths relative to where it ran), that one is used.
    """
    if not isinstance(path, str) or os.path.isabs(path) or not base_dir:
        return path
    beside = os.path.join(base_dir, path)
    if os.path.exists(beside) or not os.path.exists(path):
        return os.path.normpath(beside)
    return path


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
        for first_no, line in enumerate(handle, start=1):  # noqa: B007 - used after the loop
            if line.strip():
                first = line
                break
        if not first:
            return
        base = None if path == "-" else os.path.dirname(os.path.abspath(path))
        try:
            value = _loads(first)
            whole = None
        except ValueError:
            whole = first + handle.read()
        if whole is not None:
            try:
                value = _loads(whole)
            except ValueError as exc:
                yield from _lines_after_bad_first(whole, first_no, name, base, exc)
                return
            items = value if isinstance(value, list) else [value]
            for i, item in enumerate(items):
                src = name if len(items) == 1 else f"{name}[{i}]"
                note_input(src)
                yield FrameRecord(src, item, None, base)
            return
        note_input(f"{name}:{first_no}")
        yield FrameRecord(f"{name}:{first_no}", value, None, base)
        for line_no, line in enumerate(handle, start=first_no + 1):
            if not line.strip():
                continue
            src = f"{name}:{line_no}"
            note_input(src)   # what an unexpected exception while it is processed is named by
            try:
                yield FrameRecord(src, _loads(line), None, base)
            except ValueError as exc:
                yield FrameRecord(src, None, _bad_line(src, line, exc), base)
    except UnicodeDecodeError:
        yield FrameRecord(name, None, BadInputError(name, None, "is not a UTF-8 text file"))
    except OSError as exc:
        yield FrameRecord(name, None, BadInputError(name, None, f"cannot read: {exc.strerror or exc}"))
    finally:
        if handle is not sys.stdin:
            handle.close()


def _bad_line(src: str, line: str, exc: ValueError) -> BadInputError:
    """The error of a line that is not JSON: ``(truncated?)`` when it is the text's last, cut without its newline."""
    if not line.endswith("\n"):
        return BadInputError(src, None, "is not valid JSON (truncated?)")
    return BadInputError(src, None, f"is not valid JSON ({exc})")


def _lines_after_bad_first(text: str, first_no: int, name: str, base, exc):
    """A text whose first line and whole are not JSON: JSON Lines with a bad first line, or one broken document.

    If any later line is a JSON value on its own, the text is JSON Lines: the
    first line (and any other bad line) becomes a bad-input record and the good
    frames go on.  Otherwise it is one broken (pretty-printed) document: one record.
    """
    rows = text.split("\n")
    parsed = []
    any_good = False
    for k, line in enumerate(rows):
        if not line.strip():
            continue
        src = f"{name}:{first_no + k}"
        if k > 0 and not any_good:
            try:
                _loads(line)
                any_good = True
            except ValueError:
                pass
        try:
            value = _loads(line)
            parsed.append(FrameRecord(src, value, None, base))
        except ValueError as line_exc:
            ended = line + "\n" if k < len(rows) - 1 else line     # the text's last row has no newline
            parsed.append(FrameRecord(src, None, _bad_line(src, ended, line_exc), base))
    if any_good:
        yield from parsed
    else:
        yield FrameRecord(name, None, BadInputError(name, None, f"is not valid JSON or JSON Lines ({exc})"), base)


_AS_IS = frozenset((str, int, bool, type(None)))     # JSON values as they are (the most common by far)


def _json_key(key) -> str:
    """A dictionary key as a string: ``True``, ``False`` and ``None`` as the JSON encoder writes them (so that a
    document gives one line whether or not :func:`dumps_frame` copies it through :func:`_to_json`), others by
    ``str``."""
    if key is True or key is False:
        return "true" if key else "false"
    return "null" if key is None else str(key)


def _to_json(value):
    kind = type(value)
    if kind in _AS_IS:
        return value
    if kind is float:
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k if type(k) is str else _json_key(k): _to_json(v) for k, v in value.items()}
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


def _json_default(value):
    """:func:`dumps_frame`'s encoder's hook: a NumPy array or scalar as :func:`_to_json` converts it (anything else
    is not JSON: a ``TypeError``, as before)."""
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, np.floating):
        return float(value)
    if isinstance(value, np.bool_):
        return bool(value)
    raise TypeError(f"Object of type {type(value).__name__} is not JSON serializable")


_ENCODE = json.JSONEncoder(separators=(",", ":"), allow_nan=False, default=_json_default).encode


def dumps_frame(doc: dict) -> str:
    """One compact JSON line of ASCII characters; numpy values converted, non-finite floats as ``null``.

    The document goes straight to orjson (:func:`_orjson`; NumPy values through :func:`_json_default`, as below),
    some twenty times faster than the standard library's encoder on a solved frame's document.  What orjson does not
    take (a key that is not a string, an integer beyond 64 bits), or writes otherwise (a character beyond ASCII,
    which the line escapes), goes to the standard library's encoder; only a document that holds a non-finite float
    (that encoder refuses it) or a key it does not take is first copied by :func:`_to_json`.  The same JSON values
    either way: orjson writes a float's shortest round-trip digits as ``repr`` does, its exponent without padding
    (``1e-6`` for ``1e-06``).  (Keys that collide written as strings, ``1`` and ``"1"``, make no JSON object: the
    encoders write both.)"""
    fast = _ORJSON[0]
    if fast is None:
        fast = _orjson()
    if fast:
        try:
            line = fast(doc)
        except TypeError:       # (orjson.JSONEncodeError is one)
            pass
        else:
            if line.isascii():
                return line.decode("ascii")
    try:
        return _ENCODE(doc)
    except (ValueError, TypeError):
        return json.dumps(_to_json(doc), separators=(",", ":"), allow_nan=False)


_ORJSON: list = [None]      # orjson's encoder as dumps_frame calls it, False without orjson; None: not looked up yet


def _orjson():
    """orjson's ``dumps`` as :func:`dumps_frame` calls it, imported at the first document (a process that writes none
    never pays its ~1 ms), or False when orjson is not installed.  Dataclasses and datetimes are passed to
    :func:`_json_default`, which refuses them as the standard library's encoder does: orjson would write them."""
    try:
        import orjson
    except ImportError:
        _ORJSON[0] = False
        return False
    import functools

    _ORJSON[0] = functools.partial(orjson.dumps, default=_json_default,
                                   option=orjson.OPT_PASSTHROUGH_DATACLASS | orjson.OPT_PASSTHROUGH_DATETIME)
    return _ORJSON[0]


def frame_line(doc: dict, base_dir: str | None = None) -> str:
    """The line a :class:`FrameWriter` whose :attr:`~FrameWriter.base_dir` is ``base_dir`` writes for ``doc``
    (newline included)."""
    if base_dir is not None:
        doc = relative_image_path(doc, base_dir)
    return dumps_frame(doc) + "\n"


def frame_key(doc, base_dir: str | None = None) -> str | None:
    """The identity of a frame, for ``--resume``: its image path and render seed, time and frame number.

    With ``base_dir`` (the directory the document's relative paths resolve against, :func:`resolve_path`)
    the image path is made absolute, so a document written beside its output (paths relative to that
    directory) and the same frame named from the current directory have one key.
    ``None`` when the document carries none of them (then frames are matched by position).
    """
    if not isinstance(doc, dict):
        return None
    image = doc.get("image") if isinstance(doc.get("image"), dict) else {}
    render = doc.get("render") if isinstance(doc.get("render"), dict) else {}
    path = image.get("path")
    if base_dir is not None and isinstance(path, str) and path and path != "-":
        path = os.path.abspath(resolve_path(path, base_dir))
    parts = [path, image.get("time"), render.get("frame_seed"), doc.get("frame")]
    if all(p is None for p in parts):
        return None
    return json.dumps(parts, default=str)


def _check_finished(doc, section: str, source: str) -> None:
    """Refuse a line of a ``--resume`` output that is not this command's result (issue 41: a ``centroid``
    document counted as a solved image)."""
    if not isinstance(doc, dict) or not str(doc.get("format", "")).startswith("startrack.frame/"):
        raise BadInputError(source, "format", "is not a startrack frame document: a resumed batch appends only to this "
                                              "command's own output")
    sec = doc.get(section)
    if not isinstance(sec, dict):
        raise BadInputError(source, section, "is missing: the document is another command's result, not this "
                                             "command's: a resumed batch appends only to this command's own output")
    status = sec.get("status")
    if status is not None and status not in ("ok", "failed"):
        raise BadInputError(source, f"{section}.status", f"is {status!r}, expected 'ok' or 'failed'")


def relative_image_path(doc, base_dir: str):
    """``doc`` with a relative ``image.path`` (relative to the current directory) rewritten relative to
    ``base_dir``, the directory of the document's own file (docs/formats.md: paths inside a document resolve
    against its directory).  Absolute paths and ``-`` stay as they are; ``doc`` itself is not changed."""
    image = doc.get("image") if isinstance(doc, dict) else None
    path = image.get("path") if isinstance(image, dict) else None
    if not isinstance(path, str) or not path or path == "-" or os.path.isabs(path):
        return doc
    try:
        rel = os.path.relpath(os.path.abspath(path), base_dir)
    except ValueError:          # another drive (Windows): no relative path exists
        rel = os.path.abspath(path)
    if rel == path:
        return doc
    return {**doc, "image": {**image, "path": rel}}


def read_finished(path: str, section: str | None = None, base_dir: str | None = None, retry_failed: bool = False):
    """Read the complete frame documents of a batch output, for ``--resume``.

    Returns ``(keys, n_unkeyed, good_bytes, failed_lines)``: a multiset (dict key -> count) of
    :func:`frame_key` of every complete line, the number of complete lines
    without a key, the byte length of the complete lines, and (with ``retry_failed``) the
    ``(line number, key)`` of every line whose ``section`` has status ``failed``: those are not counted as done.  A last line
    without its newline, or one that is not valid JSON (a write cut short by
    ``kill -9``), is not counted: the writer truncates the file to
    ``good_bytes`` before appending.  ``base_dir`` makes the keys' image paths absolute (:func:`frame_key`).
    With ``section`` (the command's own section,
    ``"solve"``), every complete line must be a frame document holding it with a
    status ``ok`` or ``failed`` (or none): else :class:`BadInputError` names the line.
    """
    keys: dict[str, int] = {}
    n_unkeyed = 0
    good = 0
    failed: list[tuple[int, str | None]] = []
    if not os.path.exists(path) or is_special(path):
        return keys, n_unkeyed, good, failed
    with open(path, "rb") as handle:
        for line_no, raw in enumerate(handle, start=1):
            if not raw.endswith(b"\n"):
                break
            if raw.strip():
                try:
                    doc = _loads(raw.decode("utf-8"))
                except (ValueError, UnicodeDecodeError):
                    if handle.read(1):
                        # not the last line: no write cut short leaves this, and cutting the file here would
                        # destroy what follows (a file that is not this command's output)
                        raise BadInputError(f"{path}:{line_no}", None, "is not a JSON frame document and lines "
                                            "follow it: not a batch output to resume (the file is left as it "
                                            "is)") from None
                    break
                if section is not None:
                    _check_finished(doc, section, f"{path}:{line_no}")
                key = frame_key(doc, base_dir)
                if retry_failed and section is not None and doc[section].get("status") == "failed":
                    failed.append((line_no, key))
                else:
                    if key is None:
                        n_unkeyed += 1
                    else:
                        keys[key] = keys.get(key, 0) + 1
            good += len(raw)
    return keys, n_unkeyed, good, failed


class FrameWriter:
    """Write frame documents as JSON Lines, one line per frame, flushed as it is written.

    * ``"-"``: standard output (refused with one line if it is closed).
    * A special file (``/dev/null``, a FIFO): written directly, never replaced.
    * A regular file (a symbolic link is written through to its target): a
      journal.  It is opened at the first frame (an input refused before any
      frame leaves an existing file untouched), each line is appended and
      flushed as its frame finishes, and the file is ``fsync``-ed at the end, so
      ``kill -9`` loses only the frames in flight.  With ``resume=True`` the
      complete lines already there are kept (a cut-off last line is dropped) and
      new frames are appended; :attr:`done` holds their :func:`frame_key`.  With
      ``section`` the lines kept must be this command's results (:func:`read_finished`).
      A relative ``image.path`` (relative to the current directory) is written relative
      to the file's directory (:func:`relative_image_path`), as docs/formats.md says, so
      the document can be read from anywhere; standard output keeps it as it is.

    Use as a context manager.
    """

    def __init__(self, path: str = "-", resume: bool = False, section: str | None = None, retry_failed: bool = False):
        self.path = path
        #: ``retry_failed``: the failed documents of the file, ``(line number, key)``; those of the frames this
        #: run does again (:meth:`skip` says False for them) are :attr:`retried` and leave the file
        self.failed_lines: list[tuple[int, str | None]] = []
        self.retried: list[int] = []
        self.count = 0
        self.resume = resume
        self._handle: io.TextIOBase | None = None
        self._own = False
        self.done: dict[str, int] = {}
        self.done_unkeyed = 0
        self._good_bytes = 0
        #: the directory relative image paths are written against (None: as given, for stdout and devices)
        self.base_dir: str | None = None
        if path == "-":
            if sys.stdout is None:
                raise BadInputError("<stdout>", None, "is closed: give -o FILE or let the output go somewhere")
            return
        check_writable(path)
        self.target = output_target(path)
        self.special = is_special(self.target)
        if not self.special:
            self.base_dir = os.path.dirname(os.path.abspath(path))
        if retry_failed and not (resume and section):
            raise ValueError("retry_failed needs resume and a section")      # a caller's bug, not the input's
        if resume and not self.special:
            self.done, self.done_unkeyed, self._good_bytes, self.failed_lines = read_finished(
                self.target, section, self.base_dir, retry_failed)

    def skip(self, doc) -> bool:
        """True (and the frame counted as done) if ``doc``'s frame is already in the output (``--resume``)."""
        if not self.resume:
            return False
        key = frame_key(doc, os.getcwd() if self.base_dir is not None else None)
        if key is None:
            if self.done_unkeyed > 0:
                self.done_unkeyed -= 1
                return True
        elif self.done.get(key, 0) > 0:
            self.done[key] -= 1
            return True
        # a failed document of this frame is done again: it leaves the file when the first line is written
        # (so every frame to retry must be asked about before the first write)
        for i, (line_no, failed_key) in enumerate(self.failed_lines):
            if failed_key == key:
                if self._handle is not None:
                    raise RuntimeError("FrameWriter.skip after the first write with retry_failed")
                self.retried.append(line_no)
                del self.failed_lines[i]
                break
        return False

    @property
    def n_done(self) -> int:
        return sum(self.done.values()) + self.done_unkeyed

    def _open(self):
        if self.path == "-":
            self._handle = sys.stdout
            return
        check_writable(self.path)  # again: an input opened since __init__ may be this file
        try:
            if self.special:
                self._handle = open(self.target, "w", encoding="utf-8")  # noqa: SIM115 - a journal kept open
            elif self.resume and os.path.exists(self.target):
                if self.retried:
                    self._drop_failed()
                self._handle = open(self.target, "r+", encoding="utf-8")  # noqa: SIM115 - a journal kept open
                self._handle.truncate(self._good_bytes)
                self._handle.seek(self._good_bytes)
            else:
                self._handle = open(self.target, "w", encoding="utf-8")  # noqa: SIM115 - a journal kept open
        except OSError as exc:
            raise write_error(self.path, exc) from None
        self._own = True

    def _drop_failed(self) -> None:
        """Replace the file, atomically, by its complete lines without the failed ones (``retry_failed``):
        their new documents are appended as they are solved again.  A run cut short after this has lost
        nothing: those images are simply not in the file, and the next ``--resume`` does them."""
        from startrack.formats.atomic import atomic_path

        drop = set(self.retried)
        kept = 0
        with atomic_path(self.path, suffix=".jsonl") as tmp:
            with open(self.target, "rb") as src, open(tmp, "wb") as dst:
                seen = 0
                for line_no, raw in enumerate(src, start=1):
                    seen += len(raw)
                    if seen > self._good_bytes:
                        break
                    if line_no not in drop:
                        dst.write(raw)
                        kept += len(raw)
        self._good_bytes = kept

    def __enter__(self):
        return self

    def write(self, doc: dict) -> None:
        self.write_line(frame_line(doc, self.base_dir))

    def write_line(self, line: str) -> None:
        """Write one document already serialized by :func:`frame_line` with this writer's :attr:`base_dir`
        (a worker process's, so that the serialization is not this process's work)."""
        if self._handle is None:
            self._open()
        try:
            self._handle.write(line)
            self._handle.flush()
        except BrokenPipeError:
            raise
        except OSError as exc:
            raise write_error("<stdout>" if self.path == "-" else self.path, exc) from None
        self.count += 1

    def close(self) -> None:
        if self._handle is None and self.path != "-" and not (self.resume and os.path.exists(self.target)):
            self._open()  # zero frames: an empty output, as before
        if self._own and self._handle is not None:
            handle, self._handle = self._handle, None
            try:
                handle.flush()
                if not self.special:
                    os.fsync(handle.fileno())
            except OSError as exc:
                raise write_error(self.path, exc) from None
            finally:
                with contextlib.suppress(OSError):
                    handle.close()

    def __exit__(self, exc_type, exc, tb):
        if exc_type is None:
            self.close()
        elif self._own and self._handle is not None:
            with contextlib.suppress(OSError):
                self._handle.close()
            self._handle = None
        return False
