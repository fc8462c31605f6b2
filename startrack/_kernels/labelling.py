"""Paper 004's labelling scan (:mod:`startrack.identify.labelling`): label look-ups of image star groups."""
import math

import numpy as np

from startrack._kernels._jit import njit
from startrack._kernels.common import _angle
from startrack._kernels.database import label_search


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
