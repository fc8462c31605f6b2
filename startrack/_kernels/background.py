"""Background kernels: a sample's level and noise from the normal core of its distribution, on a mesh of tiles.

What :func:`startrack.centroid.estimate_background` and the pixel-noise mesh run on, and the tracking windows'
border statistics (:mod:`startrack._kernels.centroid`).
"""
import math

import numpy as np

from startrack._kernels._jit import njit

# Up to this many values an insertion sort is faster than numba's quicksort (~2.5 vs 3.4 us for a mesh tile's
# 121 values; equal at ~250).
_INSERTION_SORT_MAX = 200


@njit(cache=True)
def _insertion_sort(a):
    """Sort ``a`` (finite values) in place."""
    for i in range(1, a.shape[0]):
        v = a[i]
        j = i
        while j > 0 and a[j - 1] > v:
            a[j] = a[j - 1]
            j -= 1
        a[j] = v


#: The window of the empirical distribution function in which :func:`core_stats_of_sorted` fits the
#: background's normal core: above the lowest 1 % (dead pixels) and below the top 15 % (stars, their wings,
#: hot pixels and whatever else is brighter than the sky; a star field's sources cover far less than 15 % of it).
CORE_F_LO = 0.01
CORE_F_MID = 0.5
CORE_F_HI = 0.85


@njit(cache=True)
def _probit(p):
    """The standard normal quantile ``Phi^-1(p)`` for ``0 < p < 1`` (Acklam's rational approximation: within
    1e-7 relative, far below what a sample's distribution function resolves)."""
    if p < 0.02425:
        q = math.sqrt(-2.0 * math.log(p))
        return (((((-7.784894002430293e-03 * q - 3.223964580411365e-01) * q - 2.400758277161838e+00) * q
                  - 2.549732539343734e+00) * q + 4.374664141464968e+00) * q + 2.938163982698783e+00) / \
            ((((7.784695709041462e-03 * q + 3.224671290700398e-01) * q + 2.445134137142996e+00) * q
              + 3.754408661907416e+00) * q + 1.0)
    if p > 1.0 - 0.02425:
        return -_probit(1.0 - p)
    q = p - 0.5
    r = q * q
    return (((((-3.969683028665376e+01 * r + 2.209460984245205e+02) * r - 2.759285104469687e+02) * r
              + 1.383577518672690e+02) * r - 3.066479806614716e+01) * r + 2.506628277459239e+00) * q / \
        (((((-5.447609879822406e+01 * r + 1.615858368580409e+02) * r - 1.556989798598866e+02) * r
           + 6.680131188771972e+01) * r - 1.328068155200130e+01) * r + 1.0)


@njit(cache=True)
def _line(sw, sx, sz, sxx, sxz, m):
    """The weighted least-squares line ``z = a + b x`` from its sums: ``(a, b)``, b 0 when undetermined."""
    if m < 2:
        return 0.0, 0.0
    mx = sx / sw
    mz = sz / sw
    vxx = sxx / sw - mx * mx
    if not vxx > 0.0:
        return 0.0, 0.0
    b = (sxz / sw - mx * mz) / vxx
    return mz - b * mx, b


@njit(cache=True)
def _step_table(n, z_of, w_of):
    """The probit ``z`` and weight ``w`` of every step ``j`` (``F = (j + 1) / n``) of a sample of ``n`` values, into
    ``z_of[:n - 1]`` and ``w_of[:n - 1]``: what :func:`_core_fit` computes at a step, by the same operations.  They
    depend on ``n`` alone: a mesh's tiles of as many samples share one table."""
    for j in range(n - 1):
        f = (j + 1) / n
        z = _probit(f)
        phi = math.exp(-0.5 * z * z)
        z_of[j] = z
        w_of[j] = phi * phi / (f * (1.0 - f))


