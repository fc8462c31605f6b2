"""Kernels on the celestial sphere: neighbour pairs and field-of-view counts."""
import numpy as np

from startrack._kernels._jit import njit, prange


@njit(cache=True, inline="always")
def project_to_pixel(x, y, z, focal, cx, cy, k1, k2, k3, k4, proj):
    """Camera-frame direction to pixel ``(x, y)``, the model of :class:`startrack.camera.Camera`.

    ``proj`` is the projection's index in :data:`startrack.camera.PROJECTIONS`.  A pinhole
    (0, ``z`` > 0) with radial distortion ``1 + k1 r^2 + k2 r^4``; a fisheye ``r = f g(theta_d)``,
    ``theta_d = theta (1 + k1 theta^2 + ... + k4 theta^8)``, ``g`` = ``theta`` (1, equidistant),
    ``2 sin(theta / 2)`` (2, equisolid), ``2 tan(theta / 2)`` (3, stereographic), ``sin(theta)``
    (4, orthographic).  The caller keeps ``theta`` within the model's range
    (:attr:`startrack.camera.Camera.max_theta`: a cone cut ``z >= cos``)."""
    if proj == 0:
        u = x / z
        v = y / z
        r2 = u * u + v * v
        scale = 1.0 + k1 * r2 + k2 * r2 * r2
        return cx + focal * u * scale, cy + focal * v * scale
    rxy = np.sqrt(x * x + y * y)
    theta = np.arctan2(rxy, z)
    t2 = theta * theta
    td = theta * (1.0 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))
    if proj == 1:
        r = td
    elif proj == 2:
        r = 2.0 * np.sin(0.5 * td)
    elif proj == 3:
        r = 2.0 * np.tan(0.5 * td)
    else:
        r = np.sin(td)
    if rxy > 0.0:
        s = focal * r / rxy
    else:
        s = 0.0
    return cx + x * s, cy + y * s


@njit(cache=True, parallel=True)
def pairs_within(vectors, dec, order, max_angle, cos_max):
    """All pairs ``i < j`` (in ``order``) whose angle is at most ``max_angle``.

    A declination sweep: stars sorted by ``dec`` (``order``) and, for each star,
    only those within ``max_angle`` in declination are tested, because the
    declination difference never exceeds the angular separation.

    Returns ``(first, second, cosine)`` with ``first``/``second`` original
    indices; pairs come grouped by the first star's position in ``order``.
    """
    n = order.shape[0]
    counts = np.zeros(n + 1, dtype=np.int64)
    for a in prange(n):
        i = order[a]
        c = 0
        for b in range(a + 1, n):
            j = order[b]
            if dec[j] - dec[i] > max_angle:
                break
            d = vectors[i, 0] * vectors[j, 0] + vectors[i, 1] * vectors[j, 1] + vectors[i, 2] * vectors[j, 2]
            if d >= cos_max:
                c += 1
        counts[a + 1] = c
    for a in range(n):
        counts[a + 1] += counts[a]
    total = counts[n]
    first = np.empty(total, dtype=np.int64)
    second = np.empty(total, dtype=np.int64)
    cosine = np.empty(total, dtype=np.float64)
    for a in prange(n):
        i = order[a]
        k = counts[a]
        for b in range(a + 1, n):
            j = order[b]
            if dec[j] - dec[i] > max_angle:
                break
            d = vectors[i, 0] * vectors[j, 0] + vectors[i, 1] * vectors[j, 1] + vectors[i, 2] * vectors[j, 2]
            if d >= cos_max:
                first[k] = i
                second[k] = j
                cosine[k] = d
                k += 1
    return first, second, cosine


@njit(cache=True, parallel=True)
def count_in_fov(vectors_by_dec, dec_sorted, mags_by_dec, dcms, focal, cx, cy, width, height,
                 k1, k2, k3, k4, proj, max_off_axis):
    """Stars inside a camera's image for many attitudes (:func:`project_to_pixel`'s lens terms;
    ``max_off_axis`` within the model's range).

    ``vectors_by_dec`` are ICRS unit vectors sorted by declination
    (``dec_sorted``); ``dcms`` has shape ``(m, 3, 3)``.  A star is in the
    field when it projects inside ``[-0.5, width - 0.5] x [-0.5, height - 0.5]``.

    Returns ``(count, brightest_mag)``, ``brightest_mag`` NaN when empty.
    """
    m = dcms.shape[0]
    counts = np.zeros(m, dtype=np.int64)
    brightest = np.full(m, np.nan)
    n = dec_sorted.shape[0]
    cos_off = np.cos(max_off_axis)
    for k in prange(m):
        bx, by, bz = dcms[k, 2, 0], dcms[k, 2, 1], dcms[k, 2, 2]
        bdec = np.arcsin(min(1.0, max(-1.0, bz)))
        lo = np.searchsorted(dec_sorted, bdec - max_off_axis)
        hi = np.searchsorted(dec_sorted, bdec + max_off_axis, side="right")
        c = 0
        best = np.inf
        for s in range(lo, min(hi, n)):
            vx, vy, vz = vectors_by_dec[s, 0], vectors_by_dec[s, 1], vectors_by_dec[s, 2]
            z = bx * vx + by * vy + bz * vz
            if z < cos_off:
                continue
            x = dcms[k, 0, 0] * vx + dcms[k, 0, 1] * vy + dcms[k, 0, 2] * vz
            y = dcms[k, 1, 0] * vx + dcms[k, 1, 1] * vy + dcms[k, 1, 2] * vz
            px, py = project_to_pixel(x, y, z, focal, cx, cy, k1, k2, k3, k4, proj)
            if px >= -0.5 and px <= width - 0.5 and py >= -0.5 and py <= height - 0.5:
                c += 1
                if mags_by_dec[s] < best:
                    best = mags_by_dec[s]
        counts[k] = c
        if c > 0:
            brightest[k] = best
    return counts, brightest
