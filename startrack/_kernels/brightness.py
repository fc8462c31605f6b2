"""Paper 003's brightness-referenced search (Zhang, Zhao, Liu & Liu 2014, Sec. 4.2-4.3, Figs. 5-6).

The star-pair catalog (Eq. 10) is held *oriented* and *banded*: every pair twice, as
``(X, Y)`` with ``X`` the catalog candidate of the image star looked up, split by the
pair's brightness order (``X`` the brighter star ``I`` of Eq. 10, or the dimmer ``J``) and
by ``X``'s magnitude band; each segment is sorted by cosine and has its own k-vector
(Eqs. 11-12).  A look-up (Eqs. 13-14) then searches only the segments the brightness
allows -- the brighter side when the image star is brighter by more than ``gamma``
(Sec. 4.3), the bands of the reference stars (``B_I < 3``, Sec. 4.3.1) or of a magnitude
window -- so the index ranges are narrowed *before* the search instead of filtered inside
the whole k-vector range.  The entries examined (the sum of the narrowed ranges) and
the entries the unnarrowed k-vector range of the same angle holds (both orientations of
each pair) are counted: the scope of Sec. 4.3.
"""
import math

import numpy as np

from startrack._kernels._jit import njit
from startrack._kernels.database import kvector_range


@njit(cache=True, inline="always")
def _angle(u, v):
    return math.acos(min(1.0, max(-1.0, u[0] * v[0] + u[1] * v[1] + u[2] * v[2])))


@njit(cache=True)
def lookup(th, eps, dmag, gamma, mag_lo, mag_hi, star_mag, ent_x, ent_y, ent_cos, seg_ptr, kv_ptr, kv_all, seg_line,
           band_lo, band_hi, full_kvector, full_line, scope):
    """Oriented candidates ``(X, Y)`` of an image pair at angle ``th`` (rad), sorted by ``X``.

    ``dmag`` = instrumental magnitude of the looked-up star minus its partner's: below
    ``-gamma`` the star is the pair's brighter one (``I``, side 0 only), above ``gamma``
    the dimmer (``J``, side 1 only), otherwise either (Sec. 4.3).  Only bands of ``X``
    overlapping ``[mag_lo, mag_hi]`` are searched, and ``X`` must lie in the window.
    ``scope[0]`` += entries examined (Eqs. 13-14 on each segment), ``scope[1]`` += two
    entries per pair of the unnarrowed k-vector range (what a search of the whole
    star-pair catalog examines, both orientations).
    """
    lo = math.cos(th + eps)
    hi = math.cos(max(th - eps, 0.0))
    s0, e0 = kvector_range(full_kvector, full_line[0], full_line[1], lo, hi)
    scope[1] += 2 * (e0 - s0)
    nb = band_lo.shape[0]
    total = 0
    starts = np.zeros(2 * nb, dtype=np.int64)
    ends = np.zeros(2 * nb, dtype=np.int64)
    for side in range(2):
        if side == 0 and dmag > gamma:
            continue
        if side == 1 and dmag < -gamma:
            continue
        for band in range(nb):
            if band_hi[band] < mag_lo or band_lo[band] > mag_hi:
                continue
            g = side * nb + band
            a = seg_ptr[g]
            n = seg_ptr[g + 1] - a
            if n == 0:
                continue
            s, e = kvector_range(kv_all[kv_ptr[g]:kv_ptr[g + 1]], seg_line[g, 0], seg_line[g, 1], lo, hi)
            starts[g] = a + s
            ends[g] = a + e
            total += e - s
    scope[0] += total
    out = np.empty((total, 2), dtype=np.int64)
    k = 0
    for g in range(2 * nb):
        for t in range(starts[g], ends[g]):
            c = ent_cos[t]
            if c < lo or c > hi:
                continue
            m = star_mag[ent_x[t]]
            if m < mag_lo or m > mag_hi:
                continue
            out[k, 0] = ent_x[t]
            out[k, 1] = ent_y[t]
            k += 1
    out = out[:k]
    order = np.argsort(out[:, 0], kind="mergesort")
    return out[order]


@njit(cache=True)
def _partners(sorted_pairs, x):
    lo = 0
    hi = sorted_pairs.shape[0]
    while lo < hi:
        mid = (lo + hi) >> 1
        if sorted_pairs[mid, 0] < x:
            lo = mid + 1
        else:
            hi = mid
    q = lo
    while q < sorted_pairs.shape[0] and sorted_pairs[q, 0] == x:
        q += 1
    return sorted_pairs[lo:q, 1]


@njit(cache=True)
def _unique_triangle(cij, cik, star_vec, th_jk, eps, cat):
    """Triples ``(I, J, K)``: ``I`` in both candidate sets (``R_i``), ``theta_JK`` within ``eps``
    of the measured ``delta_jk``; stops past two.  The last found is in ``cat[:3]``; returns the count."""
    found = 0
    p = 0
    while p < cij.shape[0]:
        I = cij[p, 0]
        js = _partners(cij, I)
        p += js.shape[0]
        ks = _partners(cik, I)
        for J in js:
            for K in ks:
                if K != J and abs(_angle(star_vec[J], star_vec[K]) - th_jk) <= eps:
                    found += 1
                    cat[0] = I
                    cat[1] = J
                    cat[2] = K
        if found > 1:
            break
    return found


