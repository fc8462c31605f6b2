"""Streak (line-segment PSF) fitting kernels: see :mod:`startrack.streak` for the model and its equations."""
import math

import numpy as np

from startrack._kernels._jit import njit
from startrack._kernels.background import core_stats_of_sorted

_SQRT2 = math.sqrt(2.0)
_INV_SQRT_2PI = 1.0 / math.sqrt(2.0 * math.pi)
N_PARAMS = 7     # cx, cy, l (half length), theta, flux, background, sigma
STEP_TOL = 0.05  # converged: the last step in position, length and direction below this many sigma
STEP_ABS_PX = 0.01  # ... and below 0.01 px in position and length
STEP_ABS_ANGLE = 1e-3  # ... and 1 mrad in direction
N_OUT = 14       # cx, cy, l, theta, flux, bg, sigma, sig_cx, sig_cy, sig_l, sig_theta, chi2_dof, n_pix, ok


@njit(cache=True, inline="always")
def _phi(z):
    return _INV_SQRT_2PI * math.exp(-0.5 * z * z)


@njit(cache=True, inline="always")
def _cdf(z):
    return 0.5 * (1.0 + math.erf(z / _SQRT2))


_Z_FLAT = 6.0    # beyond 6 sigma Phi is 0 or 1 and phi is 0 to 1e-8 of the peak: not evaluated


@njit(cache=True, inline="always")
def _edge(z):
    """``(Phi(z), phi(z))``, with the far tails (``|z| > 6``) taken as exactly flat."""
    if z > _Z_FLAT:
        return 1.0, 0.0
    if z < -_Z_FLAT:
        return 0.0, 0.0
    return _cdf(z), _phi(z)


@njit(cache=True)
def _small_step(jtj, step, cost, npx, tol):
    """True when the last step in ``cx``, ``cy``, ``l`` (px) and ``theta`` (rad) was below both ``tol``
    times their 1-sigma (``(J^T J)^-1 cost / dof``) and an absolute ``STEP_ABS`` (0.01 px, 0.001 rad):
    converged to a small fraction of the parameters' own uncertainty, and not merely slow on a
    parameter the data hardly constrain (a short streak's length)."""
    s2 = cost / max(npx - N_PARAMS, 1)
    for a_ in range(4):
        lim = STEP_ABS_ANGLE if a_ == 3 else STEP_ABS_PX
        if abs(step[a_]) > lim:
            return False
    for a_ in range(4):
        e = np.zeros(N_PARAMS)
        e[a_] = 1.0
        col, good = _solve(jtj, e, N_PARAMS)
        if not good or step[a_] * step[a_] > tol * tol * col[a_] * s2:
            return False
    return True


@njit(cache=True)
def _solve(a, b, n):
    """Solve a x = b (n x n, symmetric positive definite) by Cholesky; returns (x, ok)."""
    lo = np.zeros((n, n))
    for i in range(n):
        for j in range(i + 1):
            acc = a[i, j]
            for k in range(j):
                acc -= lo[i, k] * lo[j, k]
            if i == j:
                if acc <= 0.0:
                    return np.zeros(n), False
                lo[i, i] = math.sqrt(acc)
            else:
                lo[i, j] = acc / lo[j, j]
    y = np.zeros(n)
    for i in range(n):
        acc = b[i]
        for k in range(i):
            acc -= lo[i, k] * y[k]
        y[i] = acc / lo[i, i]
    x = np.zeros(n)
    for i in range(n - 1, -1, -1):
        acc = y[i]
        for k in range(i + 1, n):
            acc -= lo[k, i] * x[k]
        x[i] = acc / lo[i, i]
    return x, True


