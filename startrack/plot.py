"""Pictures people would rather look at than read: annotated images (OpenCV drawing).

Library code: takes arrays and dicts, writes PNG files atomically; never prints.
"""
from __future__ import annotations

import math

import numpy as np

__all__ = ["stretch", "annotate_stars"]


def stretch(image: np.ndarray, low_pct: float = 50.0, high_pct: float = 99.95) -> np.ndarray:
    """An 8-bit display version: smooth background removed, percentile limits, asinh stretch."""
    import cv2

    img = np.asarray(image, dtype=np.float32)
    h, w = img.shape
    small = cv2.resize(img, (max(1, w // 32), max(1, h // 32)), interpolation=cv2.INTER_AREA)
    small = cv2.medianBlur(small, 3) if min(small.shape) >= 3 else small
    img = (img - cv2.resize(small, (w, h), interpolation=cv2.INTER_LINEAR)).astype(np.float64)
    lo, hi = np.percentile(img[:: max(1, img.shape[0] // 256), :: max(1, img.shape[1] // 256)], [low_pct, high_pct])
    if hi <= lo:
        hi = lo + 1.0
    x = np.clip((img - lo) / (hi - lo), 0, None)
    y = np.arcsinh(10.0 * x) / np.arcsinh(10.0)
    return np.clip(y * 255.0, 0, 255).astype(np.uint8)


def annotate_stars(path: str, image: np.ndarray, stars: list, rejected: list | None = None, labels: dict | None = None,
                   predicted: list | None = None, title: str | None = None, n_numbered: int = 20) -> None:
    """Write a PNG of ``image`` with the detected stars circled.

    Parameters
    ----------
    stars : list of dict
        ``x``, ``y`` (and ``flux``), brightest first: green circles, the
        ``n_numbered`` brightest numbered by rank (0 = brightest).
    rejected : list of dict, optional
        Set-aside detections (hot pixels, trails): red crosses.
    labels : dict, optional
        Star index -> text (e.g. ``"HIP 24436 Rigel"``) drawn beside it.
    predicted : list of (x, y), optional
        Catalog positions predicted from an attitude: small blue squares.
    """
    import cv2

    from startrack.formats.atomic import atomic_path

    base = stretch(image)
    canvas = cv2.cvtColor(base, cv2.COLOR_GRAY2BGR)
    scale = max(1.0, max(image.shape) / 1024.0)
    thick = max(1, int(round(scale)))
    font = cv2.FONT_HERSHEY_SIMPLEX
    for x, y in predicted or []:
        if np.isfinite(x) and np.isfinite(y):
            c = (int(round(x)), int(round(y)))
            cv2.rectangle(canvas, (c[0] - 4, c[1] - 4), (c[0] + 4, c[1] + 4), (255, 160, 0), thick)
    for r in rejected or []:
        c = (int(round(r["x"])), int(round(r["y"])))
        cv2.drawMarker(canvas, c, (0, 0, 255), cv2.MARKER_TILTED_CROSS, int(8 * scale), thick)
    for i, s in enumerate(stars):
        c = (int(round(s["x"])), int(round(s["y"])))
        radius = int(max(5, min(25, 3 + 2 * math.log10(max(s.get("flux", 10.0), 10.0)))) * scale)
        cv2.circle(canvas, c, radius, (0, 220, 0), thick, lineType=cv2.LINE_AA)
        text = None
        if labels and i in labels:
            text = labels[i]
        elif i < n_numbered:
            text = str(i)
        if text:
            cv2.putText(canvas, text, (c[0] + radius + 2, c[1] - radius), font, 0.45 * scale, (0, 255, 255), thick,
                        cv2.LINE_AA)
    if title:
        cv2.putText(canvas, title, (8, int(20 * scale)), font, 0.55 * scale, (255, 255, 255), thick, cv2.LINE_AA)
    with atomic_path(path, suffix=".png") as tmp:
        if not cv2.imwrite(tmp, canvas):
            from startrack.errors import BadInputError

            raise BadInputError(path, None, "could not write the PNG")
