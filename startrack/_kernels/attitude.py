"""Attitude kernels: QUEST (Shuster & Oh 1981) without LAPACK, for use inside other kernels."""
import math

import numpy as np

from startrack._kernels._jit import njit
from startrack._kernels.sphere import project_to_pixel


@njit(cache=True)
def profile(b, r, w):
    """``B = sum w_i b_i r_i^T`` (paper 000 Eq. 19)."""
    bm = np.zeros((3, 3))
    for i in range(b.shape[0]):
        for p in range(3):
            for q in range(3):
                bm[p, q] += w[i] * b[i, p] * r[i, q]
    return bm


@njit(cache=True)
def _quest_core(bm, lam0):
    """QUEST on a profile matrix: Newton on the characteristic equation, adjugate quaternion.

    Shuster & Oh (1981): with ``S = B + B^T``, ``sigma = tr B``,
    ``Z = (B23 - B32, B31 - B13, B12 - B21)``, ``kappa = tr adj S``,
    ``Delta = det S``: ``a = sigma^2 - kappa``, ``b = sigma^2 + Z.Z``,
    ``c = Delta + Z.S Z``, ``d = Z.S^2 Z``,
    ``f(l) = l^4 - (a + b) l^2 - c l + (a b + c sigma - d)``; Newton from
    ``lam0`` (Shuster starts at ``sum w``; an upper bound makes sure the largest
    root is the one found).  Then ``alpha = l^2 - sigma^2 + kappa``, ``beta = l - sigma``,
    ``gamma = (l + sigma) alpha - Delta``, ``X = (alpha I + beta S + S^2) Z`` and
    ``q = (X, gamma) / norm``.  Returns ``(q1, q2, q3, q4, lambda, gamma_rel)``.
    """
    # Scalars throughout (no temporary arrays: this runs once per leave-one-out star); the same
    # operations in the same order as the matrix expressions in the docstring.
    s00 = bm[0, 0] + bm[0, 0]
    s01 = bm[0, 1] + bm[1, 0]
    s02 = bm[0, 2] + bm[2, 0]
    s10 = bm[1, 0] + bm[0, 1]
    s11 = bm[1, 1] + bm[1, 1]
    s12 = bm[1, 2] + bm[2, 1]
    s20 = bm[2, 0] + bm[0, 2]
    s21 = bm[2, 1] + bm[1, 2]
    s22 = bm[2, 2] + bm[2, 2]
    sigma = bm[0, 0] + bm[1, 1] + bm[2, 2]
    z0 = bm[1, 2] - bm[2, 1]
    z1 = bm[2, 0] - bm[0, 2]
    z2 = bm[0, 1] - bm[1, 0]
    kappa = (s00 * s11 - s01 * s10) + (s00 * s22 - s02 * s20) + (s11 * s22 - s12 * s21)
    delta = s00 * (s11 * s22 - s12 * s21) - s01 * (s10 * s22 - s12 * s20) + s02 * (s10 * s21 - s11 * s20)
    sz0 = s00 * z0 + s01 * z1 + s02 * z2
    sz1 = s10 * z0 + s11 * z1 + s12 * z2
    sz2 = s20 * z0 + s21 * z1 + s22 * z2
    s2z0 = s00 * sz0 + s01 * sz1 + s02 * sz2
    s2z1 = s10 * sz0 + s11 * sz1 + s12 * sz2
    s2z2 = s20 * sz0 + s21 * sz1 + s22 * sz2
    a = sigma * sigma - kappa
    b = sigma * sigma + (z0 * z0 + z1 * z1 + z2 * z2)
    c = delta + (z0 * sz0 + z1 * sz1 + z2 * sz2)
    d = z0 * s2z0 + z1 * s2z1 + z2 * s2z2
    lam = lam0
    prev = np.inf
    for _ in range(50):
        f = lam ** 4 - (a + b) * lam * lam - c * lam + (a * b + c * sigma - d)
        fp = 4 * lam ** 3 - 2 * (a + b) * lam - c
        if fp == 0.0:
            break
        step = f / fp
        lam -= step
        scale = max(1.0, abs(lam))
        if abs(step) < 1e-15 * scale:
            break
        # Converged to the round-off of f: the steps stop shrinking and only bounce by a few
        # ulps (they used to run all 50 iterations, most of a solve's time).
        if abs(step) >= prev and abs(step) < 1e-12 * scale:
            break
        prev = abs(step)
    alpha = lam * lam - sigma * sigma + kappa
    beta = lam - sigma
    gamma = (lam + sigma) * alpha - delta
    x0 = alpha * z0 + beta * sz0 + s2z0
    x1 = alpha * z1 + beta * sz1 + s2z1
    x2 = alpha * z2 + beta * sz2 + s2z2
    norm = math.sqrt(gamma * gamma + (x0 * x0 + x1 * x1 + x2 * x2))
    # (X, gamma) scales as lambda^3: a tiny norm is all round-off (a rotation of 180 degrees).
    if norm <= 1e-10 * max(1.0, abs(lam)) ** 3:
        return 0.0, 0.0, 0.0, 1.0, lam, 0.0
    return x0 / norm, x1 / norm, x2 / norm, gamma / norm, lam, abs(gamma) / norm


