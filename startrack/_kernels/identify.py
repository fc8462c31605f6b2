"""Identification kernels: pyramid (Mortari et al. 2004) and geometric voting (Kolomenkin et al. 2008)."""
import math

import numpy as np

from startrack._kernels._jit import njit
from startrack._kernels.attitude import leave_one_out, quat_to_dcm, quest_pairs, refine_from
from startrack._kernels.database import bisect_left, bisect_right, kvector_range, label_search, quadratic_range
from startrack._kernels.sphere import project_to_pixel


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


@njit(cache=True, inline="always")
def vote_once(votes, stamp, i, c, key):
    """One vote for hypothesis ``(i, c)`` per ``key`` (an image pair): ``stamp`` remembers the last key."""
    if stamp[i, c] != key:
        stamp[i, c] = key
        votes[i, c] += 1


@njit(cache=True)
def smart_triads(n):
    """Mortari's smart index sequence over triads (dj, dk, i loops): every triad once, spikes spread out."""
    count = n * (n - 1) * (n - 2) // 6
    out = np.empty((count, 3), dtype=np.int64)
    t = 0
    for dj in range(1, n - 1):
        for dk in range(1, n - dj):
            for i in range(0, n - dj - dk):
                j = i + dj
                k = j + dk
                out[t, 0] = i
                out[t, 1] = j
                out[t, 2] = k
                t += 1
    return out


@njit(cache=True)
def free_focal_patterns(b, tol, margin, i, j, k, focal_error):
    """The image patterns triad ``(i, j, k)`` compares with the database when the focal length is free
    within ``focal_error`` (:func:`pyramid_candidates`): one per scale its longest side tells apart,
    ``1 + ceil(2 focal_error theta / e)`` (``e`` that side's tolerance).  The look-elsewhere count of
    the false-match probability: a random catalog triangle has that many more chances to fit."""
    best = -1.0
    e_best = 1.0
    for t in range(3):
        th, e = _side(b, tol, margin, i if t < 2 else j, j if t == 0 else k)
        if th > best:
            best = th
            e_best = e
    return 1 + int(math.ceil(2.0 * focal_error * best / e_best))


@njit(cache=True)
def pyramid_triangles(b, tol, margin, i, j, k, star_vec, pair_i, pair_j, pair_cos, kvector, line, kquad,
                      quad, use_quadratic, max_triangles, focal_error):
    """The catalog triangles of image triad ``(i, j, k)``: :func:`pyramid_candidates`' first step.

    Returns ``(tri, tri_s, n_triangles)``: the triangles ``(I, J, K)`` in the order found and the
    focal-length scales each allows (``(1, 1)`` at the nominal focal length); none and
    ``max_triangles + 1`` when there are more than ``max_triangles``."""
    s_lo = 1.0 - focal_error
    s_hi = 1.0 + focal_error
    th_ij, e_ij = _side(b, tol, margin, i, j)
    th_ik, e_ik = _side(b, tol, margin, i, k)
    th_jk, e_jk = _side(b, tol, margin, j, k)
    lo_ij, hi_ij = _scaled_window(th_ij, e_ij, s_lo, s_hi)
    lo_ik, hi_ik = _scaled_window(th_ik, e_ik, s_lo, s_hi)
    # Catalog pairs at theta_ik, linked per star (both orientations): no sorting.
    s2, e2 = _window(pair_cos, kvector, line, kquad, quad, use_quadratic, lo_ik, hi_ik)
    n_cat = star_vec.shape[0]
    head = np.full(n_cat, -1, dtype=np.int32)
    nxt = np.empty(2 * max(e2 - s2, 0), dtype=np.int32)
    other = np.empty(2 * max(e2 - s2, 0), dtype=np.int32)
    m = 0
    for t in range(s2, e2):
        a = pair_i[t]
        z = pair_j[t]
        other[m] = z
        nxt[m] = head[a]
        head[a] = m
        m += 1
        other[m] = a
        nxt[m] = head[z]
        head[z] = m
        m += 1
    if m == 0:
        return np.empty((0, 3), dtype=np.int64), np.empty((0, 2)), 0
    cb = _triple_rows(b, i, j, k)
    # |angle(J, K) - th_jk| <= e_jk as a cosine window (no acos per candidate).
    lo_jk, hi_jk = _scaled_window(th_jk, e_jk, s_lo, s_hi)
    # J and K of a triangle both have a database pair at theta_jk when that window lies within the
    # database's pairs (every pair of its stars closer than its largest angle is in it, and
    # pair_cos[0] is the smallest cosine; 1e-9 to spare at that edge): stars without one are
    # passed over before their vectors are read.  The window is widened by 1e-12 so that no
    # cosine rounding can drop a star the exact test below would keep.
    mark = np.empty(n_cat, dtype=np.bool_)
    if pair_cos.shape[0] > 0 and lo_jk - 1e-12 >= pair_cos[0] + 1e-9:
        mark[:] = False
        s3, e3 = _window(pair_cos, kvector, line, kquad, quad, False, lo_jk - 1e-12, hi_jk + 1e-12)
        for t in range(s3, e3):
            mark[pair_i[t]] = True
            mark[pair_j[t]] = True
    else:
        mark[:] = True
    tri = np.empty((max_triangles, 3), dtype=np.int64)
    tri_s = np.empty((max_triangles, 2))
    nt = 0
    scaled = focal_error > 0.0
    s, e = _window(pair_cos, kvector, line, kquad, quad, use_quadratic, lo_ij, hi_ij)
    # The pairs at theta_ij (both orientations, in order) whose first star I has a pair at
    # theta_ik, gathered without a branch: about four in five have none, and a branch on that
    # is mispredicted often enough to double the loop's time.  ``t`` is orientation (i, j),
    # ``-1 - t`` the other.
    lead = np.empty(2 * max(e - s, 0), dtype=np.int64)
    nl = 0
    # (Two passes: the tests first, each pair's independent of the others', then the gathering.)
    sel = np.empty(2 * max(e - s, 0), dtype=np.bool_)
    for t in range(s, e):
        pi_ = pair_i[t]
        pj_ = pair_j[t]
        sel[2 * (t - s)] = (head[pi_] >= 0) & mark[pj_]
        sel[2 * (t - s) + 1] = (head[pj_] >= 0) & mark[pi_]
    for u in range(2 * (e - s)):
        t = s + (u >> 1)
        lead[nl] = t if (u & 1) == 0 else -1 - t
        nl += sel[u]
    for u in range(nl):
        t = lead[u]
        I = pair_i[t] if t >= 0 else pair_j[-1 - t]
        J = pair_j[t] if t >= 0 else pair_i[-1 - t]
        p = head[I]
        while p >= 0:
            K = other[p]
            p = nxt[p]
            if K == J or not mark[K]:
                continue
            d = _dot_rows(star_vec, J, star_vec, K)
            if d < lo_jk or d > hi_jk:
                continue
            if (_triple_rows(star_vec, I, J, K) > 0) != (cb > 0):
                continue
            t_lo = 1.0
            t_hi = 1.0
            if scaled:
                # One scale for the three sides (each side's scales within its tolerance).
                t_lo, t_hi = _scale_range(_dot_rows(star_vec, I, star_vec, J), th_ij, e_ij, s_lo, s_hi)
                t_lo, t_hi = _scale_range(_dot_rows(star_vec, I, star_vec, K), th_ik, e_ik, t_lo, t_hi)
                t_lo, t_hi = _scale_range(d, th_jk, e_jk, t_lo, t_hi)
                if t_lo > t_hi:
                    continue
            if nt >= max_triangles:
                return tri[:0], tri_s[:0], nt + 1
            tri[nt, 0] = I
            tri[nt, 1] = J
            tri[nt, 2] = K
            tri_s[nt, 0] = t_lo
            tri_s[nt, 1] = t_hi
            nt += 1
    return tri[:nt], tri_s[:nt], nt


@njit(cache=True, inline="always")
def pyramid_fourth(b, tol, margin, i, j, k, tri, tri_s, t, star_vec, pair_cos, adj_ptr, adj_other, adj_cos,
                   focal_error, win, made):
    """The fourth star of triangle ``tri[t]`` of image triad ``(i, j, k)`` (:func:`pyramid_triangles`):
    ``(r, R)``, the first other image star ``r`` (in index order) whose three angles to the triangle
    match exactly one catalog star ``R``, else ``(-1, -1)`` (:func:`pyramid_candidates`' second step).

    ``win`` (n, 6) and ``made`` (n, bool, False at the triad's first triangle): the other stars'
    cosine windows, made at their first use and kept for the triad's next triangles."""
    n = b.shape[0]
    scaled = focal_error > 0.0
    c_min = pair_cos[0] if pair_cos.shape[0] > 0 else -1.0
    c_max = pair_cos[pair_cos.shape[0] - 1] if pair_cos.shape[0] > 0 else 1.0
    fI = tri[t, 0]
    fJ = tri[t, 1]
    fK = tri[t, 2]
    a0 = adj_ptr[fI]
    a1 = adj_ptr[fI + 1]
    for r in range(n):
        if r == i or r == j or r == k:
            continue
        if not made[r] and scaled:
            win[r, 0], win[r, 1] = _side(b, tol, margin, i, r)
            win[r, 2], win[r, 3] = _side(b, tol, margin, j, r)
            win[r, 4], win[r, 5] = _side(b, tol, margin, k, r)
            made[r] = True
        elif not made[r]:
            win[r, 0], win[r, 1] = _pair_window(b, tol, margin, i, r)
            win[r, 2], win[r, 3] = _pair_window(b, tol, margin, j, r)
            win[r, 4], win[r, 5] = _pair_window(b, tol, margin, k, r)
            made[r] = True
        if scaled:
            # The triangle's own scales (a narrower range than the search's).
            lo, hi = _scaled_window(win[r, 0], win[r, 1], tri_s[t, 0], tri_s[t, 1])
            lo_jr, hi_jr = _scaled_window(win[r, 2], win[r, 3], tri_s[t, 0], tri_s[t, 1])
            lo_kr, hi_kr = _scaled_window(win[r, 4], win[r, 5], tri_s[t, 0], tri_s[t, 1])
        else:
            lo = win[r, 0]
            hi = win[r, 1]
            lo_jr = win[r, 2]
            hi_jr = win[r, 3]
            lo_kr = win[r, 4]
            hi_kr = win[r, 5]
        # I's pairs with lo <= cos <= hi (its cosines ascending): the first at or above lo.
        p = _first_at_or_above(adj_cos, a0, a1, lo, c_min, c_max)
        nR = 0
        fR = -1
        while p < a1 and adj_cos[p] <= hi:
            R = adj_other[p]
            p += 1
            if R == fJ or R == fK:
                continue
            d = _dot_rows(star_vec, fJ, star_vec, R)
            if d < lo_jr or d > hi_jr:
                continue
            d = _dot_rows(star_vec, fK, star_vec, R)
            if d < lo_kr or d > hi_kr:
                continue
            nR += 1
            fR = R
            if nR > 1:
                break
        if nR == 1:
            return r, fR
    return -1, -1


