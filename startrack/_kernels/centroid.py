"""Centroiding kernels: blob labelling and measurements, deblending, sub-pixel fits, tracking windows (the
background mesh is :mod:`startrack._kernels.background`)."""
import math

import numpy as np

from startrack._kernels._jit import njit
from startrack._kernels.background import core_stats_of_sorted


@njit(cache=True)
def windowed_centroid(residual, x0, y0, sigma_w, half, n_iter):
    """Iterative intensity-weighted centroid with a Gaussian window (like XWIN).

    Weights ``w = I exp(-r^2 / (2 sigma_w^2))`` around the current estimate,
    re-centred until it moves less than 1e-4 px.  For a Gaussian star this
    converges to the unbiased centre; it suppresses the noise of far pixels.
    """
    h, w = residual.shape
    cx = x0
    cy = y0
    inv = 1.0 / (2.0 * sigma_w * sigma_w)
    for _ in range(n_iter):
        xi = int(math.floor(cx + 0.5))
        yi = int(math.floor(cy + 0.5))
        sw = 0.0
        sx = 0.0
        sy = 0.0
        for y in range(max(0, yi - half), min(h, yi + half + 1)):
            dy = y - cy
            for x in range(max(0, xi - half), min(w, xi + half + 1)):
                dx = x - cx
                v = residual[y, x]
                wgt = v * math.exp(-(dx * dx + dy * dy) * inv)
                sw += wgt
                sx += wgt * dx
                sy += wgt * dy
        if sw <= 0:
            return x0, y0, False
        # The Gaussian window halves the offset for a Gaussian star of the
        # same width: the fixed point of the update is the true centre.
        step_x = 2.0 * sx / sw
        step_y = 2.0 * sy / sw
        cx += step_x
        cy += step_y
        if abs(cx - x0) > half or abs(cy - y0) > half:
            return x0, y0, False
        if abs(step_x) < 1e-4 and abs(step_y) < 1e-4:
            break
    return cx, cy, True


@njit(cache=True)
def _g(x, sigma, a, b):
    """Fraction of a unit 1-D Gaussian at ``x`` falling in ``[a, b]`` (paper 003 Eq. 5 / sqrt(pi))."""
    s = math.sqrt(2.0) * sigma
    return 0.5 * (math.erf((b - x) / s) - math.erf((a - x) / s))


@njit(cache=True)
def quine_offset(i_left, i_mid, i_right, sigma):
    """Sub-pixel offset of a Gaussian star from three adjacent pixel sums.

    Quine et al. (2007) / paper 003 Eqs. 4-6: the pixel values are
    ``A g(x, sigma, k - 1/2, k + 1/2)``; eliminating ``A`` between the
    brightest pixel and its brighter neighbour leaves one equation in ``x``,
    solved here by bisection on ``[-0.5, 0.5]`` (monotonic there).
    """
    if i_mid <= 0:
        return 0.0
    if i_right >= i_left:
        ratio = max(i_right, 1e-12) / i_mid
        side = 1.0
    else:
        ratio = max(i_left, 1e-12) / i_mid
        side = -1.0
    lo = 0.0
    hi = 0.5
    for _ in range(50):
        mid = 0.5 * (lo + hi)
        x = side * mid
        r = _g(x, sigma, side - 0.5, side + 0.5) / _g(x, sigma, -0.5, 0.5)
        if r < ratio:
            lo = mid
        else:
            hi = mid
    return side * 0.5 * (lo + hi)


@njit(cache=True, inline="always")
def _solve5_into(m, x):
    """Solve the 5 x 5 system ``m x = b`` of a fit's step in place (Gaussian elimination, partial pivoting):
    ``m`` is overwritten, ``x`` (the right-hand side ``b``) becomes the solution; returns ok.

    numba's ``np.linalg`` needs SciPy's BLAS.  The fits call it on their own scratch (no allocation an
    iteration); the size is known to the compiler, which unrolls the loops.
    """
    n = 5
    for col in range(n):
        piv = col
        best = abs(m[col, col])
        for r in range(col + 1, n):
            if abs(m[r, col]) > best:
                best = abs(m[r, col])
                piv = r
        if best < 1e-300:
            return False
        if piv != col:
            for c in range(n):
                m[col, c], m[piv, c] = m[piv, c], m[col, c]
            x[col], x[piv] = x[piv], x[col]
        for r in range(col + 1, n):
            f = m[r, col] / m[col, col]
            for c in range(col, n):
                m[r, c] -= f * m[col, c]
            x[r] -= f * x[col]
    for col in range(n - 1, -1, -1):
        acc = x[col]
        for c in range(col + 1, n):
            acc -= m[col, c] * x[c]
        x[col] = acc / m[col, col]
    return True


@njit(cache=True, inline="always")
def _axis_factors(k0, n_px, c, s, axes, row):
    """Pixel-integrated 1-D Gaussian ``g(k; c, s)`` (paper 003 Eq. 5) at the pixels ``k0 <= k < k0 + n_px``
    into ``axes[row, :n_px]``, its derivatives in ``c`` and ``s`` into rows ``row + 1`` and ``row + 2``."""
    r2 = math.sqrt(2.0) * s
    norm = math.sqrt(math.pi) * r2
    eb = 0.0
    pb = 0.0
    for n in range(n_px):
        k = k0 + n
        if n > 0:
            # The pixel's lower edge is the previous pixel's upper edge (k - 0.5 == (k - 1) + 0.5 exactly for
            # whole k, so it is the previous upper edge to the bit): its erf and exp are already known.
            ea = eb
            pa = pb
        else:
            ua = (k - 0.5 - c) / r2
            ea = math.erf(ua)
            pa = math.exp(-ua * ua)
        ub = (k + 0.5 - c) / r2
        eb = math.erf(ub)
        pb = math.exp(-ub * ub)
        axes[row, n] = 0.5 * (eb - ea)
        axes[row + 1, n] = (pa - pb) / norm
        axes[row + 2, n] = ((k - 0.5 - c) * pa - (k + 0.5 - c) * pb) / (norm * s)


