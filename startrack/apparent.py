"""Apparent places: the time of a frame, the observer's velocity and stellar aberration.

A camera that moves at velocity ``v`` sees a star displaced from its catalog
(astrometric, ICRS) direction toward the direction of motion by up to
``v / c``: 20.5 arcsec for the Earth's orbital motion (about 30 km/s), up to
5 arcsec more for a spacecraft in low Earth orbit.  A frame's observed
directions are compared with *apparent* catalog directions: proper motion to the
frame's epoch (``Catalog.propagate``), then light deflection by the Sun and
relativistic aberration for the observer's barycentric velocity, the Earth's
(``erfa.epv00``: no ephemeris of our own) plus the spacecraft's own velocity
relative to the geocentre (GCRS).

* :func:`frame_time` finds a frame's time (UTC) and says where it came from.
* :func:`earth_velocity_km_s`, :func:`observer_state` give the velocity.
* :func:`aberrate` / :func:`unaberrate` move unit vectors between the
  astrometric and apparent places (``erfa.ldsun`` then ``erfa.ab``: the
  Explanatory Supplement 3rd ed. Eq. 7.40 made rigorous, SOFA/ERFA); they agree
  with astropy's ICRS -> GCRS transformation of a star at infinity to well under
  a milliarcsecond (``tests/test_apparent.py``).

Velocities are added as vectors (the barycentric velocity of the spacecraft
``v_earth + v_sc``): the relativistic composition differs by terms of order
``v_earth v_sc / c^2``, about 1e-9 rad (0.2 mas).  Parallax is not applied.
"""
from __future__ import annotations

import datetime as _dt
import math
from dataclasses import dataclass

import numpy as np

from startrack.errors import BadInputError

__all__ = [
    "C_KM_S",
    "FrameTime",
    "ObserverState",
    "aberrate",
    "unaberrate",
    "earth_velocity_km_s",
    "observer_state",
    "frame_time",
    "fits_time",
    "exif_time",
    "apparent_scale",
]

C_KM_S = 299792.458
AU_KM = 149597870.7
_DAY_S = 86400.0


@dataclass(frozen=True)
class FrameTime:
    """A frame's time (UTC, mid-exposure as far as the source says) and where it came from.

    ``source`` is one of ``"given"`` (by the user, for every frame), ``"image.time"`` (the frame
    document), ``"FITS DATE-OBS"``, ``"FITS MJD-OBS"``, ``"EXIF DateTimeOriginal"``, or
    ``None`` with ``time`` ``None`` when nothing gives one.
    """

    time: _dt.datetime | None
    source: str | None

    @property
    def known(self) -> bool:
        return self.time is not None


@dataclass(frozen=True)
class ObserverState:
    """What aberration needs at one time: the observer's barycentric velocity and the Sun.

    ``velocity_km_s`` is BCRS (barycentric, ICRS axes) in km/s: the Earth's plus the
    spacecraft's GCRS velocity ``spacecraft_km_s``; ``sun_to_observer`` the unit vector
    from the Sun to the geocentre and ``sun_distance_au`` its length.
    """

    velocity_km_s: np.ndarray
    earth_km_s: np.ndarray
    spacecraft_km_s: np.ndarray
    sun_to_observer: np.ndarray
    sun_distance_au: float
    #: The observer's barycentric position (au, ICRS axes): the Earth's (``erfa.epv00``); None: parallax unknown.
    position_au: np.ndarray | None = None

    @property
    def beta(self) -> np.ndarray:
        return self.velocity_km_s / C_KM_S


def _tdb_jd(t: _dt.datetime) -> tuple[float, float]:
    """Two-part Julian date, TT (= TDB within 2 ms, which moves the Earth's velocity by 1e-11 of itself)."""
    import erfa

    t = t.astimezone(_dt.timezone.utc)
    seconds = t.hour * 3600 + t.minute * 60 + t.second + t.microsecond * 1e-6
    jd1, jd2 = erfa.cal2jd(t.year, t.month, t.day)
    jd1 = float(jd1) + float(jd2)
    leap = float(erfa.dat(t.year, t.month, t.day, seconds / _DAY_S))
    return jd1, (seconds + leap + 32.184) / _DAY_S


