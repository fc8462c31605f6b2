"""Tracking kernel: prediction, windowed centroids and streak-aware refinement of all predicted stars in one call.

See :mod:`startrack.track` (steps 1-2) for the method.
"""
import math

import numpy as np

from startrack._kernels._jit import njit
from startrack._kernels.attitude import _inv3
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
    return project_to_pixel(x, y, z, focal, cx, cy, k1, k2, 0.0, 0.0, 0)


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


# ------------------------------------------------------------------ the attitude-and-rate filter
# (the equations are in startrack.track's docstring; AttitudeRateFilter calls these)

@njit(cache=True)
def _mm(a, b):
    """Matrix product of small matrices (numba's matmul needs BLAS from scipy)."""
    n, m = a.shape
    k = b.shape[1]
    out = np.zeros((n, k))
    for i in range(n):
        for j in range(k):
            acc = 0.0
            for t in range(m):
                acc += a[i, t] * b[t, j]
            out[i, j] = acc
    return out


@njit(cache=True)
def _mv(a, v):
    """Matrix times vector."""
    out = np.zeros(a.shape[0])
    for i in range(a.shape[0]):
        acc = 0.0
        for t in range(a.shape[1]):
            acc += a[i, t] * v[t]
        out[i] = acc
    return out


@njit(cache=True)
def cross_matrix(v):
    """``[v x]``."""
    out = np.zeros((3, 3))
    out[0, 1] = -v[2]
    out[0, 2] = v[1]
    out[1, 0] = v[2]
    out[1, 2] = -v[0]
    out[2, 0] = -v[1]
    out[2, 1] = v[0]
    return out


@njit(cache=True)
def exp_minus(phi):
    """``exp(-[phi x])`` (Rodrigues): the passive rotation by ``|phi|`` about ``phi``."""
    angle = math.sqrt(phi[0] * phi[0] + phi[1] * phi[1] + phi[2] * phi[2])
    if angle < 1e-12:
        return np.eye(3) - cross_matrix(phi)
    k = cross_matrix(phi / angle)
    return np.eye(3) - math.sin(angle) * k + (1.0 - math.cos(angle)) * _mm(k, k)


@njit(cache=True)
def log_minus(r):
    """``phi`` with ``exp(-[phi x]) = r`` (angles below pi)."""
    v = np.empty(3)
    v[0] = 0.5 * (r[1, 2] - r[2, 1])
    v[1] = 0.5 * (r[2, 0] - r[0, 2])
    v[2] = 0.5 * (r[0, 1] - r[1, 0])
    s = math.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])
    c = 0.5 * (r[0, 0] + r[1, 1] + r[2, 2] - 1.0)
    if s < 1e-12:
        return v
    return v * (math.atan2(s, c) / s)


@njit(cache=True)
def filter_predict(dcm, p, w, dt, q):
    """``(A^-, P^-)``: ``A^- = exp(-[w x] dt) A``, ``P^- = F P F^T + Q`` written out by blocks."""
    a = _mm(exp_minus(w * dt), dcm)
    out = np.empty((6, 6))
    q3 = q * dt ** 3 / 3.0
    q2 = q * dt ** 2 / 2.0
    q1 = q * dt
    for i in range(3):
        for j in range(3):
            paa = p[i, j]
            pab = p[i, 3 + j]
            pbb = p[3 + i, 3 + j]
            out[i, j] = paa + dt * (pab + p[j, 3 + i]) + dt * dt * pbb + (q3 if i == j else 0.0)
            out[i, 3 + j] = pab + dt * pbb + (q2 if i == j else 0.0)
            out[3 + i, 3 + j] = pbb + (q1 if i == j else 0.0)
    # P^- is symmetric: the lower-left block is the transpose of the upper-right.
    for i in range(3):
        for j in range(3):
            out[3 + i, j] = out[j, 3 + i]
    return a, out


@njit(cache=True)
def filter_update(dcm, p, rate, z, h, r):
    """Kalman update with a 3-vector measurement ``z = H x + v``, ``cov(v) = R``:
    ``S = H P H^T + R``, ``K = P H^T S^-1``, ``dx = K z``, ``P = (I - K H) P`` (symmetrised),
    ``A = exp(-[dtheta x]) A``, ``w += dw``.  Returns ``(A, P, w, z^T S^-1 z)``."""
    pht = _mm(p, h.T)
    si = _inv3(_mm(h, pht) + r)
    k = _mm(pht, si)
    dx = _mv(k, z)
    pn = p - _mm(k, _mm(h, p))
    pn = 0.5 * (pn + pn.T)
    siz = _mv(si, z)
    return _mm(exp_minus(dx[:3]), dcm), pn, rate + dx[3:], z[0] * siz[0] + z[1] * siz[1] + z[2] * siz[2]


@njit(cache=True)
def attitude_residual(dcm_meas, dcm):
    """``z = rotvec(A_meas A^T)`` (the attitude measurement's innovation)."""
    return log_minus(_mm(dcm_meas, dcm.T))


@njit(cache=True)
def offset_inliers(mx, my, px, py, ok, limit):
    """The entries of ``ok`` whose offset (measured - predicted) lies within ``limit`` px of the median
    offset (per axis medians): a false star or a neighbour in a window moves its star off the common shift."""
    n = ok.shape[0]
    dx = np.empty(n)
    dy = np.empty(n)
    for j in range(n):
        dx[j] = mx[ok[j]] - px[ok[j]]
        dy[j] = my[ok[j]] - py[ok[j]]
    cx = np.median(dx)
    cy = np.median(dy)
    keep = np.empty(n, dtype=np.int64)
    m = 0
    for j in range(n):
        if math.hypot(dx[j] - cx, dy[j] - cy) <= limit:
            keep[m] = ok[j]
            m += 1
    return keep[:m]
