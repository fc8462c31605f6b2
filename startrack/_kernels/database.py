"""Database kernels: k-vector range queries and the label database sweep."""
import math

import numpy as np

from startrack._kernels._jit import njit, prange


@njit(cache=True, inline="always")
def kvector_range(kvector, m, q, y_lo, y_hi):
    """Candidate range ``[start, end)`` (0-based) for ``y_lo <= y <= y_hi`` (Mortari & Neta 2000).

    ``kvector[k]`` (k = 0..n) is the number of sorted values ``y <= m k + q``
    (paper 003 Eq. 12 with Mortari's ``xi`` shift).  Eqs. 13-14:
    ``j_b = floor((y_lo - q) / m)``, ``j_t = ceil((y_hi - q) / m)``, and the
    values with 1-based index in ``[K(j_b) + 1, K(j_t)]`` are the candidates;
    the range is exact up to the elements between consecutive line points.
    """
    n = kvector.shape[0] - 1
    jb = int(math.floor((y_lo - q) / m))
    jt = int(math.ceil((y_hi - q) / m))
    jb = min(max(jb, 0), n)
    jt = min(max(jt, 0), n)
    return kvector[jb], kvector[jt]


@njit(cache=True, inline="always")
def quadratic_range(kquad, p1, p2, p3, y_lo, y_hi):
    """Candidate range for the quadratic search of paper 000 (Eqs. 10-12).

    ``kquad[k]`` is the number of sorted values ``<= p1 k^2 + p2 k + p3``;
    ``k`` solves ``p1 k^2 + p2 k + p3 = y`` on the increasing branch (Eq. 11):
    ``k = (-p2 + sqrt(p2^2 - 4 p1 (p3 - y))) / (2 p1)``.
    """
    n = kquad.shape[0] - 1
    kb = _quad_inverse(p1, p2, p3, y_lo, n)
    kt = _quad_inverse(p1, p2, p3, y_hi, n)
    kb = min(max(int(math.floor(kb)), 0), n)
    kt = min(max(int(math.ceil(kt)), 0), n)
    return kquad[kb], kquad[kt]


@njit(cache=True)
def _quad_inverse(p1, p2, p3, y, n):
    if p1 == 0.0:
        return (y - p3) / p2
    disc = p2 * p2 - 4.0 * p1 * (p3 - y)
    if disc < 0.0:
        return 0.0 if y < p3 else float(n)
    return (-p2 + math.sqrt(disc)) / (2.0 * p1)


@njit(cache=True)
def count_at_or_below(sorted_values, thresholds):
    """``out[k] = #{ v <= thresholds[k] }`` for ascending ``sorted_values`` (one merge pass)."""
    n = sorted_values.shape[0]
    out = np.empty(thresholds.shape[0], dtype=np.int64)
    i = 0
    for k in range(thresholds.shape[0]):
        t = thresholds[k]
        while i < n and sorted_values[i] <= t:
            i += 1
        out[k] = i
    return out


@njit(cache=True)
def label_of_distances(distances, scale):
    """Paper 004 Eqs. 1-3: the integer label of one star group.

    ``distances`` (all pairwise, any order) are sorted in descending order;
    sub-labels ``l_1i = d_i / d_1`` (Eq. 1) are scaled by ``alpha = 10^r`` and
    rounded (Eq. 2) and combined as ``L = sum alpha^(n-i) L_1i`` (Eq. 3).
    """
    d = np.sort(distances)[::-1]
    n = d.shape[0]
    label = 0
    for i in range(1, n):
        sub = int(math.floor(scale * d[i] / d[0] + 0.5))
        label = label * int(scale) + sub
    return label


@njit(cache=True)
def _group_order(vectors, members, group):
    """Members ordered by descending sum of angular distances within the group (paper 004 Sec. 2.3)."""
    sums = np.zeros(group)
    for a in range(group):
        for b in range(group):
            if a != b:
                c = 0.0
                for t in range(3):
                    c += vectors[members[a], t] * vectors[members[b], t]
                sums[a] += math.acos(min(1.0, max(-1.0, c)))
    order = np.argsort(-sums, kind="mergesort")
    return order


@njit(cache=True, parallel=True)
def label_sweep(vectors, boresights, radius_cos, stars_per_field, group, scale, combos):
    """Labels of every group of the brightest stars around every boresight.

    ``vectors`` are sorted brightest first.  For each boresight the first
    ``stars_per_field`` stars within the field (cosine above ``radius_cos``)
    are taken and every combination in ``combos`` (``(c, group)`` indices into
    them) becomes a row: ``(label, member star indices ordered by distance
    sums)``.  Rows of fields with fewer stars are left with label -1.
    """
    nb = boresights.shape[0]
    nc = combos.shape[0]
    npairs = group * (group - 1) // 2
    labels = np.full(nb * nc, -1, dtype=np.int64)
    members_out = np.zeros((nb * nc, group), dtype=np.int32)
    for b in prange(nb):
        field = np.empty(stars_per_field, dtype=np.int64)
        found = 0
        for s in range(vectors.shape[0]):
            c = vectors[s, 0] * boresights[b, 0] + vectors[s, 1] * boresights[b, 1] + vectors[s, 2] * boresights[b, 2]
            if c >= radius_cos:
                field[found] = s
                found += 1
                if found == stars_per_field:
                    break
        if found < stars_per_field:
            continue
        dist = np.empty(npairs)
        members = np.empty(group, dtype=np.int64)
        for ci in range(nc):
            for a in range(group):
                members[a] = field[combos[ci, a]]
            k = 0
            for a in range(group):
                for bb in range(a + 1, group):
                    cc = 0.0
                    for t in range(3):
                        cc += vectors[members[a], t] * vectors[members[bb], t]
                    dist[k] = math.acos(min(1.0, max(-1.0, cc)))
                    k += 1
            row = b * nc + ci
            labels[row] = label_of_distances(dist, scale)
            order = _group_order(vectors, members, group)
            for a in range(group):
                members_out[row, a] = members[order[a]]
    return labels, members_out


@njit(cache=True, inline="always")
def bisect_left(a, lo, hi, x):
    """The first ``p`` in ``[lo, hi)`` with ``a[p] >= x``, else ``hi`` (``a[lo:hi]`` ascending):
    ``lo + np.searchsorted(a[lo:hi], x)`` without the slice."""
    while lo < hi:
        mid = (lo + hi) >> 1
        if a[mid] < x:
            lo = mid + 1
        else:
            hi = mid
    return lo


@njit(cache=True, inline="always")
def bisect_right(a, lo, hi, x):
    """The first ``p`` in ``[lo, hi)`` with ``a[p] > x``, else ``hi`` (``a[lo:hi]`` ascending):
    ``lo + np.searchsorted(a[lo:hi], x, side="right")`` without the slice."""
    while lo < hi:
        mid = (lo + hi) >> 1
        if a[mid] <= x:
            lo = mid + 1
        else:
            hi = mid
    return lo


@njit(cache=True)
def label_search(labels, label, guess, radius):
    """Range ``[start, end)`` of entries equal to ``label`` in the sorted ``labels``.

    Searches ``[guess - radius, guess + radius]`` (the trend line's error
    bound) by bisection; returns an empty range when absent.
    """
    n = labels.shape[0]
    lo = max(0, guess - radius)
    hi = min(n, guess + radius + 1)
    start = bisect_left(labels, lo, hi, label)
    return start, bisect_right(labels, start, hi, label)
