"""Kernels of paper 000's triangle database and its modified pyramid search (Sec. 3.2)."""
import math

import numpy as np

from startrack._kernels._jit import njit


@njit(cache=True)
def internal_angles(p0, p1, p2):
    """Internal angles (radians) at ``p0``, ``p1``, ``p2`` of the planar triangle through three points.

    Paper 000 Eq. 2 (angles between the side vectors ``a = s1 - s2``,
    ``b = s2 - s3``, ``c = s1 - s3``), applied to unit direction vectors: the
    three points span a plane triangle (the chord triangle) whose angles do not
    depend on where the triangle lies in the field or how the camera is turned.
    """
    out = np.empty(3)
    pts = (p0, p1, p2)
    for v in range(3):
        a = pts[v]
        b = pts[(v + 1) % 3]
        c = pts[(v + 2) % 3]
        u0, u1, u2 = b[0] - a[0], b[1] - a[1], b[2] - a[2]
        w0, w1, w2 = c[0] - a[0], c[1] - a[1], c[2] - a[2]
        nu = math.sqrt(u0 * u0 + u1 * u1 + u2 * u2)
        nw = math.sqrt(w0 * w0 + w1 * w1 + w2 * w2)
        if nu == 0.0 or nw == 0.0:
            out[v] = 0.0
        else:
            cosv = (u0 * w0 + u1 * w1 + u2 * w2) / (nu * nw)
            out[v] = math.acos(min(1.0, max(-1.0, cosv)))
    return out


@njit(cache=True)
def _handedness(p0, p1, p2):
    s = (p0[0] * (p1[1] * p2[2] - p1[2] * p2[1]) - p0[1] * (p1[0] * p2[2] - p1[2] * p2[0])
         + p0[2] * (p1[0] * p2[1] - p1[1] * p2[0]))
    return 1 if s > 0 else -1


@njit(cache=True)
def fill_triangles(ptr, idx, vec, cos_max, stars, angles, hand, fill=True):
    """Every star triple whose three pairs are within the largest separation; returns how many.

    With ``fill``, triangle ``n`` is written to ``stars[n]`` (vertex of the smallest internal angle
    first), ``angles[n]`` (ascending) and ``hand[n]``; without it the triples are only counted (the
    first of the two passes, which sizes the arrays).
    """
    n = 0
    for i in range(ptr.shape[0] - 1):
        for a in range(ptr[i], ptr[i + 1]):
            j = idx[a]
            if j <= i:
                continue
            for b in range(a + 1, ptr[i + 1]):
                k = idx[b]
                if k <= j:
                    continue
                if vec[j, 0] * vec[k, 0] + vec[j, 1] * vec[k, 1] + vec[j, 2] * vec[k, 2] < cos_max:
                    continue
                if fill:
                    ang = internal_angles(vec[i], vec[j], vec[k])
                    order = np.argsort(ang)
                    tri = (i, j, k)
                    for v in range(3):
                        stars[n, v] = tri[order[v]]
                        angles[n, v] = ang[order[v]]
                    hand[n] = _handedness(vec[stars[n, 0]], vec[stars[n, 1]], vec[stars[n, 2]])
                n += 1
    return n


@njit(cache=True)
def _angle(u, v):
    return math.acos(min(1.0, max(-1.0, u[0] * v[0] + u[1] * v[1] + u[2] * v[2])))


@njit(cache=True)
def _angle_tolerances(p, eps):
    """Half-widths of the internal-angle windows of a measured triangle.

    ``eps`` bounds the error of an inter-star angle (``k sqrt(2) sigma``: two
    stars' errors along their separation).  A star displaced by ``d``
    perpendicular to a side of length ``L`` turns that side by ``d / L``; the
    angle at a vertex moves with its two sides, each turned by its far star and
    by the vertex, so with independent errors its deviation is
    ``sigma sqrt(2/L1^2 + 2/L2^2)`` for adjacent sides ``L1``, ``L2``: at the
    same ``k``, ``eps sqrt(1/L1^2 + 1/L2^2)``.
    """
    out = np.empty(3)
    for v in range(3):
        l1 = _angle(p[v], p[(v + 1) % 3])
        l2 = _angle(p[v], p[(v + 2) % 3])
        out[v] = eps * math.sqrt(1.0 / max(l1, 1e-9) ** 2 + 1.0 / max(l2, 1e-9) ** 2)
    return out


