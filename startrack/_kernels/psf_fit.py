"""Weighted pixel-integrated Gaussian fit: the centroid that reaches the Cramér-Rao bound (issue 21).

The unweighted least-squares fit (``_kernels.centroid.gaussian_fit``) gives
every pixel the same weight; with shot noise a bright star's core pixels are
noisier than its wings, and the unweighted fit loses up to ~25 % in accuracy
against the bound (``startrack.accuracy``).  Weighting each pixel by the
inverse of its own variance, ``mu_k / g + n^2`` (DN^2: the star's shot noise at
gain ``g`` e/DN plus the background noise ``n``), and iterating the weights
with the model (iteratively reweighted least squares) gives the
maximum-likelihood estimate under the Gaussian approximation of the noise,
which is efficient: its covariance reaches the bound ``I^-1`` of
``startrack.accuracy.centroid_crb`` (Kay 1993, Sec. 7.5).
"""
import math

from startrack._kernels._jit import njit
from startrack._kernels.centroid import (
    LM_START_STOP_PX,
    LM_STOP_PX,
    _accept,
    _axis_factors,
    _solve5_into,
    _store_normal,
    aperture_flux,
    fit_workspace,
    gaussian_fit_in,
    window_bounds,
    windowed_centroid,
)

#: The weighted fit's stop (pixels): a step below it on both axes.  A hundredth of the best centroid's 1-sigma
#: (about 1e-3 px, a star of 1e6 electrons); the steps shrink by a factor of a few each iteration, so what is left
#: is of the same order, far below any star's noise.  1e-7 took 8.4 evaluations a star on an ESA frame, this 5.8.
IRLS_STOP_PX = 1e-5


@njit(cache=True, inline="always")
def _weighted_normal_equations(residual, y0, ny, x0, nx, p, noise_var, inv_gain, jtj, jtr, axes):
    cx, cy, s, amp, bg = p[0], p[1], p[2], p[3], p[4]
    # The axis factors in the caller's scratch (rows 0-2 along y, 3-5 along x): no allocation per evaluation.
    _axis_factors(y0, ny, cy, s, axes, 0)
    _axis_factors(x0, nx, cx, s, axes, 3)
    cost = 0.0
    a00 = a01 = a02 = a03 = a04 = 0.0
    a11 = a12 = a13 = a14 = 0.0
    a22 = a23 = a24 = 0.0
    a33 = a34 = 0.0
    a44 = 0.0
    b0 = b1 = b2 = b3 = b4 = 0.0
    # The symmetric J^T W J accumulated once per pair of parameters, in scalars.
    for m in range(ny):
        row = y0 + m
        gym = axes[0, m]
        dyc = axes[1, m]
        dys = axes[2, m]
        for n in range(nx):
            gxn = axes[3, n]
            model = amp * gxn * gym
            w = 1.0 / (max(model, 0.0) * inv_gain + noise_var)
            r = residual[row, x0 + n] - (model + bg)
            cost += w * r * r
            j0 = amp * axes[4, n] * gym
            j1 = amp * gxn * dyc
            j2 = amp * (axes[5, n] * gym + gxn * dys)
            j3 = gxn * gym
            w0 = w * j0
            w1 = w * j1
            w2 = w * j2
            w3 = w * j3
            b0 += w0 * r
            b1 += w1 * r
            b2 += w2 * r
            b3 += w3 * r
            b4 += w * r
            a00 += w0 * j0
            a01 += w0 * j1
            a02 += w0 * j2
            a03 += w0 * j3
            a04 += w0
            a11 += w1 * j1
            a12 += w1 * j2
            a13 += w1 * j3
            a14 += w1
            a22 += w2 * j2
            a23 += w2 * j3
            a24 += w2
            a33 += w3 * j3
            a34 += w3
            a44 += w
    _store_normal(jtj, jtr, a00, a01, a02, a03, a04, a11, a12, a13, a14, a22, a23, a24, a33, a34, a44,
                  b0, b1, b2, b3, b4)
    return cost


