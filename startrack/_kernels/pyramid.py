"""The pyramid's kernels (Mortari et al. 2004): smart triad order, catalog candidates of a triad and its
fourth star, and the one-kernel search and verification loop (:func:`pyramid_identify`) of
:mod:`startrack.identify.pyramid`."""
import math

import numpy as np

from startrack._kernels._jit import njit
from startrack._kernels.common import (
    _dot_rows,
    _first_at_or_above,
    _pair_window,
    _scale_range,
    _scaled_window,
    _side,
    _triple_rows,
    _window,
    pixels_to_unit,
)
from startrack._kernels.verify import verify_focal


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
    # (head, nxt and other: one allocation)
    w2 = 2 * max(e2 - s2, 0)
    links = np.empty(n_cat + 2 * w2, dtype=np.int32)
    head = links[:n_cat]
    head[:] = -1
    nxt = links[n_cat:n_cat + w2]
    other = links[n_cat + w2:]
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
    # The pairs at theta_ij (below), their window first: its scratch shares the allocations of the others'.
    s, e = _window(pair_cos, kvector, line, kquad, quad, use_quadratic, lo_ij, hi_ij)
    # (mark and sel, below: one allocation)
    flags = np.empty(n_cat + 2 * max(e - s, 0), dtype=np.bool_)
    mark = flags[:n_cat]
    # J and K of a triangle both have a database pair at theta_jk when that window lies within the
    # database's pairs (every pair of its stars closer than its largest angle is in it, and
    # pair_cos[0] is the smallest cosine; 1e-9 to spare at that edge): stars without one are
    # passed over before their vectors are read.  The window is widened by 1e-12 so that no
    # cosine rounding can drop a star the exact test below would keep.
    if pair_cos.shape[0] > 0 and lo_jk - 1e-12 >= pair_cos[0] + 1e-9:
        mark[:] = False
        s3, e3 = _window(pair_cos, kvector, line, kquad, quad, False, lo_jk - 1e-12, hi_jk + 1e-12)
        for t in range(s3, e3):
            mark[pair_i[t]] = True
            mark[pair_j[t]] = True
    else:
        mark[:] = True
    # (tri and lead, below: one allocation)
    ints = np.empty(3 * max_triangles + 2 * max(e - s, 0), dtype=np.int64)
    tri = ints[:3 * max_triangles].reshape((max_triangles, 3))
    tri_s = np.empty((max_triangles, 2))
    nt = 0
    scaled = focal_error > 0.0
    # The pairs at theta_ij (both orientations, in order) whose first star I has a pair at
    # theta_ik, gathered without a branch: about four in five have none, and a branch on that
    # is mispredicted often enough to double the loop's time.  ``t`` is orientation (i, j),
    # ``-1 - t`` the other.
    lead = ints[3 * max_triangles:]
    nl = 0
    # (Two passes: the tests first, each pair's independent of the others', then the gathering.)
    sel = flags[n_cat:]
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

    ``win`` (n, 6) and ``made`` (n, 0 at the triad's first triangle; bool or integers): the other stars'
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
            made[r] = 1
        elif not made[r]:
            win[r, 0], win[r, 1] = _pair_window(b, tol, margin, i, r)
            win[r, 2], win[r, 3] = _pair_window(b, tol, margin, j, r)
            win[r, 4], win[r, 5] = _pair_window(b, tol, margin, k, r)
            made[r] = 1
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
def pyramid_identify(xs, ys, sig_px, flux_in, triads, fpar, ipar, state, seen, best, res_i, res_f, star_vec, pair_i,
                     pair_j, pair_cos,
                     kvector, line, kquad, quad, star_mag, mag_sorted, sky_cells, sky_ra, adj_ptr, adj_other, adj_cos,
                     star_id):
    """The pyramid's search and the verification of its proposals in one call (a pinhole camera).

    What :func:`startrack.identify.driver.run` does with :func:`startrack.identify.pyramid.search_pyramid`
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
    b = b_all[:use]
    # The search stars' tolerances and their cosine windows to a triad (pyramid_fourth), in one allocation.
    fw = np.empty(7 * use)
    tol = fw[:use]
    tol[:] = 0.0
    win = fw[use:].reshape((use, 6))
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
    # A proposal's key (below) and its image and catalog stars (3 or 4: views of img4 and cat4, which the
    # verification only reads), in one allocation.
    iw = np.empty(17 + use, dtype=np.int64)
    key = iw[:9]
    img4 = iw[9:13]
    cat4 = iw[13:17]
    made = iw[17:]      # (pyramid_fourth's: 0/1)
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
        made[:] = 0
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
