"""The camera model: a pinhole with optional radial distortion, or a fisheye projection.

Frames and units (``docs/formats.md``): image ``x`` is the column and ``y`` the
row, with ``(0, 0)`` the centre of the top-left pixel; the camera frame has
``+x`` along image ``x``, ``+y`` along image ``y`` and ``+z`` along the
boresight.  Before distortion a camera-frame direction ``(X, Y, Z)`` lands at
``x = cx + f X / Z``, ``y = cy + f Y / Z`` with ``f`` in pixels.

Radial distortion acts on the normalised image coordinates ``(u, v) = (X/Z, Y/Z)``:
``(u_d, v_d) = (u, v) (1 + k1 r^2 + k2 r^4)`` with ``r^2 = u^2 + v^2`` (the
Brown-Conrady radial terms, as OpenCV uses them).

Paper 000 Eq. 13 gives the star vector of a centroid as
``W = (mu_l (x_o - x), mu_w (y_o - y), f) / norm``, with the focal length in
metres and pixel pitches ``mu``; with ``f`` in pixels and our axis signs that is
``W = (x - cx, y - cy, f) / norm`` (:meth:`Camera.pixels_to_vectors`).

Fisheye projections (``projection`` other than ``"pinhole"``) map the angle
``theta`` between a direction and the boresight to a radius from the principal
point, ``r = f g(theta_d)``, along the direction's azimuth ``(X, Y) / hypot(X, Y)``:

============== ======================= ===================
projection     ``g(theta)``            largest ``theta``
============== ======================= ===================
equidistant    ``theta``               180 deg
equisolid      ``2 sin(theta / 2)``    180 deg
stereographic  ``2 tan(theta / 2)``    below 180 deg
orthographic   ``sin(theta)``          90 deg
============== ======================= ===================

with the radial distortion acting on the angle,
``theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8)``: for the
equidistant projection that is OpenCV's fisheye model (``cv2.fisheye``, Kannala and
Brandt 2006), which has ``r = f theta_d``.  Each ``g`` has ``g'(0) = 1``, so ``f`` is the
focal length in pixels at the principal point for every projection.
"""
from __future__ import annotations

import dataclasses
import functools
import math
from dataclasses import dataclass, field

import numpy as np

from startrack.errors import BadInputError, ParameterError

__all__ = ["Camera", "parse_size", "PROJECTIONS"]

CAMERA_FORMAT = "startrack.camera/1"

#: Every projection, ``"pinhole"`` first (the default); the kernels' code of each is its index.
PROJECTIONS = ("pinhole", "equidistant", "equisolid", "stereographic", "orthographic")

# The largest angle from the boresight (radians) each projection maps one-to-one.
_THETA_MAX = {"pinhole": math.pi / 2, "equidistant": math.pi, "equisolid": math.pi, "stereographic": math.pi,
              "orthographic": math.pi / 2}

# Newton's stopping step, relative: four units in the last place.  Once converged, a step is rounding noise of
# about one ulp of the radius (2.2e-16 at 1, 2.6e-16 at 1.17): a bound below that (1e-16) was never met on about a
# third of a lens's calls, which then ran all their iterations for nothing.
_NEWTON_TOL = 4.0 * np.finfo(np.float64).eps


def projection_radius(projection: str, theta):
    """``g(theta)`` of ``projection``: the radius over the focal length (radians in)."""
    theta = np.asarray(theta, dtype=np.float64)
    if projection == "equidistant":
        return theta
    if projection == "equisolid":
        return 2.0 * np.sin(theta / 2.0)
    if projection == "stereographic":
        return 2.0 * np.tan(theta / 2.0)
    if projection == "orthographic":
        return np.sin(theta)
    if projection == "pinhole":
        return np.tan(theta)
    raise ParameterError("projection", f"unknown projection {projection!r}; one of {', '.join(PROJECTIONS)}")


def projection_angle(projection: str, radius):
    """The inverse of :func:`projection_radius`: ``theta`` (radians) of ``radius = r / f``; NaN where none."""
    radius = np.asarray(radius, dtype=np.float64)
    # A rounding error's worth beyond the largest radius is the largest radius (90 deg orthographic).
    with np.errstate(invalid="ignore"):
        if projection == "equidistant":
            return np.where(radius <= math.pi * (1 + 1e-12), np.minimum(radius, math.pi), np.nan)
        if projection == "equisolid":
            return 2.0 * np.arcsin(np.where(radius <= 2.0 * (1 + 1e-12), np.minimum(radius, 2.0), np.nan) / 2.0)
        if projection == "stereographic":
            return 2.0 * np.arctan(radius / 2.0)
        if projection == "orthographic":
            return np.arcsin(np.where(radius <= 1.0 + 1e-12, np.minimum(radius, 1.0), np.nan))
        if projection == "pinhole":
            return np.arctan(radius)
    raise ParameterError("projection", f"unknown projection {projection!r}; one of {', '.join(PROJECTIONS)}")


