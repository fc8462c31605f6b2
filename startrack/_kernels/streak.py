"""Streak (line-segment PSF) fitting kernels: see :mod:`startrack.streak` for the model and its equations."""
import math

import numpy as np
from numba import njit

_SQRT2 = math.sqrt(2.0)
_INV_SQRT_2PI = 1.0 / math.sqrt(2.0 * math.pi)
N_PARAMS = 7     # cx, cy, l (half length), theta, flux, background, sigma
N_OUT = 14       # cx, cy, l, theta, flux, bg, sigma, sig_cx, sig_cy, sig_l, sig_theta, chi2_dof, n_pix, ok


@njit(cache=True, inline="always")
def _phi(z):
    return _INV_SQRT_2PI * math.exp(-0.5 * z * z)


@njit(cache=True, inline="always")
def _cdf(z):
    return 0.5 * (1.0 + math.erf(z / _SQRT2))


@njit(cache=True)
def _model(px, py, p, grad):
    """Segment PSF at pixel (px, py) and its gradient w.r.t. the 7 parameters (paper-free: see startrack.streak)."""
    cx, cy, l, th, f, b, s = p[0], p[1], p[2], p[3], p[4], p[5], p[6]
    ux = math.cos(th)
    uy = math.sin(th)
    rx = px - cx
    ry = py - cy
    a = rx * ux + ry * uy          # along the streak
    d = -rx * uy + ry * ux         # across it
    g = _INV_SQRT_2PI / s * math.exp(-0.5 * d * d / (s * s))
    zp = (a + l) / s
    zm = (a - l) / s
    e = _cdf(zp) - _cdf(zm)
    inv2l = 0.5 / l
    core = g * e * inv2l           # profile for unit flux
    i = f * core
    pp = _phi(zp)
    pm = _phi(zm)
    di_da = f * g * inv2l * (pp - pm) / s
    di_dd = -i * d / (s * s)
    # d/d cx: a = r.u, d = r.n, r = p - c
    grad[0] = -(di_da * ux - di_dd * uy)
    grad[1] = -(di_da * uy + di_dd * ux)
    grad[2] = f * g * inv2l * (pp + pm) / s - i / l
    grad[3] = di_da * d + di_dd * (-a)
    grad[4] = core
    grad[5] = 1.0
    grad[6] = i * (d * d / (s * s * s) - 1.0 / s) + f * g * inv2l * (-pp * zp / s + pm * zm / s)
    return i + b


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


@njit(cache=True, inline="always")
def _signal(image, x, y, x0, x1, y0, y1, thr):
    """A pixel above the threshold with at least two of its 8 neighbours above it too (not lone noise)."""
    if image[y, x] <= thr:
        return False
    c = 0
    for yy in range(max(y0, y - 1), min(y1, y + 1) + 1):
        for xx in range(max(x0, x - 1), min(x1, x + 1) + 1):
            if (xx != x or yy != y) and image[yy, xx] > thr:
                c += 1
    return c >= 2


