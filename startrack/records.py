"""Typed records: what flows between startrack's stages.

Each record is a dataclass whose fields carry their frame-document name, unit
and meaning in ``metadata`` (see :func:`schema_field`).  That one schema is used
three ways, all by :mod:`startrack.formats.sections`:

* to **read** a frame-document section into a record, validating every field
  (type, finiteness, required) with a one-line :class:`~startrack.errors.BadInputError`;
* to **write** a record back as its section (``docs/formats.md``: degrees,
  arcseconds, milliseconds; no radians, no NaN);
* to **generate** the field tables of ``docs/formats.md``.

Records hold numbers in the units of the file (degrees, arcseconds, pixels,
milliseconds) so that what a user reads in Python is what the file says;
rotation matrices and quaternions are plain NumPy arrays (scalar-last
quaternion, ``A`` maps ICRS to the camera frame).

This module imports only NumPy (and, in the astropy views of :class:`SolveResult`, astropy).

Why dataclasses and a small schema table rather than msgspec: the records hold
NumPy arrays (star columns, rotation and covariance matrices) that msgspec does
not type; frame documents must pass unknown fields through untouched; and the
project's error contract (one line naming file, field path and problem) needs
control of every message.  The table below costs ~100 lines and no dependency.
"""
from __future__ import annotations

import dataclasses
import enum
import functools
import math
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np

__all__ = [
    "Attitude",
    "Identification",
    "Match",
    "ReasonCode",
    "SolveResult",
    "StarTable",
    "Status",
    "TrackState",
    "schema_field",
]


class Status(str, enum.Enum):
    """Outcome of a stage on one frame; the value is what the file says."""

    OK = "ok"
    FAILED = "failed"

    def __str__(self) -> str:
        return self.value


class ReasonCode(str, enum.Enum):
    """Machine-readable reason a stage failed on a frame (the ``reason_code`` field).

    The human-readable ``reason`` stays beside it.  Add members freely; never
    rename one (files and scripts match on the value).  A reader keeps a code it
    does not know as a plain string.
    """

    TOO_FEW_STARS = "too_few_stars"
    NO_STARS = "no_stars"
    NO_PATTERN = "no_pattern"
    FALSE_MATCH_PROBABILITY = "false_match_probability"
    VERIFICATION_FAILED = "verification_failed"
    TIMEOUT = "timeout"
    BAD_INPUT = "bad_input"
    RESIDUALS_TOO_LARGE = "residuals_too_large"
    NOT_IDENTIFIED = "not_identified"
    FOCAL_LENGTH = "focal_length"
    LOST = "lost"
    DUPLICATE_MATCH = "duplicate_match"
    DEGENERATE_GEOMETRY = "degenerate_geometry"
    OTHER = "other"

    @property
    def description(self) -> str:
        """One line saying what the code means (for the documentation)."""
        return _REASON_DOCS.get(self.value, "")

    def __str__(self) -> str:
        return self.value


_REASON_DOCS = {
    "too_few_stars": "Fewer stars detected or identified than the stage needs.",
    "no_stars": "Nothing was detected in the image.",
    "no_pattern": "No star pattern of the database matched.",
    "false_match_probability": "A match was found but its chance of being a coincidence is above the limit.",
    "verification_failed": "The proposal's stars do not agree with the refined attitude, or too few others match.",
    "timeout": "The time limit ran out before an answer.",
    "bad_input": "The frame's input is unusable (non-finite values, missing section).",
    "residuals_too_large": "The attitude's residuals are larger than the centroid noise allows.",
    "not_identified": "An upstream stage (identification) failed, so this one could not run.",
    "focal_length": "The measured focal length is outside the range searched or given.",
    "lost": "Tracking lost the attitude and lost-in-space recovery failed.",
    "duplicate_match": "The identification lists an image star or a catalog id twice.",
    "degenerate_geometry": "The identified stars are too close together (in units of their sigmas) to fix the roll.",
    "other": "A reason without a code of its own (see ``reason``).",
}


def schema_field(default: Any = None, *, key: str | None = None, kind: str = "number", unit: str = "",
                 doc: str = "", required: bool = False, factory=None, derived: bool = False):
    """A dataclass field carrying its frame-document schema.

    Parameters
    ----------
    default : object
        Default value (``None``: absent, not written).
    key : str, optional
        Name in the file when it differs from the attribute.
    kind : str
        ``number``, ``int``, ``bool``, ``str``, ``status``, ``reason_code``,
        ``vector`` (list of numbers -> float array), ``matrix`` (list of lists ->
        2-D float array), ``list`` (list of JSON values), ``object`` (JSON
        object), ``matches``, ``stars``, ``camera``, or ``record:<Name>``.
    unit : str
        Unit in the file (``deg``, ``arcsec``, ``px``, ``ms``, ...).
    doc : str
        One line for the documentation table.
    required : bool
        Required by the contract (``../shared/FORMATS.md``).
    factory : callable, optional
        ``default_factory`` for mutable defaults.
    derived : bool
        Written for readers but recomputed from other fields when read.
    """
    meta = {"key": key, "kind": kind, "unit": unit, "doc": doc, "required": required, "derived": derived}
    if factory is not None:
        return field(default_factory=factory, metadata=meta)
    return field(default=default, metadata=meta)