def parse_size(text: str, source: str = "size") -> tuple[int, int]:
    """Parse ``"WIDTHxHEIGHT"`` (e.g. ``"1024x768"``) into positive integers."""
    parts = str(text).lower().replace("×", "x").split("x")
    try:
        if len(parts) != 2:
            raise ValueError
        width, height = int(parts[0]), int(parts[1])
    except ValueError:
        raise ParameterError(source, f"expected WIDTHxHEIGHT such as 1024x768, got {text!r}") from None
    if width <= 0 or height <= 0:
        raise ParameterError(source, f"width and height must be positive, got {text!r}")
    return width, height


#: Bounds a camera read from a document must lie within: physically generous, finite (the largest sensors are about
#: 100k px a side; 1e9 px of focal length is 0.0002"/px, beyond any telescope; a focal length of 1e-4 of the
#: image's longer side is a pinhole field of 179.98 deg and a stereographic one of over 359 deg).  The principal
#: point may lie off the image (a crop), but within one image size of it.
MAX_SIDE_PX = 1_000_000
MAX_FOCAL_LENGTH_PX = 1e9
MIN_FOCAL_LENGTH_PER_SIDE = 1e-4
#: The lens terms k1..k4 are held by what they do, not by their size: the radial factor they apply at the image's
#: farthest corner, ``k1 x^2 + k2 x^4 (+ k3 x^6 + k4 x^8)`` with ``x`` the corner's normalised radius (a pinhole's
#: Brown-Conrady terms) or its off-axis angle in radians (OpenCV's fisheye terms; at most 90 deg, since a fisheye's
#: corners may lie beyond its image circle), lies within +-1: no lens moves a
#: corner by more than its own distance from the centre.  A term's size alone says little: a 2 deg field's k2 of
#: 1,000 moves its corner by 0.01 % (narrow-field calibrations often carry such ill-determined terms), while a
#: 120 deg pinhole's k1 of 1 moves it by 300 %.
MAX_DISTORTION_FRACTION = 1.0
#: Pixel pitch, micrometres: from under any sensor's smallest pixels (about 0.5 um, the wavelength of light)
#: to a millimetre.
PIXEL_PITCH_UM = (0.1, 1000.0)
DISTORTION_TERMS = ("k1", "k2", "k3", "k4")


def _bounds_problem(values: dict):
    """The first of ``values`` (width, height, focal_length_px, cx, cy, k1..k4, pixel_pitch_um: finite numbers;
    projection)
    outside the bounds above, as ``(field, problem)`` with ``field`` as a camera document spells it (``cx``,
    ``distortion.k1``); None when every one holds."""
    w, h = values["width"], values["height"]
    for name in ("width", "height"):
        if values[name] > MAX_SIDE_PX:
            return name, f"{values[name]:g} px is larger than any sensor (at most {MAX_SIDE_PX:g} px a side)"
    for name, size in (("cx", w), ("cy", h)):
        v = values[name]
        if not -size <= v <= 2 * size:
            side = "width" if name == "cx" else "height"
            return name, f"{v:g} is outside the image (0..{side} = 0..{size}, within one {side} of it: " \
                         f"{-size}..{2 * size})"
    pitch = values.get("pixel_pitch_um")
    lo, hi = PIXEL_PITCH_UM  # first: a focal length in mm over an absurd pitch is absurd in px
    if pitch is not None and not lo <= pitch <= hi:
        return "pixel_pitch_um", f"{pitch:g} um is outside {lo:g}..{hi:g} um (no sensor's pixels are smaller " \
                                 "than the light's wavelength, nor larger than a millimetre)"
    f = values["focal_length_px"]
    lo = MIN_FOCAL_LENGTH_PER_SIDE * max(w, h)
    if not lo <= f <= MAX_FOCAL_LENGTH_PX:
        return "focal_length_px", f"{f:g} px is outside {lo:g}..{MAX_FOCAL_LENGTH_PX:g} px (1e-4 of the image's " \
                                  f"longer side, {max(w, h)} px, up to 0.0002 arcsec per pixel)"
    ks = [float(values.get(name, 0.0)) for name in DISTORTION_TERMS]
    if any(ks):
        x = _corner_radius(values, f)
        effect = sum(k * x ** (2 * i + 2) for i, k in enumerate(ks))
        if not abs(effect) <= MAX_DISTORTION_FRACTION:
            terms = ", ".join(f"{n} {k:g}" for n, k in zip(DISTORTION_TERMS, ks, strict=True) if k)
            return "distortion", f"the lens terms ({terms}) move the image's farthest corner by {100 * effect:.3g} % of its " \
                                 f"radius (at most {100 * MAX_DISTORTION_FRACTION:g} %: no lens does more)"
    return None


def _corner_radius(values: dict, f: float) -> float:
    """The variable of the lens terms' polynomial at the image's farthest corner from the principal point: the
    normalised radius of a pinhole, the off-axis angle (radians) of a fisheye projection (its largest where
    the corner lies beyond the projection's range)."""
    w, h, cx, cy = values["width"], values["height"], values["cx"], values["cy"]
    rho = math.hypot(max(cx + 0.5, w - 0.5 - cx), max(cy + 0.5, h - 0.5 - cy)) / f
    projection = values.get("projection", "pinhole")
    if projection == "pinhole":
        return rho
    # A fisheye's corners may lie beyond its image circle, where the terms, fitted inside it, say nothing: they
    # are held to their effect within 90 deg of the axis at most.
    theta = float(projection_angle(projection, rho))
    return min(theta, math.pi / 2) if math.isfinite(theta) else math.pi / 2