@njit(cache=True, fastmath=True)
def _accumulate(pxs, pys, vals, npx, p, grad, jtj, jtr, meat):
    """Eq. (1) of :mod:`startrack.streak` at parameters ``p`` on the fit's pixels: the sum of squared
    residuals, the normal equations ``J^T J``, ``J^T r`` (analytic Jacobian) and the sandwich estimator's
    middle term ``sum r_i^2 J_i J_i^T``.

    Parameters ``p = cx, cy, l, theta, F, B, s``.  With ``a``, ``d`` the pixel's offsets along and across
    the segment, ``g = exp(-d^2 / 2 s^2) / (sqrt(2 pi) s)``, ``z+- = (a +- l) / s``:
    ``I = B + F g [Phi(z+) - Phi(z-)] / 2 l``.
    """
    cx, cy, l, th, f, b, s = p[0], p[1], p[2], p[3], p[4], p[5], p[6]
    ux = math.cos(th)
    uy = math.sin(th)
    inv_s = 1.0 / s
    inv_s2 = inv_s * inv_s
    inv2l = 0.5 / l
    inv_l = 1.0 / l
    jtj[:, :] = 0.0
    jtr[:] = 0.0
    meat[:, :] = 0.0
    cost = 0.0
    for i in range(npx):
        rx = pxs[i] - cx
        ry = pys[i] - cy
        a = rx * ux + ry * uy          # along the streak
        d = -rx * uy + ry * ux         # across it
        g = _INV_SQRT_2PI * inv_s * math.exp(-0.5 * d * d * inv_s2)
        zp = (a + l) * inv_s
        zm = (a - l) * inv_s
        cp, pp = _edge(zp)
        cm, pm = _edge(zm)
        core = g * (cp - cm) * inv2l   # profile for unit flux
        val = f * core
        fg = f * g * inv2l * inv_s
        di_da = fg * (pp - pm)
        di_dd = -val * d * inv_s2
        # d/d cx: a = r.u, d = r.n, r = p - c
        grad[0] = -(di_da * ux - di_dd * uy)
        grad[1] = -(di_da * uy + di_dd * ux)
        grad[2] = fg * (pp + pm) - val * inv_l
        grad[3] = di_da * d - di_dd * a
        grad[4] = core
        grad[5] = 1.0
        grad[6] = val * inv_s * (d * d * inv_s2 - 1.0) - fg * (pp * zp - pm * zm)
        r = vals[i] - (val + b)
        r2 = r * r
        cost += r2
        for a_ in range(N_PARAMS):
            ga = grad[a_]
            jtr[a_] += ga * r
            for b_ in range(a_ + 1):
                gg = ga * grad[b_]
                jtj[a_, b_] += gg
                meat[a_, b_] += r2 * gg
    for a_ in range(N_PARAMS):
        for b_ in range(a_):
            jtj[b_, a_] = jtj[a_, b_]
            meat[b_, a_] = meat[a_, b_]
    return cost


@njit(cache=True)
def _moments(image, xc, yc, half, k_sigma):
    """Background, noise and the thresholded second moments in a box: the fit's starting point.

    Returns (ok, bg, noise, mx, my, l, theta, flux, touches_border).
    """
    h, w = image.shape
    xi = int(math.floor(xc + 0.5))
    yi = int(math.floor(yc + 0.5))
    x0 = max(0, xi - half)
    x1 = min(w - 1, xi + half)
    y0 = max(0, yi - half)
    y1 = min(h - 1, yi + half)
    if x1 - x0 < 4 or y1 - y0 < 4:
        return False, 0.0, 0.0, xc, yc, 0.5, 0.0, 0.0, False
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
    bg, noise = core_stats_of_sorted(border)     # the normal core: also on a frame clipped at 0
    if noise <= 0.0:
        noise = max(1e-3, math.sqrt(max(bg, 1.0)) * 0.01)
    thr = bg + k_sigma * noise
    # Pixels above the threshold (one pass over the box), then the signal among them: those with at
    # least two of their 8 neighbours (inside the box) above it too, not lone noise.
    nx = x1 - x0 + 1
    ny = y1 - y0 + 1
    above = np.zeros((ny + 2, nx + 2), dtype=np.uint8)
    n_above = 0
    for y in range(y0, y1 + 1):
        for x in range(x0, x1 + 1):
            if image[y, x] > thr:
                above[y - y0 + 1, x - x0 + 1] = 1
                n_above += 1
    s0 = 0.0
    sx = 0.0
    sy = 0.0
    sxx = 0.0
    syy = 0.0
    sxy = 0.0
    touches = False
    if n_above > 0:
        for j in range(1, ny + 1):
            for i in range(1, nx + 1):
                if above[j, i] == 0:
                    continue
                c = (above[j - 1, i - 1] + above[j - 1, i] + above[j - 1, i + 1] + above[j, i - 1]
                     + above[j, i + 1] + above[j + 1, i - 1] + above[j + 1, i] + above[j + 1, i + 1])
                if c < 2:
                    continue
                # Only the signal counts: weight by (value - background) above the threshold; raw moments
                # about the box's corner.
                wgt = image[y0 + j - 1, x0 + i - 1] - bg
                xr = float(i - 1)
                yr = float(j - 1)
                s0 += wgt
                sx += wgt * xr
                sy += wgt * yr
                sxx += wgt * xr * xr
                syy += wgt * yr * yr
                sxy += wgt * xr * yr
                if i == 1 or i == nx or j == 1 or j == ny:
                    touches = True
    if s0 <= 0.0:
        return False, bg, noise, xc, yc, 0.5, 0.0, 0.0, False
    mxr = sx / s0
    myr = sy / s0
    sxx = sxx / s0 - mxr * mxr
    syy = syy / s0 - myr * myr
    sxy = sxy / s0 - mxr * myr
    mx = x0 + mxr
    my = y0 + myr
    tr = sxx + syy
    disc = math.sqrt(max(0.25 * (sxx - syy) * (sxx - syy) + sxy * sxy, 0.0))
    l1 = 0.5 * tr + disc
    l2 = max(0.5 * tr - disc, 0.0)
    theta = 0.5 * math.atan2(2.0 * sxy, sxx - syy)
    # A uniform segment of half length l has variance l^2 / 3 along it.
    length = math.sqrt(max(3.0 * (l1 - l2), 0.0))
    return True, bg, noise, mx, my, max(length, 0.3), theta, s0, touches