class _Record:
    """What every typed record offers: its frame-document form and a short ``repr``.

    ``to_dict()`` is what the commands write (:func:`startrack.formats.sections.to_frame` /
    :func:`~startrack.formats.sections.to_section`, one schema: ``docs/formats.md``); ``to_json()`` its
    JSON text.  ``dataclasses.asdict`` works on every record (plain values, arrays and named tuples).
    """

    def to_dict(self) -> dict:
        """The record as the frame document (or section) the commands write: JSON-ready, degrees, arcseconds."""
        return record_to_dict(self)

    def to_json(self, **kwargs) -> str:
        """:meth:`to_dict` as JSON text (``kwargs`` go to :func:`json.dumps`, e.g. ``indent=2``)."""
        import json

        return json.dumps(self.to_dict(), **kwargs)

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self._summary()})"

    def _summary(self) -> str:       # pragma: no cover - every record defines its own
        return ""


def _fmt(value, spec: str = ".4f") -> str:
    return "?" if value is None else format(float(value), spec)


def _status_text(record) -> str:
    status = str(getattr(record, "status", ""))
    if status == "failed":
        code = getattr(record, "reason_code", None)
        reason = getattr(record, "reason", None) or ""
        return f"failed{f' [{code}]' if code else ''}: {reason}"
    return status


class Match(NamedTuple):
    """One identified star: ``star`` indexes the frame's star table, ``id`` is the catalog id (HIP)."""

    star: int
    id: int


# Columns of a star table beyond x, y, flux that are numbers for every star.
_STAR_NUMERIC = ("sigma_px", "peak", "npix", "snr", "fwhm_px", "mag")


