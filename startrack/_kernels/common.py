"""Small kernels the identification kernels share: dot products and angles of unit-vector rows, the cosine
windows of an angle and its tolerance, k-vector ranges, small sorts and the pinhole's pixels to unit vectors."""
import math

import numpy as np

from startrack._kernels._jit import njit
from startrack._kernels.database import bisect_left, bisect_right, kvector_range, quadratic_range


@njit(cache=True, inline="always")
def _dot(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


@njit(cache=True, inline="always")
def _dot_rows(x, i, y, j):
    """``x[i] . y[j]`` (rows of two arrays, without a view of either row)."""
    return x[i, 0] * y[j, 0] + x[i, 1] * y[j, 1] + x[i, 2] * y[j, 2]


@njit(cache=True, inline="always")
def _angle(u, v):
    """Angle (rad) between unit vectors ``u`` and ``v``, rounding-safe."""
    return math.acos(min(1.0, max(-1.0, _dot(u, v))))


@njit(cache=True, inline="always")
def _chord_rows(x, i, y, j):
    """The chord ``|x[i] - y[j]|`` between unit vectors (``2 sin(theta / 2)``: monotonic in their angle,
    proportional to it to ``theta^2 / 24``, and exact to rounding without an ``acos``)."""
    dx = x[i, 0] - y[j, 0]
    dy = x[i, 1] - y[j, 1]
    dz = x[i, 2] - y[j, 2]
    return math.sqrt(dx * dx + dy * dy + dz * dz)


@njit(cache=True, inline="always")
def _cos_window(th, e):
    """The cosines ``(lo, hi)`` of the angles ``th + e`` (at most pi) and ``th - e`` (at least 0): a pair
    of image stars at angle ``th`` matches a catalog pair whose cosine lies in ``[lo, hi]``."""
    return _scaled_window(th, e, 1.0, 1.0)


@njit(cache=True, inline="always")
def _scaled_window(th, e, s_lo, s_hi):
    """:func:`_cos_window` of a pair whose catalog angle is its image angle ``th`` times a focal-length
    scale in ``[s_lo, s_hi]``: the cosines of ``th s_hi + e`` and ``th s_lo - e`` (``th * 1.0`` is ``th``:
    with ``s_lo = s_hi = 1`` the same bits as the nominal window)."""
    return math.cos(min(th * s_hi + e, math.pi)), math.cos(max(th * s_lo - e, 0.0))


@njit(cache=True, inline="always")
def _side(b, tol, margin, u, v):
    """``(theta, e)`` of image stars ``u`` and ``v``: their angle and its tolerance
    ``sqrt(tol_u^2 + tol_v^2) + margin``."""
    return _angle(b[u], b[v]), math.sqrt(tol[u] ** 2 + tol[v] ** 2) + margin


@njit(cache=True, inline="always")
def _pair_window(b, tol, margin, u, v):
    """:func:`_cos_window` of image stars ``u`` and ``v`` (:func:`_side`)."""
    th, e = _side(b, tol, margin, u, v)
    return _cos_window(th, e)


@njit(cache=True, inline="always")
def _scale_range(cos_cat, th, e, s_lo, s_hi):
    """``[s_lo, s_hi]`` narrowed to the scales ``s`` with ``|theta_cat - s theta| <= e`` for a pair of
    catalog cosine ``cos_cat`` and image angle ``th`` (empty: ``lo > hi``)."""
    a = math.acos(min(1.0, max(-1.0, cos_cat)))
    if th <= 0.0:
        return (s_lo, s_hi) if a <= e else (1.0, 0.0)
    return max(s_lo, (a - e) / th), min(s_hi, (a + e) / th)


@njit(cache=True, inline="always")
def _triple_rows(x, i, j, k):
    """Scalar triple product ``x[i] . (x[j] x x[k])`` of three rows (the handedness of a triangle), without a
    view of a row (as :func:`_dot_rows`)."""
    return (x[i, 0] * (x[j, 1] * x[k, 2] - x[j, 2] * x[k, 1]) - x[i, 1] * (x[j, 0] * x[k, 2] - x[j, 2] * x[k, 0])
            + x[i, 2] * (x[j, 0] * x[k, 1] - x[j, 1] * x[k, 0]))


@njit(cache=True, inline="always")
def _range(kvector, line, kquad, quad, use_quadratic, cos_lo, cos_hi):
    s, e = kvector_range(kvector, line[0], line[1], cos_lo, cos_hi)
    if use_quadratic:
        s2, e2 = quadratic_range(kquad, quad[0], quad[1], quad[2], cos_lo, cos_hi)
        s = max(s, s2)
        e = min(e, e2)
        if e < s:
            e = s
    return s, e


@njit(cache=True, inline="always")
def _window(pair_cos, kvector, line, kquad, quad, use_quadratic, cos_lo, cos_hi):
    """The pairs with ``cos_lo <= pair_cos <= cos_hi``, exactly: ``[start, end)`` of :func:`_range`'s
    candidates narrowed by bisection (``pair_cos`` is ascending), so that the loops over a window
    test no cosine (the k-vector's range holds a few more at each end)."""
    s, e = _range(kvector, line, kquad, quad, use_quadratic, cos_lo, cos_hi)
    s = bisect_left(pair_cos, s, e, cos_lo)
    return s, bisect_right(pair_cos, s, e, cos_hi)


@njit(cache=True, inline="always")
def _first_at_or_above(a, p0, p1, x, lo, hi):
    """``p0 + np.searchsorted(a[p0:p1], x)`` (the first ``p`` in ``[p0, p1)`` with ``a[p] >= x``, else ``p1``)
    for ``a[p0:p1]`` ascending within ``[lo, hi]``, starting where ``x`` would lie were the values evenly
    spread over ``[lo, hi]`` and doubling the step from there, then bisecting.

    A star's database pairs are spread about evenly in cosine (a cap's area is linear in its cosine),
    so the first guess is within a few entries: two or three reads of a cold array where a bisection
    from the ends makes eight or nine, each a cache miss."""
    n = p1 - p0
    if n <= 0:
        return p1
    g = p0
    if hi > lo:
        f = (x - lo) / (hi - lo)
        if f >= 1.0:
            g = p1 - 1
        elif f > 0.0:
            g = min(p1 - 1, p0 + int(f * n))
    # Bracket [a_lo, a_hi] with a[a_lo - 1] < x <= a[a_hi] (a_lo = p0 / a_hi = p1 at the ends).
    if a[g] >= x:
        a_hi = g
        step = 1
        a_lo = g - step
        while a_lo >= p0 and a[a_lo] >= x:
            a_hi = a_lo
            step *= 2
            a_lo = a_hi - step
        a_lo = max(a_lo + 1, p0)
    else:
        a_lo = g + 1
        step = 1
        a_hi = g + step
        while a_hi < p1 and a[a_hi] < x:
            a_lo = a_hi + 1
            step *= 2
            a_hi = a_lo - 1 + step
        a_hi = min(a_hi, p1)
    return bisect_left(a, a_lo, a_hi, x)


@njit(cache=True)
def _sort_small(a, n):
    """``a[:n]`` ascending, in place: an insertion sort up to 24 values (no call; its moves grow as n^2),
    numba's sort beyond."""
    if n > 24:
        a[:n].sort()
        return
    for t in range(1, n):
        v = a[t]
        u = t - 1
        while u >= 0 and a[u] > v:
            a[u + 1] = a[u]
            u -= 1
        a[u + 1] = v


@njit(cache=True)
def _sort_indices(a, n):
    """``a[:n]`` ascending, in place, for distinct non-negative integers (star indices): the insertion
    sort of :func:`_sort_small` up to 24, beyond a least-significant-digit radix sort (8-bit digits, as
    many passes as the largest value has bytes).  The same order as any sort; numba's quicksort took
    1-2 us for the 40-80 stars of a verification's cone."""
    if n <= 24:
        _sort_small(a, n)
        return
    top = 0
    for t in range(n):
        top = max(top, a[t])
    work = np.empty(n + 257, dtype=a.dtype)     # (tmp and count: one allocation)
    tmp = work[:n]
    count = work[n:]
    src = a
    dst = tmp
    shift = 0
    while (top >> shift) > 0:
        count[:] = 0
        for t in range(n):
            count[((src[t] >> shift) & 255) + 1] += 1
        for d in range(256):
            count[d + 1] += count[d]
        for t in range(n):
            d = (src[t] >> shift) & 255
            dst[count[d]] = src[t]
            count[d] += 1
        src, dst = dst, src
        shift += 8
    if src is not a:
        for t in range(n):
            a[t] = src[t]


@njit(cache=True)
def _median_in_place(a, n):
    """``np.median(a[:n])`` (the same value; ``n >= 1``, no NaN): up to 24 values sorted in place
    (:func:`_sort_small`) instead of copied and partitioned, more by ``np.median``."""
    if n > 24:
        return np.median(a[:n])
    _sort_small(a, n)
    h = n >> 1
    if n & 1 == 0:
        return (a[h - 1] + a[h]) / 2
    return a[h]


@njit(cache=True)
def pixels_to_unit(xs, ys, focal, cx, cy):
    """Unit vectors of pixel positions through a distortion-free pinhole (paper 000 Eq. 13)."""
    n = xs.shape[0]
    out = np.empty((n, 3))
    for i in range(n):
        u = (xs[i] - cx) / focal
        v = (ys[i] - cy) / focal
        s = 1.0 / math.sqrt(u * u + v * v + 1.0)
        out[i, 0] = u * s
        out[i, 1] = v * s
        out[i, 2] = s
    return out