def _earth_pv(t: _dt.datetime):
    import erfa

    jd1, jd2 = _tdb_jd(t)
    pvh, pvb = erfa.epv00(jd1, jd2)
    # pyerfa returns structured position-velocity arrays: p (au) and v (au/day).
    return np.asarray(pvh["p"], dtype=float), np.asarray(pvb["v"], dtype=float), np.asarray(pvb["p"], dtype=float)


def earth_velocity_km_s(t: _dt.datetime) -> np.ndarray:
    """The Earth's (geocentre's) barycentric velocity at UTC ``t``, km/s, ICRS axes (``erfa.epv00``)."""
    _, vb, _ = _earth_pv(t)
    return vb * AU_KM / _DAY_S


def observer_state(t: _dt.datetime, spacecraft_km_s=None) -> ObserverState:
    """The observer's state at UTC ``t``: the Earth's barycentric velocity plus ``spacecraft_km_s`` (GCRS, km/s)."""
    ph, vb, pb = _earth_pv(t)
    earth = vb * AU_KM / _DAY_S
    sc = np.zeros(3) if spacecraft_km_s is None else np.asarray(spacecraft_km_s, dtype=float).reshape(3)
    if not np.all(np.isfinite(sc)):
        raise BadInputError("observer velocity", None, "must be three finite numbers (km/s)")
    total = earth + sc
    if np.linalg.norm(total) >= 0.01 * C_KM_S:
        raise BadInputError("observer velocity", None, f"{np.linalg.norm(total):.0f} km/s is not an orbital speed")
    distance = float(np.linalg.norm(ph))
    # The spacecraft's offset from the geocentre (< 3e-4 au even at the Moon's distance) is left out of the
    # parallax: it moves the nearest star's direction by under 0.3 mas.
    return ObserverState(total, earth, sc, ph / distance, distance, pb)


def velocity_state(velocity_km_s, sun_to_observer=(1.0, 0.0, 0.0), sun_distance_au: float = 1.0) -> ObserverState:
    """An :class:`ObserverState` for a given barycentric velocity (km/s) without a time (tests, studies)."""
    v = np.asarray(velocity_km_s, dtype=float).reshape(3)
    e = np.asarray(sun_to_observer, dtype=float).reshape(3)
    return ObserverState(v, v, np.zeros(3), e / np.linalg.norm(e), float(sun_distance_au))


def aberrate(vectors, state: ObserverState, deflection: bool = True, parallax_mas=None) -> np.ndarray:
    """Apparent directions of stars for the observer ``state``.

    Parameters
    ----------
    vectors : ndarray (n, 3) or (3,)
        Astrometric unit vectors (ICRS, at the frame's epoch), as seen from the barycentre.
    state : ObserverState
    deflection : bool
        Light deflection by the Sun first (``erfa.ldsun``; 4 mas at 90 deg from the Sun).
    parallax_mas : float or ndarray (n,), optional
        The stars' parallaxes: each direction is first moved to the observer's place,
        ``u - p * b`` renormalised with ``p`` the parallax (rad) and ``b`` the observer's
        barycentric position (au; SOFA's ``iauPmpx`` without the space motion, which
        :meth:`startrack.catalog.Catalog.propagate` applies); up to 0.77" (alpha Centauri).
        Needs ``state.position_au``; without it, or without parallaxes, stars are at infinity.

    Returns
    -------
    ndarray of the same shape: apparent unit vectors (ICRS axes), relativistic aberration
    (``erfa.ab`` with the Sun's distance term, as SOFA's ``iauAtciqz``).
    """
    import erfa

    u = np.ascontiguousarray(vectors, dtype=np.float64)
    if parallax_mas is not None and state.position_au is not None:
        p = np.asarray(parallax_mas, dtype=np.float64) * (math.pi / 180.0 / 3600.0e3)
        if np.any(p != 0):
            u = u - (p[..., None] if u.ndim > 1 else p) * state.position_au
            u = u / np.linalg.norm(u, axis=-1, keepdims=True)
    if deflection:
        u = erfa.ldsun(u, state.sun_to_observer, state.sun_distance_au)
    beta = state.beta
    bm1 = math.sqrt(1.0 - float(beta @ beta))
    return erfa.ab(u, beta, state.sun_distance_au, bm1)


