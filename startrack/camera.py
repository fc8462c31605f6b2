"""The camera model: a pinhole with optional radial distortion.

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
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from startrack.errors import BadInputError, ParameterError

__all__ = ["Camera", "parse_size"]

CAMERA_FORMAT = "startrack.camera/1"


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
    """A pinhole camera with optional radial distortion.

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
        Radial distortion coefficients on normalised coordinates.
    pixel_pitch_um : float or None
        Pixel pitch in micrometres, when known (only for reporting in mm).
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

    # ------------------------------------------------------------------ builders
    @classmethod
    def from_fov(cls, fov_deg: float, width: int, height: int, **kw) -> "Camera":
        """A camera whose horizontal field of view (across ``width``) is ``fov_deg``.

        The field spans the full pixel extent, ``width`` pixels, so
        ``f = (width / 2) / tan(fov / 2)``.
        """
        fov_deg = _parameter(fov_deg, "fov_deg", "Camera.from_fov", positive=True)
        if not fov_deg < 180.0:
            raise ParameterError("fov_deg", f"must be below 180 degrees, got {fov_deg:g}", "Camera.from_fov")
        if width <= 0 or height <= 0:
            raise ParameterError("width", f"width and height must be positive, got {width}x{height}")
        f = (width / 2.0) / math.tan(math.radians(fov_deg) / 2.0)
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
        dist = doc.get("distortion") or {}
        if not isinstance(dist, dict):
            raise BadInputError(source, "camera.distortion", "must be an object with k1, k2")
        k1 = _finite(dist.get("k1", 0.0), source, "camera.distortion.k1")
        k2 = _finite(dist.get("k2", 0.0), source, "camera.distortion.k2")
        pitch = doc.get("pixel_pitch_um")
        if pitch is not None:
            pitch = _finite(pitch, source, "camera.pixel_pitch_um", positive=True)
        known = {"format", "width", "height", "focal_length_px", "cx", "cy", "distortion",
                 "pixel_pitch_um", "focal_length_mm", "fov_deg"}
        extra = {k: v for k, v in doc.items() if k not in known}
        return cls(values["width"], values["height"], values["focal_length_px"],
                   values["cx"], values["cy"], k1, k2, pitch, extra)

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
        if self.k1 or self.k2:
            doc["distortion"] = {"k1": float(self.k1), "k2": float(self.k2)}
        if self.pixel_pitch_um is not None:
            doc["pixel_pitch_um"] = float(self.pixel_pitch_um)
            doc["focal_length_mm"] = float(self.focal_length_px * self.pixel_pitch_um / 1000.0)
        fx, fy = self.fov_deg
        doc["fov_deg"] = [round(fx, 6), round(fy, 6)]
        doc.update(self.extra)
        return doc

    def with_focal_length(self, focal_length_px: float) -> "Camera":
        """The same camera with another focal length (e.g. a perturbed one)."""
        return Camera(self.width, self.height, float(focal_length_px), self.cx, self.cy,
                      self.k1, self.k2, self.pixel_pitch_um, dict(self.extra))

    # --------------------------------------------------------------- geometry
    @property
    def has_distortion(self) -> bool:
        return bool(self.k1 or self.k2)

    @property
    def max_valid_r2(self) -> float:
        """Largest squared normalised radius where the lens model is one-to-one.

        ``r_d = r (1 + k1 r^2 + k2 r^4)`` turns back on itself where
        ``1 + 3 k1 r^2 + 5 k2 r^4 = 0``; directions beyond that radius would fold
        back into the image, so :meth:`vectors_to_pixels` returns NaN for them.
        """
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

    def distort(self, u, v):
        """Apply radial distortion to normalised coordinates."""
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
            if np.all(np.abs(step) <= 1e-16 * (1.0 + np.abs(r))):
                break
        with np.errstate(invalid="ignore", divide="ignore"):
            ratio = np.where(rd > 0, r / np.where(rd > 0, rd, 1.0), 1.0)
        return ud * ratio, vd * ratio

    def pixels_to_vectors(self, x, y):
        """Unit vectors in the camera frame of pixel positions (paper 000 Eq. 13).

        Parameters
        ----------
        x, y : array_like
            Column and row in pixels.

        Returns
        -------
        ndarray, shape (..., 3)
            Unit vectors, distortion removed.
        """
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        u, v = self.undistort((x - self.cx) / self.focal_length_px,
                              (y - self.cy) / self.focal_length_px)
        vec = np.stack([u, v, np.ones_like(u)], axis=-1)
        return vec / np.linalg.norm(vec, axis=-1, keepdims=True)

    def vectors_to_pixels(self, vectors):
        """Pixel positions of camera-frame directions.

        Returns
        -------
        x, y : ndarray
            NaN where the direction points away from the sky side (``Z <= 0``)
            or lies beyond the radius where the distortion model folds back.
        """
        vec = np.asarray(vectors, dtype=np.float64)
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

    @property
    def fov_deg(self) -> tuple[float, float]:
        """Horizontal and vertical field of view in degrees (edge to edge, through the centre)."""
        xs = np.array([-0.5, self.width - 0.5])
        ys = np.array([-0.5, self.height - 0.5])
        vx = self.pixels_to_vectors(xs, np.full(2, self.cy))
        vy = self.pixels_to_vectors(np.full(2, self.cx), ys)
        ax = math.degrees(math.acos(float(np.clip(vx[0] @ vx[1], -1, 1))))
        ay = math.degrees(math.acos(float(np.clip(vy[0] @ vy[1], -1, 1))))
        return ax, ay

    @property
    def diagonal_fov_deg(self) -> float:
        """The largest angle between two image corners, in degrees."""
        c = self.pixels_to_vectors(np.array([-0.5, self.width - 0.5, -0.5, self.width - 0.5]),
                                   np.array([-0.5, self.height - 0.5, self.height - 0.5, -0.5]))
        a = math.acos(float(np.clip(c[0] @ c[1], -1, 1)))
        b = math.acos(float(np.clip(c[2] @ c[3], -1, 1)))
        return math.degrees(max(a, b))

    @property
    def max_off_axis_deg(self) -> float:
        """The largest angle between the boresight and any image corner, in degrees."""
        c = self.pixels_to_vectors(np.array([-0.5, self.width - 0.5, -0.5, self.width - 0.5]),
                                   np.array([-0.5, self.height - 0.5, self.height - 0.5, -0.5]))
        return math.degrees(math.acos(float(np.clip(c[:, 2].min(), -1, 1))))

    @property
    def pixel_scale_arcsec(self) -> float:
        """Angular size of one pixel at the principal point, in arcseconds."""
        return math.degrees(1.0 / self.focal_length_px) * 3600.0
