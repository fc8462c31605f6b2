"""The shared verification of a proposal (:mod:`startrack.identify.verify`): match every detection,
unambiguous and magnitude-consistent matches, leave-one-out, bright stars missing, and the false-match
probability's numbers; :func:`verify_focal` with the focal-length steps in one call."""
import math

import numpy as np

from startrack._kernels._jit import njit
from startrack._kernels.attitude import (
    dcm_into,
    leave_one_out,
    quat_to_dcm,
    quest,
    quest_pairs,
    quest_pairs_unit,
    refine_from,
)
from startrack._kernels.common import _angle, _dot_rows, _median_in_place, pixels_to_unit
from startrack._kernels.focal import (
    _chord_scale,
    _pair_chords,
    field_scale_near,
    focal_scale,
    scale_cells,
    scale_interval,
    scale_significant,
)
from startrack._kernels.sky_index import cone_stars


@njit(cache=True, inline="always")
def check_matches(b, star_vec, star_mag, dcm, match, cos_r, radius, is_core, inst, mag_sorted, on_stars, on_pv, zp,
                  matched):
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
    database-wide counts come from ``mag_sorted``, every database magnitude sorted.  ``zp`` and ``matched``:
    scratch, ``n`` floats and ``len(star_vec)`` integers.

    Returns ``(match, n_pred, p_local, missing, n_bright, cut, p_mag, n_bright_pred, zero_point, scatter)``,
    ``n_bright_pred`` the predicted stars brighter than ``cut``, the zero point and scatter NaN with
    fewer than three matched fluxes; ``match`` is the argument, updated in place.
    """
    n = b.shape[0]
    npred = on_stars.shape[0]
    out = match
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
    matched[:] = 0
    for i in range(n):
        if out[i] >= 0:
            matched[out[i]] = 1
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

    Returns ``(match, n_refused, n_inconsistent)``, ``match`` the argument, updated in place.
    """
    n = b.shape[0]
    out = match
    # Projected stars (their rows in ``stars``) within some detection's radius.
    nproj = stars.shape[0]
    # (cand, ncand, cnt, parent, members and first below: one allocation)
    iw = np.empty(12 * n + nproj, dtype=np.int64)
    cand = iw[:8 * n].reshape((n, 8))
    cand[:] = -1
    work = iw[8 * n:12 * n].reshape((4, n))
    work[:] = 0
    ncand = work[0]
    cnt = work[1]
    rmax = 0.0
    for i in range(n):
        rmax = max(rmax, radius[i])
    cos_rmax = math.cos(rmax)
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
    parent = work[2]
    for i in range(n):
        parent[i] = i
    first = iw[12 * n:]
    first[:] = -1
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
    members = work[3]
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


@njit(cache=True, inline="always")
def _to_global(match, sub):
    """``match``'s indices into ``sub`` as ``sub``'s values (-1 stays), in place."""
    for i in range(match.shape[0]):
        if match[i] >= 0:
            match[i] = sub[match[i]]
    return match


