"""Typed records <-> frame-document sections, from one schema.

The schema is the ``metadata`` of the fields of the records in
:mod:`startrack.records` (see :func:`startrack.records.schema_field`).  This
module reads a section into a record (validating it: one
:class:`~startrack.errors.BadInputError` naming source, field path and
problem), writes a record as its section (JSON-ready: lists, floats, no NaN,
enum values as strings), and renders the field tables of ``docs/formats.md``
(``python -m startrack.formats.sections`` prints them).
"""
from __future__ import annotations

import json
import math

import numpy as np

from startrack.errors import BadInputError
from startrack.records import (  # noqa: F401 - the writers live with the records (re-exported here)
    Attitude,
    Identification,
    Match,
    ReasonCode,
    SolveResult,
    StarTable,
    Status,
    TrackState,
    _json_value,
    _key,
    _schema_fields,
    enum_types,
    record_to_dict,
    solve_result_to_frame,
    stars_to_section,
    to_frame,
    to_section,
)

__all__ = [
    "SECTIONS",
    "from_section",
    "to_section",
    "field_table",
    "stars_from_section",
    "stars_to_section",
    "solve_result_to_frame",
    "solve_result_from_frame",
    "to_frame",
    "record_to_dict",
    "identification_record",
    "camera_from_file",
]

# frame-document section -> record class
SECTIONS = {"identification": Identification, "attitude": Attitude, "track": TrackState, "solve": SolveResult}


def _number(value, source, path, integer=False):
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise BadInputError(source, path, f"must be a number, got {json.dumps(value)[:40]}")
    if not math.isfinite(value):
        raise BadInputError(source, path, f"must be a finite number, got {value}")
    if integer:
        if int(value) != value:
            raise BadInputError(source, path, f"must be an integer, got {value}")
        return int(value)
    return float(value)


def _read_value(kind, value, source, path):
    if kind == "number":
        return _number(value, source, path)
    if kind == "int":
        return _number(value, source, path, integer=True)
    if kind == "bool":
        if not isinstance(value, bool):
            raise BadInputError(source, path, "must be true or false")
        return value
    if kind == "str":
        if not isinstance(value, str):
            raise BadInputError(source, path, f"must be a string, got {json.dumps(value)[:40]}")
        return value
    if kind == "status":
        try:
            return Status(value)
        except ValueError:
            raise BadInputError(source, path, f"must be 'ok' or 'failed', got {json.dumps(value)[:40]}") from None
    if kind == "reason_code":
        if not isinstance(value, str):
            raise BadInputError(source, path, "must be a string")
        try:
            return ReasonCode(value)
        except ValueError:
            return value        # a code of a newer version: kept as it is
    if kind == "vector":
        if not isinstance(value, list):
            raise BadInputError(source, path, "must be a list of numbers")
        return np.array([_number(v, source, f"{path}[{i}]") for i, v in enumerate(value)])
    if kind == "matrix":
        if not isinstance(value, list) or not all(isinstance(r, list) for r in value):
            raise BadInputError(source, path, "must be a list of lists of numbers")
        return np.array([[_number(v, source, f"{path}[{i}][{j}]") for j, v in enumerate(row)]
                         for i, row in enumerate(value)])
    if kind == "list":
        if not isinstance(value, list):
            raise BadInputError(source, path, "must be a list")
        return value
    if kind == "object":
        if not isinstance(value, dict):
            raise BadInputError(source, path, "must be an object")
        return value
    if kind == "matches":
        if not isinstance(value, list):
            raise BadInputError(source, path, "must be a list")
        out = []
        for i, m in enumerate(value):
            if not isinstance(m, dict) or "star" not in m or "id" not in m:
                raise BadInputError(source, f"{path}[{i}]", "needs 'star' and 'id'")
            out.append(Match(_number(m["star"], source, f"{path}[{i}].star", integer=True),
                             _number(m["id"], source, f"{path}[{i}].id", integer=True)))
        return out
    raise ValueError(f"unknown schema kind {kind!r}")


def _own_value(kind, value):
    """:func:`_read_value` of a value this library wrote itself (a section just made from a result): the same
    conversions, without the checks a document read from a file needs."""
    if kind == "number":
        return float(value)
    if kind == "int":
        return int(value)
    if kind == "status":
        return Status(value)
    if kind == "reason_code":
        try:
            return ReasonCode(value)
        except ValueError:
            return value
    if kind == "vector" or kind == "matrix":
        return np.array(value, dtype=np.float64)
    if kind == "matches":
        return [Match(int(m["star"]), int(m["id"])) for m in value]
    return value


