"""Pattern-index kernels: neighbour grid, uniform thinning, 4-star patterns, keys and look-up.

A pattern is four stars; its key is the five smaller of its six edge angles
divided by the largest, each quantised into ``NBINS`` bins (a 25-bit integer).
Keys are free of the focal length, so one index serves every field of view.
"""
import math

import numpy as np

from startrack._kernels._jit import njit

NBINS = 32
PREFIX_SHIFT = 9            # a 25-bit key >> 9 is a 16-bit prefix
PREFIX_SIZE = 1 << 16
#: A pattern's shape (:func:`pattern_shapes`): its six edges ascending over their sum, times this, rounded to a
#: uint16.  Every edge is at most a third of the sum (the largest edge ``AB`` is at most ``AC + CB`` and ``AD + DB``),
#: so 0.5 in 65,535 steps keeps a resolution of 3.8e-6 of the sum.
SHAPE_SCALE = 131070.0
#: The shape pre-filter's allowance for that rounding, as a fraction of the edge sum: 2.6 times the largest rounding
#: error (0.5 / SHAPE_SCALE), so that no pattern :func:`_sorted_fit` accepts is refused.
SHAPE_SLACK = 1e-5


@njit(cache=True, inline="always")
def _angle(a, b):
    """Angle (rad) between unit vectors, accurate for small and large angles (atan2 of |a x b| and a.b)."""
    cx = a[1] * b[2] - a[2] * b[1]
    cy = a[2] * b[0] - a[0] * b[2]
    cz = a[0] * b[1] - a[1] * b[0]
    return math.atan2(math.sqrt(cx * cx + cy * cy + cz * cz), a[0] * b[0] + a[1] * b[1] + a[2] * b[2])


@njit(cache=True)
def _cells(vec, h):
    """Cube-grid cell of each unit vector (cell side ``h``): (cell id, n per axis)."""
    n = int(math.ceil(2.0 / h)) + 1
    out = np.empty(vec.shape[0], dtype=np.int64)
    for i in range(vec.shape[0]):
        ix = int((vec[i, 0] + 1.0) / h)
        iy = int((vec[i, 1] + 1.0) / h)
        iz = int((vec[i, 2] + 1.0) / h)
        out[i] = (ix * n + iy) * n + iz
    return out, n


@njit(cache=True)
def _cell_range(sorted_cells, cell):
    lo = np.searchsorted(sorted_cells, cell)
    hi = np.searchsorted(sorted_cells, cell + 1)
    return lo, hi