@dataclass(repr=False)
class StarTable(_Record):
    """Detected (or listed) stars of one frame, brightest first, as columns.

    Parameters
    ----------
    x, y : ndarray of float64, shape (n,)
        Centroid, pixels; ``x`` is the column, ``y`` the row, ``(0, 0)`` the
        centre of the top-left pixel.
    flux : ndarray of float64, shape (n,)
        Background-subtracted flux (DN in the aperture); NaN when unknown.
    sigma_px : ndarray of float64, shape (n,), optional
        Estimated 1-sigma centroid uncertainty per axis, pixels.
    columns : dict of str to ndarray
        Other numeric per-star columns (``peak``, ``npix``, ``snr``, ``fwhm_px``, ...).
    other : list of dict, optional
        Per-star fields that are not numeric columns (``saturated``,
        ``deblended``, ``prior``, ``window``, ...), passed through unchanged.
    """

    x: np.ndarray
    y: np.ndarray
    flux: np.ndarray
    sigma_px: np.ndarray | None = None
    columns: dict = field(default_factory=dict)
    other: list | None = None

    def __post_init__(self):
        self.x = np.asarray(self.x, dtype=np.float64).reshape(-1)
        self.y = np.asarray(self.y, dtype=np.float64).reshape(-1)
        n = len(self.x)
        self.flux = np.full(n, np.nan) if self.flux is None else np.asarray(self.flux, dtype=np.float64).reshape(-1)
        if self.sigma_px is not None:
            self.sigma_px = np.asarray(self.sigma_px, dtype=np.float64).reshape(-1)
        for name, col in [("y", self.y), ("flux", self.flux), ("sigma_px", self.sigma_px),
                          *self.columns.items()]:
            if col is not None and len(col) != n:
                raise ValueError(f"star table column {name!r} has {len(col)} values for {n} stars")

    def __len__(self) -> int:
        return len(self.x)

    def _summary(self) -> str:
        cols = ["x", "y", "flux"] + (["sigma_px"] if self.sigma_px is not None else []) + list(self.columns)
        return f"{len(self)} stars; columns {', '.join(cols)}"

    @property
    def xy(self) -> np.ndarray:
        """Centroids as an ``(n, 2)`` array of ``(x, y)`` pixels."""
        return np.column_stack([self.x, self.y])

    @classmethod
    def empty(cls) -> StarTable:
        return cls(np.zeros(0), np.zeros(0), np.zeros(0))

    @classmethod
    def from_list(cls, stars: list) -> StarTable:
        """From the ``stars`` section: a list of objects with ``x``, ``y`` and optionally ``flux``, ...

        No validation here: :func:`startrack.formats.sections.stars_from_section`
        validates a section read from a file.
        """
        n = len(stars)
        if n:
            keys = tuple(stars[0])
            if all(tuple(s) == keys for s in stars):
                return cls._from_rows(keys, stars)
        x = np.array([s["x"] for s in stars], dtype=np.float64)
        y = np.array([s["y"] for s in stars], dtype=np.float64)
        flux = np.array([s.get("flux", np.nan) if s.get("flux") is not None else np.nan for s in stars],
                        dtype=np.float64)
        sigma, columns = _numeric_columns(lambda name: [s.get(name) for s in stars] if n else None)
        known = {"x", "y", "flux", "sigma_px", *columns}
        # The stars of one list mostly share their keys (in order): the other keys found once per set of keys.
        other_keys: dict = {}
        other = []
        for s in stars:
            keys = tuple(s)
            rest = other_keys.get(keys)
            if rest is None:
                rest = other_keys[keys] = [k for k in keys if k not in known]
            other.append({k: s[k] for k in rest})
        return cls(x, y, flux, sigma, columns, other if any(other) else None)

    @classmethod
    def _from_rows(cls, keys: tuple, stars: list) -> StarTable:
        """:meth:`from_list` of stars that all have the keys ``keys``, in that order (a detector's list): the same
        table, made column by column."""
        cols = dict(zip(keys, zip(*[s.values() for s in stars], strict=True), strict=True))
        n = len(stars)
        x = np.array(cols["x"], dtype=np.float64)
        y = np.array(cols["y"], dtype=np.float64)
        flux = cols.get("flux")
        if flux is None:
            flux = np.full(n, np.nan)
        else:
            flux = np.array([np.nan if v is None else v for v in flux] if any(v is None for v in flux) else flux,
                            dtype=np.float64)
        sigma, columns = _numeric_columns(cols.get)
        known = {"x", "y", "flux", "sigma_px", *columns}
        rest = [k for k in keys if k not in known]
        # (each star's own values of those keys: a comprehension per star makes them faster than zip's rows)
        other = [{k: s[k] for k in rest} for s in stars] if rest else None
        return cls(x, y, flux, sigma, columns, other)

    def to_list(self) -> list:
        """The ``stars`` section: one object per star, ``x``, ``y``, ``flux`` first."""
        out = []
        for i in range(len(self)):
            star = {"x": float(self.x[i]), "y": float(self.y[i])}
            if math.isfinite(self.flux[i]):
                star["flux"] = float(self.flux[i])
            if self.sigma_px is not None:
                star["sigma_px"] = float(self.sigma_px[i])
            for name, col in self.columns.items():
                v = col[i]
                star[name] = int(v) if name == "npix" and math.isfinite(v) else float(v)
            if self.other is not None:
                star.update(self.other[i])
            out.append(star)
        return out


def _is_number(v) -> bool:
    return isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, bool)


_NUMBER_TYPES = frozenset((int, float, np.float64, np.float32, np.int64, np.int32))


def _all_numbers(values: list) -> bool:
    """Whether every value is a number (:func:`_is_number`): by their types at once when they are the usual ones."""
    if set(map(type, values)) <= _NUMBER_TYPES:
        return True
    return all(_is_number(v) for v in values)


def _numeric_columns(values_of) -> tuple:
    """``(sigma_px, columns)`` of a star list: each numeric column of :data:`_STAR_NUMERIC` whose values
    (``values_of(name)``, None: no such column) are all numbers, as float64; ``sigma_px`` apart (None: none)."""
    columns = {}
    sigma = None
    for name in _STAR_NUMERIC:
        values = values_of(name)
        if values is not None and _all_numbers(values):
            col = np.array(values, dtype=np.float64)
            if name == "sigma_px":
                sigma = col
            else:
                columns[name] = col
    return sigma, columns