@njit(cache=True)
def pyramid_candidates(b, tol, margin, i, j, k, star_vec, pair_i, pair_j, pair_cos, kvector, line, kquad, quad,
                       use_quadratic, max_triangles, max_out, adj_ptr, adj_other, adj_cos, focal_error):
    """The catalog pyramids of image triad ``(i, j, k)`` (Mortari et al. 2004, as one step of a generator).

    The triad's catalog triangles come from k-vector (or paper 000 quadratic)
    range look-ups on its angles ``theta_ij`` and ``theta_ik``, the third angle
    and the specular (handedness) test.  Each triangle is confirmed by the
    first other image star ``r`` (brightest first) whose three angles to it
    match exactly one catalog star ``R``; with three image stars the triangle
    itself is the candidate.  The tolerance of pair ``(u, v)`` is
    ``sqrt(tol_u^2 + tol_v^2) + margin``.  The fourth star's candidates ``R`` are the
    database pairs of ``I`` at the angle ``theta_ir``: a search of ``I``'s pairs sorted by
    cosine (:func:`_first_at_or_above`; ``adj_ptr``, ``adj_other``, ``adj_cos``: :func:`pair_adjacency`).

    ``focal_error`` > 0: the focal length is known to that fraction only, so every catalog
    angle is the image angle times one common scale ``s`` in ``[1 - focal_error, 1 + focal_error]``
    (up to each pair's tolerance): the three windows are widened to that, a triangle is kept
    when one scale fits its three sides (the scales each side allows overlap), and the fourth
    star's windows are those of the triangle's scales.  0: the nominal focal length (the
    published search).

    The two steps are :func:`pyramid_triangles` and :func:`pyramid_fourth` (the fused search takes a
    triangle's fourth star only when it comes to that triangle).

    Returns ``(out, n_triangles)``: rows ``(r, I, J, K, R)`` (``r = R = -1`` for
    a bare triangle), at most ``max_out``; ``n_triangles`` the catalog
    triangles found (``max_triangles + 1`` when there were more: the triad is
    then skipped as uninformative).
    """
    n = b.shape[0]
    out = np.empty((max_out, 5), dtype=np.int64)     # every row returned is written whole
    tri, tri_s, nt = pyramid_triangles(b, tol, margin, i, j, k, star_vec, pair_i, pair_j, pair_cos, kvector, line,
                                       kquad, quad, use_quadratic, max_triangles, focal_error)
    no = 0
    if n == 3:
        for t in range(min(tri.shape[0], max_out)):
            out[no, 0] = -1
            out[no, 4] = -1
            out[no, 1] = tri[t, 0]
            out[no, 2] = tri[t, 1]
            out[no, 3] = tri[t, 2]
            no += 1
        return out[:no], nt
    # The fourth star's cosine windows to I, J and K (with a free scale, its sides: the windows are the
    # triangle's), made at its first use (the same for every triangle).
    win = np.empty((n, 6))
    made = np.zeros(n, dtype=np.bool_)
    for t in range(tri.shape[0]):
        if no >= max_out:
            break
        r, R = pyramid_fourth(b, tol, margin, i, j, k, tri, tri_s, t, star_vec, pair_cos, adj_ptr, adj_other, adj_cos,
                              focal_error, win, made)
        if r >= 0:
            out[no, 0] = r
            out[no, 1] = tri[t, 0]
            out[no, 2] = tri[t, 1]
            out[no, 3] = tri[t, 2]
            out[no, 4] = R
            no += 1
    return out[:no], nt


@njit(cache=True)
def pair_adjacency(n_stars, pair_i, pair_j, pair_cos):
    """Every star's database pairs sorted by cosine: ``(ptr, other, cos)``, star ``s``'s pairs being
    ``other[ptr[s]:ptr[s + 1]]`` at ``cos[ptr[s]:ptr[s + 1]]`` (ascending; each pair is listed under
    both its stars)."""
    count = np.zeros(n_stars + 1, dtype=np.int64)
    m = pair_i.shape[0]
    for t in range(m):
        count[pair_i[t] + 1] += 1
        count[pair_j[t] + 1] += 1
    for s in range(n_stars):
        count[s + 1] += count[s]
    ptr = count.copy()
    other = np.empty(2 * m, dtype=np.int32)
    cos = np.empty(2 * m)
    fill = count[:n_stars].copy()
    # pair_cos is sorted ascending (the k-vector's order), so each star's pairs are filled in order.
    for t in range(m):
        a = pair_i[t]
        z = pair_j[t]
        other[fill[a]] = z
        cos[fill[a]] = pair_cos[t]
        fill[a] += 1
        other[fill[z]] = a
        cos[fill[z]] = pair_cos[t]
        fill[z] += 1
    return ptr, other, cos


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
    tmp = np.empty(n, dtype=a.dtype)
    count = np.empty(257, dtype=np.int64)
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


@njit(cache=True, inline="always")
def check_matches(b, star_vec, star_mag, dcm, match, cos_r, radius, is_core, inst, mag_sorted, on_stars, on_pv):
    """The verification's bookkeeping after the attitude, in one pass.

    * catalog stars predicted in the image with ``dcm``: ``on_stars``, projected to ``on_pv``
      (:func:`startrack._kernels.attitude.project_stars`' list of those on the sensor);
    * each detection's match kept only within its own ``radius[i]`` (rad; ``cos_r`` its cosine);
    * an unresolved pair -- two predicted stars within a detection's radius of
      it and of each other -- is named after its brighter star (the one the
      sensor sees), when that star is not matched elsewhere;
    * the chance-hit probability of the detections outside the core: the mean
      over them of ``min(1, k_i / 100)``, ``k_i`` the predicted stars within ten
      of its radii (the local density; a circle of one radius is 1/100 of it);
    * the bright stars missing: with the frame's zero point (median of catalog
      magnitude - instrumental magnitude ``inst`` (-2.5 log10 flux; NaN without a flux) over
      matched stars) and its robust scatter, ``cut`` = (faintest detection's magnitude) -
      max(0.5, 3 scatter); ``missing`` = unmatched predicted stars brighter than ``cut``;
      ``n_bright`` = database stars brighter than ``cut`` (``cut`` is NaN with fewer than
      three matched fluxes).

    * the magnitude agreement of the core (``is_core``): the chance that random
      catalog stars agree with the core's fluxes as well (``p_mag``, 1 without
      fluxes).

    ``star_vec``/``star_mag`` may be the part of the database near the field; the
    database-wide counts come from ``mag_sorted``, every database magnitude sorted.

    Returns ``(match, n_pred, p_local, missing, n_bright, cut, p_mag, n_bright_pred, zero_point, scatter)``,
    ``n_bright_pred`` the predicted stars brighter than ``cut``, the zero point and scatter NaN with
    fewer than three matched fluxes.
    """
    n = b.shape[0]
    npred = on_stars.shape[0]
    out = match.copy()
    for i in range(n):
        c = out[i]
        if c < 0:
            continue
        d = dcm[0, 0] * star_vec[c, 0] + dcm[0, 1] * star_vec[c, 1] + dcm[0, 2] * star_vec[c, 2]
        e = dcm[1, 0] * star_vec[c, 0] + dcm[1, 1] * star_vec[c, 1] + dcm[1, 2] * star_vec[c, 2]
        f = dcm[2, 0] * star_vec[c, 0] + dcm[2, 1] * star_vec[c, 1] + dcm[2, 2] * star_vec[c, 2]
        if b[i, 0] * d + b[i, 1] * e + b[i, 2] * f < cos_r[i]:
            out[i] = -1
    hit_sum = 0.0
    n_others = 0
    r_last = np.nan
    cos_l = 1.0
    for i in range(n):
        if radius[i] != r_last:     # (the radii are mostly equal: one cosine for a run of them)
            r_last = radius[i]
            cos_l = math.cos(10.0 * r_last)
        best = -1
        near = 0
        for u in range(npred):
            d = b[i, 0] * on_pv[u, 0] + b[i, 1] * on_pv[u, 1] + b[i, 2] * on_pv[u, 2]
            if d >= cos_l:
                near += 1
            if out[i] >= 0 and d >= cos_r[i]:
                s = on_stars[u]
                if best < 0 or star_mag[s] < star_mag[best]:
                    best = s
        if not is_core[i]:
            hit_sum += min(1.0, near * 0.01)
            n_others += 1
        c = out[i]
        if c < 0 or best < 0 or best == c:
            continue
        if (star_vec[best, 0] * star_vec[c, 0] + star_vec[best, 1] * star_vec[c, 1]
                + star_vec[best, 2] * star_vec[c, 2]) < cos_r[i]:
            continue
        used = False
        for j in range(n):
            if out[j] == best:
                used = True
                break
        if not used:
            out[i] = best
    p_local = hit_sum / n_others if n_others > 0 else 0.0
    # Bright stars that should have been detected.
    zp = np.empty(n)
    nz = 0
    faint = -np.inf
    for i in range(n):
        if np.isfinite(inst[i]):
            faint = max(faint, inst[i])
            if out[i] >= 0:
                zp[nz] = star_mag[out[i]] - inst[i]
                nz += 1
    if nz < 3:
        return out, npred, p_local, 0, 0, np.nan, 1.0, 0, np.nan, np.nan
    z0 = _median_in_place(zp, nz)
    for t in range(nz):
        zp[t] = abs(zp[t] - z0)
    scatter = 1.4826 * _median_in_place(zp, nz)
    delta = max(0.5, 3.0 * scatter)
    cut = faint + z0 - delta
    # Magnitude agreement of the core: a chance pattern has catalog magnitudes drawn from
    # the database, so a core star whose catalog magnitude lies within delta of the one its
    # flux predicts does so by chance with probability (database stars within delta) / N.
    # The product over the core, less its largest factor (the zero point was fitted).
    p_mag = 1.0
    worst = 0.0
    for i in range(n):
        if not is_core[i] or out[i] < 0 or not np.isfinite(inst[i]):
            continue
        want = inst[i] + z0
        if abs(star_mag[out[i]] - want) > delta:
            continue
        got = np.searchsorted(mag_sorted, want + delta, side="right") - np.searchsorted(mag_sorted, want - delta)
        frac = got / mag_sorted.shape[0]
        p_mag *= frac
        worst = max(worst, frac)
    if worst > 0.0:
        p_mag /= worst
    matched = np.zeros(star_vec.shape[0], dtype=np.bool_)
    for i in range(n):
        if out[i] >= 0:
            matched[out[i]] = True
    missing = 0
    bright = 0
    for u in range(npred):
        s = on_stars[u]
        if star_mag[s] > cut:
            continue
        bright += 1
        if not matched[s]:
            missing += 1
    n_bright = np.searchsorted(mag_sorted, cut, side="right")
    return out, npred, p_local, missing, n_bright, cut, p_mag, bright, z0, scatter


@njit(cache=True, inline="always")
def core_window(b, img, r, cat, nc, floor, cap):
    """``max |theta_b - theta_r|`` over the pairs of the core (the first ``nc`` of ``b[img]``,
    ``r[cat]``; rad), clipped to ``[floor, cap]``."""
    worst = 0.0
    for u in range(nc):
        for v in range(u + 1, nc):
            tb = math.acos(min(1.0, max(-1.0, _dot_rows(b, img[u], b, img[v]))))
            tr = math.acos(min(1.0, max(-1.0, _dot_rows(r, cat[u], r, cat[v]))))
            worst = max(worst, abs(tb - tr))
    return min(cap, max(worst, floor))