def unaberrate(vectors, state: ObserverState, deflection: bool = True) -> np.ndarray:
    """Astrometric directions of apparent ones: the inverse of :func:`aberrate` (fixed point, < 1e-15 rad).

    Each step shrinks the error by about the map's own departure from the identity: 1e-4 (v/c), but more for
    a star a few tenths of a degree from the Sun, whose light bends by arcseconds: steps until the change is
    below 1e-16 rad, at most 12 (4 left 4e-14 rad 0.14 deg from the Sun)."""
    target = np.ascontiguousarray(vectors, dtype=np.float64)
    u = target
    for _ in range(12):
        step = aberrate(u, state, deflection) - target
        u = u - step
        u = u / np.linalg.norm(u, axis=-1, keepdims=True)
        if float(np.max(np.abs(step))) < 1e-16:
            break
    return u


def apparent_scale(boresight, state: ObserverState) -> float:
    """Apparent over astrometric angular scale near ``boresight``: ``1 - beta cos(psi)`` to first order.

    Aberration crowds stars toward the apex: near a direction at ``psi`` from it both the
    radial and the transverse scale shrink by ``1 - (v/c) cos psi`` (conformal to first order).
    """
    b = np.asarray(boresight, dtype=float)
    return 1.0 - float(state.beta @ (b / np.linalg.norm(b)))


def parse_velocity(text, source: str) -> np.ndarray:
    """``"VX,VY,VZ"`` or a list of three numbers (km/s) -> array; bad input names ``source``."""
    if isinstance(text, str):
        parts = text.split(",")
        try:
            values = [float(p) for p in parts]
        except ValueError:
            raise BadInputError(source, None, f"expected VX,VY,VZ in km/s, got {text!r}") from None
    elif isinstance(text, (list, tuple)) and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in text):
        values = [float(v) for v in text]
    else:
        raise BadInputError(source, None, "must be a list of three numbers (km/s)")
    if len(values) != 3 or not all(math.isfinite(v) for v in values):
        raise BadInputError(source, None, "must be three finite numbers (km/s)")
    if math.hypot(*values) > 0.01 * C_KM_S:
        raise BadInputError(source, None, f"{math.hypot(*values):.0f} km/s is not an orbital speed")
    return np.array(values)


def fits_time(header) -> FrameTime:
    """The time of a FITS header: ``DATE-OBS`` (ISO 8601, UTC), else ``MJD-OBS`` (UTC)."""
    from startrack.timeutil import parse_time

    date = header.get("DATE-OBS") if header is not None else None
    if isinstance(date, str) and date.strip():
        text = date.strip()
        if "T" not in text and isinstance(header.get("TIME-OBS"), str):
            text = f"{text}T{header['TIME-OBS'].strip()}"
        return FrameTime(parse_time(text, "FITS DATE-OBS"), "FITS DATE-OBS")
    mjd = header.get("MJD-OBS") if header is not None else None
    if isinstance(mjd, (int, float)) and not isinstance(mjd, bool) and math.isfinite(mjd):
        t = _dt.datetime(1858, 11, 17, tzinfo=_dt.timezone.utc) + _dt.timedelta(days=float(mjd))
        return FrameTime(t, "FITS MJD-OBS")
    return FrameTime(None, None)


def exif_time(text: str | None, utc_offset_hours: float | None) -> FrameTime:
    """EXIF ``DateTimeOriginal`` (``YYYY:MM:DD HH:MM:SS``, local time without zone) at ``utc_offset_hours``.

    Without an offset the time is not known (EXIF has no zone): ``FrameTime(None, None)``.
    """
    if not text or utc_offset_hours is None:
        return FrameTime(None, None)
    try:
        local = _dt.datetime.strptime(text.strip().rstrip("\x00"), "%Y:%m:%d %H:%M:%S")
    except ValueError:
        raise BadInputError("EXIF DateTimeOriginal", None, f"not an EXIF time: {text!r}") from None
    zone = _dt.timezone(_dt.timedelta(hours=float(utc_offset_hours)))
    return FrameTime(local.replace(tzinfo=zone).astimezone(_dt.timezone.utc), "EXIF DateTimeOriginal")