@dataclass(repr=False)
class Attitude(_Record):
    """The ``attitude`` section: the rotation from ICRS to the camera frame and its quality.

    ``quaternion`` is authoritative (scalar last, ``A(q)`` maps ICRS unit
    vectors to camera-frame unit vectors, paper 000 Eqs. 20-22); ``ra``,
    ``dec`` (boresight, degrees) and ``roll`` (degrees, ``docs/formats.md``)
    are derived from it and written for readers.
    """

    status: Status = schema_field(Status.OK, kind="status", required=True, doc="`ok` or `failed`")
    method: str = schema_field("quest", kind="str", required=True, doc="Wahba solver (`quest`, `svd`, ...)")
    quaternion: np.ndarray | None = schema_field(kind="vector", required=True,
                                                 doc="`[q1, q2, q3, q4]`, scalar last, ICRS to camera")
    ra: float | None = schema_field(unit="deg", required=True, derived=True, doc="boresight right ascension, [0, 360)")
    dec: float | None = schema_field(unit="deg", required=True, derived=True, doc="boresight declination")
    roll: float | None = schema_field(unit="deg", required=True, derived=True,
                                      doc="position angle of image up, east of north")
    reason: str | None = schema_field(kind="str", doc="why it failed (human-readable)")
    reason_code: ReasonCode | str | None = schema_field(kind="reason_code", doc="why it failed (machine-readable)")
    n_stars: int | None = schema_field(kind="int", doc="stars used")
    loss: float | None = schema_field(doc="Wahba loss (paper 000 Eq. 15), normalised weights")
    residuals: list = schema_field(kind="list", factory=list, doc="each `star`, `id`, `residual_arcsec`")
    rms_residual_arcsec: float | None = schema_field(unit="arcsec", doc="RMS of the residuals")
    covariance_arcsec2: np.ndarray | None = schema_field(kind="matrix", unit="arcsec^2",
                                                         doc="3 x 3 attitude covariance, camera axes")
    variance_factor: float | None = schema_field(doc="> 1 when the residuals showed the centroid sigmas too small")
    crb_cross_boresight_arcsec: float | None = schema_field(
        unit="arcsec", doc="the frame's Cramér-Rao bound, per cross-boresight axis (`startrack.accuracy`)")
    crb_roll_arcsec: float | None = schema_field(unit="arcsec", doc="the frame's Cramér-Rao bound about the boresight")
    crb_pitch_yaw_arcsec: np.ndarray | None = schema_field(
        kind="vector", unit="arcsec", doc="the frame's Cramér-Rao bound about camera x and y (when the stars carry "
        "`sigma_px`)")
    sigma_cross_boresight_arcsec: float | None = schema_field(
        unit="arcsec", doc="1-sigma pointing uncertainty per cross-boresight axis (from `covariance_arcsec2`)")
    sigma_pitch_yaw_arcsec: np.ndarray | None = schema_field(kind="vector", unit="arcsec",
                                                             doc="1-sigma about camera x and y")
    sigma_roll_arcsec: float | None = schema_field(unit="arcsec", doc="1-sigma about the boresight")
    euler123_deg: dict | None = schema_field(kind="object", unit="deg",
                                             doc="`yaw`, `pitch`, `roll` of `A = R3(roll) R2(pitch) R1(yaw)`")
    rejected: list = schema_field(kind="list", factory=list, doc="stars dropped by the chi-square gate")
    epoch: float | None = schema_field(unit="yr", doc="decimal year of the catalog positions")
    time_ms: float | None = schema_field(unit="ms", doc="time taken")
    details: dict = schema_field(kind="object", factory=dict,
                                 doc="other fields (`dcm`, `wcs`, `apparent`, ...)")

    @property
    def ok(self) -> bool:
        return self.status == Status.OK

    def _summary(self) -> str:
        if not self.ok:
            return _status_text(self)
        text = (f"ok, {self.method}: RA {_fmt(self.ra)}, Dec {_fmt(self.dec, '+.4f')}, roll {_fmt(self.roll, '.3f')} "
                f"deg")
        if self.n_stars is not None:
            text += f", {self.n_stars} stars"
        if self.sigma_cross_boresight_arcsec is not None:
            text += f", sigma {_fmt(self.sigma_cross_boresight_arcsec, '.2f')}\" cross-boresight"
            if self.sigma_roll_arcsec is not None:
                text += f", {_fmt(self.sigma_roll_arcsec, '.1f')}\" roll"
        return text

    @property
    def dcm(self) -> np.ndarray | None:
        """The 3 x 3 rotation matrix ``A`` (ICRS to camera; rows are the camera axes in ICRS)."""
        if self.quaternion is None:
            return None
        from startrack.rotations import quaternion_to_dcm

        return quaternion_to_dcm(self.quaternion)

    @classmethod
    def from_dcm(cls, dcm, method: str = "quest", **kw) -> Attitude:
        """An ``ok`` attitude from a rotation matrix, with ``ra``, ``dec``, ``roll`` derived (degrees)."""
        from startrack.rotations import dcm_to_quaternion, dcm_to_radec_roll

        dcm = np.asarray(dcm, dtype=np.float64)
        ra, dec, roll = dcm_to_radec_roll(dcm)
        q = dcm_to_quaternion(dcm)
        return cls(Status.OK, method, np.asarray(q, dtype=np.float64), float(ra), float(dec), float(roll), **kw)

    @classmethod
    def failed(cls, reason: str, reason_code: ReasonCode | str = ReasonCode.OTHER, method: str = "quest",
               **kw) -> Attitude:
        return cls(Status.FAILED, method, reason=reason, reason_code=reason_code, **kw)