@njit(cache=True)
def _inner(p, q, r):
    """Spherical angle at vertex ``p`` between the arcs to ``q`` and ``r``."""
    u0 = p[1] * q[2] - p[2] * q[1]
    u1 = p[2] * q[0] - p[0] * q[2]
    u2 = p[0] * q[1] - p[1] * q[0]
    v0 = p[1] * r[2] - p[2] * r[1]
    v1 = p[2] * r[0] - p[0] * r[2]
    v2 = p[0] * r[1] - p[1] * r[0]
    nu = math.sqrt(u0 * u0 + u1 * u1 + u2 * u2)
    nv = math.sqrt(v0 * v0 + v1 * v1 + v2 * v2)
    if nu == 0.0 or nv == 0.0:
        return 0.0
    return math.acos(min(1.0, max(-1.0, (u0 * v0 + u1 * v1 + u2 * v2) / (nu * nv))))


@njit(cache=True, inline="always")
def pattern_chance(n_cat, eps, v):
    """Expected catalog patterns matching directions ``v`` (2-4 rows) within ``eps`` by chance.

    Mortari et al. (2004) / LOST: a pair ``N (N-1)/2 eps sin(theta)``; a triangle
    ``N^3 eps^3 sin(theta_ij) / (pi sin(phi_k))``; a pyramid
    ``N^4 eps^5 sin(theta_ij) / (2 pi^2 sin(phi_k) max sin(phi))``.
    """
    n = v.shape[0]
    if n < 3:
        th = _angle(v[0], v[1]) if n == 2 else math.pi / 2
        return n_cat * (n_cat - 1) / 2.0 * eps * math.sin(th)
    th_ij = _angle(v[0], v[1])
    p0 = _inner(v[0], v[1], v[2])
    p1 = _inner(v[1], v[0], v[2])
    p2 = _inner(v[2], v[0], v[1])
    s2 = max(math.sin(p2), 1e-6)
    if n < 4:
        return float(n_cat) ** 3 * eps ** 3 * math.sin(th_ij) / (math.pi * s2)
    smax = max(max(math.sin(p0), math.sin(p1)), max(math.sin(p2), 1e-6))
    return float(n_cat) ** 4 * eps ** 5 * math.sin(th_ij) / (2.0 * math.pi ** 2 * s2 * smax)


@njit(cache=True)
def geometric_voting_top(b, n_cat, pair_i, pair_j, pair_cos, kvector, line, eps, star_vec, top):
    """Kolomenkin et al. (2008) voting, keeping each image star's ``top`` most-voted identities.

    First step (each image pair votes for both
    stars of every catalog pair at its angle within ``eps``, once per image
    pair).  Each image star keeps its ``top`` most-voted catalog stars (ties
    by index).  Second (verification) step over these hypotheses: hypothesis
    ``(i, a)`` gets a vote from every hypothesis ``(j, c)`` of another star
    whose catalog angle agrees with the image angle within ``eps``.

    Returns ``(identity[n, top], votes1[n, top], votes2[n, top])``, identity -1
    where fewer candidates were voted for.
    """
    n = b.shape[0]
    votes = np.zeros((n, n_cat), dtype=np.int32)
    stamp = np.full((n, n_cat), -1, dtype=np.int64)
    pair_id = 0
    for i in range(n):
        for j in range(i + 1, n):
            th = _angle(b[i], b[j])
            lo, hi = _cos_window(th, eps)
            s, e = kvector_range(kvector, line[0], line[1], lo, hi)
            for t in range(s, e):
                c = pair_cos[t]
                if c < lo or c > hi:
                    continue
                k = pair_i[t]
                l = pair_j[t]
                vote_once(votes, stamp, i, k, pair_id)
                vote_once(votes, stamp, i, l, pair_id)
                vote_once(votes, stamp, j, k, pair_id)
                vote_once(votes, stamp, j, l, pair_id)
            pair_id += 1
    identity = np.full((n, top), -1, dtype=np.int64)
    votes1 = np.zeros((n, top), dtype=np.int64)
    for i in range(n):
        for c in range(n_cat):
            v = votes[i, c]
            if v == 0 or v <= votes1[i, top - 1]:
                continue
            # insert into the sorted top list
            p = top - 1
            while p > 0 and votes1[i, p - 1] < v:
                votes1[i, p] = votes1[i, p - 1]
                identity[i, p] = identity[i, p - 1]
                p -= 1
            votes1[i, p] = v
            identity[i, p] = c
    votes2 = np.zeros((n, top), dtype=np.int64)
    for i in range(n):
        for a in range(top):
            ci = identity[i, a]
            if ci < 0:
                continue
            for j in range(i + 1, n):
                th = _angle(b[i], b[j])
                for c in range(top):
                    cj = identity[j, c]
                    if cj < 0 or cj == ci:
                        continue
                    if abs(_angle(star_vec[ci], star_vec[cj]) - th) <= eps:
                        votes2[i, a] += 1
                        votes2[j, c] += 1
    return identity, votes1, votes2


@njit(cache=True, inline="always")
def resolve_conflicts(b, star_mag, match, radius, cos_r, sigma, inst, is_core, max_chi2, z0, scatter, mag_floor,
                      mag_gate, stars, pv):
    """Make every match unambiguous within its tolerance, and magnitude-consistent.

    Each detection ``i`` is linked to every catalog star predicted in front of the
    camera (``stars`` projected to ``pv`` with the attitude,
    :func:`startrack._kernels.attitude.project_stars`) within its own radius ``radius[i]``
    (rad; ``cos_r`` its cosine).  Detections linked to a common
    star form a group; in a group of two or more detections, every one-to-one
    assignment of the group's detections to its stars (a detection may stay
    unassigned, at the cost of ``radius / sigma`` squared) is scored by
    ``sum (offset_i / sigma_i)^2`` plus, with fluxes, ``sum (m_cat - m_pred)^2 /
    sigma_m^2`` -- ``m_pred`` = instrumental magnitude ``inst`` + the frame's
    zero point ``z0`` (:func:`check_matches`; NaN: no magnitudes), ``sigma_m`` its robust
    ``scatter``, at least ``mag_floor``.  The best assignment names its
    detections, except a detection whose star differs in another assignment
    scoring within ``max_chi2`` of the best: that detection is left unnamed
    (a close pair the frame cannot tell apart is refused, never swapped).  A
    group too large to enumerate leaves all its detections unnamed.  A
    detection alone with its stars keeps its match (the unresolved-pair rule
    of :func:`check_matches`).  Finally a match whose magnitude disagrees by
    more than ``max(mag_gate, 4 sigma_m)`` is dropped (a false star on an
    undetected catalog star); in the proposal's core only when the detection is
    the brighter (saturated true stars look fainter, never brighter).

    Returns ``(match, n_refused, n_inconsistent)``.
    """
    n = b.shape[0]
    out = match.copy()
    # Projected stars (their rows in ``stars``) within some detection's radius.
    cand = np.full((n, 8), -1, dtype=np.int64)
    ncand = np.zeros(n, dtype=np.int64)
    cnt = np.zeros(n, dtype=np.int64)
    rmax = 0.0
    for i in range(n):
        rmax = max(rmax, radius[i])
    cos_rmax = math.cos(rmax)
    nproj = stars.shape[0]
    for u in range(nproj):
        for i in range(n):
            d = b[i, 0] * pv[u, 0] + b[i, 1] * pv[u, 1] + b[i, 2] * pv[u, 2]
            if d < cos_rmax or d < cos_r[i]:
                continue
            if ncand[i] < 8:
                cand[i, ncand[i]] = u
            ncand[i] += 1
    # Zero point and scatter of the frame's magnitudes.
    has_mag = not math.isnan(z0)
    sig_m = max(mag_floor, scatter) if has_mag else mag_floor
    # Groups: detections sharing a star (union-find over detections, each joined to the first detection
    # that listed the star; a group's root is its lowest detection, so the groups and their roots do not
    # depend on the order of the joins).
    parent = np.arange(n)
    first = np.full(nproj, -1, dtype=np.int64)
    for i in range(n):
        for c in range(min(ncand[i], 8)):
            u = cand[i, c]
            if first[u] < 0:
                first[u] = i
                continue
            a = first[u]
            while parent[a] != a:
                a = parent[a]
            root_i = i
            while parent[root_i] != root_i:
                root_i = parent[root_i]
            if a != root_i:
                parent[max(a, root_i)] = min(a, root_i)
    for i in range(n):
        a = i
        while parent[a] != a:
            a = parent[a]
        parent[i] = a
    for i in range(n):
        cnt[parent[i]] += 1
    refused = 0
    members = np.empty(n, dtype=np.int64)
    for root in range(n):
        if cnt[root] < 2:
            continue
        k = 0
        total = 1
        too_big = False
        for i in range(n):
            if parent[i] == root:
                members[k] = i
                k += 1
                if ncand[i] > 8:
                    too_big = True
                total *= ncand[i] + 1
        if too_big or total > 4096:
            for t in range(k):
                if out[members[t]] >= 0:
                    refused += 1
                out[members[t]] = -1
            continue
        # Cost of each (detection, option); option ncand = unassigned.
        cost = np.zeros((k, 9))
        for t in range(k):
            i = members[t]
            for c in range(ncand[i]):
                u = cand[i, c]
                ang = math.acos(min(1.0, b[i, 0] * pv[u, 0] + b[i, 1] * pv[u, 1] + b[i, 2] * pv[u, 2]))
                cc = (ang / sigma[i]) ** 2
                if has_mag and np.isfinite(inst[i]):
                    cc += ((star_mag[stars[u]] - inst[i] - z0) / sig_m) ** 2
                cost[t, c] = cc
            cost[t, ncand[i]] = (radius[i] / sigma[i]) ** 2
        digits = np.zeros(k, dtype=np.int64)
        best = np.inf
        best_digits = np.zeros(k, dtype=np.int64)
        # First pass: the best assignment; second pass: which detections differ within max_chi2.
        unsure = np.zeros(k, dtype=np.bool_)
        for rnd in range(2):
            for t in range(k):
                digits[t] = 0
            for _ in range(total):
                ok = True
                for t in range(k):
                    if digits[t] == ncand[members[t]]:
                        continue
                    s = cand[members[t], digits[t]]
                    for v in range(t):
                        if digits[v] < ncand[members[v]] and cand[members[v], digits[v]] == s:
                            ok = False
                if ok:
                    total_cost = 0.0
                    for t in range(k):
                        total_cost += cost[t, digits[t]]
                    if rnd == 0:
                        if total_cost < best:
                            best = total_cost
                            best_digits[:] = digits
                    elif total_cost < best + max_chi2:
                        for t in range(k):
                            if digits[t] != best_digits[t]:
                                unsure[t] = True
                t = 0
                while t < k:
                    digits[t] += 1
                    if digits[t] <= ncand[members[t]]:
                        break
                    digits[t] = 0
                    t += 1
        for t in range(k):
            i = members[t]
            if unsure[t] or best_digits[t] == ncand[i]:
                if out[i] >= 0:
                    refused += 1
                out[i] = -1
            else:
                out[i] = stars[cand[i, best_digits[t]]]
    # Magnitude consistency of the matches.  Outside the core both ways; in the core only a
    # detection brighter than its catalog star allows (a false star on an undetected catalog
    # star): saturation makes a true bright star look fainter, never brighter.
    inconsistent = 0
    if has_mag:
        gate = max(mag_gate, 4.0 * sig_m)
        for i in range(n):
            if out[i] < 0 or not np.isfinite(inst[i]):
                continue
            dm = star_mag[out[i]] - inst[i] - z0
            if dm > gate or (dm < -gate and not is_core[i]):
                out[i] = -1
                inconsistent += 1
    # One detection per star (a group assignment is one-to-one; guard the rest).
    for i in range(n):
        if out[i] < 0:
            continue
        for j in range(i + 1, n):
            if out[j] == out[i]:
                out[j] = -1
                refused += 1
    return out, refused, inconsistent