@njit(cache=True)
def _core_fit(s, f_lo, f_mid, f_hi, z_of, w_of):
    """Weighted lines ``z = a + b x`` through the distribution function's steps inside ``[f_lo, f_hi]`` and
    inside ``[f_lo, f_mid]`` (one pass): ``(a, b, points, a_low, b_low, points_low)``.  ``z_of``, ``w_of``: the
    steps' table of :func:`_step_table` for ``len(s)`` values, else empty (computed step by step)."""
    n = s.shape[0]
    tabulated = z_of.shape[0] >= n - 1
    if tabulated:
        return _core_fit_tabulated(s, f_lo, f_mid, f_hi, z_of, w_of)
    # The sums in scalars (registers), not a 5-array a step (each += a store and a reload on the sum's chain).
    t0 = t1 = t2 = t3 = t4 = 0.0
    u0 = u1 = u2 = u3 = u4 = 0.0
    m = 0
    m2 = 0
    i = 0
    while i < n:
        j = i
        while j + 1 < n and s[j + 1] == s[i]:
            j += 1
        if j + 1 < n:
            f = (j + 1) / n
            if f_lo <= f <= f_hi:
                x = 0.5 * (s[j] + s[j + 1])
                if tabulated:
                    z = z_of[j]
                    w = w_of[j]
                else:
                    z = _probit(f)
                    phi = math.exp(-0.5 * z * z)
                    w = phi * phi / (f * (1.0 - f))
                t0 += w
                t1 += w * x
                t2 += w * z
                t3 += w * x * x
                t4 += w * x * z
                m += 1
                if f <= f_mid:
                    u0, u1, u2, u3, u4 = t0, t1, t2, t3, t4
                    m2 = m
        i = j + 1
    a, b = _line(t0, t1, t2, t3, t4, m)
    a2, b2 = _line(u0, u1, u2, u3, u4, m2)
    return a, b, m, a2, b2, m2


@njit(cache=True)
def _core_fit_tabulated(s, f_lo, f_mid, f_hi, z_of, w_of):
    """:func:`_core_fit` with the steps' table, without a branch on the sample's ties: every ``j`` whose ``F``
    lies in the window adds its terms times 1 at a step of the distribution function (``s[j] < s[j + 1]``)
    and times 0 elsewhere, so each sum gets the step's terms, in the same order, and +-0 elsewhere, which
    leaves it as it is (a sum is never -0: it starts at +0).  On whole DN a tile's ~100 samples hold a few
    dozen ties at random places, and the branch on them was mispredicted at most of them."""
    n = s.shape[0]
    t0 = t1 = t2 = t3 = t4 = 0.0
    u0 = u1 = u2 = u3 = u4 = 0.0
    m = 0
    m2 = 0
    for j in range(n - 1):
        f = (j + 1) / n
        if f < f_lo:
            continue
        if f > f_hi:
            break           # F grows with j
        step = s[j + 1] != s[j]
        k = 1.0 if step else 0.0
        x = 0.5 * (s[j] + s[j + 1])
        z = z_of[j]
        w = w_of[j]
        t0 += w * k
        t1 += w * x * k
        t2 += w * z * k
        t3 += w * x * x * k
        t4 += w * x * z * k
        m += 1 if step else 0
        if f <= f_mid:
            # (between steps the sums and m are as at the last step: the same values as _core_fit keeps)
            u0, u1, u2, u3, u4 = t0, t1, t2, t3, t4
            m2 = m
    a, b = _line(t0, t1, t2, t3, t4, m)
    a2, b2 = _line(u0, u1, u2, u3, u4, m2)
    return a, b, m, a2, b2, m2


@njit(cache=True)
def core_stats_of_sorted(s):
    """Level and noise (DN) of a background sample, from the normal core of its distribution (sorted, finite).

    A star field's background is normal noise about a level; what else is in a
    sample is brighter (stars, hot pixels) or was cut off below (a
    dark-subtracted frame clipped at 0 holds many zeros; an 8-bit frame of low
    noise holds a few grey levels).  Each step of the empirical distribution
    function between two adjacent values ``v_j < v_(j+1)`` says
    ``P(X <= (v_j + v_(j+1)) / 2) = F_j``: for ``X ~ N(mu, sigma)`` the probit
    ``Phi^-1(F_j)`` is the straight line ``(x - mu) / sigma`` of the step's
    position ``x``.  A weighted line fit (weights ``phi(z)^2 / (F (1 - F))``, the
    inverse variance of ``z`` from ``F``) over the steps with ``F`` in
    [:data:`CORE_F_LO`, :data:`CORE_F_HI`] gives ``mu`` and ``sigma``.  Why it holds
    where a median and MAD do not:

    - values cut off at a floor (clipping) all sit in the first step, and the
      steps above it keep the normal's own ``F``: the fit is unbiased until the
      floor passes ``CORE_F_HI`` of the sample (a MAD of a sample 37 % zeros is
      biased low, and 0 when half of it is);
    - on whole DN the steps sit between grey levels and the fit measures the
      normal's sigma, also below 1 DN (a MAD of 0.3 DN noise is 0);
    - the bright tail (stars) only lowers every ``F`` by its own fraction,
      ~0.01 sigma for 1 % of the pixels.

    When more than the top 15 % is not background (a tile across a lit limb or
    a nebula's edge), the steps above the median bend away from the line: the
    fit over the lower half alone (``F`` up to :data:`CORE_F_MID`) is taken when
    its sigma is below the whole window's by over a fifth (on a normal sample
    the two agree to the scatter of ~100 values' fits, and either is unbiased).
    When fewer than two steps fall in the window (nearly all pixels in one or
    two grey levels, or clipped), the steps between 0.05 % and 90 % are used; a
    sample of one value, or of two, has ``sigma`` 0 (below the quantisation) and
    its median as the level; the caller adds the quantisation's 1/12 DN^2.
    """
    return _core_stats(s, np.empty(0), np.empty(0))