@njit(cache=True)
def quest(b, r, w):
    """Optimal quaternion (scalar last) of Wahba's problem by QUEST, with sequential rotations.

    When ``gamma`` is small (rotation near 180 degrees) the problem is solved
    again with the reference frame turned by 180 degrees about x, y or z
    (Shuster & Oh's method of sequential rotations: two columns of ``B``
    negated) and the result turned back.  Returns ``(q, lambda_max)``.
    """
    every = np.arange(w.shape[0])
    return quest_pairs(b, every, r, every, w)


@njit(cache=True)
def quest_pairs(b, img, r, cat, w):
    """:func:`quest` of ``b[img]``, ``r[cat]``, ``w`` without gathering the rows (the same sums in the same
    order, so the same bits)."""
    bm = np.zeros((3, 3))
    for t in range(img.shape[0]):
        i = img[t]
        c = cat[t]
        for p in range(3):
            for q in range(3):
                bm[p, q] += w[t] * b[i, p] * r[c, q]
    # Newton from an upper bound of lambda_max (sum w |b| |r|), so that it
    # converges to the largest root even when the second root is close (two
    # stars) or the vectors are not exactly unit.
    lam0 = 0.0
    for t in range(img.shape[0]):
        lam0 += w[t] * math.sqrt(_norm2(b, img[t]) * _norm2(r, cat[t]))
    return quest_profile(bm, lam0)


@njit(cache=True)
def quest_pairs_unit(b, img, r, cat):
    """:func:`quest_pairs` with every weight 1 (the same sums in the same order: ``1.0 * x`` is ``x``, so the
    same bits), without a weight array."""
    fw = np.empty(13)
    q = fw[:4]
    lam = _quest_unit_into(b, img, r, cat, fw[4:].reshape((3, 3)), q)
    return q, lam


@njit(cache=True, inline="always")
def _quest_unit_into(b, img, r, cat, bm, q):
    """:func:`quest_pairs_unit` on the caller's scratch ``bm`` (3, 3), the quaternion into ``q`` (4);
    returns lambda."""
    bm[:] = 0.0
    for t in range(img.shape[0]):
        i = img[t]
        c = cat[t]
        for u in range(3):
            for v in range(3):
                bm[u, v] += b[i, u] * r[c, v]
    lam0 = 0.0
    for t in range(img.shape[0]):
        lam0 += math.sqrt(_norm2(b, img[t]) * _norm2(r, cat[t]))
    q1, q2, q3, q4, lam = _quest_scalars(bm, lam0)
    q[0] = q1
    q[1] = q2
    q[2] = q3
    q[3] = q4
    return lam


@njit(cache=True, inline="always")
def _norm2(v, i):
    """``|v[i]|^2`` (the row's squared length, without a view of the row)."""
    return v[i, 0] * v[i, 0] + v[i, 1] * v[i, 1] + v[i, 2] * v[i, 2]


@njit(cache=True)
def quest_profile(bm, lam0):
    """:func:`quest` from the profile matrix ``bm`` and the bound ``lam0 = sum w |b| |r|``."""
    q1, q2, q3, q4, lam = _quest_scalars(bm, lam0)
    return np.array([q1, q2, q3, q4]), lam