@njit(cache=True)
def _polyval(coef, x):
    r = 0.0
    for c in coef:
        r = r * x + c
    return r


@njit(cache=True)
def labelling_scan(b, combos, start, labels, members, star_vec, trend, trend_scale, trend_radius, scale, boundary,
                   max_flips, max_scale, eps, max_entries, perms, pa, pc, max_found):
    """Paper 004's label search over image groups ``combos[start:]`` until one matches (Kim & Cho 2019).

    For each group (rows of ``combos``, image star indices): the pairwise angles
    ``theta`` (pairs ``pa, pc``), the label of Eqs. 1-3 (``scale`` = 10^r) with
    the sub-labels within ``boundary`` of a rounding boundary looked up both
    ways (at most ``max_flips`` of them, closest first), each label's entries
    found through the trend line (``trend`` polynomial of ``label /
    trend_scale`` -> index, ``trend_radius`` its error bound) and at most
    ``max_entries`` of them examined: over the group orders ``perms`` the
    smallest Eq. 5 error ``sum |s theta - theta_cat|`` after the best common
    scale ``s`` (``|s - 1| <= max_scale``); an entry is a match when that error is
    within ``len(theta) (eps + 0.5 |s - 1| max(theta)^3)``.

    Returns ``(t, found_members, found_err, found_scale, n)``: the first group
    index ``t`` with matches (``-1`` when none is left) and its ``n`` distinct
    matches (member stars in the group's order), best error first.
    """
    g = combos.shape[1]
    npair = pa.shape[0]
    out_m = np.empty((max_found, g), dtype=np.int64)
    out_e = np.empty(max_found)
    out_s = np.empty(max_found)
    mea = np.empty(npair)
    d = np.empty(npair)
    cat = np.empty(npair)
    x = np.empty(npair - 1)
    base = np.empty(npair - 1, dtype=np.int64)
    close = np.empty(npair - 1)
    unc = np.empty(npair - 1, dtype=np.int64)
    cvec = np.empty((g, 3))
    for t in range(start, combos.shape[0]):
        for p in range(npair):
            mea[p] = _angle(b[combos[t, pa[p]]], b[combos[t, pc[p]]])
            d[p] = mea[p]
        d.sort()
        d0 = d[npair - 1]
        if d0 <= 0.0:
            continue
        nu = 0
        for u in range(npair - 1):
            x[u] = scale * d[npair - 2 - u] / d0
            base[u] = int(math.floor(x[u] + 0.5))
            fr = x[u] - math.floor(x[u])
            close[u] = abs(fr - 0.5)
            if close[u] < boundary:
                unc[nu] = u
                nu += 1
        # the max_flips closest to a boundary
        for a in range(nu):
            for c in range(a + 1, nu):
                if close[unc[c]] < close[unc[a]]:
                    tmp = unc[a]
                    unc[a] = unc[c]
                    unc[c] = tmp
        nu = min(nu, max_flips)
        mm = 0.0
        mea2 = 0.0
        for p in range(npair):
            mm = max(mm, mea[p])
            mea2 += mea[p] * mea[p]
        n = 0
        for flips in range(1 << nu):
            label = 0
            for u in range(npair - 1):
                sub = base[u]
                for f in range(nu):
                    if unc[f] == u and (flips >> f) & 1:
                        sub = int(math.floor(x[u])) if base[u] > x[u] else int(math.floor(x[u])) + 1
                label = label * int(scale) + sub
            guess = int(math.floor(_polyval(trend, label / trend_scale) + 0.5))
            s0, e0 = label_search(labels, label, guess, trend_radius)
            for entry in range(s0, min(e0, s0 + max_entries)):
                for a in range(g):
                    for c in range(3):
                        cvec[a, c] = star_vec[members[entry, a], c]
                best_err = np.inf
                best_p = -1
                best_s = 1.0
                for q in range(perms.shape[0]):
                    num = 0.0
                    for p in range(npair):
                        cat[p] = _angle(cvec[perms[q, pa[p]]], cvec[perms[q, pc[p]]])
                        num += cat[p] * mea[p]
                    s = num / mea2
                    if abs(s - 1.0) > max_scale:
                        continue
                    err = 0.0
                    for p in range(npair):
                        err += abs(s * mea[p] - cat[p])
                    if err < best_err:
                        best_err = err
                        best_p = q
                        best_s = s
                if best_p < 0:
                    continue
                allowance = npair * (eps + 0.5 * abs(best_s - 1.0) * mm ** 3)
                if best_err > allowance:
                    continue
                # One match per catalog group (the best over label variants).
                dup = -1
                for k in range(n):
                    same = True
                    for a in range(g):
                        if out_m[k, a] != members[entry, perms[best_p, a]]:
                            same = False
                            break
                    if same:
                        dup = k
                        break
                if dup >= 0:
                    if best_err < out_e[dup]:
                        out_e[dup] = best_err
                        out_s[dup] = best_s
                    continue
                if n >= max_found:
                    continue
                for a in range(g):
                    out_m[n, a] = members[entry, perms[best_p, a]]
                out_e[n] = best_err
                out_s[n] = best_s
                n += 1
        if n > 0:
            order = np.argsort(out_e[:n])
            return t, out_m[order], out_e[order], out_s[order], n
    return -1, out_m[:0], out_e[:0], out_s[:0], 0


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


@njit(cache=True)
def focal_scale(b, img, star_vec, cat):
    """Least-squares ``s`` with ``c_cat = s c_mea`` over the pairs of ``img``/``cat`` (NaN if < 3 or
    degenerate), ``c`` a pair's chord (:func:`_chord_rows`).

    The chord ratio is the angle ratio to a relative ``(s^2 - 1) theta^2 / 24`` (2e-4 for a 1 % scale
    over 30 deg: the focal loop's next step takes it up) and needs no ``acos``; at the true focal length
    both are 1 up to the noise."""
    if img.shape[0] < 3:
        return np.nan
    ang, mea = _pair_chords(b, img, star_vec, cat)
    return _chord_scale(ang, mea)


@njit(cache=True, inline="always")
def _pair_chords(b, img, star_vec, cat):
    """``(ang, mea)``: the catalog and the measured chords (:func:`_chord_rows`) of the pairs ``u < v`` of
    ``img`` -> ``cat``, in the order ``(0, 1), (0, 2), ..., (1, 2), ...`` (the scale estimates' order)."""
    n = img.shape[0]
    npair = n * (n - 1) // 2
    ang = np.empty(npair)
    mea = np.empty(npair)
    t = 0
    for u in range(n):
        for v in range(u + 1, n):
            mea[t] = _chord_rows(b, img[u], b, img[v])
            ang[t] = _chord_rows(star_vec, cat[u], star_vec, cat[v])
            t += 1
    return ang, mea


#: A focal-length scale fitted to the matches is applied only when it is this many of its standard
#: errors (:func:`scale_sigma`) from 1: a smaller one is noise, and a verification at it changes nothing
#: but the time (at the exact focal length a third of the frames re-verified for one).
SCALE_Z = 3.0


@njit(cache=True)
def scale_sigma(xs, ys, sig_px, idx):
    """The standard error of a scale fitted to detections ``idx`` (pixel positions ``xs``, ``ys``, per-axis
    sigmas ``sig_px``): ``1 / sqrt(sum_i |x_i - x_w|^2 / sigma_i^2)``, ``x_w`` their weighted centre.

    That is the scale's variance in a least-squares similarity fit (scale, rotation, shift) of
    positions with isotropic noise: only the radial part of each error, about the centre, informs the
    scale.  The chord and median estimates of :func:`focal_scale` and :func:`field_scale` are no more
    precise than it.  ``inf`` for fewer than two detections or no spread."""
    n = idx.shape[0]
    if n < 2:
        return np.inf
    ws = 0.0
    mx = 0.0
    my = 0.0
    for t in range(n):
        w = 1.0 / (sig_px[idx[t]] * sig_px[idx[t]])
        ws += w
        mx += w * xs[idx[t]]
        my += w * ys[idx[t]]
    mx /= ws
    my /= ws
    info = 0.0
    for t in range(n):
        dx = xs[idx[t]] - mx
        dy = ys[idx[t]] - my
        info += (dx * dx + dy * dy) / (sig_px[idx[t]] * sig_px[idx[t]])
    if not info > 0.0:
        return np.inf
    return 1.0 / math.sqrt(info)


@njit(cache=True, inline="always")
def _chord_scale(ang, mea):
    """The least-squares ``s`` with ``ang = s mea`` over the pairs' chords (NaN without pairs)."""
    num = 0.0
    den = 0.0
    for t in range(ang.shape[0]):
        num += ang[t] * mea[t]
        den += mea[t] * mea[t]
    if den <= 0.0:
        return np.nan
    return num / den


@njit(cache=True)
def scale_significant(xs, ys, sig_px, focal, img, ang, mea):
    """Whether the matched detections ``img`` (their pairs' catalog and measured chords ``ang``, ``mea``, in
    :func:`focal_scale`'s order) tell the focal-length scale from 1: their least-squares chord scale
    (:func:`_chord_scale`) is more than :data:`SCALE_Z` standard errors from 1.

    The standard error is :func:`scale_sigma`'s, with the detections' stated sigmas or, when larger,
    the scatter the pairs show about that scale (a chord's error has the variance of two detections'
    along it): a frame whose stars are noisier than stated, or holds an odd wrong match, would
    otherwise look scaled.  The scatter is measured after the scale is fitted, so a real
    focal-length error does not hide itself.  (Tested against the stated sigmas alone, the field's
    scale asked for a verification at a new scale in one frame in ten at the exact focal length.)"""
    nm = img.shape[0]
    npair = ang.shape[0]
    if nm < 3 or npair < 2:
        return False
    ls = _chord_scale(ang, mea)
    if math.isnan(ls):
        return True
    ss = 0.0
    for t in range(npair):
        e = ang[t] - ls * mea[t]
        ss += e * e
    sig_emp = focal * math.sqrt(ss / (npair - 1) / 2.0)
    mx = 0.0
    my = 0.0
    for t in range(nm):
        mx += xs[img[t]]
        my += ys[img[t]]
    mx /= nm
    my /= nm
    spread = 0.0
    for t in range(nm):
        spread += (xs[img[t]] - mx) ** 2 + (ys[img[t]] - my) ** 2
    sigma = scale_sigma(xs, ys, sig_px, img)
    if spread > 0.0:
        sigma = max(sigma, sig_emp / math.sqrt(spread))
    return abs(ls - 1.0) > SCALE_Z * sigma