@njit(cache=True, inline="always")
def _axis_values(k0, n_px, c, s, axes, row):
    """:func:`_axis_factors`' ``g`` alone (no derivatives): the same values to the bit."""
    r2 = math.sqrt(2.0) * s
    eb = 0.0
    for n in range(n_px):
        k = k0 + n
        if n > 0:
            ea = eb
        else:
            ea = math.erf((k - 0.5 - c) / r2)
        eb = math.erf((k + 0.5 - c) / r2)
        axes[row, n] = 0.5 * (eb - ea)


@njit(cache=True, inline="always")
def _gauss_cost(residual, y0, ny, x0, nx, p, axes):
    """:func:`_gauss_normal_equations`' cost alone (the same value to the bit), for a step whose normal equations
    are not needed."""
    cx, cy, s, amp, bg = p[0], p[1], p[2], p[3], p[4]
    _axis_values(y0, ny, cy, s, axes, 0)
    _axis_values(x0, nx, cx, s, axes, 3)
    cost = 0.0
    for m in range(ny):
        row = y0 + m
        gym = axes[0, m]
        for n in range(nx):
            r = residual[row, x0 + n] - (amp * axes[3, n] * gym + bg)
            cost += r * r
    return cost


@njit(cache=True, inline="always")
def _gauss_normal_equations(residual, y0, ny, x0, nx, p, jtj, jtr, axes):
    """Cost of the pixel-integrated Gaussian model at ``p`` on the window of rows ``y0 <= y < y0 + ny`` and
    columns ``x0 <= x < x0 + nx``, and its normal equations.

    The model is separable, so the row and column factors are computed once
    per axis, not once per pixel (into the caller's scratch ``axes``: rows 0-2 along y, 3-5 along x); the
    symmetric ``J^T J`` is accumulated once per pair of parameters, in scalars.
    """
    cx, cy, s, amp, bg = p[0], p[1], p[2], p[3], p[4]
    _axis_factors(y0, ny, cy, s, axes, 0)
    _axis_factors(x0, nx, cx, s, axes, 3)
    cost = 0.0
    a00 = a01 = a02 = a03 = a04 = 0.0
    a11 = a12 = a13 = a14 = 0.0
    a22 = a23 = a24 = 0.0
    a33 = a34 = 0.0
    a44 = 0.0
    b0 = b1 = b2 = b3 = b4 = 0.0
    for m in range(ny):
        row = y0 + m
        gym = axes[0, m]
        dyc = axes[1, m]
        dys = axes[2, m]
        for n in range(nx):
            gxn = axes[3, n]
            r = residual[row, x0 + n] - (amp * gxn * gym + bg)
            cost += r * r
            j0 = amp * axes[4, n] * gym
            j1 = amp * gxn * dyc
            j2 = amp * (axes[5, n] * gym + gxn * dys)
            j3 = gxn * gym
            b0 += j0 * r
            b1 += j1 * r
            b2 += j2 * r
            b3 += j3 * r
            b4 += r
            a00 += j0 * j0
            a01 += j0 * j1
            a02 += j0 * j2
            a03 += j0 * j3
            a04 += j0
            a11 += j1 * j1
            a12 += j1 * j2
            a13 += j1 * j3
            a14 += j1
            a22 += j2 * j2
            a23 += j2 * j3
            a24 += j2
            a33 += j3 * j3
            a34 += j3
            a44 += 1.0
    _store_normal(jtj, jtr, a00, a01, a02, a03, a04, a11, a12, a13, a14, a22, a23, a24, a33, a34, a44,
                  b0, b1, b2, b3, b4)
    return cost


@njit(cache=True, inline="always")
def _store_normal(jtj, jtr, a00, a01, a02, a03, a04, a11, a12, a13, a14, a22, a23, a24, a33, a34, a44,
                  b0, b1, b2, b3, b4):
    """Write the 15 distinct sums of a symmetric 5 x 5 ``J^T J`` and the 5 of ``J^T r``."""
    jtj[0, 0] = a00
    jtj[0, 1] = jtj[1, 0] = a01
    jtj[0, 2] = jtj[2, 0] = a02
    jtj[0, 3] = jtj[3, 0] = a03
    jtj[0, 4] = jtj[4, 0] = a04
    jtj[1, 1] = a11
    jtj[1, 2] = jtj[2, 1] = a12
    jtj[1, 3] = jtj[3, 1] = a13
    jtj[1, 4] = jtj[4, 1] = a14
    jtj[2, 2] = a22
    jtj[2, 3] = jtj[3, 2] = a23
    jtj[2, 4] = jtj[4, 2] = a24
    jtj[3, 3] = a33
    jtj[3, 4] = jtj[4, 3] = a34
    jtj[4, 4] = a44
    jtr[0] = b0
    jtr[1] = b1
    jtr[2] = b2
    jtr[3] = b3
    jtr[4] = b4


#: :func:`gaussian_fit`'s stop when its answer is the centroid (a step below it on both axes, pixels).
LM_STOP_PX = 1e-6
#: ... and when it only starts the inverse-variance weighted fit (:mod:`startrack._kernels.psf_fit`), which moves
#: the position on to its own optimum: a thousandth of a pixel, about the best centroid's 1-sigma (a star of 1e6
#: electrons), is start enough.  On the ESA frames it took 10.5 evaluations a star at LM_STOP_PX, 5.7 at this.
LM_START_STOP_PX = 1e-3


