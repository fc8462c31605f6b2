"""Bias, dark and flat frames: read, combine, check and apply, as every camera user calibrates.

``calibrated = (image - dark) / flat``, the dark holding the bias (a dark frame is a bias plus
the dark current of the same exposure; without a dark, the bias alone is removed), the flat
with the bias removed and scaled to a median of 1.  Several files of one kind are combined by
their per-pixel median (a cosmic ray or a satellite in one of them is voted out).

Hot pixels are taken from the dark: pixels far above the dark's own noise, measured from the
differences of neighbouring pixels (the scatter of ``d[i, j+1] - d[i, j]`` is ``sqrt(2)`` times
the pixel noise, whatever the dark's level, gradient or amplifier glow, and its median absolute
deviation ignores the hot pixels themselves), with a threshold at the Gaussian tail probability
of 0.1 / N for N pixels, so a frame of pure noise flags one pixel in ten frames of any size.  A
hot pixel's value is replaced by the median of its 3 x 3 neighbourhood before detection, so the
centroider never sees it.
"""
from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass, field

import numpy as np

from startrack.errors import BadInputError

__all__ = ["CalibrationFrames", "load_calibration_frames", "hot_pixel_map"]

KINDS = ("bias", "dark", "flat")


def _sha256(path):
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _combined(kind, paths, shape=None):
    """The per-pixel median of the files of one kind, all of one size; ``(frame, shape, records)``."""
    from startrack.imageio import read_image

    frames, records = [], []
    for path in paths:
        image, _ = read_image(path)
        if shape is None:
            shape = image.shape
        elif image.shape != shape:
            raise BadInputError(path, None, f"{kind} frame is {image.shape[1]}x{image.shape[0]} pixels, "
                                f"the other calibration frames {shape[1]}x{shape[0]}")
        frames.append(image)
        records.append({"kind": kind, "path": str(path), "sha256": _sha256(path)})
    if not frames:
        return None, shape, records
    frame = frames[0] if len(frames) == 1 else np.median(np.stack(frames), axis=0).astype(np.float32)
    return np.ascontiguousarray(frame, dtype=np.float32), shape, records


def hot_pixel_map(dark, false_per_frame: float = 0.1):
    """Pixels of ``dark`` far above its own noise: ``(mask, level, sigma)``.

    ``sigma`` from the median absolute deviation of the differences of horizontal neighbours
    (divided by ``sqrt(2)``), floored at the quantisation of one DN (``1 / sqrt(12)``); a pixel is hot
    above ``median + k sigma`` with ``k`` the Gaussian quantile of ``1 - false_per_frame / N``.
    """
    from statistics import NormalDist

    d = np.asarray(dark, dtype=np.float64)
    diff = np.diff(d, axis=1).ravel() if d.shape[1] > 1 else np.diff(d, axis=0).ravel()
    mad = float(np.median(np.abs(diff - np.median(diff)))) if diff.size else 0.0
    sigma = max(1.4826 * mad / math.sqrt(2.0), 1.0 / math.sqrt(12.0))
    level = float(np.median(d))
    k = NormalDist().inv_cdf(1.0 - false_per_frame / d.size)
    return d > level + k * sigma, level, sigma


@dataclass
class CalibrationFrames:
    """Combined calibration frames and the hot pixels of the dark; :meth:`apply` calibrates an image."""

    bias: np.ndarray | None = None
    dark: np.ndarray | None = None
    flat: np.ndarray | None = None            # bias removed, median 1
    hot: np.ndarray | None = None             # bool mask
    files: list = field(default_factory=list)

    @property
    def shape(self):
        for frame in (self.dark, self.bias, self.flat):
            if frame is not None:
                return frame.shape
        return None

    def apply(self, image, saturation: float | None = None, source: str = "image"):
        """The calibrated image (float32) and its saturation level.

        Raises :class:`BadInputError` naming ``source`` when its size is not the calibration
        frames'.  Saturated pixels (at or above ``saturation`` in the raw image) are set to the
        returned level, which no calibrated unsaturated pixel reaches.
        """
        image = np.asarray(image, dtype=np.float32)
        if image.shape != self.shape:
            names = ", ".join(f"{f['kind']} {f['path']}" for f in self.files[:3])
            raise BadInputError(source, None, f"is {image.shape[1]}x{image.shape[0]} pixels, the calibration frames "
                                f"({names}) {self.shape[1]}x{self.shape[0]}")
        offset = self.dark if self.dark is not None else self.bias
        out = image - offset if offset is not None else image.copy()
        if self.flat is not None:
            out /= self.flat
        if self.hot is not None and self.hot.any():
            import cv2

            median = cv2.medianBlur(np.ascontiguousarray(out, dtype=np.float32), 3)
            out[self.hot] = median[self.hot]
        new_saturation = saturation
        if saturation is not None:
            low = float(offset.min()) if offset is not None else 0.0
            flat_min = float(self.flat.min()) if self.flat is not None else 1.0
            new_saturation = (float(saturation) - low) / flat_min
            saturated = image >= saturation
            if self.hot is not None:
                saturated &= ~self.hot
            out[saturated] = new_saturation
        return np.ascontiguousarray(out, dtype=np.float32), new_saturation

    def record(self) -> dict:
        """The ``image.calibration`` section: the files (kind, path, sha256) and the hot pixels masked."""
        return {"files": [dict(f) for f in self.files],
                "hot_pixels": int(self.hot.sum()) if self.hot is not None else 0}


def load_calibration_frames(bias=(), dark=(), flat=()) -> CalibrationFrames | None:
    """Read, combine and check the calibration files; ``None`` when none is given.

    Raises :class:`~startrack.errors.BadInputError` naming the file: unreadable, a size unlike the
    others, a flat with pixels at or below zero once the bias is removed.
    """
    bias, dark, flat = list(bias or ()), list(dark or ()), list(flat or ())
    if not (bias or dark or flat):
        return None
    b, shape, files = _combined("bias", bias)
    d, shape, more = _combined("dark", dark, shape)
    files += more
    f, shape, more = _combined("flat", flat, shape)
    files += more
    hot = None
    if d is not None:
        hot, _, _ = hot_pixel_map(d - b if b is not None else d)
    if f is not None:
        signal = f - b if b is not None else f
        bad = int(np.count_nonzero(~(signal > 0)))
        if bad:
            name = flat[0] if len(flat) == 1 else ", ".join(flat)
            raise BadInputError(name, None, f"flat has {bad} pixel(s) at or below zero"
                                + (" once the bias is removed" if b is not None else "")
                                + ": not a flat frame (an illuminated exposure)")
        f = np.ascontiguousarray(signal / np.median(signal), dtype=np.float32)
    return CalibrationFrames(b, d, f, hot, files)