@njit(cache=True)
def matched_scale(b, xs, ys, sig_px, focal, star_vec, img, cat):
    """The focal-length scale of the matches ``img`` -> ``cat`` (:func:`focal_scale`, the same value) and
    whether they tell it from 1 (:func:`scale_significant`): ``(scale, significant)``."""
    if img.shape[0] < 3:
        return np.nan, False
    ang, mea = _pair_chords(b, img, star_vec, cat)
    return _chord_scale(ang, mea), scale_significant(xs, ys, sig_px, focal, img, ang, mea)


@njit(cache=True)
def field_scale(b, xs, ys, sig_px, star_vec, dcm, cos_front, focal, cx, cy, k1, k2, core, radius_px, max_err,
                sky_cells, sky_ra):
    """The focal-length scale a whole field implies (NaN with fewer than four tentative matches, or when
    they cannot tell it from 1: :func:`scale_significant`).

    See :func:`startrack.identify.base._field_scale`: each detection takes the one
    catalog star projected (``dcm``) within its radius widened by ``max_err`` times its
    distance from the core's centre (none when two are; each star once, the first
    detection keeps it); the scale is the median of catalog over measured chord
    (:func:`focal_scale`) over the pairs at least 0.3 of the longest.  ``sky_cells``/``sky_ra``: see
    :func:`cone_stars`.
    """
    return _field_scale_cone(b, xs, ys, sig_px, star_vec, dcm, cos_front, focal, cx, cy, k1, k2, core, radius_px,
                             max_err, sky_cells, sky_ra)


@njit(cache=True)
def _field_scale_cone(b, xs, ys, sig_px, star_vec, dcm, cos_front, focal, cx, cy, k1, k2, core, radius_px, max_err,
                      sky_cells, sky_ra):
    """:func:`field_scale` on the stars of the cone in front of ``dcm`` (:func:`cone_stars`)."""
    front = np.empty(star_vec.shape[0], dtype=np.int64)
    nf = cone_stars(dcm[2, 0], dcm[2, 1], dcm[2, 2], cos_front, star_vec, sky_cells, sky_ra, front)
    return _field_scale_of(b, xs, ys, sig_px, star_vec, dcm, focal, cx, cy, k1, k2, core, radius_px, max_err, front,
                           nf)


@njit(cache=True)
def field_scale_near(b, xs, ys, sig_px, star_vec, dcm, cos_front, focal, cx, cy, k1, k2, core, radius_px, max_err,
                     sky_cells, sky_ra, near):
    """:func:`field_scale`, its cone of stars taken from ``near`` (:func:`verify_core`'s stars near
    the field) when that cone holds it: the same stars in the same order, without a search of
    the database.  The cone of ``near`` holds the field's cone when the angle between their axes
    plus the field's radius is within the cone's radius (1e-6 rad to spare for rounding).

    Returns the scale (:func:`_field_scale_of`)."""
    sub, n_cone, ax, ay, az, cos_cone = near
    fx = dcm[2, 0]
    fy = dcm[2, 1]
    fz = dcm[2, 2]
    apart = math.acos(min(1.0, max(-1.0, ax * fx + ay * fy + az * fz)))
    if apart + math.acos(min(1.0, max(-1.0, cos_front))) + 1e-6 > math.acos(min(1.0, max(-1.0, cos_cone))):
        return _field_scale_cone(b, xs, ys, sig_px, star_vec, dcm, cos_front, focal, cx, cy, k1, k2, core,
                                 radius_px, max_err, sky_cells, sky_ra)
    front = np.empty(n_cone, dtype=np.int64)
    nf = 0
    for t in range(n_cone):
        s = sub[t]
        if fx * star_vec[s, 0] + fy * star_vec[s, 1] + fz * star_vec[s, 2] > cos_front:
            front[nf] = s
            nf += 1
    return _field_scale_of(b, xs, ys, sig_px, star_vec, dcm, focal, cx, cy, k1, k2, core, radius_px, max_err, front,
                           nf)


@njit(cache=True)
def field_tentative_matches(xs, ys, star_vec, dcm, focal, cx, cy, k1, k2, core, radius_px, max_err, front, nf):
    """The field scale's tentative matches: the stars ``front[:nf]`` projected with ``dcm`` (a pinhole of
    ``focal``, ``k1``/``k2``), each detection takes the one star within its radius ``radius_px`` widened
    by ``max_err`` times its distance from the core's centre (none when two are; a star once, the first
    detection keeps it).  Returns ``(img, cat)``, the detections ascending (empty with fewer than four
    stars projected)."""
    none = np.empty(0, dtype=np.int64)
    n = xs.shape[0]
    px = np.empty(nf)
    py = np.empty(nf)
    idx = np.empty(nf, dtype=np.int64)
    k = 0
    for t in range(nf):
        s = front[t]
        z = dcm[2, 0] * star_vec[s, 0] + dcm[2, 1] * star_vec[s, 1] + dcm[2, 2] * star_vec[s, 2]
        x = dcm[0, 0] * star_vec[s, 0] + dcm[0, 1] * star_vec[s, 1] + dcm[0, 2] * star_vec[s, 2]
        y = dcm[1, 0] * star_vec[s, 0] + dcm[1, 1] * star_vec[s, 1] + dcm[1, 2] * star_vec[s, 2]
        a, c = project_to_pixel(x, y, z, focal, cx, cy, k1, k2)
        if not (np.isfinite(a) and np.isfinite(c)):
            continue
        px[k] = a
        py[k] = c
        idx[k] = s
        k += 1
    if k < 4:
        return none, none
    mx = 0.0
    my = 0.0
    for t in range(core.shape[0]):
        mx += xs[core[t]]
        my += ys[core[t]]
    mx /= core.shape[0]
    my /= core.shape[0]
    img = np.empty(n, dtype=np.int64)
    cat = np.empty(n, dtype=np.int64)
    allow = np.empty(n)
    reach = 0.0
    for i in range(n):
        allow[i] = radius_px[i] + max_err * math.hypot(xs[i] - mx, ys[i] - my)
        reach = max(reach, allow[i])
    # The projected stars by columns of pixels at least ``reach`` wide (a counting sort): a detection's
    # stars within its radius are in its column or the two beside it.  Only the nearest two within the
    # radius decide (a third star, or one beyond, changes nothing), so looking at those columns decides
    # as looking at every star; small frames look at every star.
    ncol = 0
    x0 = 0.0
    width = 1.0
    if n * k >= 256 and reach > 0.0:
        x0 = px[0]
        x1 = px[0]
        for t in range(k):
            x0 = min(x0, px[t])
            x1 = max(x1, px[t])
        width = max(reach, (x1 - x0) / k)
        ncol = int((x1 - x0) / width) + 1
    start = np.zeros(ncol + 1, dtype=np.int64)
    order = np.empty(k if ncol > 0 else 0, dtype=np.int64)
    if ncol > 0:
        for t in range(k):
            start[int((px[t] - x0) / width) + 1] += 1
        for q in range(ncol):
            start[q + 1] += start[q]
        fill = start[:ncol].copy()
        for t in range(k):
            q = int((px[t] - x0) / width)
            order[fill[q]] = t
            fill[q] += 1
    nm = 0
    for i in range(n):
        allowed = allow[i]
        # Squared distances (the nearest two; no square root per star).
        d1 = np.inf
        d2 = np.inf
        a1 = -1
        p0 = 0
        p1 = k
        if ncol > 0:
            # The detection's column and the two beside it (none for a NaN or far detection).
            f = (xs[i] - x0) / width
            p1 = 0
            if f > -2.0 and f < ncol + 1.0:
                q = int(math.floor(f))
                p0 = start[max(0, q - 1)]
                p1 = start[min(ncol, q + 2)]
        for p in range(p0, p1):
            t = order[p] if ncol > 0 else p
            dx = xs[i] - px[t]
            dy = ys[i] - py[t]
            d = dx * dx + dy * dy
            if d < d1:
                d2 = d1
                d1 = d
                a1 = t
            elif d < d2:
                d2 = d
        if d1 > allowed * allowed or d2 <= allowed * allowed:
            continue
        s = idx[a1]
        dup = False
        for u in range(nm):
            if cat[u] == s:
                dup = True
                break
        if dup:
            continue
        img[nm] = i
        cat[nm] = s
        nm += 1
    return img[:nm], cat[:nm]


@njit(cache=True)
def _field_scale_of(b, xs, ys, sig_px, star_vec, dcm, focal, cx, cy, k1, k2, core, radius_px, max_err, front, nf):
    """:func:`field_scale` on the stars ``front[:nf]`` (its cone).

    Returns the scale: NaN with fewer than four tentative matches (:func:`field_tentative_matches`) or
    when they cannot tell it from 1 (:func:`scale_significant`)."""
    img, cat = field_tentative_matches(xs, ys, star_vec, dcm, focal, cx, cy, k1, k2, core, radius_px, max_err, front,
                                       nf)
    if img.shape[0] < 4:
        return np.nan
    ang, mea = _pair_chords(b, img, star_vec, cat)
    npair = mea.shape[0]
    longest = mea.max()
    if not scale_significant(xs, ys, sig_px, focal, img, ang, mea):
        return np.nan
    keep = np.empty(npair)
    nk = 0
    for t in range(npair):
        ratio = ang[t] / mea[t] if mea[t] > 0 else np.nan
        if mea[t] >= 0.3 * longest and np.isfinite(ratio):
            keep[nk] = ratio
            nk += 1
    return _median_in_place(keep, nk) if nk >= 3 else np.nan


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
                s = sky_cells[base + t]
                if ax * star_vec[s, 0] + ay * star_vec[s, 1] + az * star_vec[s, 2] > cos_r:
                    out[k] = s
                    k += 1
    _sort_indices(out, k)
    return k


@njit(cache=True, inline="always")
def _to_global(match, sub):
    out = np.full(match.shape[0], -1, dtype=np.int64)
    for i in range(match.shape[0]):
        if match[i] >= 0:
            out[i] = sub[match[i]]
    return out