def frame_time(doc: dict | None = None, explicit: _dt.datetime | None = None, fits_header=None,
               exif_datetime: str | None = None, utc_offset_hours: float | None = None,
               source: str = "frame") -> FrameTime:
    """A frame's time from wherever it is known, in this order: ``explicit`` (the user's, source ``"given"``), the frame
    document's ``image.time``, a FITS header's ``DATE-OBS``/``MJD-OBS``, EXIF ``DateTimeOriginal`` with
    ``utc_offset_hours``.  ``FrameTime(None, None)`` when none of them gives one.
    """
    from startrack.timeutil import parse_time

    if explicit is not None:
        return FrameTime(explicit.astimezone(_dt.timezone.utc), "given")
    text = ((doc or {}).get("image") or {}).get("time") if isinstance(doc, dict) else None
    if text:
        return FrameTime(parse_time(text, f"{source}: image.time"), "image.time")
    if fits_header is not None:
        found = fits_time(fits_header)
        if found.known:
            return found
    return exif_time(exif_datetime, utc_offset_hours)


def frame_velocity(doc: dict | None, explicit=None, source: str = "frame"):
    """The spacecraft's GCRS velocity (km/s) for a frame and where it came from: ``explicit``
    (``"given"`` by the user for every frame), else the document's ``observer.velocity_km_s``, else ``(None, None)``."""
    if explicit is not None:
        return np.asarray(explicit, dtype=float), "given"
    observer = (doc or {}).get("observer") if isinstance(doc, dict) else None
    if observer is None:
        return None, None
    if not isinstance(observer, dict):
        raise BadInputError(source, "observer", "must be an object")
    if observer.get("velocity_km_s") is None:
        return None, None
    return parse_velocity(observer["velocity_km_s"], f"{source}: observer.velocity_km_s"), "observer.velocity_km_s"


@dataclass(frozen=True)
class ApparentOptions:
    """How a run turns catalog directions into apparent ones.

    ``aberration`` False turns the correction off (catalog directions as if the camera were at
    rest); ``time`` overrides every frame's own time; ``velocity_km_s`` (GCRS, km/s) overrides
    every frame's ``observer.velocity_km_s``.
    """

    aberration: bool = True
    time: _dt.datetime | None = None
    velocity_km_s: tuple | None = None


@dataclass(frozen=True)
class FrameApparent:
    """One frame's apparent-place setting: its time, the observer's state (``None``: no correction)
    and the record written into outputs (:meth:`record`)."""

    time: FrameTime
    state: ObserverState | None
    aberration: str                   # "corrected", "disabled" or "no_time"
    velocity_source: str | None = None

    def record(self) -> dict:
        from startrack.timeutil import format_time

        out = {"aberration": self.aberration,
               "time": format_time(self.time.time) if self.time.known else None,
               "time_source": self.time.source}
        if self.state is not None:
            out["velocity_km_s"] = [round(float(v), 6) for v in self.state.velocity_km_s]
            if self.velocity_source is not None:
                out["observer_velocity_km_s"] = [float(v) for v in self.state.spacecraft_km_s]
                out["velocity_source"] = self.velocity_source
        return out

    def apparent(self, vectors, parallax_mas=None) -> np.ndarray:
        """Catalog (astrometric) unit vectors at this frame's apparent places (unchanged without a state);
        ``parallax_mas`` the stars' parallaxes (:func:`aberrate`)."""
        if self.state is None:
            return np.ascontiguousarray(vectors, dtype=np.float64)
        return aberrate(vectors, self.state, parallax_mas=parallax_mas)


def frame_apparent(doc: dict | None, options: ApparentOptions, source: str = "frame", fits_header=None,
                   exif_datetime: str | None = None, utc_offset_hours: float | None = None) -> FrameApparent:
    """The apparent-place setting of one frame (its time, velocity and whether aberration is corrected)."""
    ft = frame_time(doc, options.time, fits_header, exif_datetime, utc_offset_hours, source)
    if not options.aberration:
        return FrameApparent(ft, None, "disabled")
    if not ft.known:
        return FrameApparent(ft, None, "no_time")
    velocity, vsource = frame_velocity(doc, options.velocity_km_s, source)
    return FrameApparent(ft, observer_state(ft.time, velocity), "corrected", vsource)