@njit(cache=True)
def fit_streaks(image, xs, ys, l0s, th0s, half0, max_half, psf_sigma, k_sigma, max_iter, out):
    """Fit a line-segment PSF to the streak near each ``(xs[k], ys[k])``; results in ``out[k, :N_OUT]``.

    Start: the thresholded moments in a box of half-size ``half0`` (doubled,
    up to ``max_half``, while the streak touches the box's border).  Fit:
    Levenberg-Marquardt on the pixels within ``3 sigma + 2`` px of the
    starting segment; parameters ``cx, cy`` (mid-exposure position), ``l``
    (half length), ``theta`` (direction), flux, background and PSF sigma.
    Where ``l0s[k]`` is finite the start is given instead: centre
    ``(xs[k], ys[k])``, half length ``l0s[k]``, direction ``th0s[k]`` (a streak
    predicted from a known rate: faint streaks whose pixels are too few above
    the threshold for the moments).
    Uncertainties: the sandwich estimator ``(J^T J)^-1 (sum r^2 J J^T) (J^T J)^-1``
    (right under shot noise, whose variance grows with the signal).  ``out[k, 13]`` is 1 when the fit converged.
    """
    h, w = image.shape
    n = xs.shape[0]
    p = np.empty(N_PARAMS)
    trial = np.empty(N_PARAMS)
    grad = np.empty(N_PARAMS)
    jtj = np.empty((N_PARAMS, N_PARAMS))
    jtr = np.empty(N_PARAMS)
    jtj2 = np.empty((N_PARAMS, N_PARAMS))
    jtr2 = np.empty(N_PARAMS)
    meat = np.empty((N_PARAMS, N_PARAMS))
    meat2 = np.empty((N_PARAMS, N_PARAMS))
    for k in range(n):
        out[k, :] = np.nan
        out[k, 13] = 0.0
        half = half0
        if np.isfinite(l0s[k]):
            half = min(max_half, int(math.ceil(l0s[k] + 3.0 * psf_sigma + 4.0)))
            ok, bg, noise, mx, my, l0, th0, f0, touches = _moments(image, xs[k], ys[k], half, k_sigma)
            if noise <= 0.0:
                continue
            mx, my, l0, th0, f0, ok = xs[k], ys[k], max(l0s[k], 0.3), th0s[k], 0.0, True
        else:
            ok, bg, noise, mx, my, l0, th0, f0, touches = _moments(image, xs[k], ys[k], half, k_sigma)
            while ok and touches and half < max_half:
                half = min(2 * half, max_half)
                ok, bg, noise, mx, my, l0, th0, f0, touches = _moments(image, mx, my, half, k_sigma)
        if not ok:
            continue
        # Pixels near the starting segment.
        reach = l0 + 3.0 * psf_sigma + 3.0
        x0 = max(0, int(math.floor(mx - reach)))
        x1 = min(w - 1, int(math.ceil(mx + reach)))
        y0 = max(0, int(math.floor(my - reach)))
        y1 = min(h - 1, int(math.ceil(my + reach)))
        margin = 3.0 * psf_sigma + 2.0
        ux0 = math.cos(th0)
        uy0 = math.sin(th0)
        npx = 0
        cap = (x1 - x0 + 1) * (y1 - y0 + 1)
        pxs = np.empty(cap)
        pys = np.empty(cap)
        vals = np.empty(cap)
        for y in range(y0, y1 + 1):
            for x in range(x0, x1 + 1):
                rx = x - mx
                ry = y - my
                a = rx * ux0 + ry * uy0
                a = max(-l0, min(l0, a))
                dx = rx - a * ux0
                dy = ry - a * uy0
                if dx * dx + dy * dy <= margin * margin:
                    pxs[npx] = x
                    pys[npx] = y
                    vals[npx] = image[y, x]
                    npx += 1
        if npx <= N_PARAMS + 2:
            continue
        # Total flux from the pixels (a better start than the thresholded sum).
        ftot = 0.0
        for i in range(npx):
            ftot += vals[i] - bg
        p[0] = mx
        p[1] = my
        p[2] = l0
        p[3] = th0
        p[4] = max(ftot, f0)
        p[5] = bg
        p[6] = psf_sigma
        lam = 1e-3
        cost = _accumulate(pxs, pys, vals, npx, p, grad, jtj, jtr, meat)
        converged = False
        fails = 0
        for _ in range(max_iter):
            damped = jtj.copy()
            for a_ in range(N_PARAMS):
                damped[a_, a_] = jtj[a_, a_] * (1.0 + lam) + 1e-12
            step, good = _solve(damped, jtr, N_PARAMS)
            if not good:
                lam *= 10.0
                fails += 1
                if fails > 8:
                    break
                continue
            for a_ in range(N_PARAMS):
                trial[a_] = p[a_] + step[a_]
            trial[2] = max(trial[2], 0.05)
            trial[6] = min(max(trial[6], 0.3), 10.0)
            # One pass gives the trial's cost and, if it is accepted, its normal equations (and the
            # covariance's middle term).
            c2 = _accumulate(pxs, pys, vals, npx, trial, grad, jtj2, jtr2, meat2)
            if c2 <= cost:
                rel = (cost - c2) / max(cost, 1e-300)
                p[:] = trial
                cost = c2
                jtj[:, :] = jtj2
                jtr[:] = jtr2
                meat[:, :] = meat2
                lam = max(lam * 0.3, 1e-7)
                fails = 0
                if rel < 1e-6 or _small_step(jtj, step, cost, npx, STEP_TOL):
                    converged = True
                    break
            else:
                lam *= 10.0
                fails += 1
                if fails > 8:
                    converged = True      # no step lowers the cost: a minimum to the precision of the data
                    break
        if not (p[4] > 0.0) or not converged:
            continue
        # Covariance at the solution: the sandwich (Huber-White) estimator
        # (J^T J)^-1 (sum r_i^2 J_i J_i^T) (J^T J)^-1, valid whatever the noise model (shot noise makes the
        # bright core noisier than the wings, so the homoscedastic (J^T J)^-1 s^2 would be too small);
        # ``meat`` was summed in the pass that evaluated ``p``.
        dof = npx - N_PARAMS
        s2 = cost / dof
        inv = np.zeros((N_PARAMS, N_PARAMS))
        good_inv = True
        for a_ in range(N_PARAMS):
            e = np.zeros(N_PARAMS)
            e[a_] = 1.0
            col, good = _solve(jtj, e, N_PARAMS)
            if not good:
                good_inv = False
                break
            inv[:, a_] = col
        sig = np.full(4, np.nan)
        if good_inv:
            for a_ in range(4):
                acc = 0.0
                for b_ in range(N_PARAMS):
                    for c_ in range(N_PARAMS):
                        acc += inv[a_, b_] * meat[b_, c_] * inv[c_, a_]
                acc *= npx / dof
                if acc > 0.0:
                    sig[a_] = math.sqrt(acc)
        th = p[3]
        # theta in (-pi/2, pi/2]: a streak has no sign.
        while th > 0.5 * math.pi:
            th -= math.pi
        while th <= -0.5 * math.pi:
            th += math.pi
        out[k, 0] = p[0]
        out[k, 1] = p[1]
        out[k, 2] = p[2]
        out[k, 3] = th
        out[k, 4] = p[4]
        out[k, 5] = p[5]
        out[k, 6] = p[6]
        out[k, 7] = sig[0]
        out[k, 8] = sig[1]
        out[k, 9] = sig[2]
        out[k, 10] = sig[3]
        out[k, 11] = s2 / (noise * noise)
        out[k, 12] = npx
        out[k, 13] = 1.0