@njit(cache=True)
def verify_core(b, star_vec_all, star_mag_all, mag_sorted, img, cat_all, radius, sig_rad, flux, use_mags, cos_fov, focal,
                cx, cy, width, height, k1, k2, min_matches, eps, scale_offset, scale_range, max_chi2, mag_floor, mag_gate,
                sky_cells, sky_ra):
    """The shared verification of one proposal in one call (:func:`startrack.identify.base.verify`).

    Attitude from the proposal and two rounds of match-all (``refine_from``), the
    bookkeeping of :func:`check_matches`, unambiguous and magnitude-consistent
    matches (:func:`resolve_conflicts`), the leave-one-out test, the proposal's
    agreement, the bright stars missing, the matched count, and the numbers of the
    false-match probability (the caller multiplies them out).

    ``sky_cells``/``sky_ra``: the database's sky index (:func:`sky_index`; empty: none).

    Returns ``(code, match, q, dcm, n_pred, p_local, missing, n_bright, p_mag, bright_pred, e_core, p_hit_floor,
    near, n_cone, ax, ay, az, cos_cone)``; ``code`` 0 = passed the checks (the probability decides),
    1 = a proposal star fails leave-one-out, 2 = the proposal's stars do not agree with the refined
    attitude, 3 = most bright predicted stars missing, 4 = too few matches.  The last six are the
    database stars near the field that it worked on (:func:`field_scale_near`): ``near[:n_cone]``
    the stars ``s`` with ``(ax, ay, az) . star_vec_all[s] > cos_cone`` (:func:`cone_stars`,
    ascending), the rest of ``near`` the proposal's stars outside that cone.
    """
    n = b.shape[0]
    m_all = star_vec_all.shape[0]
    # The database stars near the field (the proposal's attitude, 2 deg of margin beyond the
    # corners): every later pass works on them only; the proposal's stars are always in.
    q0, _ = quest_pairs(b, img, star_vec_all, cat_all, np.ones(img.shape[0]))
    a0 = quat_to_dcm(q0)
    cos_sub = math.cos(math.acos(min(1.0, cos_fov)) + math.radians(2.0))
    sub = np.empty(m_all + cat_all.shape[0], dtype=np.int64)
    ns = cone_stars(a0[2, 0], a0[2, 1], a0[2, 2], cos_sub, star_vec_all, sky_cells, sky_ra, sub)
    ns0 = ns
    cat = np.empty(cat_all.shape[0], dtype=np.int64)
    for t in range(cat_all.shape[0]):
        pos = np.searchsorted(sub[:ns], cat_all[t])
        if pos < ns and sub[pos] == cat_all[t]:
            cat[t] = pos
        else:
            sub[ns] = cat_all[t]
            cat[t] = ns
            ns += 1
    sub = sub[:ns]
    star_vec = np.empty((ns, 3))
    star_mag = np.empty(ns)
    for t in range(ns):
        s = sub[t]
        star_vec[t, 0] = star_vec_all[s, 0]
        star_vec[t, 1] = star_vec_all[s, 1]
        star_vec[t, 2] = star_vec_all[s, 2]
        star_mag[t] = star_mag_all[s]
    near = (sub, ns0, a0[2, 0], a0[2, 1], a0[2, 2], cos_sub)
    rmax = 0.0
    for i in range(n):
        rmax = max(rmax, radius[i])
    # The proposal's attitude is q0 (the same stars and weights); the projection of the refined
    # attitude stays in lists/pv for the checks below.
    lists = np.empty(3 * ns, dtype=np.int64)
    pv = np.empty((3 * ns, 3))
    match, q, counts = refine_from(b, star_vec, q0, cos_fov, focal, cx, cy, width, height, k1, k2, rmax, 2, lists, pv)
    dcm = quat_to_dcm(q)
    is_core = np.zeros(n, dtype=np.bool_)
    nc = min(4, img.shape[0])
    for t in range(nc):
        is_core[img[t]] = True
    cos_r = np.empty(n)
    inst = np.empty(n)
    for i in range(n):
        # (the radii are mostly equal: one cosine for a run of them)
        cos_r[i] = cos_r[i - 1] if i > 0 and radius[i] == radius[i - 1] else math.cos(radius[i])
        inst[i] = -2.5 * math.log10(flux[i]) if (np.isfinite(flux[i]) and flux[i] > 0) else np.nan
    match, n_pred, p_local, missing, n_bright, _, p_mag, bright_pred, z0, scatter = check_matches(
        b, star_vec, star_mag, dcm, match, cos_r, radius, is_core, inst, mag_sorted, lists[2 * ns:2 * ns + counts[2]],
        pv[2 * ns:2 * ns + counts[2]])
    if not use_mags:
        p_mag = 1.0
    match, _, _ = resolve_conflicts(b, star_mag, match, radius, cos_r, sig_rad, inst, is_core, max_chi2, z0, scatter,
                                    mag_floor, mag_gate, lists[:counts[0]], pv[:counts[0]])
    nm = 0
    for i in range(n):
        if match[i] >= 0:
            nm += 1
    if nm >= 4:
        bb = np.empty((nm, 3))
        rr = np.empty((nm, 3))
        w = np.empty(nm)
        mi = np.empty(nm, dtype=np.int64)
        t = 0
        ws = 0.0
        for i in range(n):
            if match[i] >= 0:
                mi[t] = i
                for u in range(3):
                    bb[t, u] = b[i, u]
                    rr[t, u] = star_vec[match[i], u]
                w[t] = 1.0 / sig_rad[i] ** 2
                ws += w[t]
                t += 1
        for t in range(nm):
            w[t] /= ws
        loo = leave_one_out(bb, rr, w)
        widen = math.sqrt(1.0 + 4.0 / (nm - 1))
        for t in range(nm):
            if loo[t] > radius[mi[t]] * widen:
                if is_core[mi[t]]:
                    return (1, _to_global(match, sub), q, dcm, n_pred, p_local, missing, n_bright, p_mag, bright_pred,
                            0.0, 0.0) + near
                match[mi[t]] = -1
                nm -= 1
    agree = 0
    for t in range(img.shape[0]):
        s = cat[t]
        d = 0.0
        for u in range(3):
            d += b[img[t], u] * (dcm[u, 0] * star_vec[s, 0] + dcm[u, 1] * star_vec[s, 1] + dcm[u, 2] * star_vec[s, 2])
        if d >= cos_r[img[t]]:
            agree += 1
    code = 0
    if agree < min(img.shape[0], min_matches):
        code = 2
    elif bright_pred >= 3 and missing > bright_pred // 2:
        code = 3
    elif nm < min_matches and not (n == 3 and nm == 3):
        code = 4
    if code != 0:
        return (code, _to_global(match, sub), q, dcm, n_pred, p_local, missing, n_bright, p_mag, bright_pred, 0.0,
                0.0) + near
    # The core's pattern chance with the window of its actual residual.
    bc = np.empty((nc, 3))
    smax = 0.0
    for t in range(nc):
        for u in range(3):
            bc[t, u] = b[img[t], u]
        smax = max(smax, sig_rad[img[t]])
    window = core_window(b, img, star_vec, cat, nc, math.sqrt(2.0) * smax, eps)
    e_core = pattern_chance(m_all, window, bc)
    if scale_offset > 0.0:
        # Verified at a fitted focal-length scale: a chance pattern needed to match the core's shape at
        # any one of the scales the fit could have chosen, one per ``window`` of the core's longest angle
        # (:func:`scale_cells`).
        gmin = 1.0
        for u in range(nc):
            for v in range(nc):
                gmin = min(gmin, _dot_rows(bc, u, bc, v))
        e_core *= scale_cells(math.acos(max(-1.0, min(1.0, gmin))), window, eps, scale_offset, scale_range)
    rs = 0.0
    for i in range(n):
        rs += radius[i] * focal
    mean_r = rs / n
    p_hit = max(min(1.0, n_pred * math.pi * mean_r * mean_r / (width * height)), p_local)
    return (0, _to_global(match, sub), q, dcm, n_pred, p_local, missing, n_bright, p_mag, bright_pred, e_core,
            p_hit) + near


@njit(cache=True)
def scale_cells(theta, window, eps, offset, scale_range):
    """The look-elsewhere factor of a proposal verified at a fitted focal-length scale ``1 +- offset``
    (:func:`verify_core`): the scales a chance pattern could have been fitted to, told apart by the
    core's longest angle ``theta`` at the verification's ``window``.

    The fit may take any scale within ``scale_range`` (the stated focal-length error), and the search
    found the core with its pair windows (half-width at most ``eps``) at the nominal scale, so the
    scales its longest side allows span ``2 min(eps, scale_range theta)``: ``1 + 2 min(eps,
    scale_range theta) / window`` cells, and never fewer than ``1 + offset theta / window`` (the
    fitted scale's own distance from 1; a search with the focal length free reaches beyond ``eps``).
    The count does not depend on the scale the data fitted: a chance pattern is fitted to whichever
    scale suits it."""
    free = 2.0 * min(eps, scale_range * theta)
    return 1.0 + max(free, offset * theta) / window


@njit(cache=True)
def binomial_sf(m, n, p):
    """``P(X >= m)`` for ``X ~ Binomial(n, p)`` (:func:`startrack.identify.base._binomial_sf`: exact
    binomial coefficients up to ``n = 60``, then their floating-point product)."""
    if m <= 0:
        return 1.0
    if m > n:
        return 0.0
    total = 0.0
    for k in range(m, n + 1):
        if n <= 60:
            c = 1
            for t in range(min(k, n - k)):
                c = c * (n - t) // (t + 1)
            cf = float(c)
        else:
            cf = 1.0
            for t in range(min(k, n - k)):
                cf = cf * (n - t) / (t + 1)
        total += cf * math.pow(p, float(k)) * math.pow(1.0 - p, float(n - k))
    return min(1.0, total)


@njit(cache=True)
def missing_probability(missing, n_bright, area_frac):
    """:func:`startrack.identify.base._missing_probability`: ``P(K <= missing)``, Poisson of mean
    ``0.5 n_bright area_frac``."""
    lam = 0.5 * n_bright * area_frac
    if lam <= 0:
        return 1.0
    term = math.exp(-lam)
    total = term
    for k in range(1, missing + 1):
        term *= lam / k
        total += term
    return min(1.0, total)


@njit(cache=True)
def pinhole_cos_fov(focal, cx, cy, width, height):
    """``cos`` of the farthest corner's off-axis angle plus 0.5 deg (:func:`startrack.identify.base._geometry`)."""
    dx = max(abs(-0.5 - cx), abs(width - 0.5 - cx))
    dy = max(abs(-0.5 - cy), abs(height - 0.5 - cy))
    off_axis = math.degrees(math.atan(math.hypot(dx, dy) / focal))
    return math.cos(math.radians(off_axis + 0.5))