@njit(cache=True)
def _quest_scalars(bm, lam0):
    """:func:`quest_profile` as five scalars ``(q1, q2, q3, q4, lambda)`` (no array: it runs once per
    leave-one-out star).  ``bm`` is read at the start only, so that numba releases its reference there
    and drops the pair of reference-count updates (the rare sequential rotations work on copies of its
    values)."""
    b00, b01, b02 = bm[0, 0], bm[0, 1], bm[0, 2]
    b10, b11, b12 = bm[1, 0], bm[1, 1], bm[1, 2]
    b20, b21, b22 = bm[2, 0], bm[2, 1], bm[2, 2]
    lam0 *= 1.0 + 1e-12
    q1, q2, q3, q4, lam, g = _quest_core(bm, lam0)
    if g > 1e-2:
        if q4 < 0:
            return -q1, -q2, -q3, -q4, lam
        return q1, q2, q3, q4, lam
    best_g = g
    bm2 = np.empty((3, 3))
    for axis in range(3):
        # bm with every column but ``axis`` negated
        k0 = axis == 0
        k1 = axis == 1
        k2 = axis == 2
        bm2[0, 0] = b00 if k0 else -b00
        bm2[0, 1] = b01 if k1 else -b01
        bm2[0, 2] = b02 if k2 else -b02
        bm2[1, 0] = b10 if k0 else -b10
        bm2[1, 1] = b11 if k1 else -b11
        bm2[1, 2] = b12 if k2 else -b12
        bm2[2, 0] = b20 if k0 else -b20
        bm2[2, 1] = b21 if k1 else -b21
        bm2[2, 2] = b22 if k2 else -b22
        p1, p2, p3, p4, lam2, g2 = _quest_core(bm2, lam0)
        if g2 > best_g:
            # Undo the 180-degree turn of the reference frame: q = q' (x) e_axis.
            if axis == 0:
                q1, q2, q3, q4 = p4, -p3, p2, -p1
            elif axis == 1:
                q1, q2, q3, q4 = p3, p4, -p1, -p2
            else:
                q1, q2, q3, q4 = -p2, p1, p4, -p3
            best_g = g2
            lam = lam2
        if best_g > 0.3:
            break
    if q4 < 0:
        return -q1, -q2, -q3, -q4, lam
    return q1, q2, q3, q4, lam


@njit(cache=True)
def quat_to_dcm(q):
    """``A(q) = (q4^2 - |q|^2) I + 2 q q^T - 2 q4 [q x]`` (paper 000 Eq. 21)."""
    a = np.empty((3, 3))
    dcm_into(q, a)
    return a


@njit(cache=True, inline="always")
def dcm_into(q, a):
    """:func:`quat_to_dcm` of ``q`` into the 3 x 3 array ``a``."""
    q1, q2, q3, q4 = q[0], q[1], q[2], q[3]
    a[0, 0] = q1 * q1 - q2 * q2 - q3 * q3 + q4 * q4
    a[0, 1] = 2 * (q1 * q2 + q3 * q4)
    a[0, 2] = 2 * (q1 * q3 - q2 * q4)
    a[1, 0] = 2 * (q1 * q2 - q3 * q4)
    a[1, 1] = -q1 * q1 + q2 * q2 - q3 * q3 + q4 * q4
    a[1, 2] = 2 * (q2 * q3 + q1 * q4)
    a[2, 0] = 2 * (q1 * q3 + q2 * q4)
    a[2, 1] = 2 * (q2 * q3 - q1 * q4)
    a[2, 2] = -q1 * q1 - q2 * q2 + q3 * q3 + q4 * q4