def parameter_bounds(width: int, height: int) -> dict:
    """``{name: (lo, hi)}``: the bounds of a ``width`` x ``height`` camera's focal length and principal point (those
    :class:`Camera` holds to), e.g. for a fit to keep its steps within.  The lens terms' bound is on their effect
    (:data:`MAX_DISTORTION_FRACTION`), not a box."""
    return {"focal_length_px": (MIN_FOCAL_LENGTH_PER_SIDE * max(width, height), MAX_FOCAL_LENGTH_PX),
            "cx": (-width, 2 * width), "cy": (-height, 2 * height)}


def _check_geometry(values: dict, source: str) -> None:
    """Refuse finite but absurd camera values (bounds above), naming the field (``camera.FIELD``)."""
    problem = _bounds_problem(values)
    if problem is not None:
        raise BadInputError(source, f"camera.{problem[0]}", problem[1])


def _finite(value, source, name, positive=False):
    if isinstance(value, bool) or not isinstance(value, (int, float, np.floating, np.integer)):
        raise BadInputError(source, name, f"must be a number, got {type(value).__name__}")
    value = float(value)
    if not math.isfinite(value):
        raise BadInputError(source, name, f"must be a finite number, got {value}")
    if positive and value <= 0:
        raise BadInputError(source, name, f"must be positive, got {value:g}")
    return value


def _parameter(value, name, source, positive=False):
    """``value`` as a finite float, else :class:`ParameterError` naming the parameter ``name``."""
    try:
        return _finite(value, source, name, positive)
    except BadInputError as exc:
        raise ParameterError(name, exc.problem, source) from None