@njit(cache=True, inline="always")
def _verify_pinhole(b, star_vec, star_mag, mag_sorted, img, cat, sig_px, flux, use_mags, focal, cx, cy,
                    width, height, fixed_radius_px, match_sigma, margin_rad, min_matches, eps, scale_offset,
                    scale_range, max_chi2, mag_floor, mag_gate, trials, max_false, sky_cells, sky_ra):
    """:func:`startrack.identify.base.verify` of one proposal at focal length ``focal`` (a pinhole camera).

    Returns ``(code, match, q, dcm, p_false, missing, bright_pred, n_matched, near)``: ``code`` 0 =
    accepted, 1-4 as :func:`verify_core`, 5 = false-match probability above ``max_false``; ``near``
    the stars near the field (:func:`verify_core`'s last six values).
    """
    n = b.shape[0]
    radius = np.empty(n)
    sig_rad = np.empty(n)
    margin_px = margin_rad * focal
    for i in range(n):
        r = fixed_radius_px if fixed_radius_px > 0 else max(1.0, match_sigma * sig_px[i] + margin_px)
        radius[i] = r / focal
        sig_rad[i] = sig_px[i] / focal
    cos_fov = pinhole_cos_fov(focal, cx, cy, width, height)
    got = verify_core(
        b, star_vec, star_mag, mag_sorted, img, cat, radius, sig_rad, flux, use_mags, cos_fov, focal, cx, cy,
        width, height, 0.0, 0.0, min_matches, eps, scale_offset, scale_range, max_chi2, mag_floor, mag_gate, sky_cells,
        sky_ra)
    code, match, q, dcm, missing, n_bright, p_mag, bright_pred, e_core, p_hit = (
        got[0], got[1], got[2], got[3], got[6], got[7], got[8], got[9], got[10], got[11])
    near = (got[12], got[13], got[14], got[15], got[16], got[17])
    nm = 0
    for i in range(n):
        if match[i] >= 0:
            nm += 1
    if code != 0:
        return code, match, q, dcm, np.nan, missing, bright_pred, nm, near
    nc = min(4, img.shape[0])
    distinct = 0
    agree = 0
    for t in range(nc):
        first = True
        for u in range(t):
            if img[u] == img[t]:
                first = False
        if first:
            distinct += 1
        if match[img[t]] >= 0:
            agree += 1
    p_missing = missing_probability(missing, n_bright, width * height / focal ** 2 / (4 * math.pi)) * p_mag
    p_false = min(1.0, e_core * max(trials, 1)) * binomial_sf(nm - agree, n - distinct, p_hit) * p_missing
    if p_false > max_false:
        return 5, match, q, dcm, p_false, missing, bright_pred, nm, near
    return 0, match, q, dcm, p_false, missing, bright_pred, nm, near


@njit(cache=True)
def verify_focal(xs, ys, b0, star_vec, star_mag, mag_sorted, img, cat, sig_px, flux, use_mags, focal0, cx, cy, width,
                 height, fixed_radius_px, match_sigma, margin_rad, min_matches, eps, max_chi2, mag_floor, mag_gate,
                 trials, max_false, max_focal_error, sky_cells, sky_ra):
    """:func:`startrack.identify.base._verify_with_focal` in one call, for a distortion-free camera.

    The same steps as the Python driver (focal scale of the proposal, verification, the
    field's scale, re-estimates from the matches), on the same kernels, without a
    Python round trip between them.  ``fixed_radius_px`` <= 0: radii from the sigmas.

    Returns ``(code, match, q, dcm, p_false, missing, bright_pred, n_matched, scale, matched, resid_rms)``:
    ``code`` 0 = accepted, 1-5 as :func:`_verify_pinhole`; ``q`` normalised, scalar part
    >= 0; ``scale`` the focal-length scale used (1.0: none); ``matched`` the matched
    detections (ascending) and ``resid_rms`` the rms angle (arcsec) between them and their
    stars at the final attitude and scale, of an accepted verdict (else none and NaN).
    """
    n = xs.shape[0]
    scale = focal_scale(b0, img, star_vec, cat)
    if not math.isnan(scale) and (abs(scale - 1.0) > max_focal_error or abs(scale - 1.0) < 5e-4):
        scale = np.nan
    focal = focal0
    b = b0
    offset = 0.0
    if not math.isnan(scale):
        focal = focal0 / scale
        b = pixels_to_unit(xs, ys, focal, cx, cy)
        offset = abs(scale - 1.0)
    code, match, q, dcm, p_false, missing, bright_pred, nm, near = _verify_pinhole(
        b, star_vec, star_mag, mag_sorted, img, cat, sig_px, flux, use_mags, focal, cx, cy, width, height,
        fixed_radius_px, match_sigma, margin_rad, min_matches, eps, offset, max_focal_error, max_chi2, mag_floor,
        mag_gate, trials, max_false, sky_cells, sky_ra)
    total = 1.0 if math.isnan(scale) else scale
    if code != 0:
        return _verdict(code, match, q, dcm, p_false, missing, bright_pred, nm, total, b, star_vec)
    margin_px = margin_rad * focal
    radius_px = np.empty(n)
    rmin = np.inf
    for i in range(n):
        radius_px[i] = fixed_radius_px if fixed_radius_px > 0 else max(1.0, match_sigma * sig_px[i] + margin_px)
        rmin = min(rmin, radius_px[i])
    step = np.nan
    if nm < n:
        # (Every detection matched: the whole field speaks through the matches' least-squares scale
        # below, and the widened search of the field's scale could only find the same stars.)
        cos_front = math.cos(math.acos(pinhole_cos_fov(focal, cx, cy, width, height)) + math.radians(0.5))
        core = img[:min(4, img.shape[0])].copy()
        step = field_scale_near(b, xs, ys, sig_px, star_vec, dcm, cos_front, focal, cx, cy, 0.0, 0.0, core, radius_px,
                                max_focal_error, sky_cells, sky_ra, near)
    # (step is NaN also when the tentative matches cannot tell the field's scale from 1: noise.)
    if not math.isnan(step) and abs(step - 1.0) >= 5e-4 and abs(total * step - 1.0) <= max_focal_error:
        total *= step
        focal = focal0 / total
        b = pixels_to_unit(xs, ys, focal, cx, cy)
        code, match, q, dcm, p_false, missing, bright_pred, nm, near = _verify_pinhole(
            b, star_vec, star_mag, mag_sorted, img, cat, sig_px, flux, use_mags, focal, cx, cy, width,
            height, fixed_radius_px, match_sigma, margin_rad, min_matches, eps, abs(total - 1.0), max_focal_error,
            max_chi2, mag_floor, mag_gate, trials, max_false, sky_cells, sky_ra)
    for _ in range(4):
        if code != 0 or nm < 3:
            break
        mi = np.empty(nm, dtype=np.int64)
        mc = np.empty(nm, dtype=np.int64)
        t = 0
        far = 0.0
        for i in range(n):
            if match[i] >= 0:
                mi[t] = i
                mc[t] = match[i]
                far = max(far, math.hypot(xs[i] - cx, ys[i] - cy))
                t += 1
        step, significant = matched_scale(b, xs, ys, sig_px, focal, star_vec, mi, mc)
        if math.isnan(step) or abs(step - 1.0) < 1e-5 or abs(total * step - 1.0) > max_focal_error:
            break
        if abs(step - 1.0) * far < 0.1 * rmin or not significant:
            break
        total *= step
        focal = focal0 / total
        b = pixels_to_unit(xs, ys, focal, cx, cy)
        code, match, q, dcm, p_false, missing, bright_pred, nm, near = _verify_pinhole(
            b, star_vec, star_mag, mag_sorted, img, cat, sig_px, flux, use_mags, focal, cx, cy, width,
            height, fixed_radius_px, match_sigma, margin_rad, min_matches, eps, abs(total - 1.0), max_focal_error,
            max_chi2, mag_floor, mag_gate, trials, max_false, sky_cells, sky_ra)
    return _verdict(code, match, q, dcm, p_false, missing, bright_pred, nm, total, b, star_vec)


@njit(cache=True, inline="always")
def _verdict(code, match, q, dcm, p_false, missing, bright_pred, nm, total, b, star_vec):
    """:func:`verify_focal`'s result: the quaternion normalised (scalar part >= 0), the matched
    detections and their rms residual (arcsec; an accepted verdict's only, else NaN and no detections).

    A residual is the angle of the chord between detection and predicted star, ``2 asin(c / 2)``:
    ``acos`` of their dot product loses half the digits at arcsecond angles (the dot is 1 - 1e-11)."""
    norm = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    sign = -1.0 if q[3] < 0 else 1.0
    qn = np.empty(4)
    for u in range(4):
        qn[u] = sign * q[u] / norm
    matched = np.empty(nm if code == 0 else 0, dtype=np.int64)
    t = 0
    ss = 0.0
    for i in range(match.shape[0]):
        if match[i] >= 0 and t < matched.shape[0]:
            matched[t] = i
            t += 1
            c = match[i]
            c2 = 0.0
            for u in range(3):
                e = b[i, u] - (dcm[u, 0] * star_vec[c, 0] + dcm[u, 1] * star_vec[c, 1] + dcm[u, 2] * star_vec[c, 2])
                c2 += e * e
            ch = math.sqrt(c2)
            # 2 asin(c / 2) by its series below 0.01 rad (the next term is 5 c^7 / 7168: < 1e-17)
            ang = ch * (1.0 + c2 / 24.0 + 3.0 * c2 * c2 / 640.0) if ch < 0.01 else 2.0 * math.asin(min(1.0, ch / 2.0))
            r = math.degrees(ang) * 3600.0
            ss += r * r
    rms = math.sqrt(ss / t) if t > 0 else np.nan
    return code, match, qn, dcm, p_false, missing, bright_pred, nm, total, matched[:t], rms


@njit(cache=True)
def grow_clusters(b, keep, tol, margin, star_vec, fi, fc, fv, start, stop, threshold):
    """Geometric voting's clusters (:func:`startrack.identify.voting._clusters`) of seeds ``start`` to ``stop``.

    ``fi``, ``fc``, ``fv``: the hypotheses (image star, catalog star, support), strongest
    first.  Each seed with support >= ``threshold`` grows greedily through the list: a
    hypothesis joins when neither its image star nor its catalog star is in the cluster
    and its image angle to every member agrees with the catalog angle within the pair
    tolerance ``hypot(tol[keep[i]], tol[keep[m]]) + margin``.

    Returns ``(members, sizes, end)``: row ``s - start`` of ``members`` holds the flat
    indices of seed ``s``'s cluster (its first ``sizes`` entries); ``end`` the first seed
    not grown (below the threshold, or ``stop``).
    """
    nf = fi.shape[0]
    n = b.shape[0]
    stop = min(stop, nf)
    members = np.full((max(stop - start, 0), n), -1, dtype=np.int64)
    sizes = np.zeros(max(stop - start, 0), dtype=np.int64)
    end = start
    for s in range(start, stop):
        if fv[s] < threshold:
            break
        end = s + 1
        row = s - start
        members[row, 0] = s
        k = 1
        for f in range(nf):
            i = fi[f]
            c = fc[f]
            clash = False
            for u in range(k):
                g = members[row, u]
                if fi[g] == i or fc[g] == c:
                    clash = True
                    break
            if clash:
                continue
            ok = True
            for u in range(k):
                g = members[row, u]
                m = fi[g]
                th = math.acos(min(1.0, b[i, 0] * b[m, 0] + b[i, 1] * b[m, 1] + b[i, 2] * b[m, 2]))
                d = fc[g]
                tc = math.acos(min(1.0, star_vec[c, 0] * star_vec[d, 0] + star_vec[c, 1] * star_vec[d, 1]
                                   + star_vec[c, 2] * star_vec[d, 2]))
                if abs(th - tc) > math.hypot(tol[keep[i]], tol[keep[m]]) + margin:
                    ok = False
                    break
            if ok and k < n:
                members[row, k] = f
                k += 1
        sizes[row] = k
    return members, sizes, end