@njit(cache=True, inline="always")
def _interval(k, c, lim):
    """``{x : |k x + c| <= lim}`` as ``(lo, hi)`` (empty when ``lo > hi``; all x when ``k`` is 0 and ``|c| <= lim``)."""
    if abs(k) < 1e-12:
        return (-1e300, 1e300) if abs(c) <= lim else (1.0, -1.0)
    a = (-lim - c) / k
    b = (lim - c) / k
    return (a, b) if a <= b else (b, a)


@njit(cache=True)
def _capsule_row(y, cx, cy, ux, uy, l, r):
    """The columns ``x`` of row ``y`` within ``r`` of the segment ``(cx, cy) +- l (ux, uy)``: an interval
    (the capsule is convex), the hull of its two end discs and its slab; ``(lo, hi)``, empty when ``lo > hi``."""
    lo = 1e300
    hi = -1e300
    for sgn in (-1.0, 1.0):
        ex = cx + sgn * l * ux
        ey = cy + sgn * l * uy
        dy = y - ey
        if dy * dy <= r * r:
            h = math.sqrt(r * r - dy * dy)
            lo = min(lo, ex - h)
            hi = max(hi, ex + h)
    # Slab: |d| <= r across, |a| <= l along, both linear in x on the row.
    d_lo, d_hi = _interval(-uy, uy * cx + ux * (y - cy), r)
    a_lo, a_hi = _interval(ux, -ux * cx + uy * (y - cy), l)
    s_lo = max(d_lo, a_lo)
    s_hi = min(d_hi, a_hi)
    if s_lo <= s_hi:
        lo = min(lo, s_lo)
        hi = max(hi, s_hi)
    return lo, hi