@njit(cache=True)
def fit_workspace(width):
    """Scratch of the Gaussian fits for windows up to ``width`` px a side: ``(p, jtj, jtr, jtj2, jtr2, a, delta,
    trial, axes)`` (five-vectors, 5 x 5 matrices and the ``(6, width)`` axis factors).  A caller fitting many
    stars allocates it once (:func:`startrack._kernels.psf_fit.measure_candidates`), not once per fit."""
    return (np.empty(5), np.empty((5, 5)), np.empty(5), np.empty((5, 5)), np.empty(5), np.empty((5, 5)), np.empty(5),
            np.empty(5), np.empty((6, max(width, 1))))


@njit(cache=True, inline="always")
def window_bounds(c, half, n):
    """The window ``|k - round(c)| <= half`` along an axis of ``n`` pixels, clipped to it: ``(first, count)``."""
    ci = int(math.floor(c + 0.5))
    k0 = max(0, ci - half)
    return k0, max(0, min(n, ci + half + 1) - k0)


@njit(cache=True)
def gaussian_fit(residual, x0, y0, sigma0, half, n_iter, stop_px):
    """2-D pixel-integrated Gaussian least squares (Levenberg-Marquardt).

    Model ``A g(x_k; cx, s) g(y_k; cy, s) + B`` on a ``(2 half + 1)^2`` window
    (``g`` as in paper 003 Eq. 5); parameters ``cx, cy, s, A, B``.
    The iterations stop after a step below ``stop_px`` (pixels) on both axes (:data:`LM_STOP_PX` for a
    centroid).  Returns ``(cx, cy, s, A, ok)``.
    """
    return gaussian_fit_in(residual, x0, y0, sigma0, half, n_iter, stop_px, fit_workspace(2 * half + 1))


@njit(cache=True, _nrt=False)
def gaussian_fit_in(residual, x0, y0, sigma0, half, n_iter, stop_px, ws):
    """:func:`gaussian_fit` in the scratch ``ws`` of :func:`fit_workspace` (at least ``2 half + 1`` wide)."""
    p, jtj, jtr, jtj2, jtr2, a, delta, trial, axes = ws
    h, w = residual.shape
    ya, ny = window_bounds(y0, half, h)
    xa, nx = window_bounds(x0, half, w)
    if ny * nx < 9:
        return x0, y0, sigma0, 0.0, False
    tot = 0.0
    for y in range(ya, ya + ny):
        for x in range(xa, xa + nx):
            tot += residual[y, x]
    p[0] = x0
    p[1] = y0
    p[2] = sigma0
    p[3] = max(tot, 1e-9)
    p[4] = 0.0
    cost = _gauss_normal_equations(residual, ya, ny, xa, nx, p, jtj, jtr, axes)
    lam = 1e-3
    ok = False
    for _ in range(n_iter):
        for r in range(5):
            for c in range(5):
                a[r, c] = jtj[r, c]
            delta[r] = jtr[r]
        for d in range(5):
            a[d, d] += lam * (jtj[d, d] + 1e-12)
        if not _solve5_into(a, delta):
            break
        for d in range(5):
            trial[d] = p[d] + delta[d]
        if trial[2] <= 0.2 or trial[2] > 4 * half or trial[3] <= 0:
            lam *= 10.0
            if lam > 1e8:
                break
            continue
        if abs(delta[0]) < stop_px and abs(delta[1]) < stop_px:
            # A step below the convergence tolerance is the last: taken when it lowers the cost, else the minimum
            # is reached, to the precision of the arithmetic (raising the damping up to 1e8 would only repeat the
            # evaluation).  Its cost alone decides; its normal equations would not be used.
            if _gauss_cost(residual, ya, ny, xa, nx, trial, axes) < cost:
                for d in range(5):
                    p[d] = trial[d]
                ok = True
            break
        new_cost = _gauss_normal_equations(residual, ya, ny, xa, nx, trial, jtj2, jtr2, axes)
        if new_cost < cost:
            _accept(p, jtj, jtr, trial, jtj2, jtr2)
            cost = new_cost
            lam = max(lam * 0.3, 1e-9)
            ok = True
        else:
            lam *= 10.0
            if lam > 1e8:
                break
    if abs(p[0] - x0) > half or abs(p[1] - y0) > half:
        return x0, y0, sigma0, 0.0, False
    return p[0], p[1], p[2], p[3], ok


@njit(cache=True, inline="always")
def _accept(p, jtj, jtr, trial, jtj2, jtr2):
    """A fit's accepted step: the trial parameters and their normal equations become the current ones."""
    for r in range(5):
        p[r] = trial[r]
        jtr[r] = jtr2[r]
        for c in range(5):
            jtj[r, c] = jtj2[r, c]


@njit(cache=True, inline="always")
def _mesh_cell(p, cell, n):
    """The two mesh tiles whose centres bracket pixel ``p`` along one axis of ``n`` tiles of ``cell`` pixels, and
    the second one's weight: ``(i0, i1, t)`` of the bilinear background (as ``cv2.resize``), clamped at the edges."""
    f = min(max((p + 0.5) / cell - 0.5, 0.0), n - 1.0)
    i0 = min(int(f), n - 2) if n > 1 else 0
    return i0, min(i0 + 1, n - 1), f - i0


@njit(cache=True, inline="always")
def _mesh_row(mesh, j0, j1, ty, out):
    """``out[i]``: column ``i`` of ``mesh`` between its rows ``j0`` and ``j1`` at weight ``ty``."""
    for i in range(mesh.shape[1]):
        out[i] = mesh[j0, i] * (1.0 - ty) + mesh[j1, i] * ty


@njit(cache=True, inline="always")
def _clipped_sums(row, lim, cn, c1, c2):
    """One residual row into the per-column sums of :func:`subtract_background_rows`' noise: the count, sum and
    sum of squares (the square in the residual's precision) of the values within ``lim`` of zero."""
    for x in range(row.shape[0]):
        v = row[x]
        keep = abs(v) <= lim[x]
        cn[x] += 1.0 if keep else 0.0
        c1[x] += v if keep else 0.0
        c2[x] += v * v if keep else 0.0