@njit(cache=True)
def pyramid_identify(xs, ys, sig_px, flux_in, triads, fpar, ipar, state, seen, best, res_i, res_f, star_vec, pair_i,
                     pair_j, pair_cos,
                     kvector, line, kquad, quad, star_mag, mag_sorted, sky_cells, sky_ra, adj_ptr, adj_other, adj_cos,
                     star_id):
    """The pyramid's search and the verification of its proposals in one call (a pinhole camera).

    What :func:`startrack.identify.base.run` does with :func:`startrack.identify.pyramid.search_pyramid`
    and :func:`verify_focal`, without a Python round trip per triad and proposal: the frame's
    unit vectors (:func:`pixels_to_unit`), the search stars' tolerances, then the triads
    ``triads[t]`` (smart index sequence; the first ``ipar[0]``) give their pyramids
    (:func:`pyramid_candidates`, in the order found; a triad with more than ``ipar[1]`` triangles
    none), and when the focal length may be off (``fpar[14]`` > 0) the triads once more with the
    focal length free within that (``focal_error``; each such triad counts :func:`free_focal_patterns`
    patterns and may have that many times ``ipar[1]`` triangles); a proposal whose set of (image,
    catalog) pairs was tried already is no new trial (with a second pass, the first has half the
    ``ipar[5]`` proposals); each other is verified (:func:`verify_focal`, ``trials = max(tried,
    patterns)``, a triad's patterns its use - 3 four-star ones: each other search star may complete
    its pyramid)
    and the first accepted ends the search.  Fluxes count when at least three are finite
    (else all NaN, as the driver passes them).

    ``adj_*``: :func:`pair_adjacency`.  ``fpar``: search margin (rad), focal, cx, cy, width, height, fixed match radius (px; <= 0:
    none), match sigma, match-radius margin (rad), eps, max chi2, magnitude floor, magnitude
    gate, max false-match probability, max focal error, tolerance sigma (< 0: no per-star
    tolerance, the margin alone).  ``ipar``: max triads, max triangles, min matches, quadratic
    (0/1), search uses brightness (0/1), max proposals, pause, search stars, focal-length passes (0 = both,
    1 = the nominal focal length's alone, 2 = the free focal length's alone).

    In/out: ``state`` = (next triad, next row of its pyramids, proposals tried, patterns, the second
    pass's patterns beyond one a triad before the next triad, the trials of earlier searches of the frame
    (a search of more stars after one of fewer found nothing: added to this search's count of trials,
    ``max(tried, patterns)``, in the false-match probability; read only));
    ``seen`` (max proposals, 9): each tried proposal's pairs (count, then image/catalog
    indices sorted by image index); ``best`` = (set, code, p_false, missing, bright_pred,
    n_matched, triangles) of the rejected proposal with the lowest false-match probability
    (the first while none has one: NaN).

    Returns ``(status, code, p_false, n_matched, scale, rms, triangles)``:
    ``status`` 0 = accepted (the rest is :func:`verify_focal`'s verdict of that proposal and
    its triad's triangle count), 1 = every triad searched, 2 = ``ipar[5]`` proposals tried,
    3 = paused after ``ipar[6]`` rejected proposals in this call (call again to go on: the
    caller looks at its clock in between).  The verdict's arrays go to the caller's buffers
    (a new array returned to Python costs more than the rest of a small frame's bookkeeping):
    ``res_i[:n]`` the match of every detection (-1: none), ``res_i[n:n + n_matched]`` the matched
    detections, the next ``n_matched`` their stars' ``star_id`` and the next their database indices;
    ``res_f[:4]`` the quaternion, ``res_f[4:13]`` the attitude matrix by rows (``res_i`` holds at least
    ``4 n``, ``res_f`` 13).
    """
    n_tr = min(triads.shape[0], ipar[0])
    n = xs.shape[0]
    margin = fpar[0]
    b_all = pixels_to_unit(xs, ys, fpar[1], fpar[2], fpar[3])
    use = ipar[7]
    b = np.ascontiguousarray(b_all[:use])
    tol = np.zeros(use)
    if fpar[15] >= 0.0:
        for u in range(use):
            tol[u] = fpar[15] * sig_px[u] / fpar[1]
    finite = 0
    for u in range(n):
        if np.isfinite(flux_in[u]):
            finite += 1
    flux = flux_in if finite >= 3 else np.full(n, np.nan)
    use_mags = finite >= 3 and ipar[4] == 0
    rejected = 0
    t = state[0]
    row0 = state[1]
    # The triads at the nominal focal length, then (a focal error allowed) again with the focal
    # length free within it: t counts on through the second pass (the patterns compared).  ipar[8]: 1 = the
    # first pass alone, 2 = the second alone (t starts there, and ``extra`` takes the first pass's triads off
    # the count: this search compares the second pass's patterns only).
    passes = 2 if fpar[14] > 0.0 and ipar[8] != 1 else 1
    extra = state[4]
    if ipar[8] == 2 and t < n_tr:
        extra -= n_tr - t
        t = n_tr
    key = np.empty(9, dtype=np.int64)
    # A proposal's image and catalog stars (3 or 4: views of these, which the verification only reads).
    img4 = np.empty(4, dtype=np.int64)
    cat4 = np.empty(4, dtype=np.int64)
    win = np.empty((use, 6))
    # A triad of the second pass compares free_focal_patterns() triads' patterns: ``extra`` (kept in state[4]
    # between calls) counts those beyond one of the triads before t (the count is (t + 1 + extra) * fourth).
    # A triad's pyramid is completed by whichever other search star matches (the first that does), so a
    # triad puts use - 3 four-star patterns to the test: the gate's look-elsewhere factor counts them all.
    fourth = max(1, use - 3)
    while t < passes * n_tr:
        tt = t % n_tr
        i = triads[tt, 0]
        j = triads[tt, 1]
        k = triads[tt, 2]
        more = 0 if t < n_tr else free_focal_patterns(b, tol, margin, i, j, k, fpar[14]) - 1
        # (never fewer than the patterns compared before: state[3], which a caller searching the same triads a
        # second time against more of the database sets to the first search's count)
        looked = max(state[3], (t + 1 + extra + more) * fourth)
        # A scale-free triad's windows hold its triangles at each of the 1 + more scales it tells apart:
        # it is uninformative beyond that many times the nominal limit.
        focal_error = 0.0 if t < n_tr else fpar[14]
        tri, tri_s, n_tri = pyramid_triangles(b, tol, margin, i, j, k, star_vec, pair_i, pair_j, pair_cos, kvector,
                                              line, kquad, quad, ipar[3] != 0, ipar[1] * (1 + more), focal_error)
        # pyramid_candidates' rows (at most 256), each triangle's fourth star looked for when the search
        # comes to it: the triangles after an accepted proposal's are never completed.
        made = np.zeros(use, dtype=np.bool_)
        rr = -1
        for tn in range(tri.shape[0]):
            r4 = -1
            R4 = -1
            if use > 3:
                r4, R4 = pyramid_fourth(b, tol, margin, i, j, k, tri, tri_s, tn, star_vec, pair_cos, adj_ptr, adj_other,
                                        adj_cos, focal_error, win, made)
                if r4 < 0:
                    continue
            rr += 1
            if rr >= 256:
                break
            if rr < row0:
                continue
            size = 4 if r4 >= 0 else 3
            img = img4[:size]
            cat = cat4[:size]
            img[0] = i
            img[1] = j
            img[2] = k
            cat[0] = tri[tn, 0]
            cat[1] = tri[tn, 1]
            cat[2] = tri[tn, 2]
            if size == 4:
                img[3] = r4
                cat[3] = R4
            # The set of pairs, sorted by image index (the image indices are distinct: an insertion sort
            # of the (image, catalog) pairs into the key).
            key[0] = size
            for u in range(8):
                key[1 + u] = -1
            for u in range(size):
                a = img[u]
                c = cat[u]
                v = u
                while v > 0 and key[2 * v - 1] > a:
                    key[2 * v + 1] = key[2 * v - 1]
                    key[2 * v + 2] = key[2 * v]
                    v -= 1
                key[2 * v + 1] = a
                key[2 * v + 2] = c
            dup = False
            for s in range(state[2]):
                same = True
                for u in range(9):
                    if seen[s, u] != key[u]:
                        same = False
                        break
                if same:
                    dup = True
                    break
            if dup:
                continue
            seen[state[2]] = key
            state[2] += 1
            state[3] = max(state[3], looked)
            code, match, q, dcm, p_false, missing, bright_pred, nm, total, matched, rms = verify_focal(
                xs, ys, b_all, star_vec, star_mag, mag_sorted, img, cat, sig_px, flux, use_mags, fpar[1], fpar[2],
                fpar[3], fpar[4], fpar[5], fpar[6], fpar[7], fpar[8], ipar[2], fpar[9], fpar[10], fpar[11], fpar[12],
                state[5] + max(state[2], looked), fpar[13], fpar[14], sky_cells, sky_ra)
            if code == 0:
                _keep(state, t, rr + 1, extra)
                _put_verdict(res_i, res_f, match, q, dcm, matched, star_id)
                return 0, code, p_false, nm, total, rms, n_tri
            if best[0] == 0.0 or (not math.isnan(p_false) and (math.isnan(best[2]) or p_false < best[2])):
                best[0] = 1.0
                best[1] = code
                best[2] = p_false
                best[3] = missing
                best[4] = bright_pred
                best[5] = nm
                best[6] = n_tri
            rejected += 1
            if state[2] >= ipar[5]:
                _keep(state, t, rr + 1, extra)
                return 2, code, p_false, nm, total, rms, n_tri
            if t < n_tr and passes == 2 and state[2] >= (ipar[5] + 1) // 2:
                # The nominal focal length has had half the budget: on to the second pass (a dense field
                # seen through a focal length a few per cent off can spend it all on chance pyramids here).
                # The nominal triads after t were not looked at: ``extra`` takes them off the count.
                extra -= n_tr - 1 - t
                t = n_tr - 1
                break
            if rejected >= ipar[6]:
                _keep(state, t, rr + 1, extra)
                return 3, code, p_false, nm, total, rms, n_tri
        t += 1
        extra += more
        row0 = 0
    _keep(state, t, 0, extra)
    return 1, -1, np.nan, 0, 1.0, np.nan, 0


@njit(cache=True, inline="always")
def _keep(state, t, row, extra):
    """:func:`pyramid_identify`'s place for its next call: triad ``t``, its pyramid ``row``, the second pass's
    extra patterns."""
    state[0] = t
    state[1] = row
    state[4] = extra


@njit(cache=True)
def _put_verdict(res_i, res_f, match, q, dcm, matched, star_id):
    """:func:`pyramid_identify`'s verdict arrays into the caller's buffers (see there)."""
    n = match.shape[0]
    nm = matched.shape[0]
    for i in range(n):
        res_i[i] = match[i]
    for t in range(nm):
        res_i[n + t] = matched[t]
        res_i[n + nm + t] = star_id[match[matched[t]]]
        res_i[n + 2 * nm + t] = match[matched[t]]
    for u in range(4):
        res_f[u] = q[u]
    for u in range(3):
        for v in range(3):
            res_f[4 + 3 * u + v] = dcm[u, v]
