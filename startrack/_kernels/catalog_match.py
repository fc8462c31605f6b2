"""The final catalog match's per-detection decisions (:func:`startrack.identify.catalog_match.match_catalog`)
in one call: nearest predicted star, ambiguity, unresolved pairs, the chance of a neighbour that close, one
detection per catalog star."""
import math

import numpy as np

from startrack._kernels._jit import njit


@njit(cache=True)
def match_detections(dots, pc, radius, sigma, rows, mag, ids, taken, max_chance, focal, area):
    """The detections that take a catalog star (:func:`startrack.identify.catalog_match._match_once`).

    ``dots`` (detections x predicted stars): cosines between the unmatched detections and the catalog stars
    predicted in the image, whose camera-frame directions are ``pc`` and whose catalog rows are ``rows``
    (``mag`` and ``ids`` index by row: float64 magnitudes, int64 ids).  ``radius`` (rad) and ``sigma`` (rad, the
    1-sigma noise; the radius when unknown) per detection; ``taken`` the ids matched already; ``focal`` (px) and
    ``area`` (px^2, the image's): the image's mean count of predicted stars in a disc of the radius is
    ``len(pc) pi (radius focal)^2 / area``.

    A detection takes its nearest predicted star when that is within its radius, unless a second one is
    within twice the radius and the two are farther apart than the radius (ambiguous); when they are closer
    (an unresolved pair) the brighter is taken.  The chance of a catalog star that close by accident,
    ``1 - exp(-lambda min(1, max(offset, sigma) / radius)^2)`` (``lambda`` the others within ten radii over
    100, at least the image's mean), must not exceed ``max_chance``, and the star's id must not be taken.
    One detection per catalog star: the nearer (larger cosine) keeps it, the earlier on a tie.

    Returns ``(det, cand)``: the detections (rows of ``dots``, ascending) and the predicted star each takes
    (column of ``dots``)."""
    nt, nk = dots.shape
    det = np.empty(nt, dtype=np.int64)
    cand = np.empty(nt, dtype=np.int64)
    cdot = np.empty(nt)
    cid = np.empty(nt, dtype=np.int64)
    m = 0
    if nk == 0:
        return det[:0], cand[:0]
    for t in range(nt):
        # The two largest cosines (the nearest two stars; one star: both are it).
        a1 = 0
        d1 = dots[t, 0]
        a2 = -1
        d2 = -np.inf
        for c in range(1, nk):
            d = dots[t, c]
            if d > d1:
                d2 = d1
                a2 = a1
                d1 = d
                a1 = c
            elif a2 < 0 or d > d2:
                d2 = d
                a2 = c
        if nk == 1:
            a2 = a1
            d2 = d1
        r = radius[t]
        cos_r = math.cos(r)
        ok = d1 >= cos_r
        best = a1
        if nk > 1:
            near2 = d2 >= math.cos(2.0 * r)
            pair = pc[a1, 0] * pc[a2, 0] + pc[a1, 1] * pc[a2, 1] + pc[a1, 2] * pc[a2, 2]
            distinct = pair < cos_r
            if near2 and distinct:
                ok = False
            if near2 and not distinct and mag[rows[a2]] < mag[rows[a1]]:
                best = a2
        if not ok:
            continue
        dot = dots[t, best]
        local = -1
        c10 = math.cos(10.0 * r)
        for c in range(nk):
            if dots[t, c] >= c10:
                local += 1
        offset = math.acos(min(1.0, dot))
        closest = max(offset, sigma[t]) / r
        lam = max(local / 100.0, nk * math.pi * (r * focal) ** 2 / area)
        chance = 1.0 - math.exp(-lam * min(1.0, closest) ** 2)
        if chance > max_chance:
            continue
        star = ids[rows[best]]
        known = False
        for u in range(taken.shape[0]):
            if taken[u] == star:
                known = True
                break
        if known:
            continue
        det[m] = t
        cand[m] = best
        cdot[m] = dot
        cid[m] = star
        m += 1
    # One detection per catalog star (det is ascending: the earlier wins a tie).
    keep = np.ones(m, dtype=np.bool_)
    for u in range(m):
        for v in range(u + 1, m):
            if cid[u] == cid[v] and keep[u] and keep[v]:
                if cdot[v] > cdot[u]:
                    keep[u] = False
                else:
                    keep[v] = False
    n = 0
    for u in range(m):
        if keep[u]:
            det[n] = det[u]
            cand[n] = cand[u]
            n += 1
    return det[:n], cand[:n]
