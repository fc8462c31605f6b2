"""The focal-length scale a proposal or a field implies (chords of catalog over measured stars) and whether
the stars tell it from 1 (:mod:`startrack.identify.verify`'s focal-length steps)."""
import math

import numpy as np

from startrack._kernels._jit import njit
from startrack._kernels.common import _chord_rows, _median_in_place
from startrack._kernels.sky_index import cone_stars
from startrack._kernels.sphere import project_to_pixel


@njit(cache=True)
def focal_scale(b, img, star_vec, cat):
    """Least-squares ``s`` with ``c_cat = s c_mea`` over the pairs of ``img``/``cat`` (NaN if < 3 or
    degenerate), ``c`` a pair's chord (:func:`_chord_rows`).

    The chord ratio is the angle ratio to a relative ``(s^2 - 1) theta^2 / 24`` (2e-4 for a 1 % scale
    over 30 deg: the focal loop's next step takes it up) and needs no ``acos``; at the true focal length
    both are 1 up to the noise."""
    n = img.shape[0]
    if n < 3:
        return np.nan
    # _chord_scale of _pair_chords' chords, summed as they are made (the same sums in the same order), without
    # their array
    num = 0.0
    den = 0.0
    for u in range(n):
        for v in range(u + 1, n):
            mea = _chord_rows(b, img[u], b, img[v])
            ang = _chord_rows(star_vec, cat[u], star_vec, cat[v])
            num += ang * mea
            den += mea * mea
    if den <= 0.0:
        return np.nan
    return num / den


@njit(cache=True, inline="always")
def _pair_chords(b, img, star_vec, cat):
    """``(ang, mea)``: the catalog and the measured chords (:func:`_chord_rows`) of the pairs ``u < v`` of
    ``img`` -> ``cat``, in the order ``(0, 1), (0, 2), ..., (1, 2), ...`` (the scale estimates' order)."""
    n = img.shape[0]
    npair = n * (n - 1) // 2
    chords = np.empty((2, npair))       # (ang and mea: rows of one allocation)
    ang = chords[0]
    mea = chords[1]
    t = 0
    for u in range(n):
        for v in range(u + 1, n):
            mea[t] = _chord_rows(b, img[u], b, img[v])
            ang[t] = _chord_rows(star_vec, cat[u], star_vec, cat[v])
            t += 1
    return ang, mea


@njit(cache=True, inline="always")
def _residual(b, i, star_vec, c, dcm):
    """``R r_c - b_i`` (:func:`scale_interval`): ``dcm`` of a quaternion of any norm is that norm squared
    times a rotation ``R``, the row brought back to unit length; NaNs when it has none."""
    rx = dcm[0, 0] * star_vec[c, 0] + dcm[0, 1] * star_vec[c, 1] + dcm[0, 2] * star_vec[c, 2]
    ry = dcm[1, 0] * star_vec[c, 0] + dcm[1, 1] * star_vec[c, 1] + dcm[1, 2] * star_vec[c, 2]
    rz = dcm[2, 0] * star_vec[c, 0] + dcm[2, 1] * star_vec[c, 1] + dcm[2, 2] * star_vec[c, 2]
    rn = math.sqrt(rx * rx + ry * ry + rz * rz)
    if not rn > 0.0:
        return np.nan, np.nan, np.nan
    return rx / rn - b[i, 0], ry / rn - b[i, 1], rz / rn - b[i, 2]


@njit(cache=True)
def scale_interval(b, img, star_vec, cat, dcm):
    """An interval that holds :func:`focal_scale`'s ``s`` of ``img`` -> ``cat`` in O(n), without its pairs:
    ``(lo, hi)``, both NaN when the detections have no spread (the caller computes ``s`` instead).

    With ``e_u = R r_u - b_u`` (``R`` the rotation of ``dcm``, which leaves every chord as it is) and, for a
    pair, ``x = b_u - b_v``, ``d = e_u - e_v``, ``m = |x|`` and ``a = |x + d|`` its measured and catalog
    chords: ``x . d <= (a - m) m <= x . d + |d|^2 / 2`` (projection on ``x``, and the concavity of the square
    root).  Summed over the pairs (``sum_{u<v} (x_u - x_v) . (y_u - y_v) = n sum_u (x_u - x_bar) . (y_u -
    y_bar)``), ``s = sum a m / sum m^2`` lies in ``1 + [P, P + R / 2] / Q`` with ``P = sum (b_u - b_bar) .
    (e_u - e_bar)``, ``R = sum |e_u - e_bar|^2`` and ``Q = sum |b_u - b_bar|^2``.  The interval is widened by
    a bound of the rounding of both computations (:func:`_chord_scale`'s sums of ``n^2 / 2`` terms and these
    of ``n``: relative errors of a few ``n^2`` ulps), so that ``s`` as computed lies in it too.  Its width
    is the residuals' squared over the chords' squared: 1e-7 for residuals of 1e-3 of the chords."""
    n = img.shape[0]
    if n < 3:
        return np.nan, np.nan
    # Two passes (the means, then the sums about them), each computing e_u again: no array to allocate.
    bx = by = bz = ex = ey = ez = 0.0
    for t in range(n):
        e0, e1, e2 = _residual(b, img[t], star_vec, cat[t], dcm)
        if math.isnan(e0):
            return np.nan, np.nan
        bx += b[img[t], 0]
        by += b[img[t], 1]
        bz += b[img[t], 2]
        ex += e0
        ey += e1
        ez += e2
    bx /= n
    by /= n
    bz /= n
    ex /= n
    ey /= n
    ez /= n
    p = 0.0
    r = 0.0
    q = 0.0
    for t in range(n):
        e0, e1, e2 = _residual(b, img[t], star_vec, cat[t], dcm)
        d0 = b[img[t], 0] - bx
        d1 = b[img[t], 1] - by
        d2 = b[img[t], 2] - bz
        e0 -= ex
        e1 -= ey
        e2 -= ez
        p += d0 * e0 + d1 * e1 + d2 * e2
        r += e0 * e0 + e1 * e1 + e2 * e2
        q += d0 * d0 + d1 * d1 + d2 * d2
    if not q > 0.0 or not math.isfinite(p + r):
        return np.nan, np.nan
    npair = n * (n - 1) // 2
    slack = 1e-10 * (1.0 + math.sqrt(n / q)) + 64.0 * (npair + n) * 2.220446049250313e-16
    return 1.0 + p / q - slack, 1.0 + (p + 0.5 * r) / q + slack


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

    See :func:`startrack.identify.verify._field_scale`: each detection takes the one
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
        a, c = project_to_pixel(x, y, z, focal, cx, cy, k1, k2, 0.0, 0.0, 0)
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