def astrometric_attitude(dcm, camera, state: ObserverState | None):
    """The attitude and camera whose map takes pixels to *astrometric* (catalog) directions.

    ``dcm`` is the camera's true orientation (apparent directions ``u' = A^T b``).  Removing
    aberration from every pixel's direction is, over a field of view, a rotation and a uniform
    scale ``1 / (1 - beta cos psi)`` (:func:`apparent_scale`) to first order in the field angle
    ``theta``; the rest, below ``beta theta^2`` (0.3 arcsec at the corner of an 11 x 9 deg
    image), is not representable by a pinhole and is left out (terms in ``beta^2`` are ~1e-8 rad).
    The rotation is fitted (Wahba, SVD) over a grid of the image's pixels; the focal length of the
    returned camera is ``f * apparent_scale``.  A lens whose map is not a pinhole's away from the axis
    may leave more than that: when the grid's worst direction is off by more than ``beta theta^2``,
    the scale is fitted with the rotation (least squares over the grid, :func:`_fitted_scale`).  A
    fitted fisheye polynomial over 100 deg: ``apparent_scale`` left 35-84 arcsec at the field's edge,
    more than aberration itself, the fit 10-14; a pinhole of k1 -0.07 over 37 deg, 1.9 against a
    bound of 3.8, not fitted (the check: 0.42 ms a call against 0.37; a fit costs 0.8 ms more there).
    Only the grid's pixels the lens maps are used: a lens fitted on the stars of a wide field may
    fold beyond them, in a corner with no star, where it has no direction.
    Returns ``(dcm_astrometric, camera_astrometric)``; ``(dcm, camera)`` without a state.
    """
    a = np.asarray(dcm, dtype=np.float64)
    if state is None:
        return a, camera
    scale = apparent_scale(a[2], state)
    plain = camera.is_pinhole and not camera.has_distortion
    cam_astro = camera.with_focal_length(camera.focal_length_px * scale)
    extent = 1.0
    while True:
        # The image's grid; with fewer than 9 of its pixels mapped, a grid half as wide about the principal point.
        x0, x1, y0, y1 = -0.5, camera.width - 0.5, -0.5, camera.height - 0.5
        if extent < 1.0:
            x0, x1 = camera.cx + extent * (x0 - camera.cx), camera.cx + extent * (x1 - camera.cx)
            y0, y1 = camera.cy + extent * (y0 - camera.cy), camera.cy + extent * (y1 - camera.cy)
        xs, ys = np.meshgrid(np.linspace(x0, x1, 9), np.linspace(y0, y1, 9))
        xs, ys = xs.ravel(), ys.ravel()
        dirs = np.asarray(camera.pixels_to_vectors(xs, ys))
        body = np.asarray(cam_astro.pixels_to_vectors(xs, ys))
        mapped = np.isfinite(dirs).all(axis=1) & np.isfinite(body).all(axis=1)
        if np.count_nonzero(mapped) >= 9 or extent < 1e-3:
            break
        extent /= 2.0
    if np.count_nonzero(mapped) < 3:
        raise ValueError("the camera maps no pixel near its principal point to a direction")
    if not mapped.all():
        xs, ys, dirs, body = xs[mapped], ys[mapped], dirs[mapped], body[mapped]
    astrometric = unaberrate(dirs @ a, state)
    rot, _ = _wahba(body, astrometric)
    if not plain:
        # The first-order map's worst direction on the grid against the second-order term beta theta^2.
        beta = float(np.linalg.norm(state.beta))
        worst = float(np.max(np.linalg.norm(np.cross(body @ rot, astrometric), axis=1)))
        theta = math.acos(max(-1.0, min(1.0, float(np.min(dirs[:, 2])))))
        if worst > beta * theta * theta:
            # The scales the fit may try: the grid's pixels mapped at each end (a fold moves with the scale).
            lo, hi = scale - 4.0 * beta, scale + 4.0 * beta
            keep = np.ones(len(xs), dtype=bool)
            for s_ in (lo, hi):
                keep &= np.isfinite(np.asarray(camera.with_focal_length(camera.focal_length_px * s_)
                                               .pixels_to_vectors(xs, ys))).all(axis=1)
            if np.count_nonzero(keep) >= 3:
                xs, ys, astrometric = xs[keep], ys[keep], astrometric[keep]
                scale = _fitted_scale(camera, xs, ys, astrometric, lo, hi)
                cam_astro = camera.with_focal_length(camera.focal_length_px * scale)
                rot, _ = _wahba(np.asarray(cam_astro.pixels_to_vectors(xs, ys)), astrometric)
    return rot, cam_astro