@njit(cache=True)
def segment_one(image, x_start, y_start, hx, hy, radius, iters):
    """One streak of :func:`segment_centroids`: ``(x, y, flux, sigma_px, ok)``."""
    h, w = image.shape
    cx = x_start
    cy = y_start
    l = math.sqrt(hx * hx + hy * hy)
    ux = hx / l if l > 1e-9 else 1.0
    uy = hy / l if l > 1e-9 else 0.0
    reach_x = abs(hx) + radius + 3.0
    reach_y = abs(hy) + radius + 3.0
    x0 = max(0, int(math.floor(cx - reach_x)))
    x1 = min(w - 1, int(math.ceil(cx + reach_x)))
    y0 = max(0, int(math.floor(cy - reach_y)))
    y1 = min(h - 1, int(math.ceil(cy + reach_y)))
    if x1 - x0 < 4 or y1 - y0 < 4:
        return np.nan, np.nan, 0.0, np.nan, False
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
    bg, noise = core_stats_of_sorted(border)     # the normal core: also on a frame clipped at 0
    r2 = radius * radius
    sw = 0.0
    sx = 0.0
    sy = 0.0
    # Each pass visits only the columns of each row that the capsule can cover (its exact test decides).
    s2 = 0.0
    for it in range(iters + 1):
        if it < iters:
            sw = 0.0
            sx = 0.0
            sy = 0.0
        for y in range(y0, y1 + 1):
            lo, hi = _capsule_row(float(y), cx, cy, ux, uy, l, radius)
            if lo > hi:
                continue
            xa = max(x0, int(math.floor(lo)) - 1)
            xb = min(x1, int(math.ceil(hi)) + 1)
            for x in range(xa, xb + 1):
                rx = x - cx
                ry = y - cy
                a = rx * ux + ry * uy
                a = max(-l, min(l, a))
                dx = rx - a * ux
                dy = ry - a * uy
                if dx * dx + dy * dy <= r2:
                    if it == iters:
                        s2 += 0.5 * (rx * rx + ry * ry)
                    else:
                        v = image[y, x] - bg
                        sw += v
                        sx += v * x
                        sy += v * y
        if it == iters:
            break
        if sw <= 0.0:
            return np.nan, np.nan, 0.0, np.nan, False
        cx = sx / sw
        cy = sy / sw
    if sw <= 0.0:
        return np.nan, np.nan, 0.0, np.nan, False
    return cx, cy, sw, math.sqrt(s2) * noise / sw, True


@njit(cache=True)
def segment_centroids(image, xs, ys, hxs, hys, radius, iters, out):
    """Intensity-weighted centroid of each streak inside a capsule aperture (the tracking-mode fast path).

    The aperture is every pixel within ``radius`` of the segment
    ``(x, y) +- (hx, hy)`` (the streak the known rate predicts), re-centred on
    the centroid ``iters`` times; a uniform streak is symmetric about its
    middle, so the fixed point is the mid-exposure position.  Background and
    noise: median and 1.4826 MAD of the surrounding box's border.  ``out[k]`` =
    ``x, y, flux, sigma_px, ok`` with ``sigma_px`` the background-noise
    centroid uncertainty ``sqrt(sum (x_i - x)^2) * noise / flux`` (per axis,
    averaged).
    """
    for k in range(xs.shape[0]):
        x, y, flux, sig, ok = segment_one(image, xs[k], ys[k], hxs[k], hys[k], radius, iters)
        out[k, 0] = x
        out[k, 1] = y
        out[k, 2] = flux
        out[k, 3] = sig
        out[k, 4] = 1.0 if ok else 0.0