@njit(cache=True, inline="always")
def _clipped_add(v, lim, n, s1, s2):
    """``(n, s1, s2)`` with the residual ``v`` added when it is within ``lim`` of zero (the square in the
    residual's precision), as :func:`_clipped_sums` adds it."""
    keep = abs(v) <= lim
    # The value and its square (in the residual's precision) made float64 before the selects: the same numbers,
    # and selects of one width that the compiler vectorises (15 % less time over a frame's four-row groups).
    vd = np.float64(v)
    sq = np.float64(v * v)
    return n + (1.0 if keep else 0.0), s1 + (vd if keep else 0.0), s2 + (sq if keep else 0.0)


@njit(cache=True, inline="always")
def _clipped_sums4(ra, rb, rc, rd, lim, cn, c1, c2):
    """:func:`_clipped_sums` of four rows in turn, in one pass over the columns: each column's sums load and
    store once for the four (a row at a time they were most of the pass), and add the rows in the same order,
    so the same values to the bit."""
    for x in range(ra.shape[0]):
        lx = lim[x]
        n, s1, s2 = _clipped_add(ra[x], lx, cn[x], c1[x], c2[x])
        n, s1, s2 = _clipped_add(rb[x], lx, n, s1, s2)
        n, s1, s2 = _clipped_add(rc[x], lx, n, s1, s2)
        n, s1, s2 = _clipped_add(rd[x], lx, n, s1, s2)
        cn[x] = n
        c1[x] = s1
        c2[x] = s2


@njit(cache=True, nogil=True)
def float32_key_range(bits):
    """The smallest and largest order key of a float32 array's values, from its bits (``bits``: the array's
    ``int32`` view, 1-D): one pass for both, in integer lanes the compiler vectorises (a float minimum cannot be,
    for its NaN rule).

    A value's key is its bits with the magnitude bits flipped when the sign bit is set: keys of finite values
    order as the values do (``-0.0`` just below ``0.0``), ``+inf`` is ``0x7F800000`` and a NaN of either sign lies
    beyond the infinity of its sign (:func:`startrack.centroid._pixel_range` reads them back).
    """
    mask = np.int32(0x7FFFFFFF)
    shift = np.int32(31)
    lo = np.int32(0x7FFFFFFF)
    hi = np.int32(-0x7FFFFFFF - 1)
    for i in range(bits.size):
        b = bits[i]
        k = np.int32(b ^ np.int32(np.int32(b >> shift) & mask))
        lo = np.int32(min(lo, k))
        hi = np.int32(max(hi, k))
    return lo, hi


@njit(cache=True, nogil=True)
def subtract_background_rows(image, level_mesh, threshold_mesh, cell, residual, labels, foreground, row_counts, row0,
                             row1, noise_mesh, kappa, truncated_std, noise_out, band0):
    """:func:`_subtract_rows` without the pixels' range."""
    _subtract_rows(image, level_mesh, threshold_mesh, cell, residual, labels, foreground, row_counts, row0, row1,
                   noise_mesh, kappa, truncated_std, noise_out, band0, np.empty((0, 0), dtype=np.int32), False)


@njit(cache=True, nogil=True)
def subtract_background_rows_keyed(image, level_mesh, threshold_mesh, cell, residual, labels, foreground, row_counts,
                                   row0, row1, noise_mesh, kappa, truncated_std, noise_out, band0, bits):
    """:func:`_subtract_rows` of a float32 ``image`` (``bits``: its ``int32`` view), returning the smallest and
    largest order key of its rows ``row0 <= y < row1`` (:func:`float32_key_range`'s, from the same pass)."""
    return _subtract_rows(image, level_mesh, threshold_mesh, cell, residual, labels, foreground, row_counts, row0,
                          row1, noise_mesh, kappa, truncated_std, noise_out, band0, bits, True)