def _wahba(body, ref):
    """Wahba by SVD: the rotation ``A`` (ICRS to camera) with ``body ~ A ref`` and its score (the sum of the
    singular values, sign-corrected: the loss is ``n - score``).  :func:`startrack.attitude.svd_solve`'s formula on
    unweighted vectors, with the determinants' sign taken exactly, as :func:`astrometric_attitude` always took it (its
    numbers unchanged), and the score its scale fit compares."""
    u, sv, vt = np.linalg.svd(body.T @ ref)
    d = np.sign(np.linalg.det(u) * np.linalg.det(vt))
    return u @ np.diag([1.0, 1.0, d]) @ vt, float(sv[0] + sv[1] + d * sv[2])


def _fitted_scale(camera, xs, ys, astrometric, lo: float, hi: float) -> float:
    """The focal-length scale in ``[lo, hi]`` whose camera, rotated by its Wahba fit, maps the pixels ``xs, ys`` nearest
    the directions ``astrometric`` (least squares).  The loss is a parabola in the scale over this range (the map
    moves by ~1e-4 of itself): its vertex through three scales a quarter of the range apart, then again through
    three an eighth of that apart about it (each loss a lens map of the grid: a fisheye's is iterated)."""
    f = camera.focal_length_px

    def loss(s):
        body = np.asarray(camera.with_focal_length(f * s).pixels_to_vectors(xs, ys))
        return -_wahba(body, astrometric)[1] if np.isfinite(body).all() else math.inf

    s = (lo + hi) / 2.0
    h = (hi - lo) / 4.0
    for _ in range(2):
        fm, f0, fp = loss(s - h), loss(s), loss(s + h)
        curvature = fp - 2.0 * f0 + fm
        if not (math.isfinite(curvature) and curvature > 0.0):
            break
        s = min(hi, max(lo, s - h * (fp - fm) / (2.0 * curvature)))
        h /= 8.0
    return s


def image_time_tags(path: str):
    """``(fits_header, exif_datetime)`` of an image file: the primary FITS header of a FITS file, the EXIF
    ``DateTimeOriginal`` (else ``DateTime``) of another; ``None`` for what the file does not carry.

    A TIFF, JPEG or PNG file's tags are read directly (:func:`_exif_datetime`: a few hundred bytes, no imaging
    library to load, no pixels decoded: Pillow decodes a whole PNG to look for an EXIF chunk after its pixels);
    other files, and any such file this reader does not follow, through Pillow."""
    import os

    ext = os.path.splitext(str(path))[1].lower()
    if ext in (".fits", ".fit", ".fts"):
        from startrack.fitsfast import read_header

        header = read_header(path)      # without astropy's import when the header is a plain one
        if header is not None:
            return header, None
        from astropy.io import fits

        try:
            return dict(fits.getheader(path)), None
        except (OSError, ValueError):
            return None, None
    import struct

    try:
        found, value = _exif_datetime(path)
    except (OSError, ValueError, struct.error):
        found = False
    if found:
        return None, value
    from PIL import Image  # a core dependency (pyproject.toml)

    try:
        with Image.open(path) as img:
            exif = img.getexif()
            value = exif.get_ifd(0x8769).get(0x9003) or exif.get(0x0132)   # DateTimeOriginal, else DateTime
    except (OSError, ValueError, SyntaxError):
        return None, None
    return None, (value if isinstance(value, str) else None)


#: TIFF field types whose values are text (ASCII; 129 is TIFF's UTF-8 extension, which Pillow also reads).
_TIFF_TEXT = {2: "latin-1", 129: "utf-8"}