@njit(cache=True)
def thin_uniform_radius(vec, radius, keep_per_disk):
    """Brightest first, keep a star unless ``keep_per_disk`` kept stars already lie within ``radius`` (rad).

    ``vec`` is sorted brightest first.  Returns the kept indices (ascending).
    The result has a nearly uniform density (about ``keep_per_disk`` stars per
    disk of ``radius``) without the cell-boundary effects of a fixed grid.
    """
    h = 2.0 * math.sin(radius / 2.0)
    cells, n = _cells(vec, h)
    order = np.argsort(cells, kind="mergesort")
    sc = cells[order]
    kept = np.zeros(vec.shape[0], dtype=np.bool_)
    cosr = math.cos(radius)
    for i in range(vec.shape[0]):
        c = cells[i]
        cz = c % n
        cy = (c // n) % n
        cx = c // (n * n)
        cnt = 0
        for dx in range(-1, 2):
            for dy in range(-1, 2):
                for dz in range(-1, 2):
                    cc = ((cx + dx) * n + cy + dy) * n + cz + dz
                    lo, hi = _cell_range(sc, cc)
                    for t in range(lo, hi):
                        j = order[t]
                        if kept[j] and vec[i, 0] * vec[j, 0] + vec[i, 1] * vec[j, 1] + vec[i, 2] * vec[j, 2] >= cosr:
                            cnt += 1
        if cnt < keep_per_disk:
            kept[i] = True
    return np.flatnonzero(kept)


@njit(cache=True)
def _neighbours(vec, radius):
    """CSR lists of later (fainter) neighbours within ``radius`` of each star."""
    h = 2.0 * math.sin(radius / 2.0)
    cells, n = _cells(vec, h)
    order = np.argsort(cells, kind="mergesort")
    sc = cells[order]
    cosr = math.cos(radius)
    m = vec.shape[0]
    counts = np.zeros(m + 1, dtype=np.int64)
    for p in range(2):
        fill = np.zeros(m, dtype=np.int64)
        if p == 1:
            for i in range(m):
                counts[i + 1] += counts[i]
            nb = np.empty(counts[m], dtype=np.int64)
        else:
            nb = np.empty(0, dtype=np.int64)
        for i in range(m):
            c = cells[i]
            cz = c % n
            cy = (c // n) % n
            cx = c // (n * n)
            for dx in range(-1, 2):
                for dy in range(-1, 2):
                    for dz in range(-1, 2):
                        cc = ((cx + dx) * n + cy + dy) * n + cz + dz
                        lo, hi = _cell_range(sc, cc)
                        for t in range(lo, hi):
                            j = order[t]
                            if j > i and vec[i, 0] * vec[j, 0] + vec[i, 1] * vec[j, 1] + vec[i, 2] * vec[j, 2] >= cosr:
                                if p == 0:
                                    counts[i + 1] += 1
                                else:
                                    nb[counts[i] + fill[i]] = j
                                    fill[i] += 1
    for i in range(m):
        _sort_run(nb, counts[i], counts[i + 1])
    return counts, nb


@njit(cache=True)
def _argsort_run(d):
    """The order that sorts ``d`` ascending, ties in their order (insertion sort: an anchor's few neighbours; no
    numpy sort to compile)."""
    idx = np.arange(d.shape[0])
    for t in range(1, d.shape[0]):
        i = idx[t]
        v = d[i]
        u = t
        while u > 0 and d[idx[u - 1]] > v:
            idx[u] = idx[u - 1]
            u -= 1
        idx[u] = i
    return idx


@njit(cache=True, inline="always")
def _sort_run(a, lo, hi):
    """``a[lo:hi]`` ascending in place (insertion sort: an anchor's few neighbours; no numpy sort to compile)."""
    for t in range(lo + 1, hi):
        v = a[t]
        u = t
        while u > lo and a[u - 1] > v:
            a[u] = a[u - 1]
            u -= 1
        a[u] = v


@njit(cache=True, inline="always")
def _edges(v0, v1, v2, v3, e):
    e[0] = _angle(v0, v1)
    e[1] = _angle(v0, v2)
    e[2] = _angle(v0, v3)
    e[3] = _angle(v1, v2)
    e[4] = _angle(v1, v3)
    e[5] = _angle(v2, v3)


@njit(cache=True)
def _edges_rows(v, i0, i1, i2, i3, e):
    """:func:`_edges` of the rows ``i0 .. i3`` of ``v`` (the same arithmetic, without a view per row).  A call,
    not inlined: query_patterns' three copies of the six angles took ~0.9 s of its ~3.5 s compilation."""
    e[0] = _angle_rows(v, i0, i1)
    e[1] = _angle_rows(v, i0, i2)
    e[2] = _angle_rows(v, i0, i3)
    e[3] = _angle_rows(v, i1, i2)
    e[4] = _angle_rows(v, i1, i3)
    e[5] = _angle_rows(v, i2, i3)


@njit(cache=True, inline="always")
def _angle_rows(v, i, j):
    """:func:`_angle` of the rows ``i`` and ``j`` of ``v``."""
    cx = v[i, 1] * v[j, 2] - v[i, 2] * v[j, 1]
    cy = v[i, 2] * v[j, 0] - v[i, 0] * v[j, 2]
    cz = v[i, 0] * v[j, 1] - v[i, 1] * v[j, 0]
    return math.atan2(math.sqrt(cx * cx + cy * cy + cz * cz),
                      v[i, 0] * v[j, 0] + v[i, 1] * v[j, 1] + v[i, 2] * v[j, 2])


@njit(cache=True)
def _key(e_sorted):
    key = 0
    for i in range(5):
        q = int(e_sorted[i] / e_sorted[5] * NBINS)
        if q >= NBINS:
            q = NBINS - 1
        key = key * NBINS + q
    return key


@njit(cache=True)
def level_patterns(vec, rho_max, rho_min, min_ratio, max_per_anchor, brightest_first=False):
    """Every 4-star pattern of ``vec`` with largest edge in (rho_min, rho_max] (rad).

    Each pattern is made once, from its brightest star (the anchor) and three of
    its fainter neighbours; patterns whose smallest edge is under ``min_ratio``
    of the largest (nearly coincident stars, whose ratios are noisy) are left
    out, and an anchor makes at most ``max_per_anchor`` patterns: its neighbours
    taken nearest first (the most compact patterns first), or with
    ``brightest_first`` in brightness order (``vec`` is sorted brightest first), so
    that the patterns of the three brightest neighbours come first, then those of the
    fourth with two of them, and so on (the order in which an image's brightest
    stars form patterns).
    Returns ``(stars (P, 4) int64 local indices, keys (P,) int64, shapes (P, 6) uint16)``, the shapes as
    :func:`pattern_shapes` makes them (from the same sorted edges).
    """
    counts, nb = _neighbours(vec, rho_max)
    m = vec.shape[0]
    e = np.empty(6)
    es = np.empty(6)
    out_p = np.empty((0, 4), dtype=np.int64)
    out_k = np.empty(0, dtype=np.int64)
    out_s = np.empty((0, 6), dtype=np.uint16)
    for p in range(2):
        total = 0
        for a in range(m):
            lst = nb[counts[a]:counts[a + 1]]
            k = lst.shape[0]
            if k < 3:
                continue
            if not brightest_first:
                # nearest first
                d = np.empty(k)
                for t in range(k):
                    d[t] = -(vec[a, 0] * vec[lst[t], 0] + vec[a, 1] * vec[lst[t], 1] + vec[a, 2] * vec[lst[t], 2])
                lst = lst[_argsort_run(d)]
            made = 0
            for ib in range(k):
                if made >= max_per_anchor:
                    break
                b = lst[ib]
                for ic in range(ib):
                    if made >= max_per_anchor:
                        break
                    c = lst[ic]
                    if _angle(vec[b], vec[c]) > rho_max:
                        continue
                    for idd in range(ic):
                        dd = lst[idd]
                        _edges(vec[a], vec[b], vec[c], vec[dd], e)
                        _sort6(e, es)
                        if es[5] > rho_max or es[5] <= rho_min or es[0] < min_ratio * es[5]:
                            continue
                        if p == 1:
                            out_p[total, 0] = a
                            out_p[total, 1] = b
                            out_p[total, 2] = c
                            out_p[total, 3] = dd
                            out_k[total] = _key(es)
                            _shape_row(es, out_s, total)
                        total += 1
                        made += 1
                        if made >= max_per_anchor:
                            break
        if p == 0:
            out_p = np.empty((total, 4), dtype=np.int64)
            out_k = np.empty(total, dtype=np.int64)
            out_s = np.empty((total, 6), dtype=np.uint16)
    return out_p, out_k, out_s


@njit(cache=True)
def prefix_table(sorted_keys):
    """``table[p]`` = first position whose key prefix is >= p (PREFIX_SIZE + 1 entries)."""
    table = np.empty(PREFIX_SIZE + 1, dtype=np.int64)
    j = 0
    n = sorted_keys.shape[0]
    for p in range(PREFIX_SIZE + 1):
        while j < n and (sorted_keys[j] >> PREFIX_SHIFT) < p:
            j += 1
        table[p] = j
    return table


@njit(cache=True)
def pattern_shapes(vec, pats):
    """Each pattern's shape: its six edge angles (:func:`_edges_rows`, as :func:`query_patterns` computes them)
    ascending, over their sum, times :data:`SHAPE_SCALE`, rounded (uint16, ``(P, 6)``).

    :func:`query_patterns` compares them with an image pattern before it reads the catalog pattern's stars: most
    catalog patterns of a probed key fail there, on one 12-byte row instead of a pattern row and four star
    vectors (memory reads that miss the cache on a 2-million-pattern index)."""
    out = np.empty((pats.shape[0], 6), dtype=np.uint16)
    ce = np.empty(6)
    cs = np.empty(6)
    for p in range(pats.shape[0]):
        _edges_rows(vec, pats[p, 0], pats[p, 1], pats[p, 2], pats[p, 3], ce)
        _sort6(ce, cs)
        _shape_row(cs, out, p)
    return out


@njit(cache=True, inline="always")
def _shape_row(cs, out, p):
    """Row ``p`` of :func:`pattern_shapes`' array from the six edges ``cs``, ascending."""
    total = cs[0] + cs[1] + cs[2] + cs[3] + cs[4] + cs[5]
    for t in range(6):
        q = int(cs[t] / total * SHAPE_SCALE + 0.5) if total > 0.0 else 0
        out[p, t] = min(max(q, 0), 65535)


@njit(cache=True, inline="always")
def _pixel_vec(x, y, cx, cy, f, out):
    u = (x - cx) / f
    v = (y - cy) / f
    n = math.sqrt(u * u + v * v + 1.0)
    out[0] = u / n
    out[1] = v / n
    out[2] = 1.0 / n


_PERMS = np.array([[a, b, c, d] for a in range(4) for b in range(4) for c in range(4) for d in range(4)
                   if len({a, b, c, d}) == 4], dtype=np.int64)
_PAIRS = np.array([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]], dtype=np.int64)


@njit(cache=True)
def _best_permutation(ie, ce, perms, pairs, sig_ang, rel_geom):
    """The star correspondence (image i -> catalog perm[i]) that fits the six edges best.

    ``ie``/``ce``: the six edges (rad) in pair order.  The scale (catalog / image)
    is the ratio of the edge sums.  Each edge's misfit ``|ce / scale - ie|`` is
    divided by its tolerance ``sig_ang + rel_geom * ie`` (centroid noise, plus
    the geometry allowance); returns ``(perm index, worst normalised misfit, scale)``.
    """
    best = -1
    best_err = 1e9
    si = 0.0
    sc = 0.0
    for t in range(6):
        si += ie[t]
        sc += ce[t]
    scale = sc / si
    for q in range(perms.shape[0]):
        worst = 0.0
        for t in range(6):
            a = perms[q, pairs[t, 0]]
            b = perms[q, pairs[t, 1]]
            lo = min(a, b)
            hi = max(a, b)
            if lo == 0:
                idx = hi - 1
            elif lo == 1:
                idx = hi + 1
            else:
                idx = 5
            r = abs(ce[idx] / scale - ie[t]) / (sig_ang + rel_geom * ie[t])
            if r > worst:
                worst = r
                if worst > best_err:
                    break
        if worst < best_err:
            best_err = worst
            best = q
    return best, best_err, scale


@njit(cache=True, inline="always")
def _sort6(src, dst):
    """``dst`` = the six values of ``src`` ascending (insertion sort: no allocation)."""
    for t in range(6):
        v = src[t]
        u = t
        while u > 0 and dst[u - 1] > v:
            dst[u] = dst[u - 1]
            u -= 1
        dst[u] = v


@njit(cache=True, inline="always")
def _sorted_fit(ie_sorted, ie, ce, sig_ang, rel_geom, cs):
    """Whether the six catalog edges ``ce`` can fit the image edges ``ie`` (``ie_sorted`` ascending) under some
    correspondence: a necessary condition of :func:`_best_permutation` returning a misfit of at most 1.

    With the scale of :func:`_best_permutation` (the ratio of the edge sums), an edge may take a catalog edge
    when ``|c / scale - i| <= sig_ang + rel_geom * i``: an interval around ``i`` whose two ends grow with
    ``i``.  Points can be matched one to one into such intervals if and only if the ascending points fit the
    ascending intervals (an exchange argument), so when the sorted edges do not fit no correspondence does,
    least of all one of the 24 that map stars to stars.  Each pair's misfit is computed as
    :func:`_best_permutation` computes it, and only one above ``1 + 1e-9`` rejects (rounding cannot turn a
    fit into a rejection).  Six sorted comparisons instead of up to 24 x 6: most catalog patterns of a
    probed key fail here.
    """
    si = 0.0
    sc = 0.0
    for t in range(6):
        si += ie[t]
        sc += ce[t]
    scale = sc / si
    _sort6(ce, cs)
    for t in range(6):
        r = abs(cs[t] / scale - ie_sorted[t]) / (sig_ang + rel_geom * ie_sorted[t])
        if r > 1.0 + 1e-9:
            return False
    return True


@njit(cache=True, inline="always")
def _shape_bounds(ie_sorted, sig_ang, rel_geom, q_lo, q_hi):
    """The bounds (:func:`pattern_shapes`' units) on each sorted edge of a catalog pattern's shape that
    :func:`_sorted_fit` can accept for the image edges ``ie_sorted`` (ascending).

    :func:`_sorted_fit` accepts when ``|c_t si / sc - i_t| <= (sig_ang + rel_geom i_t)(1 + 1e-9)`` for every sorted
    edge (``c_t`` the catalog's, ``i_t`` the image's, ``sc``, ``si`` their sums): a bound on the shape ``c_t / sc``.
    A stored shape is within ``0.5 / SHAPE_SCALE`` of it, less than :data:`SHAPE_SLACK`, which widens the bounds."""
    si = ie_sorted[0] + ie_sorted[1] + ie_sorted[2] + ie_sorted[3] + ie_sorted[4] + ie_sorted[5]
    for t in range(6):
        room = (sig_ang + rel_geom * ie_sorted[t]) * (1.0 + 1e-9) + SHAPE_SLACK * si
        q_lo[t] = (ie_sorted[t] - room) / si * SHAPE_SCALE
        q_hi[t] = (ie_sorted[t] + room) / si * SHAPE_SCALE


@njit(cache=True, inline="always")
def _shape_passes(shapes, p, q_lo, q_hi):
    """Whether the shape of catalog pattern ``p`` lies within the bounds of :func:`_shape_bounds`."""
    for t in range(6):
        v = shapes[p, t]
        if v < q_lo[t] or v > q_hi[t]:
            return False
    return True


@njit(cache=True)
def query_patterns(xy, cx, cy, combos, level_rho, level_ratio, level_start, level_prefix, keys, pats, shapes, vec,
                   allowed, sigma_px, tol_geom, f_lo, f_hi, max_out):
    """Catalog candidates for image 4-star patterns.

    For each image pattern (``combos``, rows of 4 star indices into ``xy``) and
    each level, the focal length is first guessed from the level's pattern
    sizes, the image pattern's ratio key computed, the key bins within the
    tolerance probed, and every catalog pattern found there compared edge by
    edge (all 24 correspondences); a match fixes the focal length, which is
    then refined on the pattern and the edges compared again.

    ``allowed`` (uint8, one per catalog star row): a catalog pattern with a star whose entry is 0 is not
    compared (a position hint: stars that cannot be in the field).  ``shapes`` (:func:`pattern_shapes`, one row per
    pattern): a catalog pattern whose shape cannot pass :func:`_sorted_fit` (its bounds widened by the shapes'
    rounding, :data:`SHAPE_SLACK`) is not compared either; the candidates are those of the comparison alone.

    Returns rows ``(combo, level, i0..i3 -> catalog c0..c3 , f, misfit)`` as two arrays:
    ints (n, 6) = combo, level, c0, c1, c2, c3 (catalog star of image star combos[combo, k]),
    floats (n, 2) = focal length (px), worst relative edge misfit.
    """
    out_i = np.empty((max_out, 6), dtype=np.int64)
    out_f = np.empty((max_out, 2))
    n_out = 0
    perms = _PERMS
    pairs = _PAIRS
    iv = np.empty((4, 3))
    ie = np.empty(6)
    ce = np.empty(6)
    lo_b = np.empty(5, dtype=np.int64)
    hi_b = np.empty(5, dtype=np.int64)
    cur = np.empty(5, dtype=np.int64)
    es = np.empty(6)                # ``ie`` at the probe's f0, ascending: the key's ratios
    ie_sorted = np.empty(6)         # ``ie`` ascending, kept with it (the pre-filter of _sorted_fit)
    cs = np.empty(6)
    ivr = np.empty((4, 3))          # the refinement's own arrays: a refused candidate leaves the probe's
    ier = np.empty(6)               # ``ie`` (at f0) as it was for the next catalog patterns
    q_lo = np.empty(6)              # the probe's bounds on a catalog pattern's shape (pattern_shapes' units)
    q_hi = np.empty(6)
    for ci in range(combos.shape[0]):
        # pixel extent
        lpx = 0.0
        spx = 1e18
        for t in range(6):
            a = combos[ci, pairs[t, 0]]
            b = combos[ci, pairs[t, 1]]
            d = math.hypot(xy[a, 0] - xy[b, 0], xy[a, 1] - xy[b, 1])
            lpx = max(lpx, d)
            spx = min(spx, d)
        if lpx <= 0.0 or spx < 0.05 * lpx:
            continue
        for lv in range(level_rho.shape[0]):
            rho = level_rho[lv]
            rmin = rho / level_ratio
            f_big = lpx / math.tan(rmin)      # the largest focal length this level allows
            f_small = lpx / math.tan(rho)
            if f_small > f_hi or f_big < f_lo:
                continue
            n_sub = 1 if rho < 0.15 else (2 if rho < 0.35 else 4)
            for sub in range(n_sub):
                f0 = f_small * (f_big / f_small) ** ((sub + 0.5) / n_sub)
                for k in range(4):
                    _pixel_vec(xy[combos[ci, k], 0], xy[combos[ci, k], 1], cx, cy, f0, iv[k])
                _edges_rows(iv, 0, 1, 2, 3, ie)
                _sort6(ie, es)
                _sort6(ie, ie_sorted)
                # tolerance per ratio: centroid noise on the two edges plus the geometry allowance
                g = tol_geom * (rho * rho) + 0.06 * (rho * rho) * math.log(f_big / f_small) / n_sub
                _shape_bounds(ie_sorted, 3.0 * 1.4142 * sigma_px / f0, g + 0.002, q_lo, q_hi)
                for t in range(5):
                    r = es[t] / es[5]
                    tol = 3.0 * 1.4142 * sigma_px * (1.0 / (es[t] * f0) + 1.0 / (es[5] * f0)) * r + g + 0.002
                    lo_b[t] = max(0, int((r - tol) * NBINS))
                    hi_b[t] = min(NBINS - 1, int((r + tol) * NBINS))
                    cur[t] = lo_b[t]
                base = level_start[lv]
                while True:
                    # For given bins of the first three ratios, the keys with the last two ratios in
                    # their bins lie between key_lo and key_hi (keys sorted within a level): one
                    # bisection for the first, then a scan that skips the last ratio's other bins.  The
                    # same keys in the same order as one look-up per bin combination.
                    key = 0
                    for t in range(3):
                        key = key * NBINS + cur[t]
                    key_lo = (key * NBINS + lo_b[3]) * NBINS + lo_b[4]
                    key_hi = (key * NBINS + hi_b[3]) * NBINS + hi_b[4]
                    s = level_prefix[lv, key_lo >> PREFIX_SHIFT]
                    e_ = level_prefix[lv, (key_hi >> PREFIX_SHIFT) + 1]
                    # the first key >= ``key_lo`` by bisection (a fine level's prefix bucket holds
                    # hundreds of keys)
                    lo_j = s
                    hi_j = e_
                    while lo_j < hi_j:
                        mid = (lo_j + hi_j) // 2
                        if keys[base + mid] < key_lo:
                            lo_j = mid + 1
                        else:
                            hi_j = mid
                    for j in range(lo_j, e_):
                        kj = keys[base + j]
                        if kj > key_hi:
                            break
                        b4 = kj % NBINS
                        if b4 < lo_b[4] or b4 > hi_b[4]:
                            continue
                        pj = base + j
                        if not _shape_passes(shapes, pj, q_lo, q_hi):
                            continue
                        if (allowed[pats[pj, 0]] == 0 or allowed[pats[pj, 1]] == 0 or allowed[pats[pj, 2]] == 0
                                or allowed[pats[pj, 3]] == 0):
                            continue
                        _edges_rows(vec, pats[pj, 0], pats[pj, 1], pats[pj, 2], pats[pj, 3], ce)
                        if not _sorted_fit(ie_sorted, ie, ce, 3.0 * 1.4142 * sigma_px / f0, g + 0.002, cs):
                            continue
                        q, err, scale = _best_permutation(ie, ce, perms, pairs, 3.0 * 1.4142 * sigma_px / f0,
                                                          g + 0.002)
                        if err > 1.0:
                            continue
                        # refine the focal length on the pattern, then compare again
                        f = f0
                        for _ in range(3):
                            f = f / scale
                            for k in range(4):
                                _pixel_vec(xy[combos[ci, k], 0], xy[combos[ci, k], 1], cx, cy, f, ivr[k])
                            _edges_rows(ivr, 0, 1, 2, 3, ier)
                            q, err, scale = _best_permutation(ier, ce, perms, pairs, 3.0 * 1.4142 * sigma_px / f,
                                                              tol_geom * rho * rho + 0.001)
                        if f < f_lo or f > f_hi or err > 1.0:
                            continue
                        if n_out < max_out:
                            out_i[n_out, 0] = ci
                            out_i[n_out, 1] = lv
                            for k in range(4):
                                out_i[n_out, 2 + k] = pats[pj, perms[q, k]]
                            out_f[n_out, 0] = f
                            out_f[n_out, 1] = err
                            n_out += 1
                    # next bin combination (of the first three ratios)
                    t = 2
                    while t >= 0:
                        cur[t] += 1
                        if cur[t] <= hi_b[t]:
                            break
                        cur[t] = lo_b[t]
                        t -= 1
                    if t < 0:
                        break
    return out_i[:n_out], out_f[:n_out]