@njit(cache=True, nogil=True, inline="always")
def _subtract_rows(image, level_mesh, threshold_mesh, cell, residual, labels, foreground, row_counts, row0,
                   row1, noise_mesh, kappa, truncated_std, noise_out, band0, bits, keyed):
    """``residual = image - level`` and the mask ``residual > threshold`` (both maps bilinear between tile centres,
    as ``cv2.resize``) of the rows ``row0 <= y < row1`` into ``residual`` and ``labels`` (``foreground``
    above the threshold, else 0: what :func:`label_blobs_into` labels; no separate mask; ``row_counts[y]`` their
    number in row ``y``), with the pixel noise
    of their mesh tiles in the same pass (independent rows: threads take strips of them).

    When ``noise_out`` has the mesh's shape (else it is empty and ignored), the tile rows wholly inside
    the strip get :func:`startrack._kernels.background.tile_clipped_std`'s one iteration (the residual
    within ``kappa`` times ``noise_mesh`` of zero, its standard deviation divided by ``truncated_std``; a
    tile of fewer than 50 such pixels, or no spread, keeps ``noise_mesh``): the same sums in the same
    order (per column over a tile row's rows, then over a tile's columns), so the same values to the bit,
    when the strip's bounds are tile-row bounds.  The mesh must cover the image (``cell`` times its
    shape at least the image's).

    ``image`` and ``residual`` may be bands of the frame: their row ``y - band0`` is the frame's row ``y`` (0 for
    whole frames); ``labels`` and ``row_counts`` are the whole frame's.

    ``keyed``: ``bits`` is the float32 ``image``'s ``int32`` view, and the smallest and largest order key
    (:func:`float32_key_range`) of the rows' pixels are returned (else ``bits`` is not read).
    """
    h = labels.shape[0]
    w = image.shape[1]
    ny, nx = level_mesh.shape
    kmask = np.int32(0x7FFFFFFF)
    kshift = np.int32(31)
    klo = np.int32(0x7FFFFFFF)
    khi = np.int32(-0x7FFFFFFF - 1)
    noise = noise_out.shape[0] == ny and noise_out.shape[1] == nx
    fg = foreground
    tx = np.empty(w)
    ra = np.empty(w, dtype=np.int64)
    rb = np.empty(w, dtype=np.int64)
    starts = np.empty(w + 1, dtype=np.int64)
    n_runs = 0
    for x in range(w):
        a, b, tx[x] = _mesh_cell(x, cell, nx)
        if n_runs == 0 or a != ra[n_runs - 1]:
            ra[n_runs] = a
            rb[n_runs] = b
            starts[n_runs] = x
            n_runs += 1
    starts[n_runs] = w
    lrow = np.empty(nx)
    trow = np.empty(nx)
    lim = np.empty(w)
    cn = np.zeros(w)
    c1 = np.zeros(w)
    c2 = np.zeros(w)
    icell = int(cell)
    g0 = row0       # the first row not yet in the noise sums (they take a tile row's rows four at a time)
    for y in range(row0, row1):
        j0, j1, ty = _mesh_cell(y, cell, ny)
        _mesh_row(level_mesh, j0, j1, ty, lrow)
        _mesh_row(threshold_mesh, j0, j1, ty, trow)
        count = 0
        jt = y // icell
        if keyed:
            brow = bits[y - band0]
            for x in range(w):
                kb = brow[x]
                kk = np.int32(kb ^ np.int32(np.int32(kb >> kshift) & kmask))
                klo = np.int32(min(klo, kk))
                khi = np.int32(max(khi, kk))
        if noise and (y % icell == 0 or y == row0):
            for x in range(w):
                lim[x] = kappa * noise_mesh[jt, x // icell]
                cn[x] = 0.0
                c1[x] = 0.0
                c2[x] = 0.0
        for k in range(n_runs):
            la = lrow[ra[k]]
            dl = lrow[rb[k]] - la
            ta = trow[ra[k]]
            dt = trow[rb[k]] - ta
            x0 = starts[k]
            x1 = starts[k + 1]
            t_run = tx[x0:x1]
            im_run = image[y - band0, x0:x1]
            res_run = residual[y - band0, x0:x1]
            lab_run = labels[y, x0:x1]
            for q in range(x1 - x0):
                t = t_run[q]
                v = im_run[q] - (la + dl * t)
                res_run[q] = v
                m = 1 if v > ta + dt * t else 0
                lab_run[q] = fg * m
                count += m
        row_counts[y] = count
        if noise and y + 1 - g0 == 4:
            # The last four rows again, from the cache, into the columns' sums: each column's in row order.
            _clipped_sums4(residual[g0 - band0], residual[g0 + 1 - band0], residual[g0 + 2 - band0],
                           residual[g0 + 3 - band0], lim, cn, c1, c2)
            g0 = y + 1
        if noise and ((y + 1) % icell == 0 or y + 1 == h):
            for r in range(g0, y + 1):
                _clipped_sums(residual[r - band0], lim, cn, c1, c2)
            g0 = y + 1
            for i in range(nx):
                n = 0.0
                s1 = 0.0
                s2 = 0.0
                for x in range(i * icell, min(w, (i + 1) * icell)):
                    n += cn[x]
                    s1 += c1[x]
                    s2 += c2[x]
                noise_out[jt, i] = noise_mesh[jt, i]
                if n < 50:
                    continue
                var = (s2 - s1 * s1 / n) / (n - 1)
                if var > 0.0:
                    noise_out[jt, i] = math.sqrt(var) / truncated_std
    return klo, khi


@njit(cache=True)
def label_blobs(residual, mask, image, saturation, max_blobs):
    """Label 8-connected foreground blobs and measure each as it is found.

    Each blob is grown by a depth-first flood fill from its first pixel in
    raster order (the connected-component labelling of paper 000 Fig. 6, done
    sparsely: only foreground pixels are visited twice), and measured on the
    background-subtracted image.  Stops early past ``max_blobs`` blobs.

    Returns ``(labels, table, n)``: ``labels`` int32 (0 = background) and an
    ``(n + 1, 16)`` table per blob: flux, x_com, y_com, peak, peak_x, peak_y,
    npix, mxx, myy, mxy, saturated_pixels, peak-to-3x3 ratio, left, top,
    right, bottom.
    """
    h, w = residual.shape
    fg = np.iinfo(np.int32).max
    labels = np.zeros((h, w), dtype=np.int32)
    counts = np.zeros(h, dtype=np.int64)
    for y in range(h):
        for x in range(w):
            if mask[y, x] != 0:
                labels[y, x] = fg
                counts[y] += 1
    table = np.empty((max_blobs + 1, 16))
    stack = np.empty(min(h * w, 4_000_000), dtype=np.int64)
    n = label_blobs_into(residual, image, saturation, max_blobs, labels, fg, counts, table, stack)
    if n > max_blobs:
        for y in range(h):
            for x in range(w):
                if labels[y, x] == fg:
                    labels[y, x] = 0
    return labels, table, n


@njit(cache=True)
def label_blobs_into(residual, image, saturation, max_blobs, labels, foreground, row_counts, table, stack):
    """:func:`label_blobs` into caller-owned buffers, returning ``n``.

    ``labels`` (the image's shape; an integer type holding ``max_blobs``: uint16 below 65535) holds
    ``foreground`` (above ``max_blobs``) on the pixels to label, 0 elsewhere, on entry (the mask, written by
    :func:`subtract_background_rows`; ``row_counts[y]``, their number in row ``y``: rows without any are not
    scanned, and a row's scan ends at its last; spent: they count down to 0 as the pixels are labelled); on
    return each of those pixels holds its blob's number (some keep
    ``foreground`` when there are more than ``max_blobs`` blobs); ``table``
    needs ``max_blobs + 1`` rows (each row is cleared when its blob is found);
    ``stack`` is scratch.  Reusing the buffers across frames avoids faulting
    ~10 MB of fresh pages per 1024 x 1024 frame.
    """
    return _label_blobs(residual, image, _NO_MESH, 1.0, False, saturation, max_blobs, labels, foreground,
                        row_counts, table, stack)


@njit(cache=True, inline="always")
def _residual_value(residual, image, level_mesh, cell, lazy, y, x):
    """Pixel ``(y, x)`` of the residual: read from ``residual``, or (``lazy``) computed by :func:`residual_at`."""
    if lazy:
        return residual_at(image, level_mesh, cell, y, x)
    return residual[y, x]


#: Stand-ins for the argument the other way of reading the residual does not use (:func:`_label_blobs`).
_NO_MESH = np.zeros((1, 1))
_NO_RESIDUAL = np.zeros((1, 1), dtype=np.float32)


@njit(cache=True)
def _label_blobs(residual, image, level_mesh, cell, lazy, saturation, max_blobs, labels, foreground, row_counts,
                 table, stack):
    """The labelling of :func:`label_blobs_into` (``lazy`` False: the residual read from ``residual``) and of
    :func:`label_blobs_lazy` (``lazy`` True: computed from ``image`` and ``level_mesh``)."""
    h, w = labels.shape
    fg = foreground
    table[0, :] = 0.0
    n = 0
    for y0 in range(h):
        if row_counts[y0] == 0:
            continue
        lrow = labels[y0]
        for x0 in range(w):
            if lrow[x0] != fg:
                if row_counts[y0] == 0:
                    # Every foreground pixel of the row is labelled (row_counts counts down as pixels are
                    # labelled): the rest of the row holds no seed.
                    break
                continue
            n += 1
            if n > max_blobs:
                return n
            labels[y0, x0] = n
            row_counts[y0] -= 1
            top = 0
            stack[top] = y0 * w + x0
            top += 1
            s = 0.0
            sx = 0.0
            sy = 0.0
            sxx = 0.0
            syy = 0.0
            sxy = 0.0
            peak = -1e300
            px = x0
            py = y0
            npix = 0
            nsat = 0
            left = x0
            right = x0
            upper = y0
            lower = y0
            while top > 0:
                top -= 1
                idx = stack[top]
                y = idx // w
                x = idx - y * w
                v = _residual_value(residual, image, level_mesh, cell, lazy, y, x)
                npix += 1
                if image[y, x] >= saturation:
                    nsat += 1
                if v > peak:
                    peak = v
                    px = x
                    py = y
                if v > 0:
                    s += v
                    sx += v * x
                    sy += v * y
                    sxx += v * x * x
                    syy += v * y * y
                    sxy += v * x * y
                left = min(left, x)
                right = max(right, x)
                upper = min(upper, y)
                lower = max(lower, y)
                for dy in range(-1, 2):
                    yy = y + dy
                    if yy < 0 or yy >= h:
                        continue
                    for dx in range(-1, 2):
                        xx = x + dx
                        if xx < 0 or xx >= w or labels[yy, xx] != fg:
                            continue
                        labels[yy, xx] = n
                        row_counts[yy] -= 1
                        if top < stack.shape[0]:
                            stack[top] = yy * w + xx
                            top += 1
            row = table[n]
            row[:] = 0.0
            row[0] = s
            if s > 0:
                cx = sx / s
                cy = sy / s
                row[1] = cx
                row[2] = cy
                row[7] = sxx / s - cx * cx
                row[8] = syy / s - cy * cy
                row[9] = sxy / s - cx * cy
            row[3] = peak
            row[4] = px
            row[5] = py
            row[6] = npix
            row[10] = nsat
            s9 = 0.0
            for yy in range(max(0, py - 1), min(h, py + 2)):
                for xx in range(max(0, px - 1), min(w, px + 2)):
                    s9 += max(_residual_value(residual, image, level_mesh, cell, lazy, yy, xx), 0.0)
            row[11] = peak / s9 if s9 > 0 else 1.0
            row[12] = left
            row[13] = upper
            row[14] = right
            row[15] = lower
    return n


@njit(cache=True, inline="always")
def residual_at(image, level_mesh, cell, y, x):
    """The residual of pixel ``(y, x)``, float32: ``image`` less the bilinear background level, the same
    operations as :func:`subtract_background_rows` (the same value to the bit)."""
    ny, nx = level_mesh.shape
    j0, j1, ty = _mesh_cell(y, cell, ny)
    a, b, t = _mesh_cell(x, cell, nx)
    la = level_mesh[j0, a] * (1.0 - ty) + level_mesh[j1, a] * ty
    dl = (level_mesh[j0, b] * (1.0 - ty) + level_mesh[j1, b] * ty) - la
    return np.float32(image[y, x] - (la + dl * t))


@njit(cache=True, nogil=True)
def residual_rows(image, level_mesh, cell, row0, row1, col0, col1, out):
    """The residual of the frame's rows ``row0 <= y < row1`` and columns ``col0 <= x < col1`` into ``out``
    (``out[y - row0, x - col0]``), the same values to the bit as :func:`subtract_background_rows`' (a band
    of the residual, recomputed where a measurement needs it)."""
    ny, nx = level_mesh.shape
    n = col1 - col0
    tx = np.empty(n)
    ra = np.empty(n, dtype=np.int64)
    rb = np.empty(n, dtype=np.int64)
    for q in range(n):
        ra[q], rb[q], tx[q] = _mesh_cell(col0 + q, cell, nx)
    lrow = np.empty(nx)
    for y in range(row0, row1):
        j0, j1, ty = _mesh_cell(y, cell, ny)
        _mesh_row(level_mesh, j0, j1, ty, lrow)
        im = image[y]
        res = out[y - row0]
        for q in range(n):
            la = lrow[ra[q]]
            res[q] = im[col0 + q] - (la + (lrow[rb[q]] - la) * tx[q])
    return out


@njit(cache=True)
def label_blobs_lazy(image, level_mesh, cell, saturation, max_blobs, labels, foreground, row_counts, table, stack):
    """:func:`label_blobs_into` without a residual image: each residual value read is computed from ``image``
    and the background mesh as :func:`subtract_background_rows` computes it (:func:`residual_at`, the same
    value to the bit), so a frame too large for a whole residual is labelled with its labels alone."""
    return _label_blobs(_NO_RESIDUAL, image, level_mesh, cell, True, saturation, max_blobs, labels, foreground,
                        row_counts, table, stack)


@njit(cache=True)
def clear_labels(labels, table, n):
    """Zero ``labels`` again after :func:`label_blobs_into` (blob bounding boxes only)."""
    for k in range(1, n + 1):
        for y in range(int(table[k, 13]), int(table[k, 15]) + 1):
            for x in range(int(table[k, 12]), int(table[k, 14]) + 1):
                labels[y, x] = 0


@njit(cache=True)
def aperture_flux(residual, x, y, radius):
    """Sum of ``residual`` over pixels whose centres lie within ``radius`` of (x, y); and their count."""
    h, w = residual.shape
    s = 0.0
    n = 0
    r2 = radius * radius
    for yy in range(max(0, int(math.floor(y - radius))), min(h, int(math.ceil(y + radius)) + 1)):
        for xx in range(max(0, int(math.floor(x - radius))), min(w, int(math.ceil(x + radius)) + 1)):
            if (xx - x) ** 2 + (yy - y) ** 2 <= r2:
                s += residual[yy, xx]
                n += 1
    return s, n


@njit(cache=True)
def window_one(image, x_pred, y_pred, half, k_sigma, min_pixels, box):
    """One window of :func:`window_centroids`: ``(x, y, flux, peak, snr, found)``."""
    h, w = image.shape
    if not (np.isfinite(x_pred) and np.isfinite(y_pred)):
        return np.nan, np.nan, 0.0, 0.0, 0.0, False
    xi = int(math.floor(x_pred + 0.5))
    yi = int(math.floor(y_pred + 0.5))
    x0 = max(0, xi - half)
    x1 = min(w - 1, xi + half)
    y0 = max(0, yi - half)
    y1 = min(h - 1, yi + half)
    if x1 - x0 < 4 or y1 - y0 < 4:
        return np.nan, np.nan, 0.0, 0.0, 0.0, False
    nb = 2 * (x1 - x0 + 1) + 2 * (y1 - y0 - 1)
    border = np.empty(nb)
    t = 0
    for x in range(x0, x1 + 1):
        border[t] = image[y0, x]
        border[t + 1] = image[y1, x]
        t += 2
    for y in range(y0 + 1, y1):
        border[t] = image[y, x0]
        border[t + 1] = image[y, x1]
        t += 2
    border.sort()
    bg, noise = core_stats_of_sorted(border)
    if noise <= 0:
        noise = 1.0
    peak = -1e300
    px = -1
    py = -1
    for y in range(y0, y1 + 1):
        for x in range(x0, x1 + 1):
            if image[y, x] > peak:
                peak = image[y, x]
                px = x
                py = y
    if peak - bg < k_sigma * noise:
        return np.nan, np.nan, 0.0, 0.0, 0.0, False
    count = 0
    for y in range(max(0, py - 1), min(h, py + 2)):
        for x in range(max(0, px - 1), min(w, px + 2)):
            if image[y, x] - bg > 0.5 * k_sigma * noise:
                count += 1
    if count < min_pixels:
        return np.nan, np.nan, 0.0, 0.0, 0.0, False
    cx = float(px)
    cy = float(py)
    flux = 0.0
    for _ in range(2):
        sx = 0.0
        sy = 0.0
        s = 0.0
        xc = int(math.floor(cx + 0.5))
        yc = int(math.floor(cy + 0.5))
        for y in range(max(0, yc - box), min(h, yc + box + 1)):
            for x in range(max(0, xc - box), min(w, xc + box + 1)):
                v = image[y, x] - bg
                if v > 0:
                    s += v
                    sx += v * x
                    sy += v * y
        if s <= 0:
            break
        cx = sx / s
        cy = sy / s
        flux = s
    return cx, cy, flux, peak - bg, flux / (noise * 5.0), flux > 0


@njit(cache=True)
def window_centroids(image, xs, ys, half, k_sigma, min_pixels, box):
    """Centroid the brightest star in a square window around each predicted position.

    For each window: the background and noise are the normal core of the
    window's border pixels (:func:`core_stats_of_sorted`: also on a frame clipped at 0); the brightest pixel must exceed
    ``k_sigma`` noise above the background, with at least ``min_pixels`` of
    its 3 x 3 neighbourhood above half that threshold (a hot pixel has none);
    the position is the intensity-weighted centroid over a
    ``(2 box + 1)^2`` box around the peak, iterated once on the new
    centre.  Returns ``(x, y, flux, peak, snr, found)``.
    """
    n = xs.shape[0]
    out_x = np.full(n, np.nan)
    out_y = np.full(n, np.nan)
    out_f = np.zeros(n)
    out_p = np.zeros(n)
    out_s = np.zeros(n)
    found = np.zeros(n, dtype=np.bool_)
    for k in range(n):
        cx, cy, flux, peak, snr, ok = window_one(image, xs[k], ys[k], half, k_sigma, min_pixels, box)
        if peak == 0.0 and not ok:
            continue
        out_x[k] = cx
        out_y[k] = cy
        out_f[k] = flux
        out_p[k] = peak
        out_s[k] = snr
        found[k] = ok
    return out_x, out_y, out_f, out_p, out_s, found


@njit(cache=True)
def split_blob(residual, labels, lab, left, top, bw, bh, min_separation, saddle_ratio, out):
    """Deblend one blob: its local maxima that are separate peaks, written ``(x, y)`` to ``out``; their number.

    A peak is a pixel of the blob above its eight neighbours (outside the blob
    counts as ``-inf``).  Peaks are taken from the highest down; one is kept
    when it lies at least ``min_separation`` px from every peak kept and the
    lowest residual on the straight line to each of them (sampled every half
    pixel, rounded to the nearest pixel) is at most ``saddle_ratio`` times the
    lower of the two peaks.  Fewer than two kept: 0 (not a blend).  ``out``
    holds at most ``out.shape[0]`` peaks.
    """
    npix = 0
    for y in range(top, top + bh):
        for x in range(left, left + bw):
            if labels[y, x] == lab:
                npix += 1
    if npix < 6:
        return 0
    cap = bw * bh
    py = np.empty(cap, dtype=np.int64)
    px = np.empty(cap, dtype=np.int64)
    ph = np.empty(cap)
    m = 0
    h, w = residual.shape
    for y in range(top, top + bh):
        for x in range(left, left + bw):
            if labels[y, x] != lab:
                continue
            v = residual[y, x]
            is_peak = True
            for dy in range(-1, 2):
                for dx in range(-1, 2):
                    if dx == 0 and dy == 0:
                        continue
                    yy = y + dy
                    xx = x + dx
                    if yy < top or yy >= top + bh or xx < left or xx >= left + bw or yy >= h or xx >= w:
                        continue
                    if labels[yy, xx] == lab and not v > residual[yy, xx]:
                        is_peak = False
            if is_peak:
                py[m] = y - top
                px[m] = x - left
                ph[m] = v
                m += 1
    if m < 2:
        return 0
    order = np.argsort(-ph[:m], kind="mergesort")
    kept_x = np.empty(m, dtype=np.int64)
    kept_y = np.empty(m, dtype=np.int64)
    nk = 0
    for k in order:
        ay = py[k]
        ax = px[k]
        ok = True
        for q in range(nk):
            qy = kept_y[q]
            qx = kept_x[q]
            dist = math.hypot(ax - qx, ay - qy)
            if dist < min_separation:
                ok = False
                break
            n = int(math.ceil(dist * 2))
            lowest = np.inf
            for t in range(n + 1):
                yy = int(np.round(ay + (qy - ay) * t / n))
                xx = int(np.round(ax + (qx - ax) * t / n))
                lowest = min(lowest, residual[top + yy, left + xx])
            lim = np.float32(saddle_ratio * min(residual[top + ay, left + ax], residual[top + qy, left + qx]))
            if lowest > lim:
                ok = False
                break
        if ok:
            kept_x[nk] = ax
            kept_y[nk] = ay
            nk += 1
    if nk < 2:
        return 0
    nk = min(nk, out.shape[0])
    for q in range(nk):
        out[q, 0] = left + kept_x[q]
        out[q, 1] = top + kept_y[q]
    return nk


@njit(cache=True)
def annulus_medians(residual, xs, ys, r_in, r_out, out):
    """Median residual in the annulus ``r_in <= r < r_out`` around each ``(xs[k], ys[k])`` (NaN when the annulus
    holds fewer than 8 pixels of the image), into ``out``: what surrounds a detection."""
    h, w = residual.shape
    r2i = r_in * r_in
    r2o = r_out * r_out
    reach = int(math.ceil(r_out))
    buf = np.empty((2 * reach + 1) ** 2)
    for k in range(xs.shape[0]):
        xc = xs[k]
        yc = ys[k]
        xi = int(math.floor(xc + 0.5))
        yi = int(math.floor(yc + 0.5))
        m = 0
        for y in range(max(0, yi - reach), min(h, yi + reach + 1)):
            dy2 = (y - yc) * (y - yc)
            for x in range(max(0, xi - reach), min(w, xi + reach + 1)):
                d2 = (x - xc) * (x - xc) + dy2
                if r2i <= d2 < r2o:
                    v = residual[y, x]
                    if np.isfinite(v):
                        buf[m] = v
                        m += 1
        out[k] = np.median(buf[:m]) if m >= 8 else np.nan
    return out


@njit(cache=True)
def unique_positions(xs, ys, radii, keep):
    """``keep[k]`` False for a position within ``radii[k]`` of an earlier kept one (positions in priority order).

    Kept positions are found through a grid of 8 px cells (at most 2048 a side: positions beyond share the
    edge cells, which only adds pairs to test), so the cost grows with the positions, not their square.
    """
    n = xs.shape[0]
    if n == 0:
        return keep
    cell = 8.0
    gx0 = math.floor(xs.min() / cell)
    gy0 = math.floor(ys.min() / cell)
    gw = int(min(math.floor(xs.max() / cell) - gx0 + 1, 2048))
    gh = int(min(math.floor(ys.max() / cell) - gy0 + 1, 2048))
    head = np.full(gw * gh, -1, dtype=np.int64)
    nxt = np.empty(n, dtype=np.int64)
    for k in range(n):
        x = xs[k]
        y = ys[k]
        r2 = radii[k] * radii[k]
        gx = int(min(max(math.floor(x / cell) - gx0, 0), gw - 1))
        gy = int(min(max(math.floor(y / cell) - gy0, 0), gh - 1))
        reach = int(radii[k] // cell) + 1
        dup = False
        for iy in range(max(gy - reach, 0), min(gy + reach, gh - 1) + 1):
            for ix in range(max(gx - reach, 0), min(gx + reach, gw - 1) + 1):
                j = head[iy * gw + ix]
                while j >= 0:
                    dx = x - xs[j]
                    dy = y - ys[j]
                    if dx * dx + dy * dy <= r2:
                        dup = True
                        break
                    j = nxt[j]
                if dup:
                    break
            if dup:
                break
        keep[k] = not dup
        if not dup:
            c = gy * gw + gx
            nxt[k] = head[c]
            head[c] = k
    return keep