def _exif_datetime(path: str):
    """``(True, DateTimeOriginal or DateTime or None)`` read from a classic TIFF file's first directory (and its
    EXIF directory), a JPEG file's EXIF segment or a PNG file's ``eXIf`` chunk, as Pillow reads them; ``(False,
    None)`` for any other file, and for a PNG whose EXIF is in a text chunk (the caller asks Pillow).  Raises
    ``ValueError``/``struct.error`` for a file it cannot follow."""
    import io
    import struct

    with open(path, "rb") as fh:
        head = fh.read(4)
        if head[:2] == b"\xff\xd8":                  # JPEG: the EXIF block is an APP1 segment before the image
            fh.seek(2)
            while True:
                marker = fh.read(4)
                if len(marker) < 4 or marker[0] != 0xFF:
                    return False, None
                kind, size = marker[1], struct.unpack(">H", marker[2:])[0]
                if kind in (0xDA, 0xD9):               # start of scan / end: no EXIF
                    return True, None
                body = fh.read(size - 2)
                if kind == 0xE1 and body[:6] == b"Exif\0\0":
                    return True, _tiff_datetime(io.BytesIO(body[6:]))
        if head == b"\x89PNG":
            return _png_datetime(fh)
        if head not in (b"II*\0", b"MM\0*"):
            return False, None
        return True, _tiff_datetime(fh)


#: PNG text chunks: one keyed ``Raw profile type exif`` holds EXIF as Pillow reads it when no ``eXIf`` chunk does.
_PNG_TEXT = (b"tEXt", b"zTXt", b"iTXt")


def _png_datetime(fh):
    """:func:`_exif_datetime` of the PNG file ``fh``: its chunks' headers read, their data skipped (``IDAT``'s too),
    an ``eXIf`` chunk's TIFF structure read as Pillow reads it (the last before the pixels, else the last after them:
    Pillow reads on to the chunks after the pixels only when it found none before).  ``(False, None)`` when a text chunk may hold
    the EXIF (Pillow's ``Raw profile type exif``) or the ``eXIf`` data starts with its own ``Exif`` header."""
    import io
    import struct

    fh.seek(0)
    if fh.read(8) != b"\x89PNG\r\n\x1a\n":
        raise ValueError("not a PNG signature")
    exif = [None, None]         # before the pixels, after them
    pixels = 0
    while True:
        head = fh.read(8)
        if len(head) < 8:
            raise ValueError("a PNG chunk lies beyond the file")
        length, kind = struct.unpack(">I", head[:4])[0], head[4:]
        if kind == b"IEND":
            break
        if kind == b"eXIf":
            data = fh.read(length)
            if len(data) < length:
                raise ValueError("a PNG chunk lies beyond the file")
            exif[pixels] = data
            fh.seek(4, 1)
        elif kind in _PNG_TEXT:
            if fh.read(min(length, 22)).startswith(b"Raw profile type exif"):
                return False, None
            fh.seek(length - min(length, 22) + 4, 1)
        else:
            pixels = pixels or int(kind == b"IDAT")
            fh.seek(length + 4, 1)
    exif = exif[0] if exif[0] is not None else exif[1]
    if exif is None:
        return True, None
    if exif.startswith(b"Exif\0\0"):
        return False, None
    return True, _tiff_datetime(io.BytesIO(exif))


def _tiff_datetime(fh):
    """EXIF ``DateTimeOriginal`` (tag 0x9003 of the EXIF directory, 0x8769), else ``DateTime`` (0x0132 of the
    first directory), of the TIFF structure that starts at offset 0 of the binary file ``fh``; ``None`` when
    neither is text."""
    import struct

    from startrack.tifffast import directory as tiff_directory

    def read(offset, size):
        fh.seek(offset)
        out = fh.read(size)
        if len(out) < size:
            raise ValueError("a TIFF directory or tag lies beyond the file")
        return out

    head = read(0, 8)
    order = "<" if head[:2] == b"II" else ">"
    if head[:2] not in (b"II", b"MM") or struct.unpack(order + "H", head[2:4])[0] != 42:
        raise ValueError("not a classic TIFF structure")

    def directory(offset):
        return tiff_directory(fh, order, offset)

    def text(entry):
        if entry is None or entry[0] not in _TIFF_TEXT:
            return None
        kind, count, value = entry
        raw = value[:count] if count <= 4 else read(struct.unpack(order + "I", value)[0], count)
        if raw.endswith(b"\0"):                        # as Pillow: one terminating NUL dropped
            raw = raw[:-1]
        return raw.decode(_TIFF_TEXT[kind], "replace")

    first = directory(struct.unpack(order + "I", head[4:8])[0])
    original = None
    pointer = first.get(0x8769)
    if pointer is not None and pointer[0] in (4, 13) and pointer[1] == 1:      # LONG or IFD, one value
        original = text(directory(struct.unpack(order + "I", pointer[2])[0]).get(0x9003))
    return original or text(first.get(0x0132))