def from_section(cls, doc, source: str = "<frame>", section: str | None = None, validate: bool = True):
    """Read and validate a frame-document section into a record of class ``cls``.

    Parameters
    ----------
    cls : type
        :class:`~startrack.records.Identification`, :class:`~startrack.records.Attitude`,
        :class:`~startrack.records.TrackState` or :class:`~startrack.records.SolveResult`
        (its ``solve`` section only; see :func:`solve_result_from_frame`).
    doc : dict
        The section, as parsed from JSON.
    source : str
        Where it came from (``file:line``), for messages.
    section : str, optional
        The section's name, prefixed to field paths in messages.
    validate : bool
        False for a section this library has just written from its own result (e.g.
        :meth:`startrack.attitude.AttitudeResult.section`): the same record, without checking each value.

    Raises
    ------
    BadInputError
        Naming the source, the field (``identification.matches[3].star``) and the problem.
    """
    prefix = f"{section}." if section else ""
    if not isinstance(doc, dict):
        raise BadInputError(source, section, "must be an object")
    kw = {}
    known = set()
    for f in _schema_fields(cls):
        key = _key(f)
        known.add(key)
        if f.name == "details":
            continue
        if key not in doc or doc[key] is None:
            if f.metadata["required"] and not f.metadata["derived"] and not (
                    cls is Attitude and doc.get("status") == "failed" and key != "status"):
                raise BadInputError(source, prefix + key, "is missing")
            continue
        kw[f.name] = _read_value(f.metadata["kind"], doc[key], source, prefix + key) if validate else \
            _own_value(f.metadata["kind"], doc[key])
    if any(f.name == "details" for f in _schema_fields(cls)):
        kw["details"] = {k: v for k, v in doc.items() if k not in known}
    record = cls(**kw)
    if cls is Attitude and record.quaternion is not None:
        if record.quaternion.shape != (4,):
            raise BadInputError(source, prefix + "quaternion", "must be a list of 4 numbers")
        norm = float(np.linalg.norm(record.quaternion))
        if not 0.99 < norm < 1.01:
            raise BadInputError(source, prefix + "quaternion", f"must be a unit quaternion, norm is {norm:.4g}")
        if record.ra is None:
            from startrack.rotations import dcm_to_radec_roll

            ra, dec, roll = dcm_to_radec_roll(record.dcm)
            record.ra, record.dec, record.roll = float(ra), float(dec), float(roll)
    return record


def stars_from_section(stars, source: str = "<frame>") -> StarTable:
    """Validate a ``stars`` section (finite ``x``, ``y``; ``flux`` a number when given) into a :class:`StarTable`."""
    if not isinstance(stars, list):
        raise BadInputError(source, "stars", "must be a list")
    for i, star in enumerate(stars):
        if not isinstance(star, dict):
            raise BadInputError(source, f"stars[{i}]", "must be an object")
        for name in ("x", "y"):
            if name not in star:
                raise BadInputError(source, f"stars[{i}].{name}", "is missing")
            _number(star[name], source, f"stars[{i}].{name}")
        if star.get("flux") is not None:
            _number(star["flux"], source, f"stars[{i}].flux")
    return StarTable.from_list(stars)


def identification_record(result) -> Identification:
    """An :class:`Identification` from an identification algorithm's result (or its ``identification`` section)."""
    if isinstance(result, Identification):
        return result
    section = result if isinstance(result, dict) else result.section()
    record = from_section(Identification, section, "identification")
    code = getattr(result, "reason_code", None)
    if code is not None:
        record.reason_code = code
    elif record.status == "failed" and record.reason_code is None:
        record.reason_code = ReasonCode.OTHER
    return record


def camera_from_file(path: str):
    """A camera from a ``startrack.camera/1`` file or from a frame document's ``camera`` section."""
    from startrack.camera import CAMERA_FORMAT, Camera
    from startrack.formats.frame import check_format_tag, read_json_file

    doc = read_json_file(path)
    if str(doc.get("format", CAMERA_FORMAT)).startswith("startrack.frame/"):
        check_format_tag(doc, "startrack.frame/1", path)
        if "camera" not in doc:
            raise BadInputError(path, "camera", "is missing")
        doc = doc["camera"]
    elif "format" in doc:
        check_format_tag(doc, CAMERA_FORMAT, path)
    return Camera.from_dict(doc, path)