@dataclass(repr=False)
class Identification(_Record):
    """The ``identification`` section: which detected star is which catalog star.

    ``matches`` pair an index into the frame's star table with a catalog id
    (HIP for the shipped catalog).
    """

    status: Status = schema_field(Status.OK, kind="status", required=True, doc="`ok` or `failed`")
    algorithm: str = schema_field("pyramid", kind="str", required=True, doc="identification algorithm")
    matches: list = schema_field(kind="matches", factory=list, required=True,
                                 doc="each `star` (index into `stars`) and `id` (catalog id)")
    time_ms: float | None = schema_field(unit="ms", doc="time taken")
    reason: str | None = schema_field(kind="str", doc="why it failed (human-readable)")
    reason_code: ReasonCode | str | None = schema_field(kind="reason_code", doc="why it failed (machine-readable)")
    false_match_probability: float | None = schema_field(
        doc="probability that the identification is a coincidence")
    trials: int | None = schema_field(kind="int", doc="patterns tried")
    tolerance_arcsec: float | None = schema_field(unit="arcsec", doc="half-width of the inter-star angle window")
    focal_scale: float | None = schema_field(doc="measured `theta_catalog / theta_measured` (true f = f / scale)")
    quaternion_estimate: np.ndarray | None = schema_field(kind="vector", doc="attitude of the verification")
    parity: str | None = schema_field(kind="str", doc="`normal`, or `mirrored`: the stars identified were the "
                                      "detections flipped about the principal point's column (`x -> 2 cx - x`)")
    details: dict = schema_field(kind="object", factory=dict,
                                 doc="algorithm-specific fields (`mode`, `votes`, `label_error_arcsec`, ...)")

    @property
    def ok(self) -> bool:
        return self.status == Status.OK

    def _summary(self) -> str:
        text = f"{_status_text(self)}, {self.algorithm}, {len(self.matches)} matches"
        if self.false_match_probability is not None:
            text += f", false-match probability {self.false_match_probability:.2g}"
        if self.time_ms is not None:
            text += f", {self.time_ms:.1f} ms"
        return text

    @classmethod
    def failed(cls, algorithm: str, reason: str, reason_code: ReasonCode | str = ReasonCode.OTHER,
               **kw) -> Identification:
        return cls(Status.FAILED, algorithm, [], reason=reason, reason_code=reason_code, **kw)


@dataclass(repr=False)
class TrackState(_Record):
    """The ``track`` section: what the tracker did on one frame."""

    mode: str | None = schema_field(kind="str", doc="`tracking`, `single-star`, `lost-in-space` or `lost`")
    t_s: float | None = schema_field(unit="s", doc="frame time")
    dt_s: float | None = schema_field(unit="s", doc="time since the previous frame")
    window_px: float | None = schema_field(unit="px", doc="search window half-size")
    predicted: int | None = schema_field(kind="int", doc="catalog stars predicted in the image")
    found: int | None = schema_field(kind="int", doc="predicted stars found in their windows")
    used: int | None = schema_field(kind="int", doc="stars used for the attitude")
    stars: list = schema_field(kind="list", factory=list, doc="each `id`, `predicted` [x, y], `measured` [x, y] or null")
    rate_deg_s: np.ndarray | None = schema_field(kind="vector", unit="deg/s", doc="angular rate (filtered), camera frame")
    fallback_reason: str | None = schema_field(kind="str", doc="why tracking fell back to lost-in-space")
    empirical_stars: int | None = schema_field(kind="int", doc="empirical stars used (single-star mode, paper 001 Case 2)")
    time_ms: float | None = schema_field(unit="ms", doc="time taken")
    details: dict = schema_field(kind="object", factory=dict, doc="other fields")
    # Not part of the ``track`` section: the frame's other sections (:meth:`startrack.Solver.track`).
    star_table: StarTable | None = field(default=None, metadata={"section": "stars"})
    identification: Identification | None = field(default=None, metadata={"section": "identification"})
    attitude: Attitude | None = field(default=None, metadata={"section": "attitude"})

    def _summary(self) -> str:
        text = f"{self.mode}"
        if self.t_s is not None:
            text += f", t {self.t_s:g} s"
        if self.found is not None and self.predicted is not None:
            text += f", {self.found} of {self.predicted} predicted stars found"
        if self.attitude is not None:
            text += f", attitude {self.attitude._summary()}"
        return text