@njit(cache=True)
def _core_stats(s, z_of, w_of):
    """:func:`core_stats_of_sorted` with the steps' table of :func:`_step_table` (else empty arrays)."""
    n = s.shape[0]
    if n == 0:
        return 0.0, 0.0
    med = s[n // 2] if n & 1 else 0.5 * (s[n // 2 - 1] + s[n // 2])
    if s[0] == s[n - 1]:
        return s[0], 0.0
    a, b, m, a2, b2, m2 = _core_fit(s, CORE_F_LO, CORE_F_MID, CORE_F_HI, z_of, w_of)
    if m2 >= 3 and b2 > 0.0 and b > 0.0 and 1.0 / b > 1.25 / b2:
        a, b = a2, b2
    if m < 2:
        a, b, m, _, _, _ = _core_fit(s, 0.0005, 0.0, 0.9, z_of, w_of)
    if m < 2 or not b > 0.0:
        return med, 0.0
    return -a / b, 1.0 / b


@njit(cache=True)
def mesh_core_stats(ordered, counts, sampled, ny, nx):
    """:func:`mesh_stats` with :func:`core_stats_of_sorted`: each tile's level and noise from its samples' normal core."""
    level = np.empty((ny, nx))
    sigma = np.empty((ny, nx))
    buf = np.empty(ordered.shape[1])
    # The steps' probits and weights depend on a tile's sample count alone: tabulated once per count (a mesh's
    # tiles mostly hold as many samples), not per tile.
    z_of = np.empty(ordered.shape[1])
    w_of = np.empty(ordered.shape[1])
    table_n = -1
    for t in range(ny * nx):
        k = counts[t]
        if k < min(MIN_TILE_SAMPLES, sampled[t]):
            level[t // nx, t % nx] = np.nan
            sigma[t // nx, t % nx] = np.nan
            continue
        for i in range(k):
            buf[i] = ordered[t, i]
        if k != table_n:
            _step_table(k, z_of, w_of)
            table_n = k
        med, sig = _core_stats(buf[:k], z_of[:max(k - 1, 0)], w_of[:max(k - 1, 0)])
        level[t // nx, t % nx] = med
        sigma[t // nx, t % nx] = sig
    return level, sigma


# Serial on purpose: these passes are memory-bound (two multiply-adds per pixel,
# ~100 samples per tile), and for star-tracker frames numba's thread start-up and
# spinning cost more than they save; under contention (``-j N`` batches, a busy
# cluster node) parallel loops were 2-3x slower in wall time.
@njit(cache=True)
def background_mesh(image, cell, step):
    """Level and noise (:func:`core_stats_of_sorted`) on a mesh of ``cell`` x ``cell`` tiles.

    Every ``step``-th pixel of a tile is sampled; NaN and infinite pixels are no
    data (a tile with fewer than :data:`MIN_TILE_SAMPLES` finite samples gets NaN:
    the caller fills it from its neighbours).  Returns ``(level, sigma)`` arrays of
    shape ``(ceil(h / cell), ceil(w / cell))``.
    """
    h, w = image.shape
    ny = (h + cell - 1) // cell
    nx = (w + cell - 1) // cell
    level = np.empty((ny, nx))
    sigma = np.empty((ny, nx))
    for t in range(ny * nx):
        j = t // nx
        i = t % nx
        y0 = j * cell
        x0 = i * cell
        y1 = min(h, y0 + cell)
        x1 = min(w, x0 + cell)
        n = ((y1 - y0 + step - 1) // step) * ((x1 - x0 + step - 1) // step)
        buf = np.empty(n)
        k = 0
        for y in range(y0, y1, step):
            for x in range(x0, x1, step):
                v = image[y, x]
                if np.isfinite(v):
                    buf[k] = v
                    k += 1
        if k < min(MIN_TILE_SAMPLES, n):
            level[j, i] = np.nan
            sigma[j, i] = np.nan
            continue
        sub = buf[:k]
        if k <= _INSERTION_SORT_MAX:
            _insertion_sort(sub)
        else:
            sub.sort()
        med, sig = core_stats_of_sorted(sub)
        level[j, i] = med
        sigma[j, i] = sig
    return level, sigma


#: A mesh tile with fewer finite samples than this (of its ~100) has no level of its own: its
#: neighbours' stand in (:func:`median3` over the finite ones), else the frame's.
MIN_TILE_SAMPLES = 10


@njit(cache=True)
def mesh_samples(image, cell, step, saturation):
    """The samples of :func:`background_mesh`'s tiles, one row a tile (row-major tiles), for a sort by numpy.

    Returns ``(samples (ny * nx, n_max) float32, counts, sampled)``: a tile's finite samples below
    ``saturation`` (NaN, infinite and saturated pixels are no data; ``inf``: no saturation level), then
    +inf; ``counts[t]`` their number, ``sampled[t]`` the pixels sampled.
    """
    h, w = image.shape
    ny = (h + cell - 1) // cell
    nx = (w + cell - 1) // cell
    n_max = ((min(cell, h) + step - 1) // step) * ((min(cell, w) + step - 1) // step)
    samples = np.full((ny * nx, n_max), np.inf, dtype=np.float32)
    counts = np.empty(ny * nx, dtype=np.int64)
    sampled = np.empty(ny * nx, dtype=np.int64)
    for t in range(ny * nx):
        y0 = (t // nx) * cell
        x0 = (t % nx) * cell
        k = 0
        m = 0
        for y in range(y0, min(h, y0 + cell), step):
            for x in range(x0, min(w, x0 + cell), step):
                v = image[y, x]
                m += 1
                if np.isfinite(v) and v < saturation:
                    samples[t, k] = v
                    k += 1
        counts[t] = k
        sampled[t] = m
    return samples, counts, sampled


@njit(cache=True, inline="always")
def _sort2(a, b):
    return min(a, b), max(a, b)


@njit(cache=True)
def _median9(p0, p1, p2, p3, p4, p5, p6, p7, p8):
    """The fifth smallest of nine values by a fixed network of 19 compare-exchanges (Paeth; Devillard's
    ``opt_med9``): no branch on the values, whose order is random (an insertion sort of a mesh's 3 x 3 cells
    mispredicted a branch at most of its steps).  NaN when any value is NaN (min and max keep it)."""
    if p0 != p0 or p1 != p1 or p2 != p2 or p3 != p3 or p4 != p4 or p5 != p5 or p6 != p6 or p7 != p7 or p8 != p8:
        return math.nan
    p1, p2 = _sort2(p1, p2)
    p4, p5 = _sort2(p4, p5)
    p7, p8 = _sort2(p7, p8)
    p0, p1 = _sort2(p0, p1)
    p3, p4 = _sort2(p3, p4)
    p6, p7 = _sort2(p6, p7)
    p1, p2 = _sort2(p1, p2)
    p4, p5 = _sort2(p4, p5)
    p7, p8 = _sort2(p7, p8)
    p0, p3 = _sort2(p0, p3)
    p5, p8 = _sort2(p5, p8)
    p4, p7 = _sort2(p4, p7)
    p3, p6 = _sort2(p3, p6)
    p1, p4 = _sort2(p1, p4)
    p2, p5 = _sort2(p2, p5)
    p4, p7 = _sort2(p4, p7)
    p4, p2 = _sort2(p4, p2)
    p6, p4 = _sort2(p6, p4)
    p4, p2 = _sort2(p4, p2)
    return p4


@njit(cache=True)
def median3(a):
    """3 x 3 median filter of a small 2-D float64 mesh, edges replicated (as ``np.median`` of the 9 values);
    NaN cells (tiles without data) are left out of their neighbours' medians and get the median of
    their finite neighbours (NaN when none is)."""
    ny, nx = a.shape
    out = np.empty((ny, nx))
    buf = np.empty(9)
    for j in range(ny):
        ju = max(j - 1, 0)
        jd = min(j + 1, ny - 1)
        for i in range(nx):
            il = max(i - 1, 0)
            ir = min(i + 1, nx - 1)
            med = _median9(a[ju, il], a[ju, i], a[ju, ir], a[j, il], a[j, i], a[j, ir], a[jd, il], a[jd, i], a[jd, ir])
            if med == med and med != 0.0:
                # Nine values, none NaN: the fifth smallest, the insertion sort's middle (a zero is left to the
                # sort, which keeps a -0 or +0 as it met them).
                out[j, i] = med
                continue
            k = 0
            for dj in range(-1, 2):
                jj = min(max(j + dj, 0), ny - 1)
                for di in range(-1, 2):
                    v = a[jj, min(max(i + di, 0), nx - 1)]
                    if v != v:
                        continue
                    # insertion sort of the finite values
                    m = k
                    while m > 0 and buf[m - 1] > v:
                        buf[m] = buf[m - 1]
                        m -= 1
                    buf[m] = v
                    k += 1
            if k == 0:
                out[j, i] = math.nan
            elif k & 1:
                out[j, i] = buf[k >> 1]
            else:
                out[j, i] = 0.5 * (buf[(k >> 1) - 1] + buf[k >> 1])
    return out


@njit(cache=True)
def tile_clipped_std(residual, cell, sigma_mesh, kappa, truncated_std, n_iter, out):
    """Per-tile noise (DN): standard deviation of the residual pixels within ``kappa`` sigma of zero.

    ``sigma`` starts at the tile's ``sigma_mesh`` and is re-estimated ``n_iter``
    times from every pixel of the tile, each time divided by
    ``truncated_std`` (the standard deviation of a unit normal truncated to
    +-kappa).  ``out`` (same shape as ``sigma_mesh``) receives it; a tile with
    fewer than 50 pixels kept keeps ``sigma_mesh``.

    Each iteration is one pass over a row of tiles, row by row, summing every
    column separately (independent sums, so the loop over a row's pixels is
    vectorised; one running sum a tile made it latency-bound), then a tile's
    columns; the same sums up to rounding.
    """
    h, w = residual.shape
    ny, nx = sigma_mesh.shape
    s = np.empty((ny, nx))
    active = np.ones((ny, nx), dtype=np.bool_)
    for j in range(ny):
        for i in range(nx):
            s[j, i] = sigma_mesh[j, i]
            out[j, i] = sigma_mesh[j, i]
    lim = np.empty(w)
    cn = np.empty(w)
    c1 = np.empty(w)
    c2 = np.empty(w)
    for _ in range(n_iter):
        for j in range(ny):
            todo = False
            for i in range(nx):
                todo = todo or active[j, i]
            if not todo:
                continue
            for x in range(w):
                i = x // cell
                lim[x] = kappa * s[j, i] if i < nx and active[j, i] else -1.0
                cn[x] = 0.0
                c1[x] = 0.0
                c2[x] = 0.0
            for y in range(j * cell, min(h, (j + 1) * cell)):
                row = residual[y]
                for x in range(w):
                    v = row[x]
                    keep = abs(v) <= lim[x]
                    cn[x] += 1.0 if keep else 0.0
                    c1[x] += v if keep else 0.0
                    c2[x] += v * v if keep else 0.0     # the square in the residual's precision, as before
            for i in range(nx):
                if not active[j, i]:
                    continue
                n = 0.0
                s1 = 0.0
                s2 = 0.0
                for x in range(i * cell, min(w, (i + 1) * cell)):
                    n += cn[x]
                    s1 += c1[x]
                    s2 += c2[x]
                if n < 50:
                    active[j, i] = False
                    continue
                var = (s2 - s1 * s1 / n) / (n - 1)
                if not var > 0.0:
                    active[j, i] = False
                    continue
                s[j, i] = math.sqrt(var) / truncated_std
                out[j, i] = s[j, i]
    return out