@njit(cache=True)
def project_stars(star_vec, dcm, cos_fov, focal, cx, cy, width, height, k1, k2, k3, k4, proj, margin_px, lists, pv):
    """The catalog stars in front of the camera with ``dcm`` (``z >= cos_fov``), in their order.

    Three lists of (star index ``lists[t]``, camera-frame direction ``pv[t] = dcm star_vec[s]``),
    each in the stars' order (``m`` = ``len(star_vec)``; ``lists`` and ``pv`` hold ``3 m``):
    rows ``[0, k)`` every star in front, ``[m, m + n_near)`` those projected on the sensor or
    within ``margin_px`` pixels of it, ``[2 m, 2 m + n_on)`` those on the sensor.  The matching
    (:func:`match_projected`) and the verification's checks
    (:func:`startrack._kernels.verify.check_matches`, ``resolve_conflicts``) read the same
    projection of an attitude instead of each projecting the stars again, each from a
    contiguous list (a slice of ``lists`` and ``pv``: indices that need no check for
    negative values).  Returns ``(k, n_near, n_on)``.
    """
    m = star_vec.shape[0]
    k = 0
    n_near = m
    n_on = 2 * m
    for s in range(m):
        z = dcm[2, 0] * star_vec[s, 0] + dcm[2, 1] * star_vec[s, 1] + dcm[2, 2] * star_vec[s, 2]
        if z < cos_fov:
            continue
        x = dcm[0, 0] * star_vec[s, 0] + dcm[0, 1] * star_vec[s, 1] + dcm[0, 2] * star_vec[s, 2]
        y = dcm[1, 0] * star_vec[s, 0] + dcm[1, 1] * star_vec[s, 1] + dcm[1, 2] * star_vec[s, 2]
        px, py = project_to_pixel(x, y, z, focal, cx, cy, k1, k2, k3, k4, proj)
        _put_row(lists, pv, k, s, x, y, z)
        k += 1
        # A star in front is written at the next row of the other two lists too, whose counts move on only
        # where it belongs (rows past a count are not read): no branch on the sensor's edges, whose outcomes
        # follow no pattern.  (The test of z stays a branch: over a whole catalog most stars are behind.)
        _put_row(lists, pv, n_near, s, x, y, z)
        n_near += not ((px < -0.5 - margin_px) | (px > width - 0.5 + margin_px) | (py < -0.5 - margin_px)
                       | (py > height - 0.5 + margin_px))
        _put_row(lists, pv, n_on, s, x, y, z)
        n_on += not ((px < -0.5) | (px > width - 0.5) | (py < -0.5) | (py > height - 0.5))
    return k, n_near - m, n_on - 2 * m


@njit(cache=True, inline="always")
def _put_row(lists, pv, t, s, x, y, z):
    lists[t] = s
    pv[t, 0] = x
    pv[t, 1] = y
    pv[t, 2] = z


@njit(cache=True)
def match_projected(b, stars, pv, radius, match):
    """Nearest catalog star (within ``radius`` rad, unambiguous) for every image vector, into ``match``.

    The candidates are the catalog stars ``stars`` projected to ``pv`` (:func:`project_stars`'
    list of those on the sensor plus the radius).  A match needs the
    nearest catalog star within the radius and no other within twice the radius, unless the
    two catalog stars are closer to each other than the radius: an unresolved pair (one
    blob), of which the nearer is taken.  Each catalog star is used once (the closer image
    star wins).  ``match[i]`` becomes a catalog index or -1.
    """
    _match_projected(b, stars, pv, radius, match, np.empty(b.shape[0]))


@njit(cache=True, inline="always")
def _match_projected(b, stars, pv, radius, match, best_cos):
    """:func:`match_projected` with the caller's scratch ``best_cos`` (n): the cosine of the angle to the
    nearest star (clipped to 1 as the angle's acos is), the larger the closer, without an acos per
    detection."""
    n = b.shape[0]
    cos_r = math.cos(radius)
    cos_2r = math.cos(2.0 * radius)
    for i in range(n):
        match[i] = -1
        d1 = -2.0
        d2 = -2.0
        a1 = -1
        a2 = -1
        for c in range(stars.shape[0]):
            d = b[i, 0] * pv[c, 0] + b[i, 1] * pv[c, 1] + b[i, 2] * pv[c, 2]
            if d > d1:
                d2 = d1
                a2 = a1
                d1 = d
                a1 = c
            elif d > d2:
                d2 = d
                a2 = c
        if a1 < 0 or d1 < cos_r:
            continue
        if a2 >= 0 and d2 >= cos_2r:
            pair = pv[a1, 0] * pv[a2, 0] + pv[a1, 1] * pv[a2, 1] + pv[a1, 2] * pv[a2, 2]
            if pair < cos_r:
                continue    # two distinct catalog stars near this image star: ambiguous
        match[i] = stars[a1]
        best_cos[i] = min(1.0, d1)
    # One image star per catalog star: keep the closer.  (acos is strictly decreasing over
    # [cos radius, 1] at the resolution of doubles, so comparing the clipped cosines orders
    # the detections as comparing their angles did.)
    for i in range(n):
        if match[i] < 0:
            continue
        for j in range(i + 1, n):
            if match[j] == match[i]:
                if best_cos[j] > best_cos[i]:
                    match[i] = -1
                    break
                else:
                    match[j] = -1


