"""Constellation stick figures: which stars to join, by Hipparcos number, and where they fall in a picture.

The figures are a data file shipped with the package, ``startrack/data/constellations.txt`` (its header
states its provenance and licence).  Each line is one constellation::

    Ori  Orion  27989 25336 25930 24436 ; 26727 26311 25930

an IAU abbreviation, the name (one word, or words joined by ``_``) and polylines of HIP numbers,
separated by ``;``: the stars of a polyline are joined in turn.
"""
from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np

from startrack.errors import BadInputError

__all__ = ["Figure", "load_figures", "figure_segments_in_image", "FIGURES_PATH"]

#: The shipped table of stick figures.
FIGURES_PATH = os.path.join(os.path.dirname(os.path.abspath(__file__)), "data", "constellations.txt")


@dataclass(frozen=True)
class Figure:
    """One constellation: ``abbr`` (IAU, e.g. ``"Ori"``), ``name`` and ``lines``, each a tuple of HIP numbers
    joined in turn."""

    abbr: str
    name: str
    lines: tuple

    def segments(self):
        """Every pair of HIP numbers joined by a line, in order."""
        for line in self.lines:
            yield from zip(line[:-1], line[1:])

    def stars(self) -> set:
        return {h for line in self.lines for h in line}


_CACHE: dict = {}


def load_figures(path: str | None = None) -> list:
    """The stick figures of ``path`` (default: the shipped table) as a list of :class:`Figure`.

    A malformed line is refused with :class:`BadInputError` naming the file and the line.
    """
    path = path or FIGURES_PATH
    if path in _CACHE:
        return _CACHE[path]
    figures = []
    try:
        with open(path, encoding="utf-8") as fh:
            for line_no, raw in enumerate(fh, start=1):
                text = raw.split("#", 1)[0].strip()
                if not text:
                    continue
                parts = text.split(None, 2)
                if len(parts) < 3:
                    raise BadInputError(f"{path}:{line_no}", None, "expected: ABBR NAME HIP HIP ... [; HIP ...]")
                abbr, name, rest = parts
                lines = []
                for chunk in rest.split(";"):
                    try:
                        ids = tuple(int(v) for v in chunk.split())
                    except ValueError:
                        raise BadInputError(f"{path}:{line_no}", None, f"{chunk.strip()!r} is not a list of HIP "
                                                                       "numbers") from None
                    if len(ids) < 2:
                        raise BadInputError(f"{path}:{line_no}", None, "a polyline needs at least two stars")
                    lines.append(ids)
                figures.append(Figure(abbr, name.replace("_", " "), tuple(lines)))
    except OSError as exc:
        raise BadInputError(path, None, f"cannot be read ({exc.strerror or exc})") from None
    _CACHE[path] = figures
    return figures


def figure_segments_in_image(figures, catalog, dcm, camera, steps: int = 16):
    """The stick figures as drawn on one picture.

    Each segment is the great-circle arc between its two stars, sampled in ``steps`` pieces and
    projected through the camera (its distortion included), so a line is right on a wide or distorted
    field too; pieces behind the camera are left out.

    Parameters
    ----------
    figures : list of Figure
    catalog : startrack.catalog.Catalog
        Star positions (at the epoch wanted); a star the catalog lacks leaves its segments out.
    dcm : ndarray (3, 3)
        The attitude, ICRS -> camera.
    camera : startrack.camera.Camera

    Returns
    -------
    list of (Figure, list of ndarray (k, 2), ndarray (2,) or None)
        Per figure with a segment crossing the image: its polylines in pixels and the place for its name
        (the mean of its stars inside the image, else of its segments' points inside), in image x, y.
    """
    rows = catalog.rows_by_id()
    vectors = catalog.vectors()
    a = np.asarray(dcm, dtype=float)
    t = np.linspace(0.0, 1.0, steps + 1)[:, None]
    out = []
    for fig in figures:
        polylines, inside_points, star_points = [], [], []
        for h1, h2 in fig.segments():
            k1, k2 = rows.get(int(h1)), rows.get(int(h2))
            if k1 is None or k2 is None:
                continue
            v1, v2 = a @ vectors[k1], a @ vectors[k2]
            if v1[2] <= 0 and v2[2] <= 0:
                continue
            arc = (1 - t) * v1 + t * v2                    # the chord, normalised: points along the great circle
            arc /= np.linalg.norm(arc, axis=1, keepdims=True)
            front = arc[:, 2] > 1e-6
            if not front.any():
                continue
            x, y = camera.vectors_to_pixels(arc[front])
            pts = np.column_stack([x, y])
            ok = np.isfinite(pts).all(axis=1)
            pts = pts[ok]
            if len(pts) < 2:
                continue
            on = camera.in_image(pts[:, 0], pts[:, 1])
            if not on.any():
                continue
            polylines.append(pts)
            inside_points.append(pts[on])
            for v, end in ((v1, pts[0]), (v2, pts[-1])):
                if v[2] > 0 and camera.in_image(end[0], end[1]):
                    star_points.append(end)
        if polylines:
            where = np.mean(star_points, axis=0) if star_points else np.mean(np.vstack(inside_points), axis=0)
            out.append((fig, polylines, where))
    return out
