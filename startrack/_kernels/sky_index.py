"""The sky index of a database: bands of z, right ascension within a band (:func:`sky_index`), and the stars
of a cone (:func:`cone_stars`): what the verification and the field's scale read instead of every star."""
import math

import numpy as np

from startrack._kernels._jit import njit
from startrack._kernels.common import _sort_indices
from startrack._kernels.database import bisect_left, bisect_right


@njit(cache=True, inline="always")
def _sky_band(z, nb):
    """The band (of ``nb`` equal-area bands in z) of a unit vector's z component."""
    return min(nb - 1, max(0, int((z + 1.0) * nb * 0.5)))


@njit(cache=True, inline="always")
def _sky_ra(x, y):
    """Right ascension in [0, 2 pi) of a direction's x, y components."""
    a = math.atan2(y, x)
    return a + 2.0 * math.pi if a < 0.0 else a


@njit(cache=True)
def sky_index(star_vec, nb):
    """The stars by band of z (``nb`` equal-area bands) and, within a band, by right ascension:
    ``(cells, ra)`` with ``cells = [nb, ptr_0 .. ptr_nb, the stars]`` (band ``b``'s stars are
    ``cells[nb + 2 + ptr_b : nb + 2 + ptr_(b+1)]``) and ``ra`` their right ascensions, ascending
    within each band (:func:`cone_stars`)."""
    m = star_vec.shape[0]
    band = np.empty(m, dtype=np.int64)
    ra = np.empty(m)
    count = np.zeros(nb + 1, dtype=np.int64)
    for s in range(m):
        band[s] = _sky_band(star_vec[s, 2], nb)
        ra[s] = _sky_ra(star_vec[s, 0], star_vec[s, 1])
        count[band[s] + 1] += 1
    for b in range(nb):
        count[b + 1] += count[b]
    order = np.empty(m, dtype=np.int64)
    fill = count[:nb].copy()
    for s in range(m):
        order[fill[band[s]]] = s
        fill[band[s]] += 1
    cells = np.empty(nb + 2 + m, dtype=np.int64)
    cells[0] = nb
    cells[1:nb + 2] = count
    out_ra = np.empty(m)
    for b in range(nb):
        seg = order[count[b]:count[b + 1]]
        keys = np.empty(seg.shape[0])
        for t in range(seg.shape[0]):
            keys[t] = ra[seg[t]]
        o = np.argsort(keys, kind="mergesort")
        for t in range(seg.shape[0]):
            cells[nb + 2 + count[b] + t] = seg[o[t]]
            out_ra[count[b] + t] = keys[o[t]]
    return cells, out_ra


@njit(cache=True)
def cone_stars(ax, ay, az, cos_r, star_vec, sky_cells, sky_ra, out):
    """The stars ``s`` with ``(ax, ay, az) . star_vec[s] > cos_r``, ascending, into ``out``; returns their count.

    ``sky_cells``/``sky_ra`` (:func:`sky_index`) restrict the test to the bands of z that can
    hold the cone and, in each, to the right ascensions within the cone's widest extent
    ``asin(sin r / cos dec)`` (all of them around a pole), with small margins; arrays that
    do not index ``star_vec`` (empty): every star is tested.  Same stars, same order either way.
    """
    m = star_vec.shape[0]
    k = 0
    if sky_ra.shape[0] != m or sky_cells.shape[0] != m + 2 + (sky_cells[0] if sky_cells.shape[0] > 0 else 0):
        for s in range(m):
            if ax * star_vec[s, 0] + ay * star_vec[s, 1] + az * star_vec[s, 2] > cos_r:
                out[k] = s
                k += 1
        return k
    nb = sky_cells[0]
    dec = math.asin(max(-1.0, min(1.0, az)))
    rho = math.acos(max(-1.0, min(1.0, cos_r)))
    zlo = -2.0 if dec - rho <= -0.5 * math.pi else math.sin(dec - rho) - 1e-9
    zhi = 2.0 if dec + rho >= 0.5 * math.pi else math.sin(dec + rho) + 1e-9
    full = zlo <= -1.0 or zhi >= 1.0
    half = 0.0
    a0 = 0.0
    if not full:
        w = math.sin(rho) / math.cos(dec)
        if w >= 1.0:
            full = True
        else:
            half = math.asin(w) + 1e-6
            a0 = _sky_ra(ax, ay)
            full = half >= math.pi
    # Up to two right-ascension intervals (the cone may straddle 0).
    lo1 = 0.0
    hi1 = 2.0 * math.pi
    lo2 = 1.0
    hi2 = 0.0
    if not full:
        lo1 = a0 - half
        hi1 = a0 + half
        if lo1 < 0.0:
            lo2 = lo1 + 2.0 * math.pi
            hi2 = 2.0 * math.pi
            lo1 = 0.0
        elif hi1 >= 2.0 * math.pi:
            lo2 = 0.0
            hi2 = hi1 - 2.0 * math.pi
            hi1 = 2.0 * math.pi
    base = nb + 2
    for b in range(_sky_band(max(-1.0, zlo), nb), _sky_band(min(1.0, zhi), nb) + 1):
        p0 = sky_cells[1 + b]
        p1 = sky_cells[2 + b]
        for part in range(2):
            lo = lo1 if part == 0 else lo2
            hi = hi1 if part == 0 else hi2
            if hi < lo:
                continue
            q0 = bisect_left(sky_ra, p0, p1, lo)
            q1 = bisect_right(sky_ra, q0, p1, hi)
            for t in range(q0, q1):
                # Every candidate is written and the count moves on for those inside: no branch on a test
                # whose outcome follows no pattern (about one in four candidates is outside the cone).
                s = sky_cells[base + t]
                out[k] = s
                k += ax * star_vec[s, 0] + ay * star_vec[s, 1] + az * star_vec[s, 2] > cos_r
    _sort_indices(out, k)
    return k