@njit(cache=True)
def refine(b, star_vec, img, cat, cos_fov, focal, cx, cy, width, height, k1, k2, k3, k4, proj, radius, rounds):
    """Attitude from the proposal, then ``rounds`` of match-all / re-solve, and a
    last matching with the final attitude (so that the matches returned are the
    ones that attitude supports): :func:`refine_from` the proposal's QUEST attitude.

    Returns ``(match, q, n_predicted)``.
    """
    m = star_vec.shape[0]
    q, _ = quest_pairs(b, img, star_vec, cat, np.ones(img.shape[0]))
    match, q, counts = refine_from(b, star_vec, q, cos_fov, focal, cx, cy, width, height, k1, k2, k3, k4, proj, radius,
                                   rounds, np.empty(3 * m, dtype=np.int64), np.empty((3 * m, 3)))
    return match, q, counts[1]


@njit(cache=True)
def refine_from(b, star_vec, q, cos_fov, focal, cx, cy, width, height, k1, k2, k3, k4, proj, radius, rounds, lists,
                pv):
    """``rounds`` of match-all (:func:`match_projected`, candidates within ``radius`` rad beyond the
    sensor) / re-solve from the attitude ``q``, and a last matching with the final attitude.

    A round whose matches are those of the round before ends the loop: its solve would be
    the last one again (same stars, same weights), and so would every later matching.
    ``lists``/``pv`` are the scratch of :func:`project_stars`; they are left holding the
    projection of the returned attitude.

    Returns ``(match, q, counts)``, ``counts`` that projection's ``(k, n_near, n_on)`` (``n_near``
    the stars predicted for the matching).
    """
    n = b.shape[0]
    m = star_vec.shape[0]
    # match, the round before's, the matched detections and their stars: one allocation (rows).
    work = np.empty((4, n), dtype=np.int64)
    match = work[0]
    prev = work[1]
    mi = work[2]
    mc = work[3]
    match[:] = -1
    # The attitude matrix, QUEST's profile matrix and quaternion, each detection's nearest cosine: one allocation.
    fw = np.empty(22 + n)
    dcm = fw[:9].reshape((3, 3))
    bm = fw[9:18].reshape((3, 3))
    qr = fw[18:22]
    best_cos = fw[22:]
    margin = radius * focal
    for rnd in range(rounds):
        prev[:] = match
        dcm_into(q, dcm)
        counts = project_stars(star_vec, dcm, cos_fov, focal, cx, cy, width, height, k1, k2, k3, k4, proj,
                               margin, lists, pv)
        _match_projected(b, lists[m:m + counts[1]], pv[m:m + counts[1]], radius, match, best_cos)
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
            return match, q, counts
        _quest_unit_into(b, mi[:nm], star_vec, mc[:nm], bm, qr)
        q = qr
    dcm_into(q, dcm)
    counts = project_stars(star_vec, dcm, cos_fov, focal, cx, cy, width, height, k1, k2, k3, k4, proj,
                           margin, lists, pv)
    _match_projected(b, lists[m:m + counts[1]], pv[m:m + counts[1]], radius, match, best_cos)
    return match, q, counts


@njit(cache=True)
def leave_one_out(b, r, w):
    """For every pair ``(b_i, r_i)``: the angle (rad) between ``b_i`` and ``A r_i``, ``A`` solved
    (QUEST, weights ``w``) from all the other pairs -- how well the rest predicts this star.

    The profile matrix of all pairs is formed once; each star's is that minus its own term
    ``w_i b_i r_i^T`` (a rank-one downdate), and so is the Newton start ``sum w |b| |r|``:
    the same QUEST solve as from the other pairs' sum, without the O(n) re-sum per star."""
    n = b.shape[0]
    work = np.empty(2 * n + 9)     # (out, c and bmi: one allocation)
    out = work[:n]
    out[:] = np.inf
    if n < 3:
        return out
    bm = profile(b, r, w)
    c = work[n:2 * n]
    total = 0.0
    for j in range(n):
        c[j] = w[j] * math.sqrt(_norm2(b, j) * _norm2(r, j))
        total += c[j]
    bmi = work[2 * n:].reshape((3, 3))
    for i in range(n):
        for p in range(3):
            for q in range(3):
                bmi[p, q] = bm[p, q] - w[i] * b[i, p] * r[i, q]
        q1, q2, q3, q4, _ = _quest_scalars(bmi, total - c[i])
        out[i] = math.acos(min(1.0, max(-1.0, _rotated_dot(q1, q2, q3, q4, b, i, r, i))))
    return out