@dataclass(repr=False)
class SolveResult(_Record):
    """Everything :meth:`startrack.Solver.solve` learnt about one image.

    Written as the frame sections ``camera``, ``stars``, ``centroid``,
    ``identification``, ``attitude`` and ``solve`` (:func:`startrack.to_frame`).
    ``status`` is ``ok`` only when the attitude is; otherwise ``reason`` and
    ``reason_code`` say why.  ``ra``/``dec`` of ``attitude`` are the boresight's
    (the principal point); ``center_ra``/``center_dec`` are the image centre's.
    """

    status: Status = schema_field(Status.FAILED, kind="status", doc="`ok` or `failed`")
    reason: str | None = schema_field(kind="str", doc="why it failed (human-readable)")
    reason_code: ReasonCode | str | None = schema_field(kind="reason_code", doc="why it failed (machine-readable)")
    fov_deg: np.ndarray | None = schema_field(kind="vector", unit="deg",
                                              doc="fitted field of view `[horizontal, vertical]`")
    center_ra: float | None = schema_field(unit="deg", doc="right ascension of the image centre")
    center_dec: float | None = schema_field(unit="deg", doc="declination of the image centre")
    hypotheses: int | None = schema_field(kind="int", doc="attempts (bands, focal lengths, databases)")
    database: str | None = schema_field(kind="str", doc="file name of the database that identified it")
    catalog: str | None = schema_field(kind="str", doc="the catalog whose ids `identification.matches` holds: "
                                       "`hipparcos` (HIP numbers), `gaia` (Gaia DR3 source ids, HIP numbers "
                                       "below Hp 5) or a catalog file's name")
    parity: str | None = schema_field(kind="str", doc="`normal`, or `mirrored`: the image is the camera's flipped "
                                      "(`x -> 2 cx - x`); the attitude and camera are the un-mirrored camera's")
    time_ms: float | None = schema_field(unit="ms", doc="time taken")
    principal_point: dict | None = schema_field(kind="object", unit="deg",
                                                doc="`ra`, `dec` of the principal point (the boresight)")
    hint: dict | None = schema_field(kind="object", unit="deg",
                                     doc="the search's restrictions as given: `ra`, `dec`, `radius` (the boresight "
                                     "within `radius` of `ra`, `dec`), `fov_min`, `fov_max` (horizontal field)")
    targets: list = schema_field(kind="list", factory=list,
                                 doc="the pixels and sky positions asked for (`--target-pixel`, `--target-radec`)")
    details: dict = schema_field(kind="object", factory=dict, doc="other fields (`wcs_path`, `plot_path`, ...)")
    # Not part of the ``solve`` section: the other sections of the frame.
    camera: Any = field(default=None, metadata={"section": "camera"})
    stars: StarTable | None = field(default=None, metadata={"section": "stars"})
    centroid: dict | None = field(default=None, metadata={"section": "centroid"})
    identification: Identification | None = field(default=None, metadata={"section": "identification"})
    attitude: Attitude | None = field(default=None, metadata={"section": "attitude"})
    image: dict | None = field(default=None, metadata={"section": "image"})
    # Not written: the catalog positions (``ra``, ``dec``, degrees, at the attitude's epoch) and ``mag`` of the
    # identification's matches, in their order (arrays), for :attr:`matches`.
    matched_catalog: dict | None = field(default=None)

    @property
    def ok(self) -> bool:
        return self.status == Status.OK

    def _summary(self) -> str:
        n_stars = 0 if self.stars is None else len(self.stars)
        n_matched = 0 if self.identification is None else len(self.identification.matches)
        if not self.ok:
            text = f"{_status_text(self)}; {n_stars} stars"
        else:
            att = self.attitude
            text = f"ok: RA {_fmt(att.ra)}, Dec {_fmt(att.dec, '+.4f')}, roll {_fmt(att.roll, '.3f')} deg"
            if self.fov_deg is not None:
                text += f", field {_fmt(self.fov_deg[0], '.3f')} x {_fmt(self.fov_deg[1], '.3f')} deg"
            text += f", {n_matched} of {n_stars} stars matched"
            if att.sigma_cross_boresight_arcsec is not None:
                text += f", sigma {_fmt(att.sigma_cross_boresight_arcsec, '.2f')}\" cross-boresight"
        if self.time_ms is not None:
            text += f", {self.time_ms:.0f} ms"
        return text

    # ------------------------------------------------------------------ astropy views (astropy imported here only)
    @property
    def wcs(self):
        """The solution as an ``astropy.wcs.WCS`` (TAN, SIP for a distorted lens), ``None`` when not solved.

        Pixel coordinates are ours (0-based, ``(0, 0)`` the centre of the top-left pixel), which is astropy's
        0-based convention.  It maps pixels to *astrometric* (catalog) positions, as the ``--wcs`` file does
        (its keywords are ``attitude.wcs``, :func:`startrack.attitude.wcs_keywords`).
        """
        keywords = None if self.attitude is None else self.attitude.details.get("wcs")
        if not self.ok or not keywords:
            return None
        from astropy.io import fits
        from astropy.wcs import WCS

        header = fits.Header()
        for key, value in keywords.items():
            header[key] = value
        wcs = WCS(header)
        if "IMAGEW" in keywords and "IMAGEH" in keywords:
            wcs.pixel_shape = (int(keywords["IMAGEW"]), int(keywords["IMAGEH"]))     # so footprints work
        return wcs

    @property
    def center(self):
        """The image centre's sky position (astrometric, ICRS) as an ``astropy.coordinates.SkyCoord``."""
        if not self.ok or self.center_ra is None:
            return None
        from astropy.coordinates import SkyCoord

        return SkyCoord(self.center_ra, self.center_dec, unit="deg", frame="icrs")

    def pixel_to_world(self, x, y):
        """Sky positions (``SkyCoord``, astrometric ICRS) of pixels ``x`` (column), ``y`` (row); scalars or arrays."""
        return self._need_wcs("pixel_to_world").pixel_to_world(x, y)

    def world_to_pixel(self, coord):
        """Pixel ``(x, y)`` (0-based, ours) of sky positions (a ``SkyCoord``); NaN where behind the camera."""
        return self._need_wcs("world_to_pixel").world_to_pixel(coord)

    def _need_wcs(self, what):
        w = self.wcs
        if w is None:
            from startrack.errors import StartrackError

            raise StartrackError(f"SolveResult.{what}: the image was not solved ({self.reason})")
        return w

    @property
    def matches(self):
        """The identified stars as an ``astropy.table.Table`` with units, one row per match.

        Columns: ``star`` (index into :attr:`stars`), ``catalog_id``, ``x``, ``y`` (pix), ``ra``, ``dec`` (deg,
        the catalog star at the attitude's epoch), ``mag`` (the catalog's, Hp), ``field_ra``, ``field_dec``
        (deg, where the WCS puts the detection) and ``residual`` (arcsec, the attitude's residual; NaN for a
        star the attitude rejected or did not use).  ``ra``, ``dec`` and ``mag`` come from
        :attr:`matched_catalog`, which a solve fills; a result read from a file has them when
        :func:`startrack.formats.sections.solve_result_from_frame` is given the catalog, else NaN.
        """
        from astropy import units as u
        from astropy.table import Table

        matches = [] if self.identification is None else list(self.identification.matches)
        star = np.array([int(m[0]) for m in matches], dtype=np.int64)
        ids = np.array([int(m[1]) for m in matches], dtype=np.int64)
        x = self.stars.x[star] if len(star) else np.zeros(0)
        y = self.stars.y[star] if len(star) else np.zeros(0)
        cat = self.matched_catalog
        if cat is None or len(cat.get("ra", ())) != len(matches):
            cat = {k: np.full(len(matches), np.nan) for k in ("ra", "dec", "mag")}
        resid = {}
        if self.attitude is not None:
            resid = {(int(r["star"]), int(r["id"])): float(r["residual_arcsec"]) for r in self.attitude.residuals
                     if r.get("residual_arcsec") is not None}
        residual = np.array([resid.get((int(s), int(i)), np.nan) for s, i in zip(star, ids)], dtype=np.float64)
        field_ra = np.full(len(star), np.nan)
        field_dec = np.full(len(star), np.nan)
        if len(star) and self.wcs is not None:
            sky = self.pixel_to_world(x, y)
            field_ra, field_dec = sky.ra.deg, sky.dec.deg
        return Table([star, ids, x * u.pix, y * u.pix, np.asarray(cat["ra"], float) * u.deg,
                      np.asarray(cat["dec"], float) * u.deg, np.asarray(cat["mag"], float) * u.mag,
                      field_ra * u.deg, field_dec * u.deg, residual * u.arcsec],
                     names=["star", "catalog_id", "x", "y", "ra", "dec", "mag", "field_ra", "field_dec", "residual"])