@njit(cache=True)
def verify_core(b, star_vec_all, star_mag_all, mag_sorted, img, cat_all, radius, sig_rad, flux, use_mags, cos_fov, focal,
                cx, cy, width, height, k1, k2, k3, k4, proj, min_matches, eps, scale_offset, scale_range, max_chi2, mag_floor,
                mag_gate, sky_cells, sky_ra):
    """The shared verification of one proposal in one call (:func:`startrack.identify.verify.verify`).

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
    q0, _ = quest_pairs_unit(b, img, star_vec_all, cat_all)
    # The boresight of q0: the third row of quat_to_dcm(q0) (the same arithmetic).
    q1, q2, q3, q4 = q0[0], q0[1], q0[2], q0[3]
    ax = 2 * (q1 * q3 + q2 * q4)
    ay = 2 * (q2 * q3 - q1 * q4)
    az = -q1 * q1 - q2 * q2 + q3 * q3 + q4 * q4
    cos_sub = math.cos(math.acos(min(1.0, cos_fov)) + math.radians(2.0))
    n_cat = cat_all.shape[0]
    sub = np.empty(m_all + 2 * n_cat, dtype=np.int64)     # (and cat: its last n_cat)
    cat = sub[m_all + n_cat:]
    sub = sub[:m_all + n_cat]
    ns = cone_stars(ax, ay, az, cos_sub, star_vec_all, sky_cells, sky_ra, sub)
    ns0 = ns
    for t in range(cat_all.shape[0]):
        pos = np.searchsorted(sub[:ns], cat_all[t])
        if pos < ns and sub[pos] == cat_all[t]:
            cat[t] = pos
        else:
            sub[ns] = cat_all[t]
            cat[t] = ns
            ns += 1
    sub = sub[:ns]
    # The floats of the stars near the field and of the detections, in one allocation: the stars' vectors and
    # magnitudes, their projection (pv, below), each detection's cos(radius), instrumental magnitude and
    # zero point (check_matches), the matched pairs and weights of the leave-one-out test and the core's vectors.
    fw = np.empty(13 * ns + 10 * n + 21)
    star_vec = fw[:3 * ns].reshape((ns, 3))
    star_mag = fw[3 * ns:4 * ns]
    pv = fw[4 * ns:13 * ns].reshape((3 * ns, 3))
    f0 = 13 * ns
    cos_r = fw[f0:f0 + n]
    inst = fw[f0 + n:f0 + 2 * n]
    zp = fw[f0 + 2 * n:f0 + 3 * n]
    f0 += 3 * n
    for t in range(ns):
        s = sub[t]
        star_vec[t, 0] = star_vec_all[s, 0]
        star_vec[t, 1] = star_vec_all[s, 1]
        star_vec[t, 2] = star_vec_all[s, 2]
        star_mag[t] = star_mag_all[s]
    near = (sub, ns0, ax, ay, az, cos_sub)
    rmax = 0.0
    for i in range(n):
        rmax = max(rmax, radius[i])
    # The proposal's attitude is q0 (the same stars and weights); the projection of the refined
    # attitude stays in lists/pv for the checks below.
    # (lists, is_core, the leave-one-out's matched detections and check_matches' scratch: one allocation)
    li = np.empty(4 * ns + 2 * n, dtype=np.int64)
    lists = li[:3 * ns]
    match, q, counts = refine_from(b, star_vec, q0, cos_fov, focal, cx, cy, width, height, k1, k2, k3, k4, proj, rmax, 2,
                                   lists, pv)
    dcm = fw[f0 + 7 * n + 12:f0 + 7 * n + 21].reshape((3, 3))
    dcm_into(q, dcm)
    is_core = li[3 * ns:3 * ns + n]
    is_core[:] = 0
    nc = min(4, img.shape[0])
    for t in range(nc):
        is_core[img[t]] = 1
    for i in range(n):
        # (the radii are mostly equal: one cosine for a run of them)
        cos_r[i] = cos_r[i - 1] if i > 0 and radius[i] == radius[i - 1] else math.cos(radius[i])
        inst[i] = -2.5 * math.log10(flux[i]) if (np.isfinite(flux[i]) and flux[i] > 0) else np.nan
    match, n_pred, p_local, missing, n_bright, _, p_mag, bright_pred, z0, scatter = check_matches(
        b, star_vec, star_mag, dcm, match, cos_r, radius, is_core, inst, mag_sorted, lists[2 * ns:2 * ns + counts[2]],
        pv[2 * ns:2 * ns + counts[2]], zp, li[3 * ns + 2 * n:])
    if not use_mags:
        p_mag = 1.0
    match, _, _ = resolve_conflicts(b, star_mag, match, radius, cos_r, sig_rad, inst, is_core, max_chi2, z0, scatter,
                                    mag_floor, mag_gate, lists[:counts[0]], pv[:counts[0]])
    nm = 0
    for i in range(n):
        if match[i] >= 0:
            nm += 1
    if nm >= 4:
        bb = fw[f0:f0 + 3 * nm].reshape((nm, 3))
        rr = fw[f0 + 3 * nm:f0 + 6 * nm].reshape((nm, 3))
        w = fw[f0 + 6 * nm:f0 + 7 * nm]
        mi = li[3 * ns + n:3 * ns + n + nm]
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
    bc = fw[f0 + 7 * n:f0 + 7 * n + 3 * nc].reshape((nc, 3))
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
def binomial_sf(m, n, p):
    """``P(X >= m)`` for ``X ~ Binomial(n, p)`` (:func:`startrack.identify.verify._binomial_sf`: exact
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
    """:func:`startrack.identify.verify._missing_probability`: ``P(K <= missing)``, Poisson of mean
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
    """``cos`` of the farthest corner's off-axis angle plus 0.5 deg (:func:`startrack.identify.verify._geometry`)."""
    dx = max(abs(-0.5 - cx), abs(width - 0.5 - cx))
    dy = max(abs(-0.5 - cy), abs(height - 0.5 - cy))
    off_axis = math.degrees(math.atan(math.hypot(dx, dy) / focal))
    return math.cos(math.radians(off_axis + 0.5))


@njit(cache=True, inline="always")
def _verify_pinhole(b, star_vec, star_mag, mag_sorted, img, cat, sig_px, flux, use_mags, focal, cx, cy,
                    width, height, fixed_radius_px, match_sigma, margin_rad, min_matches, eps, scale_offset,
                    scale_range, max_chi2, mag_floor, mag_gate, trials, max_false, sky_cells, sky_ra):
    """:func:`startrack.identify.verify.verify` of one proposal at focal length ``focal`` (a pinhole camera).

    Returns ``(code, match, q, dcm, p_false, missing, bright_pred, n_matched, near)``: ``code`` 0 =
    accepted, 1-4 as :func:`verify_core`, 5 = false-match probability above ``max_false``; ``near``
    the stars near the field (:func:`verify_core`'s last six values).
    """
    n = b.shape[0]
    rs = np.empty((2, n))
    radius = rs[0]
    sig_rad = rs[1]
    margin_px = margin_rad * focal
    for i in range(n):
        r = fixed_radius_px if fixed_radius_px > 0 else max(1.0, match_sigma * sig_px[i] + margin_px)
        radius[i] = r / focal
        sig_rad[i] = sig_px[i] / focal
    cos_fov = pinhole_cos_fov(focal, cx, cy, width, height)
    got = verify_core(
        b, star_vec, star_mag, mag_sorted, img, cat, radius, sig_rad, flux, use_mags, cos_fov, focal, cx, cy,
        width, height, 0.0, 0.0, 0.0, 0.0, 0, min_matches, eps, scale_offset, scale_range, max_chi2, mag_floor, mag_gate, sky_cells,
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
    """:func:`startrack.identify.verify._verify_with_focal` in one call, for a distortion-free camera.

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
        pairs = np.empty((2, nm), dtype=np.int64)      # (mi and mc: rows of one allocation)
        mi = pairs[0]
        mc = pairs[1]
        t = 0
        far = 0.0
        for i in range(n):
            if match[i] >= 0:
                mi[t] = i
                mc[t] = match[i]
                far = max(far, math.hypot(xs[i] - cx, ys[i] - cy))
                t += 1
        # The scale's interval (scale_interval, O(n)) ends the loop where every scale in it would: then the
        # pairs' chords (O(n^2): 40 % of a 30 deg frame's verification) are not needed.  Otherwise
        # matched_scale's two values, the significance (a second pass over the pairs and the detections)
        # only when the scale itself does not already end the loop: the same verdicts.
        lo, hi = scale_interval(b, mi, star_vec, mc, dcm)
        if not math.isnan(lo):
            dev = max(abs(lo - 1.0), abs(hi - 1.0))
            if (dev < 1e-5 or dev * far < 0.1 * rmin or total * lo - 1.0 > max_focal_error
                    or 1.0 - total * hi > max_focal_error):
                break
        ang, mea = _pair_chords(b, mi, star_vec, mc)
        step = _chord_scale(ang, mea)
        if math.isnan(step) or abs(step - 1.0) < 1e-5 or abs(total * step - 1.0) > max_focal_error:
            break
        if abs(step - 1.0) * far < 0.1 * rmin or not scale_significant(xs, ys, sig_px, focal, mi, ang, mea):
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
def blind_confidence(b, img, cat, star_vec, dcm, cos_fov, radius, n_cat, eps):
    """The numbers of the blind search's confidence in a refined attitude (:func:`startrack.patterns._verify_blind`).

    ``img``/``cat``: the proposal's image rows of ``b`` and catalog rows of ``star_vec``; ``dcm`` ICRS to
    camera.  Returns ``(agree, core_agree, p_local, e_core)``: how many of the proposal's stars (of its first
    four) lie within ``radius`` (rad) of their catalog star under ``dcm``; the mean chance that one of the
    other detections lands within ``radius`` of a star predicted in the field (``star_vec . boresight >
    cos_fov``) by accident, from the predicted stars within ten radii of it *other than the one it landed on*
    (-1 when there are no other detections or no predicted stars: the caller's floor decides); and the
    expected chance matches of the first four stars' pattern (:func:`pattern_chance` with ``n_cat`` stars and
    tolerance ``eps``).

    The star a detection landed on is the event whose chance is estimated, not evidence of the density around
    it: counted, it made every matched detection's chance at least 1/100 whatever the sky, and a true field of
    few stars (4 in the pattern, 2-3 others) improbable enough to be refused.  So a detection with a predicted
    star within ``radius`` counts the others within ten radii (one fewer), an unmatched one all of them.
    """
    n = b.shape[0]
    k = img.shape[0]
    cos_r = math.cos(radius)
    agree = 0
    core_agree = 0
    for t in range(k):
        s = cat[t]
        dot = 0.0
        for a in range(3):
            p = dcm[a, 0] * star_vec[s, 0] + dcm[a, 1] * star_vec[s, 1] + dcm[a, 2] * star_vec[s, 2]
            dot += b[img[t], a] * p
        if dot >= cos_r:
            agree += 1
            if t < 4:
                core_agree += 1
    nc = min(k, 4)
    core = np.empty((nc, 3))
    is_core = np.zeros(n, dtype=np.bool_)
    for t in range(nc):
        core[t, :] = b[img[t], :]
        is_core[img[t]] = True
    e_core = pattern_chance(n_cat, eps, core)
    # The other detections in the catalog frame (b_i . (A^T s) = (A b_i) . s), counted against the predicted
    # stars within ten match radii.
    n_others = n - nc
    p_local = -1.0
    if n_others > 0:
        cos_local = math.cos(10.0 * radius)
        ref = np.empty((n, 3))
        for i in range(n):
            for a in range(3):
                ref[i, a] = dcm[0, a] * b[i, 0] + dcm[1, a] * b[i, 1] + dcm[2, a] * b[i, 2]
        counts = np.zeros(n, dtype=np.int64)
        landed = np.zeros(n, dtype=np.bool_)
        n_front = 0
        for s in range(star_vec.shape[0]):
            if dcm[2, 0] * star_vec[s, 0] + dcm[2, 1] * star_vec[s, 1] + dcm[2, 2] * star_vec[s, 2] <= cos_fov:
                continue
            n_front += 1
            for i in range(n):
                if is_core[i]:
                    continue
                d = ref[i, 0] * star_vec[s, 0] + ref[i, 1] * star_vec[s, 1] + ref[i, 2] * star_vec[s, 2]
                if d >= cos_local:
                    counts[i] += 1
                    if d >= cos_r:
                        landed[i] = True
        if n_front > 0:
            total = 0.0
            frac = (radius / (10.0 * radius)) ** 2
            for i in range(n):
                if not is_core[i]:
                    total += min(1.0, (counts[i] - landed[i]) * frac)
            p_local = total / n_others
    return agree, core_agree, p_local, e_core


@njit(cache=True)
def screen_in_cone(b, n_screen, star_vec, n_rows, img, cat, cos_fov, radius, cos_sub, rows, sky_cells, sky_ra):
    """The blind search's screen of a candidate and the catalog rows its verification may read, in one pass.

    The attitude is QUEST on the pattern (image rows ``img`` of ``b``, catalog rows ``cat`` of ``star_vec``).
    Returns ``(hits, k, axis)``: how many of the first ``n_screen`` image stars other than the pattern's have a
    catalog star (of the first ``n_rows``, in the field: ``boresight . s >= cos_fov``) within ``radius`` (rad)
    (a pattern star beyond the first ``n_screen`` is not screened); the ``k`` rows ``s < n_rows`` with
    ``axis . s > cos_sub`` written ascending into ``rows[:k]``; ``axis`` the boresight (ICRS).

    ``sky_cells``/``sky_ra``: the sky index of every row of ``star_vec``
    (:func:`startrack._kernels.sky_index.sky_index`): only the stars of the cone's bands and right ascensions are
    tested, in ascending order, with the same arithmetic; empty arrays: every row below
    ``n_rows``.  The same answer either way.
    """
    q, _ = quest(b[img], star_vec[cat], np.ones(img.shape[0]))
    dcm = quat_to_dcm(q)
    n = n_screen
    ref = np.empty((n, 3))
    for i in range(n):
        for a in range(3):
            ref[i, a] = dcm[0, a] * b[i, 0] + dcm[1, a] * b[i, 1] + dcm[2, a] * b[i, 2]
    is_pat = np.zeros(n, dtype=np.bool_)
    for t in range(img.shape[0]):
        if img[t] < n:
            is_pat[img[t]] = True
    hit = np.zeros(n, dtype=np.bool_)
    cosr = math.cos(radius)
    bz0 = dcm[2, 0]
    bz1 = dcm[2, 1]
    bz2 = dcm[2, 2]
    k = 0
    m = star_vec.shape[0]
    sky = m > 0 and sky_ra.shape[0] == m and sky_cells.shape[0] > 0 and sky_cells.shape[0] == m + 2 + sky_cells[0]
    if sky:
        # Every row with z > cos_sub or z >= cos_fov (a superset: 1e-9 below the smaller), ascending.
        near = np.empty(m, dtype=np.int64)
        n_near = cone_stars(bz0, bz1, bz2, min(cos_sub, cos_fov) - 1e-9, star_vec, sky_cells, sky_ra, near)
    else:
        near = np.empty(0, dtype=np.int64)
        n_near = n_rows
    for t in range(n_near):
        s = near[t] if sky else t
        if s >= n_rows:
            break
        z = bz0 * star_vec[s, 0] + bz1 * star_vec[s, 1] + bz2 * star_vec[s, 2]
        if z > cos_sub:
            rows[k] = s
            k += 1
        if z < cos_fov:
            continue
        for i in range(n):
            if is_pat[i] or hit[i]:
                continue
            if ref[i, 0] * star_vec[s, 0] + ref[i, 1] * star_vec[s, 1] + ref[i, 2] * star_vec[s, 2] >= cosr:
                hit[i] = True
    count = 0
    for i in range(n):
        if hit[i]:
            count += 1
    axis = np.empty(3)
    axis[0] = bz0
    axis[1] = bz1
    axis[2] = bz2
    return count, k, axis


@njit(cache=True)
def refine_in_cone(b, star_vec, img, cat, cos_fov, focal, cx, cy, width, height, k1, k2, k3, k4, proj, radius, rounds,
                   axis, cos_reach):
    """:func:`startrack._kernels.attitude.refine` on the catalog rows of a cone (``star_vec``: the rows within
    some radius ``R`` of ``axis``, in the catalog's order), with the same answer as on the whole catalog.

    Every projection reads the stars within ``acos(cos_fov)`` of its attitude's boresight; before each one, that
    boresight is checked to lie within ``acos(cos_reach)`` (``R`` less the field's radius) of ``axis``, so that the
    cone holds every star the whole catalog would give, in the same order.  Returns ``(ok, match, q, n_predicted)``
    (``match`` indexes ``star_vec``); ``ok`` False (the rest undefined) when an attitude strays beyond the reach:
    the caller refines on the whole catalog instead.
    """
    n = b.shape[0]
    m = star_vec.shape[0]
    lists = np.empty(3 * m, dtype=np.int64)
    pv = np.empty((3 * m, 3))
    q, _ = quest_pairs(b, img, star_vec, cat, np.ones(img.shape[0]))
    match = np.full(n, -1, dtype=np.int64)
    prev = np.empty(n, dtype=np.int64)
    mi = np.empty(n, dtype=np.int64)
    mc = np.empty(n, dtype=np.int64)
    # refine_from's rounds, one at a time (refine_from with no round: one projection and matching with q)
    for rnd in range(rounds):
        if not _boresight_within(q, axis, cos_reach):
            return False, match, q, 0
        prev[:] = match
        match, q, counts = refine_from(b, star_vec, q, cos_fov, focal, cx, cy, width, height, k1, k2, k3, k4, proj,
                                       radius, 0, lists, pv)
        nm = 0
        same = rnd > 0
        for i in range(n):
            if match[i] >= 0:
                mi[nm] = i
                mc[nm] = match[i]
                nm += 1
            if match[i] != prev[i]:
                same = False
        if nm < 2 or same:
            return True, match, q, counts[1]
        q, _ = quest_pairs(b, mi[:nm], star_vec, mc[:nm], np.ones(nm))
    if not _boresight_within(q, axis, cos_reach):
        return False, match, q, 0
    match, q, counts = refine_from(b, star_vec, q, cos_fov, focal, cx, cy, width, height, k1, k2, k3, k4, proj, radius,
                                   0, lists, pv)
    return True, match, q, counts[1]


@njit(cache=True)
def verify_in_cone(b, star_vec, img, cat, cos_fov, focal, cx, cy, width, height, k1, k2, k3, k4, proj, radius, rounds,
                   axis, cos_reach, n_cat, eps):
    """One verification of the blind search on a cone's catalog rows in one call: :func:`refine_in_cone`, the
    refined attitude's matrix (:func:`startrack._kernels.attitude.quat_to_dcm`) and, when the cone answered,
    :func:`blind_confidence` (``n_cat`` catalog stars, pattern tolerance ``eps``) on the cone's rows: the same
    numbers as the three calls.  Returns ``(ok, match, q, n_predicted, dcm, agree, core_agree, p_local, e_core)``,
    the last four 0 when not ``ok``."""
    ok, match, q, n_pred = refine_in_cone(b, star_vec, img, cat, cos_fov, focal, cx, cy, width, height, k1, k2, k3,
                                          k4, proj, radius, rounds, axis, cos_reach)
    dcm = quat_to_dcm(q)
    if not ok:
        return False, match, q, n_pred, dcm, 0, 0, 0.0, 0.0
    agree, core_agree, p_local, e_core = blind_confidence(b, img, cat, star_vec, dcm, cos_fov, radius, n_cat, eps)
    return True, match, q, n_pred, dcm, agree, core_agree, p_local, e_core


@njit(cache=True, inline="always")
def _boresight_within(q, axis, cos_reach):
    """Whether the boresight of ``q`` (the third row of :func:`quat_to_dcm`) is within ``acos(cos_reach)`` of
    ``axis``."""
    dcm = quat_to_dcm(q)
    return dcm[2, 0] * axis[0] + dcm[2, 1] * axis[1] + dcm[2, 2] * axis[2] >= cos_reach