@njit(cache=True, inline="always")
def _rotated_dot(q1, q2, q3, q4, b, i, r, j):
    """``b[i] . (A(q) r[j])``, ``A`` of :func:`quat_to_dcm` (the same arithmetic, without the matrix)."""
    a00 = q1 * q1 - q2 * q2 - q3 * q3 + q4 * q4
    a01 = 2 * (q1 * q2 + q3 * q4)
    a02 = 2 * (q1 * q3 - q2 * q4)
    a10 = 2 * (q1 * q2 - q3 * q4)
    a11 = -q1 * q1 + q2 * q2 - q3 * q3 + q4 * q4
    a12 = 2 * (q2 * q3 + q1 * q4)
    a20 = 2 * (q1 * q3 + q2 * q4)
    a21 = 2 * (q2 * q3 - q1 * q4)
    a22 = -q1 * q1 - q2 * q2 + q3 * q3 + q4 * q4
    d = 0.0
    d += b[i, 0] * (a00 * r[j, 0] + a01 * r[j, 1] + a02 * r[j, 2])
    d += b[i, 1] * (a10 * r[j, 0] + a11 * r[j, 1] + a12 * r[j, 2])
    d += b[i, 2] * (a20 * r[j, 0] + a21 * r[j, 1] + a22 * r[j, 2])
    return d


@njit(cache=True)
def _inv3(s):
    """Inverse of a 3 x 3 matrix (adjugate over determinant)."""
    inv = np.empty((3, 3))
    inv[0, 0] = s[1, 1] * s[2, 2] - s[1, 2] * s[2, 1]
    inv[0, 1] = s[0, 2] * s[2, 1] - s[0, 1] * s[2, 2]
    inv[0, 2] = s[0, 1] * s[1, 2] - s[0, 2] * s[1, 1]
    inv[1, 0] = s[1, 2] * s[2, 0] - s[1, 0] * s[2, 2]
    inv[1, 1] = s[0, 0] * s[2, 2] - s[0, 2] * s[2, 0]
    inv[1, 2] = s[0, 2] * s[1, 0] - s[0, 0] * s[1, 2]
    inv[2, 0] = s[1, 0] * s[2, 1] - s[1, 1] * s[2, 0]
    inv[2, 1] = s[0, 1] * s[2, 0] - s[0, 0] * s[2, 1]
    inv[2, 2] = s[0, 0] * s[1, 1] - s[0, 1] * s[1, 0]
    det = s[0, 0] * inv[0, 0] + s[0, 1] * inv[1, 0] + s[0, 2] * inv[2, 0]
    return inv / det