@dataclass(frozen=True)
class Camera:
    """A pinhole camera with optional radial distortion, or a fisheye projection.

    Parameters
    ----------
    width, height : int
        Image size in pixels.
    focal_length_px : float
        Focal length in pixels (focal length / pixel pitch).
    cx, cy : float
        Principal point in pixels; ``((width - 1) / 2, (height - 1) / 2)`` is the
        image centre.
    k1, k2 : float
        Radial distortion coefficients: on the normalised coordinates for a pinhole
        (``1 + k1 r^2 + k2 r^4``), on the off-axis angle for a fisheye
        (``theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8)``).
    pixel_pitch_um : float or None
        Pixel pitch in micrometres, when known (only for reporting in mm).
    projection : str
        One of :data:`PROJECTIONS` (module docstring); ``"pinhole"`` by default.
    k3, k4 : float
        The fisheye model's higher terms (0 for a pinhole).
    """

    width: int
    height: int
    focal_length_px: float
    cx: float
    cy: float
    k1: float = 0.0
    k2: float = 0.0
    pixel_pitch_um: float | None = None
    extra: dict = field(default_factory=dict, compare=False, repr=False)
    projection: str = "pinhole"
    k3: float = 0.0
    k4: float = 0.0

    def __post_init__(self):
        w, h, f, cx, cy, k1, k2, k3, k4 = (self.width, self.height, self.focal_length_px, self.cx, self.cy, self.k1,
                                           self.k2, self.k3, self.k4)
        if (type(w) is int and type(h) is int and type(f) is float and type(cx) is float and type(cy) is float
                and type(k1) is float and type(k2) is float and k3 == 0.0 and k4 == 0.0 and type(k3) is float
                and type(k4) is float and self.pixel_pitch_um is None and self.projection == "pinhole"
                and w > 0 and h > 0 and 0.0 < f < math.inf and math.isfinite(cx) and math.isfinite(cy)
                and math.isfinite(k1) and math.isfinite(k2)):
            # The common case (a solver's own pinhole cameras, a camera file's): every value already the type and
            # finite number the checks below make of it, so the same bounds decide.  Anything else takes the
            # full path (its messages).
            if _bounds_problem({"width": w, "height": h, "focal_length_px": f, "cx": cx, "cy": cy, "k1": k1,
                                "k2": k2, "k3": k3, "k4": k4, "projection": "pinhole"}) is None:
                return
        if self.projection not in PROJECTIONS:
            raise ParameterError("projection", f"unknown projection {self.projection!r}; one of "
                                 f"{', '.join(PROJECTIONS)}", "Camera")
        if self.projection == "pinhole" and (self.k3 or self.k4):
            raise ParameterError("k3", "a pinhole camera has k1 and k2 only (k3 and k4 are the fisheye model's)",
                                 "Camera")
        # The bounds a camera document is held to (from_dict), for library callers too: finite, physically
        # possible values, else a ParameterError naming the parameter (never a NaN deep in a kernel).
        values = {}
        for name in ("width", "height"):
            v = getattr(self, name)
            v = _parameter(v, name, "Camera", positive=True)
            if v != int(v):
                raise ParameterError(name, f"must be a whole number, got {v:g}", "Camera")
            values[name] = int(v)
            if type(getattr(self, name)) is not int:
                object.__setattr__(self, name, int(v))
        for name in ("focal_length_px", "cx", "cy", *DISTORTION_TERMS):
            values[name] = _parameter(getattr(self, name), name, "Camera", positive=(name == "focal_length_px"))
        if self.pixel_pitch_um is not None:
            values["pixel_pitch_um"] = _parameter(self.pixel_pitch_um, "pixel_pitch_um", "Camera", positive=True)
        values["projection"] = self.projection
        problem = _bounds_problem(values)
        if problem is not None:
            raise ParameterError(problem[0].split(".")[-1], problem[1], "Camera")

    @classmethod
    def _probe(cls, values: dict) -> "Camera":
        """A camera of ``values`` (every field) *without* the bounds' checks: for a fitter's finite-difference
        probes, which may step just past a bound.  Never returned to a caller: what a fit returns is built with
        ``Camera(...)``."""
        cam = object.__new__(cls)
        for f in dataclasses.fields(cls):
            object.__setattr__(cam, f.name, values[f.name])
        return cam

    # ------------------------------------------------------------------ builders
    @classmethod
    def from_fov(cls, fov_deg: float, width: int, height: int, **kw) -> "Camera":
        """A camera whose horizontal field of view (across ``width``) is ``fov_deg``.

        The field spans the full pixel extent, ``width`` pixels, so
        ``f = (width / 2) / g(fov / 2)`` with ``g`` the projection's radius function
        (``tan`` for a pinhole), before any distortion.  A pinhole's field is below
        180 degrees, an orthographic one's at most 180, the others' at most 360
        (below it for the stereographic).
        """
        fov_deg = _parameter(fov_deg, "fov_deg", "Camera.from_fov", positive=True)
        projection = kw.get("projection", "pinhole")
        if projection not in PROJECTIONS:
            raise ParameterError("projection", f"unknown projection {projection!r}; one of {', '.join(PROJECTIONS)}",
                                 "Camera.from_fov")
        limit = 2.0 * math.degrees(_THETA_MAX[projection])
        if not (fov_deg < limit if projection in ("pinhole", "stereographic") else fov_deg <= limit):
            raise ParameterError("fov_deg", f"must be {'below' if projection in ('pinhole', 'stereographic') else 'at most'} "
                                 f"{limit:g} degrees for the {projection} projection, got {fov_deg:g}", "Camera.from_fov")
        if width <= 0 or height <= 0:
            raise ParameterError("width", f"width and height must be positive, got {width}x{height}")
        f = (width / 2.0) / float(projection_radius(projection, math.radians(fov_deg) / 2.0))
        return cls(width, height, f, (width - 1) / 2.0, (height - 1) / 2.0, **kw)

    @classmethod
    def from_focal_length_mm(
        cls, focal_length_mm: float, pixel_pitch_um: float, width: int, height: int, **kw
    ) -> "Camera":
        """A camera from its lens focal length (mm) and pixel pitch (um)."""
        f_mm = _parameter(focal_length_mm, "focal_length_mm", "Camera.from_focal_length_mm", positive=True)
        pitch = _parameter(pixel_pitch_um, "pixel_pitch_um", "Camera.from_focal_length_mm", positive=True)
        if width <= 0 or height <= 0:
            raise ParameterError("width", f"width and height must be positive, got {width}x{height}")
        f = f_mm * 1000.0 / pitch
        return cls(width, height, f, (width - 1) / 2.0, (height - 1) / 2.0,
                   pixel_pitch_um=pitch, **kw)

    @classmethod
    def from_dict(cls, doc: dict, source: str = "camera") -> "Camera":
        """Build and validate a camera from a frame's ``camera`` section or a camera file."""
        if not isinstance(doc, dict):
            raise BadInputError(source, "camera", "must be a JSON object")
        values = {}
        for name in ("width", "height"):
            if name not in doc:
                raise BadInputError(source, f"camera.{name}", "is missing")
            v = _finite(doc[name], source, f"camera.{name}", positive=True)
            if v != int(v):
                raise BadInputError(source, f"camera.{name}", f"must be a whole number, got {v:g}")
            values[name] = int(v)
        for name in ("focal_length_px", "cx", "cy"):
            if name not in doc:
                raise BadInputError(source, f"camera.{name}", "is missing")
            values[name] = _finite(doc[name], source, f"camera.{name}", positive=(name == "focal_length_px"))
        _check_geometry(values, source)
        projection = doc.get("projection", "pinhole")
        if projection not in PROJECTIONS:
            raise BadInputError(source, "camera.projection", f"must be one of {', '.join(PROJECTIONS)}, "
                                f"got {projection!r}")
        dist = doc.get("distortion") or {}
        if not isinstance(dist, dict):
            raise BadInputError(source, "camera.distortion", "must be an object with k1, k2 (k3, k4 for a fisheye)")
        names = ("k1", "k2") if projection == "pinhole" else ("k1", "k2", "k3", "k4")
        unknown = sorted(set(dist) - set(names))
        if unknown:
            raise BadInputError(source, f"camera.distortion.{unknown[0]}",
                                f"is not a term of the {projection} model (it has {', '.join(names)})")
        ks = [_finite(dist.get(name, 0.0), source, f"camera.distortion.{name}") for name in ("k1", "k2", "k3", "k4")
              if name in names]
        ks += [0.0] * (4 - len(ks))
        pitch = doc.get("pixel_pitch_um")
        if pitch is not None:
            pitch = _finite(pitch, source, "camera.pixel_pitch_um", positive=True)
        _check_geometry({**values, **dict(zip(DISTORTION_TERMS, ks, strict=True)), "pixel_pitch_um": pitch,
                         "projection": projection}, source)
        known = {"format", "width", "height", "focal_length_px", "cx", "cy", "distortion",
                 "pixel_pitch_um", "focal_length_mm", "fov_deg", "projection"}
        extra = {k: v for k, v in doc.items() if k not in known}
        return cls(values["width"], values["height"], values["focal_length_px"],
                   values["cx"], values["cy"], ks[0], ks[1], pitch, extra, projection, ks[2], ks[3])

    def to_dict(self, standalone: bool = False) -> dict:
        """The camera as a ``camera`` section (or a ``startrack.camera/1`` file)."""
        doc: dict = {}
        if standalone:
            doc["format"] = CAMERA_FORMAT
        doc.update(
            width=int(self.width),
            height=int(self.height),
            focal_length_px=float(self.focal_length_px),
            cx=float(self.cx),
            cy=float(self.cy),
        )
        if self.projection != "pinhole":
            doc["projection"] = self.projection
        if self.has_distortion:
            doc["distortion"] = {"k1": float(self.k1), "k2": float(self.k2)}
            if self.projection != "pinhole":
                doc["distortion"].update(k3=float(self.k3), k4=float(self.k4))
        if self.pixel_pitch_um is not None:
            doc["pixel_pitch_um"] = float(self.pixel_pitch_um)
            doc["focal_length_mm"] = float(self.focal_length_px * self.pixel_pitch_um / 1000.0)
        fx, fy = self.fov_deg
        doc["fov_deg"] = [round(fx, 6), round(fy, 6)]
        doc.update(self.extra)
        return doc

    def with_focal_length(self, focal_length_px: float) -> "Camera":
        """The same camera with another focal length (e.g. a perturbed one)."""
        return self.replace(focal_length_px=float(focal_length_px))

    def replace(self, **changes) -> "Camera":
        """The same camera with some fields changed (as ``dataclasses.replace``, ``extra`` copied)."""
        changes.setdefault("extra", dict(self.extra))
        # dataclasses.replace's work without its per-call look-up of the fields (a fit builds a camera per round).
        values = {name: getattr(self, name) for name in _FIELD_NAMES}
        values.update(changes)
        return type(self)(**values)

    # --------------------------------------------------------------- geometry
    @property
    def is_pinhole(self) -> bool:
        return self.projection == "pinhole"

    @property
    def projection_code(self) -> int:
        """The projection's index in :data:`PROJECTIONS` (the kernels' ``proj`` argument)."""
        return PROJECTIONS.index(self.projection)

    @property
    def lens_terms(self) -> tuple:
        """``(k1, k2, k3, k4, projection_code)``: what the kernels take after the principal point."""
        return (float(self.k1), float(self.k2), float(self.k3), float(self.k4), self.projection_code)

    @property
    def has_distortion(self) -> bool:
        return bool(self.k1 or self.k2 or self.k3 or self.k4)

    @property
    def max_valid_r2(self) -> float:
        """Largest squared normalised radius where the pinhole lens model is one-to-one.

        ``r_d = r (1 + k1 r^2 + k2 r^4)`` turns back on itself where
        ``1 + 3 k1 r^2 + 5 k2 r^4 = 0``; directions beyond that radius would fold
        back into the image, so :meth:`vectors_to_pixels` returns NaN for them.
        A fisheye camera has no tangent plane: ``tan^2`` of :attr:`max_theta` (inf at
        or beyond 90 degrees).
        """
        if not self.is_pinhole:
            t = self.max_theta
            return math.tan(t) ** 2 if t < math.pi / 2 else math.inf
        if not self.has_distortion:
            return math.inf
        a, b = 5.0 * self.k2, 3.0 * self.k1
        disc = b * b - 4.0 * a
        if disc < 0:
            return math.inf
        sq = math.sqrt(disc)
        # Roots of a s^2 + b s + 1 = 0 as 2 / (-b -/+ sq): stable when a -> 0.
        real = [2.0 / d for d in (-b - sq, -b + sq) if d > 0]
        return min(real) if real else math.inf

    def theta_distorted(self, theta):
        """``theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8)`` (a fisheye's distortion)."""
        theta = np.asarray(theta, dtype=np.float64)
        t2 = theta * theta
        return theta * (1.0 + t2 * (self.k1 + t2 * (self.k2 + t2 * (self.k3 + t2 * self.k4))))

    def _theta_slope(self, theta):
        t2 = theta * theta
        return 1.0 + t2 * (3.0 * self.k1 + t2 * (5.0 * self.k2 + t2 * (7.0 * self.k3 + t2 * 9.0 * self.k4)))

    def theta_undistorted(self, theta_d):
        """Invert :meth:`theta_distorted` by Newton's method (to ~1e-15 rad); NaN beyond :attr:`max_theta`."""
        theta_d = np.asarray(theta_d, dtype=np.float64)
        if not self.has_distortion:
            return theta_d.copy()
        tmax = self.max_theta
        td_max = float(self.theta_distorted(tmax))
        with np.errstate(invalid="ignore"):
            bad = ~(theta_d <= td_max)
            target = np.where(bad, 0.0, theta_d)
        theta = np.clip(target, 0.0, tmax)
        for _ in range(60):
            step = (self.theta_distorted(theta) - target) / self._theta_slope(theta)
            theta = np.clip(theta - step, 0.0, tmax)
            if np.all(np.abs(step) <= _NEWTON_TOL * (1.0 + theta)):
                break
        return np.where(bad, np.nan, theta)

    @functools.cached_property
    def max_theta(self) -> float:
        """The largest off-axis angle (radians) the model maps one-to-one onto a radius.

        The projection's own limit (:data:`PROJECTIONS`' table in the module docstring),
        or less: where ``theta_d(theta)`` stops increasing, or where ``theta_d`` reaches the
        projection's limit.  For a pinhole, ``atan`` of ``sqrt(max_valid_r2)``.
        """
        if self.is_pinhole:
            return math.atan(math.sqrt(self.max_valid_r2)) if self.has_distortion else math.pi / 2
        limit = _THETA_MAX[self.projection]
        if not self.has_distortion:
            return limit
        # Cached by the lens terms: a fit (calibrate) builds a camera per evaluation, most with the same terms.
        return _fisheye_max_theta(limit, float(self.k1), float(self.k2), float(self.k3), float(self.k4))

    @property
    def max_radius_px(self) -> float:
        """The radius (pixels from the principal point) of :attr:`max_theta`: the image circle (inf for a pinhole)."""
        if self.is_pinhole:
            return math.inf
        return self.focal_length_px * float(projection_radius(self.projection, self.theta_distorted(self.max_theta)))

    def distort(self, u, v):
        """Apply a pinhole's radial distortion to normalised coordinates."""
        if not self.has_distortion:
            return np.asarray(u, dtype=np.float64), np.asarray(v, dtype=np.float64)
        r2 = u * u + v * v
        scale = 1.0 + self.k1 * r2 + self.k2 * r2 * r2
        return u * scale, v * scale

    def undistort(self, ud, vd):
        """Invert :meth:`distort` by Newton's method on the radius (to ~1e-15)."""
        ud = np.asarray(ud, dtype=np.float64)
        vd = np.asarray(vd, dtype=np.float64)
        if not self.has_distortion:
            return ud, vd
        rd = np.hypot(ud, vd)
        r = rd.copy()
        k1, k2 = self.k1, self.k2
        for _ in range(50):
            r2 = r * r
            g = r * (1.0 + k1 * r2 + k2 * r2 * r2) - rd
            dg = 1.0 + 3.0 * k1 * r2 + 5.0 * k2 * r2 * r2
            step = g / dg
            r = r - step
            if np.all(np.abs(step) <= _NEWTON_TOL * (1.0 + np.abs(r))):
                break
        with np.errstate(invalid="ignore", divide="ignore"):
            ratio = np.where(rd > 0, r / np.where(rd > 0, rd, 1.0), 1.0)
        return ud * ratio, vd * ratio

    def pixels_to_theta(self, x, y):
        """The off-axis angle (radians) of pixel positions; NaN beyond the model's range (a fisheye's image circle)."""
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        if self.is_pinhole:
            v = self.pixels_to_vectors(x, y)
            return np.arccos(np.clip(v[..., 2], -1.0, 1.0))
        rho = np.hypot(x - self.cx, y - self.cy) / self.focal_length_px
        return self.theta_undistorted(projection_angle(self.projection, rho))

    def pixels_to_vectors(self, x, y):
        """Unit vectors in the camera frame of pixel positions (paper 000 Eq. 13 for a pinhole).

        Parameters
        ----------
        x, y : array_like
            Column and row in pixels.

        Returns
        -------
        ndarray, shape (..., 3)
            Unit vectors, distortion removed; NaN for a fisheye's pixels outside the
            range its model maps (beyond :attr:`max_radius_px`).
        """
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        if self.is_pinhole:
            u, v = self.undistort((x - self.cx) / self.focal_length_px,
                                  (y - self.cy) / self.focal_length_px)
            return unit_vectors(u, v)
        dx = x - self.cx
        dy = y - self.cy
        rho = np.hypot(dx, dy)
        theta = self.theta_undistorted(projection_angle(self.projection, rho / self.focal_length_px))
        with np.errstate(invalid="ignore", divide="ignore"):
            s = np.where(rho > 0, np.sin(theta) / np.where(rho > 0, rho, 1.0), 0.0)
        return np.stack([dx * s, dy * s, np.cos(theta)], axis=-1)

    def vectors_to_pixels(self, vectors):
        """Pixel positions of camera-frame directions.

        Returns
        -------
        x, y : ndarray
            NaN where the model maps no pixel: for a pinhole a direction away from the
            sky side (``Z <= 0``) or beyond the radius where the distortion folds back;
            for a fisheye an off-axis angle beyond :attr:`max_theta`.
        """
        vec = np.asarray(vectors, dtype=np.float64)
        if not self.is_pinhole:
            rxy = np.hypot(vec[..., 0], vec[..., 1])
            theta = np.arctan2(rxy, vec[..., 2])
            theta = np.where(theta <= self.max_theta, theta, np.nan)
            radius = self.focal_length_px * projection_radius(self.projection, self.theta_distorted(theta))
            with np.errstate(invalid="ignore", divide="ignore"):
                s = np.where(rxy > 0, radius / np.where(rxy > 0, rxy, 1.0), 0.0)
            return self.cx + vec[..., 0] * s, self.cy + vec[..., 1] * s
        z = vec[..., 2]
        with np.errstate(invalid="ignore", divide="ignore"):
            zz = np.where(z > 0, z, np.nan)
            u = vec[..., 0] / zz
            v = vec[..., 1] / zz
        if self.has_distortion:
            beyond = u * u + v * v > self.max_valid_r2
            u = np.where(beyond, np.nan, u)
            v = np.where(beyond, np.nan, v)
        ud, vd = self.distort(u, v)
        return self.cx + self.focal_length_px * ud, self.cy + self.focal_length_px * vd

    def in_image(self, x, y, margin: float = 0.0):
        """True where ``(x, y)`` lies on the sensor (pixel edges at -0.5 and size-0.5)."""
        x = np.asarray(x)
        y = np.asarray(y)
        return ((x >= -0.5 + margin) & (x <= self.width - 0.5 - margin)
                & (y >= -0.5 + margin) & (y <= self.height - 0.5 - margin))

    def _theta_clamped(self, x, y):
        """Off-axis angles (radians) of pixel positions, those beyond the image circle at :attr:`max_theta`."""
        theta = self.pixels_to_theta(x, y)
        return np.where(np.isfinite(theta), theta, self.max_theta)

    @functools.cached_property
    def fov_deg(self) -> tuple[float, float]:
        """Horizontal and vertical field of view in degrees (edge to edge, through the principal point).

        Computed once per camera (a frozen dataclass: a changed camera is a new object).

        A fisheye's field can exceed 180 degrees: it is the sum of the two edges' off-axis
        angles, each at most :attr:`max_theta` (a circular fisheye's image circle inside the
        sensor gives the circle's field)."""
        xs = np.array([-0.5, self.width - 0.5])
        ys = np.array([-0.5, self.height - 0.5])
        if not self.is_pinhole:
            tx = self._theta_clamped(xs, np.full(2, self.cy))
            ty = self._theta_clamped(np.full(2, self.cx), ys)
            # Edges on either side of the principal point add up; on one side, they subtract.
            across_x = tx[0] + tx[1] if -0.5 <= self.cx <= self.width - 0.5 else abs(tx[1] - tx[0])
            across_y = ty[0] + ty[1] if -0.5 <= self.cy <= self.height - 0.5 else abs(ty[1] - ty[0])
            return math.degrees(across_x), math.degrees(across_y)
        if not self.has_distortion:
            # The two edges' directions lie in one plane through the boresight (y = 0, then x = 0): the angle
            # between them is the difference of their angles from the boresight (exact; no vectors made).
            f = self.focal_length_px
            return (math.degrees(math.atan((self.width - 0.5 - self.cx) / f) - math.atan((-0.5 - self.cx) / f)),
                    math.degrees(math.atan((self.height - 0.5 - self.cy) / f) - math.atan((-0.5 - self.cy) / f)))
        vx = self.pixels_to_vectors(xs, np.full(2, self.cy))
        vy = self.pixels_to_vectors(np.full(2, self.cx), ys)
        ax = math.degrees(math.acos(float(np.clip(vx[0] @ vx[1], -1, 1))))
        ay = math.degrees(math.acos(float(np.clip(vy[0] @ vy[1], -1, 1))))
        return ax, ay

    @property
    def diagonal_fov_deg(self) -> float:
        """The largest angle between two image corners, in degrees (a fisheye: the larger sum of two
        opposite corners' off-axis angles, each at most :attr:`max_theta`)."""
        xs = np.array([-0.5, self.width - 0.5, -0.5, self.width - 0.5])
        ys = np.array([-0.5, self.height - 0.5, self.height - 0.5, -0.5])
        if not self.is_pinhole:
            t = self._theta_clamped(xs, ys)
            return math.degrees(max(t[0] + t[1], t[2] + t[3]))
        c = self.pixels_to_vectors(xs, ys)
        a = math.acos(float(np.clip(c[0] @ c[1], -1, 1)))
        b = math.acos(float(np.clip(c[2] @ c[3], -1, 1)))
        return math.degrees(max(a, b))

    @functools.cached_property
    def max_off_axis_deg(self) -> float:
        """The largest angle between the boresight and any image corner, in degrees (at most
        :attr:`max_theta`: a fisheye's corners beyond its image circle see nothing)."""
        xs = np.array([-0.5, self.width - 0.5, -0.5, self.width - 0.5])
        ys = np.array([-0.5, self.height - 0.5, self.height - 0.5, -0.5])
        if not self.is_pinhole:
            return math.degrees(float(np.max(self._theta_clamped(xs, ys))))
        c = self.pixels_to_vectors(xs, ys)
        return math.degrees(math.acos(float(np.clip(c[:, 2].min(), -1, 1))))

    def cone_cos(self, margin_deg: float = 0.0) -> float:
        """``cos`` of the off-axis angle a catalog search around the boresight must reach: the farthest
        corner's plus ``margin_deg`` (a fisheye: at most :attr:`max_theta`, where the model ends)."""
        off_axis = self.max_off_axis_deg + margin_deg
        if not self.is_pinhole:
            off_axis = min(off_axis, math.degrees(self.max_theta))
        return math.cos(math.radians(off_axis))

    @functools.cached_property
    def sky_fraction(self) -> float:
        """The fraction of the whole sky the image sees (its solid angle over 4 pi sr).

        A pinhole's is ``width height / f^2 / (4 pi)`` (the tangent plane's area at the centre, as the
        verification has always counted it); a fisheye's is counted on 40,000 directions spread evenly
        over the sphere (a Fibonacci lattice: about 0.5 % of error)."""
        if self.is_pinhole:
            return self.width * self.height / self.focal_length_px ** 2 / (4.0 * math.pi)
        n = 40000
        k = np.arange(n) + 0.5
        z = 1.0 - 2.0 * k / n
        phi = math.pi * (3.0 - math.sqrt(5.0)) * k
        s = np.sqrt(1.0 - z * z)
        x, y = self.vectors_to_pixels(np.stack([s * np.cos(phi), s * np.sin(phi), z], axis=-1))
        return float(np.count_nonzero(self.in_image(x, y) & np.isfinite(x))) / n

    @property
    def pixel_scale_arcsec(self) -> float:
        """Angular size of one pixel at the principal point, in arcseconds (every projection has
        ``g'(0) = 1``, so it is ``1 / f`` radians)."""
        return math.degrees(1.0 / self.focal_length_px) * 3600.0