@njit(cache=True)
def weighted_gaussian_fit(residual, x0, y0, s0, amp0, half, noise_var, inv_gain, n_iter):
    """Inverse-variance weighted fit of ``A g(x; cx, s) g(y; cy, s) + B`` (paper 003 Eq. 5).

    Parameters
    ----------
    residual : 2-D float array
        Background-subtracted image (DN).
    x0, y0, s0, amp0 : float
        Starting point (e.g. the unweighted fit): position (px), PSF sigma
        (px), total flux (DN).
    half : int
        Half-size of the square window (px).
    noise_var : float
        Background noise variance per pixel (DN^2).
    inv_gain : float
        ``1 / g`` (DN per electron) for the star's shot noise; 0 when unknown.
    n_iter : int
        Gauss-Newton iterations (weights recomputed from the model each time;
        Levenberg damping when a step does not lower the cost).

    Returns
    -------
    (cx, cy, s, A, ok, cov_xx, cov_xy, cov_yy, chi2, n_pix)
        ``cov_*`` (px^2) is the position block of the inverse of the weighted
        normal matrix ``J^T W J`` at the solution: the fit's own covariance (the
        inverse Fisher information of the five parameters over the window's
        pixels, so a star cut by the image edge, or one whose PSF width and
        local background must be estimated alongside, gets the larger sigma it
        really has).  ``chi2`` is the weighted residual sum ``sum w r^2`` over
        the ``n_pix`` pixels: ``chi-square(n_pix - 5)`` when the model holds
        (a second star in the window, a truncated or non-Gaussian PSF raise it).
    """
    return weighted_gaussian_fit_in(residual, x0, y0, s0, amp0, half, noise_var, inv_gain, n_iter,
                                    fit_workspace(2 * half + 1))


@njit(cache=True, _nrt=False)
def weighted_gaussian_fit_in(residual, x0, y0, s0, amp0, half, noise_var, inv_gain, n_iter, ws):
    """:func:`weighted_gaussian_fit` in the scratch ``ws`` of :func:`startrack._kernels.centroid.fit_workspace`
    (at least ``2 half + 1`` wide)."""
    p, jtj, jtr, jtj2, jtr2, a, delta, trial, axes = ws
    h, w = residual.shape
    ya, ny = window_bounds(y0, half, h)
    xa, nx = window_bounds(x0, half, w)
    nan = math.nan
    n_pix = ny * nx
    if n_pix < 9 or not noise_var > 0.0 or not amp0 > 0.0:
        return x0, y0, s0, amp0, False, nan, nan, nan, nan, n_pix
    p[0] = x0
    p[1] = y0
    p[2] = s0
    p[3] = amp0
    p[4] = 0.0
    cost = _weighted_normal_equations(residual, ya, ny, xa, nx, p, noise_var, inv_gain, jtj, jtr, axes)
    lam = 1e-4
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
        new_cost = _weighted_normal_equations(residual, ya, ny, xa, nx, trial, noise_var, inv_gain, jtj2, jtr2, axes)
        # The weights move with the model, so the cost is compared at the new weights (IRLS).
        if new_cost <= cost * (1.0 + 1e-9) or lam < 1e-3:
            _accept(p, jtj, jtr, trial, jtj2, jtr2)
            cost = new_cost
            lam = max(lam * 0.3, 1e-9)
            ok = True
            if abs(delta[0]) < IRLS_STOP_PX and abs(delta[1]) < IRLS_STOP_PX:
                break
        else:
            # A step below the convergence tolerance that does not lower the cost: the minimum, to the
            # precision of the arithmetic (raising the damping up to 1e8 would only repeat the evaluation).
            if abs(delta[0]) < IRLS_STOP_PX and abs(delta[1]) < IRLS_STOP_PX:
                break
            lam *= 10.0
            if lam > 1e8:
                break
    if abs(p[0] - x0) > 1.0 or abs(p[1] - y0) > 1.0:
        return x0, y0, s0, amp0, False, nan, nan, nan, nan, n_pix
    # The weighted normal matrix at the accepted solution (jtj, from its weights) inverted, a column at a time in
    # the scratch: the position block of the estimate's covariance.
    c00 = c10 = c01 = c11 = 0.0
    for c in range(2):
        for r in range(5):
            for q in range(5):
                a[r, q] = jtj[r, q]
            delta[r] = 0.0
        delta[c] = 1.0
        if not _solve5_into(a, delta):
            return p[0], p[1], p[2], p[3], False, nan, nan, nan, nan, n_pix
        if c == 0:
            c00 = delta[0]
            c10 = delta[1]
        else:
            c01 = delta[0]
            c11 = delta[1]
    return p[0], p[1], p[2], p[3], ok, c00, 0.5 * (c01 + c10), c11, cost, n_pix


@njit(cache=True, inline="always")
def _wide_enough(ws, half, h, w):
    """``ws``, or a new :func:`startrack._kernels.centroid.fit_workspace` when its axis factors are narrower than a
    window of ``half`` px on an ``h x w`` image."""
    need = min(2 * half + 1, max(h, w))
    return ws if ws[8].shape[1] >= need else fit_workspace(need)


