"""Tracking kernel: prediction, windowed centroids and streak-aware refinement of all predicted stars in one call.

See :mod:`startrack.track` (steps 1-2) for the method.
"""
import math

import numpy as np

from startrack._kernels._jit import njit
from startrack._kernels.centroid import window_one
from startrack._kernels.sphere import project_to_pixel
from startrack._kernels.streak import segment_one

# Columns of track_windows' ``out``.
COLUMNS = ("row", "px", "py", "mx", "my", "flux", "snr", "sigma_px", "found", "hx", "hy", "ok")
N_COLUMNS = len(COLUMNS)


@njit(cache=True, inline="always")
def _rotate(m, v0, v1, v2):
    return (m[0, 0] * v0 + m[0, 1] * v1 + m[0, 2] * v2,
            m[1, 0] * v0 + m[1, 1] * v1 + m[1, 2] * v2,
            m[2, 0] * v0 + m[2, 1] * v1 + m[2, 2] * v2)


@njit(cache=True, inline="always")
def _pixel(x, y, z, focal, cx, cy, k1, k2, max_r2):
    """:meth:`startrack.camera.Camera.vectors_to_pixels` for one direction (NaN behind the camera or
    beyond the radius where the lens model folds back)."""
    if not z > 0.0:
        return np.nan, np.nan
    u = x / z
    v = y / z
    if u * u + v * v > max_r2:
        return np.nan, np.nan
    return project_to_pixel(x, y, z, focal, cx, cy, k1, k2)


@njit(cache=True)
def track_windows(image, vectors, dcm, half_turn, focal, cx, cy, k1, k2, max_r2, width, height, margin, cos_limit,
                  max_predicted, half, k_sigma, min_pixels, box, segment, seg_radius, seg_iters, max_shift, out):
    """Predict, find and measure the catalog stars of one frame; returns how many rows of ``out`` are filled.

    ``vectors`` (m, 3): ICRS unit vectors of the candidate stars, brightest first.  Each with camera-frame
    direction ``c = A r`` (``dcm``) in front of ``cos_limit`` and landing on the sensor at least ``margin``
    px inside its edges is predicted (the first ``max_predicted`` of them), as
    :func:`startrack.render.project_stars` projects.  Its expected streak is the chord between its positions
    half an exposure before and after, ``c- = H^T c`` and ``c+ = H c`` with ``half_turn`` ``H = exp(-[w x] T/2)``;
    ``(hx, hy)`` is half of it.  Then the window centroid
    (:func:`startrack._kernels.centroid.window_one`: brightest star in a square of half-size ``half``, box
    centroid of half-size ``box``) and, with ``segment``, the capsule centroid along the expected streak
    (:func:`startrack._kernels.streak.segment_one`, radius ``seg_radius``, ``seg_iters`` passes) started
    there; a segment centroid farther than ``max_shift`` px from the window centroid, or none, leaves the
    star not measured (``ok`` 0).  ``sigma_px`` is the segment centroid's noise sigma (NaN for window
    centroids).

    ``out[k]`` = ``row`` (index into ``vectors``), predicted ``px, py``, measured ``mx, my``, flux, snr,
    sigma_px, found in its window (1/0), ``hx, hy``, measured (1/0).
    """
    n = 0
    for i in range(vectors.shape[0]):
        if n >= max_predicted:
            break
        c0, c1, c2 = _rotate(dcm, vectors[i, 0], vectors[i, 1], vectors[i, 2])
        if not c2 > cos_limit:
            continue
        px, py = _pixel(c0, c1, c2, focal, cx, cy, k1, k2, max_r2)
        if not (px >= -0.5 + margin and px <= width - 0.5 - margin and py >= -0.5 + margin
                and py <= height - 0.5 - margin):
            continue
        p0, p1, p2 = _rotate(half_turn, c0, c1, c2)
        m0 = half_turn[0, 0] * c0 + half_turn[1, 0] * c1 + half_turn[2, 0] * c2
        m1 = half_turn[0, 1] * c0 + half_turn[1, 1] * c1 + half_turn[2, 1] * c2
        m2 = half_turn[0, 2] * c0 + half_turn[1, 2] * c1 + half_turn[2, 2] * c2
        xp, yp = _pixel(p0, p1, p2, focal, cx, cy, k1, k2, max_r2)
        xm, ym = _pixel(m0, m1, m2, focal, cx, cy, k1, k2, max_r2)
        hx = 0.5 * (xp - xm)
        hy = 0.5 * (yp - ym)
        if not (np.isfinite(hx) and np.isfinite(hy)):
            hx = 0.0
            hy = 0.0
        mx, my, flux, _peak, snr, found = window_one(image, px, py, half, k_sigma, min_pixels, box)
        sig = np.nan
        ok = found
        if found and segment:
            sx, sy, _sflux, ssig, sok = segment_one(image, mx, my, hx, hy, seg_radius, seg_iters)
            if sok and math.hypot(sx - mx, sy - my) < max_shift:
                mx = sx
                my = sy
                sig = ssig
            else:
                ok = False
        out[n, 0] = i
        out[n, 1] = px
        out[n, 2] = py
        out[n, 3] = mx
        out[n, 4] = my
        out[n, 5] = flux
        out[n, 6] = snr
        out[n, 7] = sig
        out[n, 8] = 1.0 if found else 0.0
        out[n, 9] = hx
        out[n, 10] = hy
        out[n, 11] = 1.0 if ok else 0.0
        n += 1
    return n