@njit(cache=True)
def triangle_candidates(b, i0, i1, i2, tri_key, tri_stars, tri_angles, tri_hand, kquad, p1, p2, p3, eps,
                        star_vec, max_out, kvector, m, q, quadratic=True):
    """Catalog triangles matching the image triangle ``(i0, i1, i2)``, with the vertex map.

    The smallest internal angle selects the search range through the fitted
    quadratic (paper 000 Eqs. 10-12), or with ``quadratic=False`` through
    Mortari's k-vector line (``kvector``, ``m``, ``q``); candidates are then kept when the second
    angle agrees, the handedness agrees and, star by star, the three
    inter-star angles agree within ``eps``.  Returns an ``(m, 3)`` array of
    catalog star indices in the image order ``i0, i1, i2``, and the length
    of the searched interval (Table 5).
    """
    pts = np.empty((3, 3))
    for d in range(3):
        pts[0, d] = b[i0, d]
        pts[1, d] = b[i1, d]
        pts[2, d] = b[i2, d]
    ang = internal_angles(pts[0], pts[1], pts[2])
    tol = _angle_tolerances(pts, eps)
    order = np.argsort(ang)
    lo = ang[order[0]] - tol[order[0]]
    hi = ang[order[0]] + tol[order[0]]
    n = tri_key.shape[0]
    if quadratic:
        kb = min(max(int(math.floor(_quad_inverse(p1, p2, p3, lo, n))), 0), n)
        kt = min(max(int(math.ceil(_quad_inverse(p1, p2, p3, hi, n))), 0), n)
        start, end = kquad[kb], kquad[kt]
    else:
        kb = min(max(int(math.floor((lo - q) / m)), 0), n)
        kt = min(max(int(math.ceil((hi - q) / m)), 0), n)
        start, end = kvector[kb], kvector[kt]
    # The second-smallest angle may swap with its neighbours within the tolerances (near-isosceles
    # triangles): the star-by-star check below decides the vertex map.
    a1 = ang[order[1]]
    t1 = tol[order[1]] + tol[order[0]]
    hand = _handedness(pts[order[0]], pts[order[1]], pts[order[2]])
    near_isosceles = (ang[order[1]] - ang[order[0]] < tol[order[0]] + tol[order[1]]) or \
        (ang[order[2]] - ang[order[1]] < tol[order[1]] + tol[order[2]])
    out = np.empty((max_out, 3), dtype=np.int64)
    m = 0
    for t in range(start, end):
        key = tri_key[t]
        if key < lo or key > hi:
            continue
        if abs(tri_angles[t, 1] - a1) > t1 and not near_isosceles:
            continue
        if not near_isosceles and tri_hand[t] != hand:
            continue
        # Star-by-star check of the vertex map (all orders when the triangle is nearly isosceles).
        for perm in range(6):
            p = _perm(perm)
            if not near_isosceles and perm != 0:
                break
            c0 = tri_stars[t, p[0]]
            c1 = tri_stars[t, p[1]]
            c2 = tri_stars[t, p[2]]
            if abs(_angle(star_vec[c0], star_vec[c1]) - _angle(pts[order[0]], pts[order[1]])) > eps:
                continue
            if abs(_angle(star_vec[c0], star_vec[c2]) - _angle(pts[order[0]], pts[order[2]])) > eps:
                continue
            if abs(_angle(star_vec[c1], star_vec[c2]) - _angle(pts[order[1]], pts[order[2]])) > eps:
                continue
            if _handedness(star_vec[c0], star_vec[c1], star_vec[c2]) != hand:
                continue
            if m < max_out:
                # The image vertex with the v-th smallest angle, order[v], is catalog star c_v.
                out[m, order[0]] = c0
                out[m, order[1]] = c1
                out[m, order[2]] = c2
                m += 1
    return out[:m], end - start


@njit(cache=True)
def _perm(k):
    if k == 0:
        return (0, 1, 2)
    if k == 1:
        return (1, 0, 2)
    if k == 2:
        return (0, 2, 1)
    if k == 3:
        return (2, 1, 0)
    if k == 4:
        return (1, 2, 0)
    return (2, 0, 1)


@njit(cache=True)
def _quad_inverse(p1, p2, p3, y, n):
    if p1 == 0.0:
        return (y - p3) / p2
    disc = p2 * p2 - 4.0 * p1 * (p3 - y)
    if disc < 0.0:
        return 0.0 if y < p3 else float(n)
    return (-p2 + math.sqrt(disc)) / (2.0 * p1)


@njit(cache=True)
def linear_interval(kvector, m, q, lo, hi):
    """Length of the k-vector interval (Mortari's line) for a smallest angle in ``[lo, hi]`` (Table 5)."""
    n = kvector.shape[0] - 1
    jb = min(max(int(math.floor((lo - q) / m)), 0), n)
    jt = min(max(int(math.ceil((hi - q) / m)), 0), n)
    return kvector[jt] - kvector[jb]