@njit(cache=True, nogil=True)
def measure_candidates(residual, cand, psf_sigma, noise_mesh, cell, quant_var, inv_gain, out):
    """Centroid and photometry of every candidate blob in one call (:func:`startrack.centroid.find_stars`,
    method ``gauss``): per candidate, the unweighted Gaussian fit, then the inverse-variance weighted fit
    started from it (or the windowed centroid for a deblended peak), then the aperture flux.

    ``cand`` rows: ``x, y, PSF sigma estimate (px), deblended (0/1)``; ``psf_sigma`` > 0 overrides the
    estimate; ``noise_mesh`` is the per-tile pixel noise (DN) on tiles of ``cell`` px, to which the
    variance ``quant_var`` (DN^2: the rounding of an integer image) is added.  ``out`` rows
    receive ``x, y, PSF sigma, weighted fit accepted (0/1), cov_xx, cov_xy, cov_yy, chi2, n_pix,
    aperture flux, aperture pixels, noise (DN)``.
    """
    h, w = residual.shape
    ny, nx = noise_mesh.shape
    # The fits' scratch, once per call (widened when a window needs it): no allocation per candidate.
    ws = fit_workspace(min(max(h, w), 31))
    for k in range(cand.shape[0]):
        cx = cand[k, 0]
        cy = cand[k, 1]
        if not (math.isfinite(cx) and math.isfinite(cy) and math.isfinite(cand[k, 2])):
            # A blob of infinite pixels (an infinity in a float frame, spread by the matched filter) has no
            # position: no star (flux 0), and no window read at an undefined place.
            out[k, :] = 0.0
            continue
        sigma_psf = psf_sigma if psf_sigma > 0 else max(0.5, min(cand[k, 2], 5.0))
        half = int(max(2, math.ceil(3 * sigma_psf)))
        x = cx
        y = cy
        ok = True
        out[k, 3] = 0.0
        if cand[k, 3] != 0:
            x, y, ok = windowed_centroid(residual, cx, cy, sigma_psf, half, 30)
        else:
            # The unweighted fit only starts the weighted one (LM_START_STOP_PX), which moves on to its optimum.
            ws = _wide_enough(ws, half, h, w)
            x, y, s_fit, amp, ok = gaussian_fit_in(residual, cx, cy, sigma_psf, half, 50, LM_START_STOP_PX, ws)
            if ok and math.isfinite(x) and math.isfinite(y):
                sigma_psf = s_fit
                xc = min(max(x, 0.0), w - 1.0)
                yc = min(max(y, 0.0), h - 1.0)
                nv = math.sqrt(noise_mesh[min(int(yc) // cell, ny - 1), min(int(xc) // cell, nx - 1)] ** 2
                               + quant_var) ** 2
                half_w = max(half, int(math.ceil(3.5 * s_fit)))
                ws = _wide_enough(ws, half_w, h, w)
                wx, wy, w_s, _, wok, cxx, cxy, cyy, chi2, n_pix = weighted_gaussian_fit_in(
                    residual, x, y, s_fit, amp, half_w, nv, inv_gain, 30, ws)
                if wok and cxx > 0 and cyy > 0 and cxx * cyy > cxy * cxy:
                    x = wx
                    y = wy
                    sigma_psf = w_s
                    out[k, 3] = 1.0
                    out[k, 4] = cxx
                    out[k, 5] = cxy
                    out[k, 6] = cyy
                    out[k, 7] = chi2
                    out[k, 8] = n_pix
                else:
                    # No weighted fit: the unweighted one is the centroid, carried on to its own precision.
                    x2, y2, s2, _, ok2 = gaussian_fit_in(residual, x, y, s_fit, half, 50, LM_STOP_PX, ws)
                    if ok2 and math.isfinite(x2) and math.isfinite(y2) and abs(x2 - cx) <= half \
                            and abs(y2 - cy) <= half:
                        x = x2
                        y = y2
                        sigma_psf = s2
        if not ok or not (math.isfinite(x) and math.isfinite(y)):
            x = cx
            y = cy
        r = max(2.0, 3.0 * sigma_psf)
        flux, n_ap = aperture_flux(residual, x, y, r)
        xc = min(max(x, 0.0), w - 1.0)
        yc = min(max(y, 0.0), h - 1.0)
        out[k, 0] = x
        out[k, 1] = y
        out[k, 2] = sigma_psf
        out[k, 9] = flux
        out[k, 10] = n_ap
        out[k, 11] = math.sqrt(noise_mesh[min(int(yc) // cell, ny - 1), min(int(xc) // cell, nx - 1)] ** 2
                               + quant_var)
    return out