@njit(cache=True)
def gated_quest(b, r, sig, weighted, gate, min_keep):
    """The loop of :func:`startrack.attitude.estimate_attitude` for QUEST: solve, chi-square gate, drop the
    worst star, repeat.

    ``b``, ``r`` (n, 3) unit vectors, ``sig`` (n,) 1-sigma (rad).  Each round: geometry check (the largest
    angle between two kept stars, in the image and in the catalog, at least 20 median sigmas), weights
    ``1 / sigma^2`` normalised (equal when not ``weighted``), QUEST, residual angles, ``chi^2 = (resid /
    sigma)^2 / k^2`` with ``k^2 = median(chi^2) / 1.386`` when at least 5 stars are kept and that exceeds
    2.5 (else 1); done when the largest ``chi^2`` is within ``gate``; else the worst is dropped while at
    least ``min_keep`` remain.

    Returns ``(code, dcm, keep, n_keep, resid, factor2, weights, rejected, rej_resid, rej_chi2, n_rej, cov,
    loss)``:
    ``code`` 0 ok, 1 degenerate geometry, 2 a star beyond the gate that cannot be dropped; ``keep[:n_keep]``
    the kept indices, ``resid[:n_keep]`` their residuals (rad), ``weights[:n_keep]`` the normalised weights;
    ``rejected[:n_rej]`` the dropped indices in order with their residual (rad) and chi-square; ``cov``
    the QUEST covariance ``[sum (I - b b^T) / sigma^2]^-1 k^2`` (rad^2) and ``loss`` Wahba's loss of the
    kept stars (when ``code`` is 0).
    """
    n = b.shape[0]
    keep = np.arange(n)
    nk = n
    resid = np.zeros(n)
    chi2 = np.zeros(n)
    w = np.zeros(n)
    rejected = np.empty(n, dtype=np.int64)
    rej_resid = np.empty(n)
    rej_chi2 = np.empty(n)
    n_rej = 0
    dcm = np.eye(3)
    factor2 = 1.0
    kb = np.empty((n, 3))
    kr = np.empty((n, 3))
    ks = np.empty(n)
    while True:
        for j in range(nk):
            kb[j] = b[keep[j]]
            kr[j] = r[keep[j]]
            ks[j] = sig[keep[j]]
        # Geometry: two directions at least 20 sigma apart (else the roll about them is unknown).
        min_b = 2.0
        min_r = 2.0
        for i in range(nk):
            for j in range(i, nk):
                db = kb[i, 0] * kb[j, 0] + kb[i, 1] * kb[j, 1] + kb[i, 2] * kb[j, 2]
                dr = kr[i, 0] * kr[j, 0] + kr[i, 1] * kr[j, 1] + kr[i, 2] * kr[j, 2]
                min_b = min(min_b, db)
                min_r = min(min_r, dr)
        scale = 20.0 * np.median(ks[:nk])
        if math.acos(min(1.0, max(-1.0, min_b))) < scale or math.acos(min(1.0, max(-1.0, min_r))) < scale:
            return 1, dcm, keep, nk, resid, factor2, w, rejected, rej_resid, rej_chi2, n_rej, np.full((3, 3), np.nan), 0.0
        total = 0.0
        for j in range(nk):
            w[j] = 1.0 / (ks[j] * ks[j]) if weighted else 1.0
            total += w[j]
        for j in range(nk):
            w[j] /= total
        q, _ = quest(kb[:nk], kr[:nk], w[:nk])
        dcm = quat_to_dcm(q)
        for j in range(nk):
            p0 = dcm[0, 0] * kr[j, 0] + dcm[0, 1] * kr[j, 1] + dcm[0, 2] * kr[j, 2]
            p1 = dcm[1, 0] * kr[j, 0] + dcm[1, 1] * kr[j, 1] + dcm[1, 2] * kr[j, 2]
            p2 = dcm[2, 0] * kr[j, 0] + dcm[2, 1] * kr[j, 1] + dcm[2, 2] * kr[j, 2]
            d = kb[j, 0] * p0 + kb[j, 1] * p1 + kb[j, 2] * p2
            resid[j] = math.acos(min(1.0, max(-1.0, d)))
            chi2[j] = (resid[j] / ks[j]) ** 2
        factor2 = np.median(chi2[:nk]) / 1.386 if nk >= 5 else 1.0
        factor2 = factor2 if factor2 > 2.5 else 1.0   # only when the sigmas are clearly too small
        worst = 0
        for j in range(nk):
            chi2[j] /= factor2
            if chi2[j] > chi2[worst]:
                worst = j
        if chi2[worst] <= gate:
            # Covariance P = [sum (I - b b^T) / sigma^2]^-1 k^2 and Wahba's loss 1/2 sum w |b - A r|^2.
            info = np.zeros((3, 3))
            loss = 0.0
            for j in range(nk):
                iw = 1.0 / (ks[j] * ks[j])
                for p in range(3):
                    info[p, p] += iw
                    for col in range(3):
                        info[p, col] -= iw * kb[j, p] * kb[j, col]
                for p in range(3):
                    d = kb[j, p] - (dcm[p, 0] * kr[j, 0] + dcm[p, 1] * kr[j, 1] + dcm[p, 2] * kr[j, 2])
                    loss += 0.5 * w[j] * d * d
            cov = _inv3(info) * factor2
            return 0, dcm, keep, nk, resid, factor2, w, rejected, rej_resid, rej_chi2, n_rej, cov, loss
        if nk - 1 < min_keep:
            return 2, dcm, keep, nk, resid, factor2, w, rejected, rej_resid, rej_chi2, n_rej, np.full((3, 3), np.nan), 0.0
        rejected[n_rej] = keep[worst]
        rej_resid[n_rej] = resid[worst]
        rej_chi2[n_rej] = chi2[worst]
        n_rej += 1
        for j in range(worst, nk - 1):
            keep[j] = keep[j + 1]
        nk -= 1