# ---------------------------------------------------------------------------------------------- writing
# A record as its frame-document section (JSON-ready: lists, floats, no NaN, enum values as strings), and a
# result as its frame's sections.  Here, beside the schema, so that ``to_dict()`` needs nothing above the
# records; :mod:`startrack.formats.sections` reads sections and re-exports these.

#: The format tag of a frame document (``docs/formats.md``).
FRAME_FORMAT = "startrack.frame/1"


@functools.lru_cache(maxsize=None)
def _schema_fields(cls) -> tuple:
    """The fields of record class ``cls`` that the schema describes (once per class: records are written per frame)."""
    return tuple(f for f in dataclasses.fields(cls) if "kind" in f.metadata)


def _key(f) -> str:
    return f.metadata.get("key") or f.name


#: Types whose values :func:`_json_value` returns as they are (an enum member's type is its enum, never one of these).
_PLAIN_JSON = frozenset((str, int, bool, type(None)))


def _json_value(value):
    """A JSON-ready copy: NumPy to Python, non-finite floats to ``None``, enums to their value."""
    kind = type(value)
    # The types a document holds by far the most often, by exact type first (the same values as the checks below).
    if kind in _PLAIN_JSON:
        return value
    if kind is float:
        return value if math.isfinite(value) else None
    if kind is dict:
        return {str(k): _json_value(v) for k, v in value.items()}
    if kind is list:
        return [_json_value(v) for v in value]
    if isinstance(value, enum_types()):
        return value.value
    if isinstance(value, dict):
        return {str(k): _json_value(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_value(v) for v in value]
    if isinstance(value, np.ndarray):
        return _json_value(value.tolist())
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        value = float(value)
        return value if math.isfinite(value) else None
    return value


def enum_types():
    return (Status, ReasonCode)


def to_section(record) -> dict:
    """The frame-document section of a record: only the fields that are set, in schema order.

    ``details`` (algorithm-specific or other fields) are merged in last.
    """
    out = {}
    for f in _schema_fields(type(record)):
        value = getattr(record, f.name)
        if f.name == "details":
            continue
        if value is None or (f.metadata["kind"] in ("list",) and not value and not f.metadata["required"]):
            continue
        if f.metadata["kind"] == "matches":
            value = [{"star": int(m[0]), "id": int(m[1])} for m in value]
        out[_key(f)] = _json_value(value)
    details = getattr(record, "details", None)
    if details:
        for k, v in details.items():
            out.setdefault(k, _json_value(v))
    return out


def stars_to_section(stars) -> list:
    """The ``stars`` section of a :class:`StarTable` (or a list of star objects, returned JSON-ready)."""
    if isinstance(stars, StarTable):
        return stars.to_list()
    return _json_value(list(stars))


def solve_result_to_frame(result: SolveResult) -> dict:
    """The frame sections of a :class:`SolveResult`: ``camera``, ``stars``, ``centroid``, ``identification``,
    ``attitude`` (those that are set) and ``solve``."""
    out = {}
    if result.image is not None:
        out["image"] = _json_value(result.image)
    if result.camera is not None:
        out["camera"] = result.camera.to_dict() if hasattr(result.camera, "to_dict") else result.camera
    if result.stars is not None:
        out["stars"] = stars_to_section(result.stars)
    if result.centroid is not None:
        out["centroid"] = _json_value(result.centroid)
    if result.identification is not None:
        out["identification"] = to_section(result.identification)
    if result.attitude is not None:
        out["attitude"] = to_section(result.attitude)
    out["solve"] = to_section(result)
    return out


def to_frame(record) -> dict:
    """The frame-document sections of a typed record, ready for JSON.

    A :class:`SolveResult` gives ``camera``, ``stars``, ``centroid``,
    ``identification``, ``attitude`` and ``solve``; a :class:`TrackState` its
    ``track`` section and the frame sections attached to it; an
    :class:`Identification` or :class:`Attitude` its one section; a
    :class:`StarTable` the ``stars`` section.
    """
    if isinstance(record, SolveResult):
        return solve_result_to_frame(record)
    if isinstance(record, TrackState):
        out = {"track": to_section(record)}
        if record.star_table is not None:
            out["stars"] = stars_to_section(record.star_table)
        if record.identification is not None:
            out["identification"] = to_section(record.identification)
        if record.attitude is not None:
            out["attitude"] = to_section(record.attitude)
        return out
    if isinstance(record, Identification):
        return {"identification": to_section(record)}
    if isinstance(record, Attitude):
        return {"attitude": to_section(record)}
    if isinstance(record, StarTable):
        return {"stars": stars_to_section(record)}
    raise TypeError(f"not a startrack record: {type(record).__name__}")


def record_to_dict(record) -> dict:
    """``record.to_dict()``: a :class:`SolveResult` or :class:`TrackState` as the frame document the commands
    write (``format`` tag first), an :class:`Identification` or :class:`Attitude` as its section, a
    :class:`StarTable` as ``{"stars": [...]}``."""
    if isinstance(record, (SolveResult, TrackState)):
        return {"format": FRAME_FORMAT, **to_frame(record)}
    if isinstance(record, (Identification, Attitude)):
        return to_section(record)
    return to_frame(record)