def unit_vectors(u, v):
    """``(u, v, 1)`` divided by its norm, shape ``(..., 3)`` (C-contiguous): a pinhole's line-of-sight vectors of
    the normalised image coordinates ``u``, ``v``.  The norm is summed as numpy's reduction over the last axis sums
    it (left to right: the bits of ``np.linalg.norm`` of the stacked vectors, tests/test_camera.py), without
    stacking them twice."""
    norm = np.sqrt(u * u + v * v + 1.0)
    su, sv = np.shape(u), np.shape(v)
    # (u and v mostly have one shape, their broadcast shape: numpy's broadcast_shapes is Python, ~2 us a call)
    vec = np.empty((su if su == sv else np.broadcast_shapes(su, sv)) + (3,))
    vec[..., 0] = u / norm
    vec[..., 1] = v / norm
    vec[..., 2] = 1.0 / norm
    return vec


#: :class:`Camera`'s fields, in order (what :meth:`Camera.replace` copies).
_FIELD_NAMES = tuple(f.name for f in dataclasses.fields(Camera))


@functools.lru_cache(maxsize=4096)
def _fisheye_max_theta(limit, k1, k2, k3, k4):
    """:attr:`Camera.max_theta` of a distorted fisheye whose projection reaches ``limit`` (radians): the first
    angle on a 20001-point grid where ``theta_d`` stops increasing or leaves ``[0, limit]``, then bisection
    (in plain floats: the same operations as the arrays')."""
    def slope(t):
        t2 = t * t
        return 1.0 + t2 * (3.0 * k1 + t2 * (5.0 * k2 + t2 * (7.0 * k3 + t2 * 9.0 * k4)))

    def distorted(t):
        t2 = t * t
        return t * (1.0 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))

    grid = np.linspace(0.0, limit, 20001)
    ok = (slope(grid) > 0) & (distorted(grid) <= limit) & (distorted(grid) >= 0)
    first_bad = np.flatnonzero(~ok)
    if len(first_bad) == 0:
        return limit
    if first_bad[0] == 0:
        return 0.0
    lo, hi = float(grid[first_bad[0] - 1]), float(grid[first_bad[0]])
    for _ in range(60):     # bisection to the boundary
        mid = 0.5 * (lo + hi)
        good = slope(mid) > 0 and 0 <= distorted(mid) <= limit
        lo, hi = (mid, hi) if good else (lo, mid)
    return lo