def solve_result_from_frame(doc: dict, source: str = "<frame>", catalog=None) -> SolveResult:
    """A :class:`SolveResult` from a frame document that ``solve`` wrote.

    ``catalog`` (:class:`startrack.catalog.Catalog`, optional): the matches' catalog positions (at the
    attitude's ``epoch``) and magnitudes are taken from it, for :attr:`SolveResult.matches`.
    """
    from startrack.camera import Camera

    result = from_section(SolveResult, doc.get("solve", {}), source, "solve")
    if "camera" in doc:
        result.camera = Camera.from_dict(doc["camera"], source)
    if "stars" in doc:
        result.stars = stars_from_section(doc["stars"], source)
    result.centroid = doc.get("centroid")
    if isinstance(doc.get("image"), dict):
        result.image = doc["image"]
    if "identification" in doc:
        result.identification = from_section(Identification, doc["identification"], source, "identification")
    if "attitude" in doc:
        result.attitude = from_section(Attitude, doc["attitude"], source, "attitude")
    if catalog is not None and result.identification is not None:
        epoch = result.attitude.epoch if result.attitude is not None else None
        # The matched stars alone, moved to the attitude's epoch: the whole catalog's numbers moved there, row by row
        # (Catalog.propagate works star by star), without moving the whole catalog for every document (~90 ms).
        found = catalog.rows_of([int(m[1]) for m in result.identification.matches])
        held = found >= 0
        cat = catalog.subset(found[held])
        if epoch is not None and epoch != catalog.epoch:
            cat = cat.propagate(epoch)

        def pick(column):
            out = np.full(len(found), np.nan)
            out[held] = column
            return out

        result.matched_catalog = {"ra": pick(cat.ra), "dec": pick(cat.dec), "mag": pick(cat.mag)}
    return result


_KIND_TYPE = {"number": "number", "int": "integer", "bool": "boolean", "str": "string",
              "status": "`\"ok\"` or `\"failed\"`", "reason_code": "string (reason code)",
              "vector": "list of numbers", "matrix": "list of lists", "list": "list", "object": "object",
              "matches": "list of `{star, id}`"}


def field_table(cls) -> str:
    """The Markdown field table of a record's section, for ``docs/formats.md``."""
    lines = ["| field | type | unit | |", "|---|---|---|---|"]
    for f in _schema_fields(cls):
        if f.name == "details":
            continue
        doc = f.metadata["doc"]
        if f.metadata["required"]:
            doc = f"*required*; {doc}"
        lines.append(f"| `{_key(f)}` | {_KIND_TYPE[f.metadata['kind']]} | {f.metadata['unit']} | {doc} |")
    return "\n".join(lines)


def reason_code_table() -> str:
    """The Markdown table of :class:`~startrack.records.ReasonCode` values."""
    lines = ["| `reason_code` | meaning |", "|---|---|"]
    for member in ReasonCode:
        lines.append(f"| `{member.value}` | {member.description} |")
    return "\n".join(lines)


BEGIN_MARK = "<!-- BEGIN GENERATED FIELD TABLES -->"
END_MARK = "<!-- END GENERATED FIELD TABLES -->"


def generated_tables() -> str:
    """Every section's field table and the reason codes, as the Markdown of ``docs/formats.md``."""
    parts = [f"#### `{name}`\n\n<!-- fields: {name} -->\n{field_table(cls)}\n" for name, cls in SECTIONS.items()]
    parts.append(f"#### Reason codes\n\n{reason_code_table()}\n")
    return "\n".join(parts)


def update_docs(text: str) -> str:
    """``text`` (``docs/formats.md``) with the generated tables put between the markers."""
    head, _, rest = text.partition(BEGIN_MARK)
    _, _, tail = rest.partition(END_MARK)
    return f"{head}{BEGIN_MARK}\n{generated_tables()}{END_MARK}{tail}"


def main(argv=None) -> None:
    """``python -m startrack.formats.sections [docs/formats.md]``: print the tables, or rewrite the file."""
    import sys

    argv = sys.argv[1:] if argv is None else argv
    if not argv:
        print(generated_tables())
        return
    with open(argv[0], encoding="utf-8") as fh:
        text = fh.read()
    with open(argv[0], "w", encoding="utf-8") as fh:
        fh.write(update_docs(text))


if __name__ == "__main__":
    main()