@njit(cache=True)
def brightness_search(b, inst_mag, est_mag, ref_ok, star_vec, star_mag, ent_x, ent_y, ent_cos, seg_ptr, kv_ptr, kv_all,
                      seg_line, band_lo, band_hi, full_kvector, full_line, eps, gamma, ref_mag, mag_window, max_loops,
                      skip, scope):
    """Paper 003's Fig. 5-6 search, resumable: the loops up to ``skip`` are passed over.

    ``b`` image vectors brightest first, ``inst_mag`` their instrumental magnitudes
    (``-2.5 log10 In``: only differences are used, against ``gamma``), ``est_mag`` their
    catalog magnitudes by the Eq. 9 calibration (NaN without one), ``ref_ok[i]`` when
    ``In_i > M_t`` (Eq. 9 at magnitude ``ref_mag``).

    * Reference-star mode (Sec. 4.3.1, Fig. 5), while ``s_i`` is brighter than ``M_t``:
      ``i`` = 1 .. n-2, ``j`` = n .. i+2, ``k`` = j-1 .. i+1 (0-based here); the ranges
      of the pairs ``s_i s_j`` and ``s_i s_k`` are searched in the reference stars'
      bands only (``B_I`` brighter than ``ref_mag``), and ``R_i`` (the intersection of the
      candidates of ``s_i``) with ``theta_JK`` ~ ``delta_jk`` must be unique.  (The text
      prints the second pair as ``s_j s_k``; ``R_i`` intersects candidates of ``s_i``, so
      both pairs contain ``s_i``.)
    * Four-star mode (Sec. 4.3.2) otherwise: a fourth loop nested, ``s_i`` with three
      dimmer stars ``j > k > l`` (starting from ``s_1, s_n, s_n-1, s_n-2``); the three
      ranges of ``p_1`` intersected, then ``J, K, L`` checked against the three angles
      among them.  With ``mag_window`` > 0 and a calibration, ``s_i``'s candidates are
      also limited to its estimated magnitude +- ``mag_window`` (not in the paper).
    * ``n = 3``: the unique triangle.

    Returns ``(mode, idx[4], cat[4], loops)``: mode 1 reference, 2 four-star, 3
    triangle, 0 none.  ``scope`` accumulates the entries examined (see :func:`lookup`).
    """
    n = b.shape[0]
    idx = np.full(4, -1, dtype=np.int64)
    cat = np.full(4, -1, dtype=np.int64)
    loops = 0
    inf = np.inf
    if n < 3:
        return 0, idx, cat, loops
    if n == 3:
        if skip >= 1:
            return 0, idx, cat, 1
        cij = lookup(_angle(b[0], b[1]), eps, inst_mag[0] - inst_mag[1], gamma, -inf, inf, star_mag, ent_x, ent_y,
                     ent_cos, seg_ptr, kv_ptr, kv_all, seg_line, band_lo, band_hi, full_kvector, full_line, scope)
        cik = lookup(_angle(b[0], b[2]), eps, inst_mag[0] - inst_mag[2], gamma, -inf, inf, star_mag, ent_x, ent_y,
                     ent_cos, seg_ptr, kv_ptr, kv_all, seg_line, band_lo, band_hi, full_kvector, full_line, scope)
        if _unique_triangle(cij, cik, star_vec, _angle(b[1], b[2]), eps, cat) == 1:
            idx[0] = 0
            idx[1] = 1
            idx[2] = 2
            return 3, idx, cat, 1
        cat[:] = -1
        return 0, idx, cat, 1
    # Reference-star mode (Fig. 5): catalog candidates of s_i brighter than ref_mag (B_I < 3).
    ref_below = ref_mag - 1e-9
    for i in range(0, n - 2):
        if not ref_ok[i]:
            break
        for j in range(n - 1, i + 1, -1):
            for k in range(j - 1, i, -1):
                loops += 1
                if loops > max_loops:
                    return 0, idx, cat, loops
                if loops <= skip:
                    continue
                cij = lookup(_angle(b[i], b[j]), eps, inst_mag[i] - inst_mag[j], gamma, -inf, ref_below, star_mag,
                             ent_x, ent_y, ent_cos, seg_ptr, kv_ptr, kv_all, seg_line, band_lo, band_hi, full_kvector,
                             full_line, scope)
                if cij.shape[0] == 0:
                    continue
                cik = lookup(_angle(b[i], b[k]), eps, inst_mag[i] - inst_mag[k], gamma, -inf, ref_below, star_mag,
                             ent_x, ent_y, ent_cos, seg_ptr, kv_ptr, kv_all, seg_line, band_lo, band_hi, full_kvector,
                             full_line, scope)
                if cik.shape[0] == 0:
                    continue
                if _unique_triangle(cij, cik, star_vec, _angle(b[j], b[k]), eps, cat) == 1:
                    idx[0] = i
                    idx[1] = j
                    idx[2] = k
                    return 1, idx, cat, loops
                cat[:] = -1
    # Four-star mode.  The look-ups of s_i's pairs are made once per i (each is used by many
    # loops) and their scope counted at every use, as if made again.
    res = np.full(4, -1, dtype=np.int64)
    memo = [np.empty((0, 2), dtype=np.int64) for _ in range(n)]
    have = np.zeros(n, dtype=np.bool_)
    cost = np.zeros((n, 2), dtype=np.int64)
    tmp = np.zeros(2, dtype=np.int64)
    tri = np.empty((64, 3), dtype=np.int64)
    nt = 0
    tri_key = -1
    for i in range(0, n - 3):
        lo_i = -inf
        hi_i = inf
        if mag_window > 0 and not math.isnan(est_mag[i]):
            lo_i = est_mag[i] - mag_window
            hi_i = est_mag[i] + mag_window
        have[:] = False
        tri_key = -1
        for j in range(n - 1, i + 2, -1):
            for k in range(j - 1, i + 1, -1):
                for l in range(k - 1, i, -1):
                    loops += 1
                    if loops > max_loops:
                        return 0, idx, cat, loops
                    if loops <= skip:
                        continue
                    if not have[j]:
                        tmp[:] = 0
                        memo[j] = lookup(_angle(b[i], b[j]), eps, inst_mag[i] - inst_mag[j], gamma, lo_i, hi_i,
                                         star_mag, ent_x, ent_y, ent_cos, seg_ptr, kv_ptr, kv_all, seg_line, band_lo,
                                         band_hi, full_kvector, full_line, tmp)
                        cost[j, 0] = tmp[0]
                        cost[j, 1] = tmp[1]
                        have[j] = True
                    scope[0] += cost[j, 0]
                    scope[1] += cost[j, 1]
                    c0 = memo[j]
                    if c0.shape[0] == 0:
                        continue
                    if not have[k]:
                        tmp[:] = 0
                        memo[k] = lookup(_angle(b[i], b[k]), eps, inst_mag[i] - inst_mag[k], gamma, lo_i, hi_i,
                                         star_mag, ent_x, ent_y, ent_cos, seg_ptr, kv_ptr, kv_all, seg_line, band_lo,
                                         band_hi, full_kvector, full_line, tmp)
                        cost[k, 0] = tmp[0]
                        cost[k, 1] = tmp[1]
                        have[k] = True
                    scope[0] += cost[k, 0]
                    scope[1] += cost[k, 1]
                    c1 = memo[k]
                    if c1.shape[0] == 0:
                        continue
                    if not have[l]:
                        tmp[:] = 0
                        memo[l] = lookup(_angle(b[i], b[l]), eps, inst_mag[i] - inst_mag[l], gamma, lo_i, hi_i,
                                         star_mag, ent_x, ent_y, ent_cos, seg_ptr, kv_ptr, kv_all, seg_line, band_lo,
                                         band_hi, full_kvector, full_line, tmp)
                        cost[l, 0] = tmp[0]
                        cost[l, 1] = tmp[1]
                        have[l] = True
                    scope[0] += cost[l, 0]
                    scope[1] += cost[l, 1]
                    c2 = memo[l]
                    if c2.shape[0] == 0:
                        continue
                    # The triangles (I, J, K) of (i, j, k) serve every l of the innermost loop.
                    if tri_key != j * n + k:
                        tri_key = j * n + k
                        nt = 0
                        th_jk = _angle(b[j], b[k])
                        p = 0
                        while p < c0.shape[0]:
                            I = c0[p, 0]
                            js = _partners(c0, I)
                            p += js.shape[0]
                            ks = _partners(c1, I)
                            for J in js:
                                for K in ks:
                                    if K == J or abs(_angle(star_vec[J], star_vec[K]) - th_jk) > eps:
                                        continue
                                    if nt == tri.shape[0]:
                                        grown = np.empty((2 * nt, 3), dtype=np.int64)
                                        grown[:nt] = tri
                                        tri = grown
                                    tri[nt, 0] = I
                                    tri[nt, 1] = J
                                    tri[nt, 2] = K
                                    nt += 1
                    th_jl = _angle(b[j], b[l])
                    th_kl = _angle(b[k], b[l])
                    found = 0
                    for t in range(nt):
                        I = tri[t, 0]
                        J = tri[t, 1]
                        K = tri[t, 2]
                        for L in _partners(c2, I):
                            if L == J or L == K:
                                continue
                            if abs(_angle(star_vec[J], star_vec[L]) - th_jl) > eps:
                                continue
                            if abs(_angle(star_vec[K], star_vec[L]) - th_kl) > eps:
                                continue
                            found += 1
                            res[0] = I
                            res[1] = J
                            res[2] = K
                            res[3] = L
                        if found > 1:
                            break
                    if found == 1:
                        idx[0] = i
                        idx[1] = j
                        idx[2] = k
                        idx[3] = l
                        cat[:] = res
                        return 2, idx, cat, loops
    return 0, idx, cat, loops