@njit(cache=True)
def _accumulate(pxs, pys, vals, npx, p, grad, jtj, jtr):
    """Sum of squared residuals at ``p``, and the normal equations ``J^T J``, ``J^T r``."""
    jtj[:, :] = 0.0
    jtr[:] = 0.0
    cost = 0.0
    for i in range(npx):
        r = vals[i] - _model(pxs[i], pys[i], p, grad)
        cost += r * r
        for a_ in range(N_PARAMS):
            jtr[a_] += grad[a_] * r
            for b_ in range(a_ + 1):
                jtj[a_, b_] += grad[a_] * grad[b_]
    for a_ in range(N_PARAMS):
        for b_ in range(a_):
            jtj[b_, a_] = jtj[a_, b_]
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
    bg = np.median(border)
    noise = 1.4826 * np.median(np.abs(border - bg))
    if noise <= 0.0:
        noise = max(1e-3, math.sqrt(max(bg, 1.0)) * 0.01)
    thr = bg + k_sigma * noise
    s0 = 0.0
    sx = 0.0
    sy = 0.0
    touches = False
    for y in range(y0, y1 + 1):
        for x in range(x0, x1 + 1):
            if _signal(image, x, y, x0, x1, y0, y1, thr):
                # Only the signal counts: weight by (value - background) above the threshold.
                wgt = image[y, x] - bg
                s0 += wgt
                sx += wgt * x
                sy += wgt * y
                if x == x0 or x == x1 or y == y0 or y == y1:
                    touches = True
    if s0 <= 0.0:
        return False, bg, noise, xc, yc, 0.5, 0.0, 0.0, False
    mx = sx / s0
    my = sy / s0
    sxx = 0.0
    syy = 0.0
    sxy = 0.0
    for y in range(y0, y1 + 1):
        for x in range(x0, x1 + 1):
            if _signal(image, x, y, x0, x1, y0, y1, thr):
                wgt = image[y, x] - bg
                sxx += wgt * (x - mx) * (x - mx)
                syy += wgt * (y - my) * (y - my)
                sxy += wgt * (x - mx) * (y - my)
    sxx /= s0
    syy /= s0
    sxy /= s0
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
        cost = _accumulate(pxs, pys, vals, npx, p, grad, jtj, jtr)
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
            # One pass gives the trial's cost and, if it is accepted, its normal equations.
            c2 = _accumulate(pxs, pys, vals, npx, trial, grad, jtj2, jtr2)
            if c2 <= cost:
                rel = (cost - c2) / max(cost, 1e-300)
                p[:] = trial
                cost = c2
                jtj[:, :] = jtj2
                jtr[:] = jtr2
                lam = max(lam * 0.3, 1e-7)
                fails = 0
                if rel < 1e-6 or (abs(step[0]) < 1e-3 and abs(step[1]) < 1e-3 and abs(step[2]) < 1e-3):
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
        # bright core noisier than the wings, so the homoscedastic (J^T J)^-1 s^2 would be too small).
        meat = np.zeros((N_PARAMS, N_PARAMS))
        for i in range(npx):
            r = vals[i] - _model(pxs[i], pys[i], p, grad)
            r2 = r * r
            for a_ in range(N_PARAMS):
                for b_ in range(N_PARAMS):
                    meat[a_, b_] += r2 * grad[a_] * grad[b_]
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
    h, w = image.shape
    n = xs.shape[0]
    for k in range(n):
        out[k, 0] = np.nan
        out[k, 1] = np.nan
        out[k, 2] = 0.0
        out[k, 3] = np.nan
        out[k, 4] = 0.0
        cx = xs[k]
        cy = ys[k]
        hx = hxs[k]
        hy = hys[k]
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
            continue
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
        bg = np.median(border)
        noise = 1.4826 * np.median(np.abs(border - bg))
        r2 = radius * radius
        good = True
        sw = 0.0
        for _ in range(iters):
            sw = 0.0
            sx = 0.0
            sy = 0.0
            for y in range(y0, y1 + 1):
                for x in range(x0, x1 + 1):
                    rx = x - cx
                    ry = y - cy
                    a = rx * ux + ry * uy
                    a = max(-l, min(l, a))
                    dx = rx - a * ux
                    dy = ry - a * uy
                    if dx * dx + dy * dy <= r2:
                        v = image[y, x] - bg
                        sw += v
                        sx += v * x
                        sy += v * y
            if sw <= 0.0:
                good = False
                break
            cx = sx / sw
            cy = sy / sw
        if not good:
            continue
        s2 = 0.0
        for y in range(y0, y1 + 1):
            for x in range(x0, x1 + 1):
                rx = x - cx
                ry = y - cy
                a = rx * ux + ry * uy
                a = max(-l, min(l, a))
                dx = rx - a * ux
                dy = ry - a * uy
                if dx * dx + dy * dy <= r2:
                    s2 += 0.5 * (rx * rx + ry * ry)
        out[k, 0] = cx
        out[k, 1] = cy
        out[k, 2] = sw
        out[k, 3] = math.sqrt(s2) * noise / sw
        out[k, 4] = 1.0
