"""Centroid accuracy studies: single rendered stars against the Cramer-Rao bound.

Used by the benchmarks (the accuracy table of ``make bench``) and the tests.
Signal-to-noise ratio is defined in electrons as
``SNR = F / sqrt(F + 4 pi s^2 (B + r^2))``: the star's total signal ``F``
against its own shot noise and the noise of the pixels of an optimal aperture
(``4 pi s^2`` pixels for a Gaussian of sigma ``s``) with background ``B`` and
read noise ``r`` per pixel.
"""
from __future__ import annotations

import math

import numpy as np

__all__ = ["accuracy_trials", "cramer_rao_bound", "flux_for_snr", "render_single_star"]


def flux_for_snr(snr: float, sigma_psf: float, noise_var_e: float) -> float:
    """Total electrons giving ``snr`` (solves ``F^2 = snr^2 (F + 4 pi s^2 v)``)."""
    a = snr * snr
    c = 4.0 * math.pi * sigma_psf**2 * noise_var_e
    return 0.5 * (a + math.sqrt(a * a + 4.0 * a * c))


def _pixel_fractions(centre, sigma, n):
    edges = np.arange(n + 1) - 0.5
    cdf = 0.5 * (1.0 + np.array([math.erf((e - centre) / (math.sqrt(2.0) * sigma)) for e in edges]))
    return np.diff(cdf)


def cramer_rao_bound(flux_e: float, sigma_psf: float, background_e: float, read_noise_e: float,
                     x0: float = 0.0, y0: float = 0.0, half: int | None = None) -> float:
    """Cramer-Rao lower bound (px, 1 sigma) on the x position of a pixel-integrated Gaussian star.

    Fisher information ``I_xx = sum_k (d mu_k / d x)^2 / (mu_k + B + r^2)``
    over the pixels, with ``mu_k`` the expected electrons of pixel ``k``
    (Poisson shot noise of star and background plus Gaussian read noise
    approximated as Poisson-like variance).  Flux and background are taken as
    known, which makes this the tightest form of the bound.
    """
    half = half or math.ceil(6 * sigma_psf) + 2
    n = 2 * half + 1
    cx = half + x0
    cy = half + y0
    fx = _pixel_fractions(cx, sigma_psf, n)
    fy = _pixel_fractions(cy, sigma_psf, n)
    edges = np.arange(n + 1) - 0.5
    dens = np.exp(-((edges - cx) ** 2) / (2 * sigma_psf**2)) / (math.sqrt(2 * math.pi) * sigma_psf)
    dfx = -(dens[1:] - dens[:-1])  # d/dcx of the pixel fraction
    mu = flux_e * np.outer(fy, fx)
    dmu = flux_e * np.outer(fy, dfx)
    info = float(np.sum(dmu**2 / (mu + background_e + read_noise_e**2)))
    return 1.0 / math.sqrt(info)


def render_single_star(rng, flux_e, sigma_psf, background_e, read_noise_e, size=33, offset=(0.0, 0.0)):
    """A ``size`` x ``size`` float image (electrons) of one star at centre + offset, with noise."""
    from startrack._kernels.render import add_stars

    signal = np.zeros((size, size))
    c = (size - 1) / 2.0
    x, y = c + offset[0], c + offset[1]
    add_stars(signal, np.array([[x]]), np.array([[y]]), np.array([float(flux_e)]), float(sigma_psf))
    lam = signal + background_e
    img = rng.poisson(lam).astype(np.float64) + rng.normal(0.0, read_noise_e, lam.shape) if read_noise_e > 0 \
        else rng.poisson(lam).astype(np.float64)
    return img, (x, y)


def accuracy_trials(method: str, snr: float, sigma_psf: float, n: int, rng, background_e: float = 100.0,
                    read_noise_e: float = 5.0, psf_known: bool = False):
    """RMS per-axis centroid error (px) of ``method`` on ``n`` random sub-pixel phases.

    Returns ``(rms_error, crb, detected_fraction)`` where ``crb`` is the mean
    per-axis Cramer-Rao bound over the same phases.
    """
    from startrack.centroid import CentroidOptions, find_stars

    noise_var = background_e + read_noise_e**2
    flux = flux_for_snr(snr, sigma_psf, noise_var)
    opts = CentroidOptions(method=method, threshold_sigma=3.0, background="global", min_pixels=2,
                           deblend=False, psf_sigma_px=sigma_psf if psf_known else None, max_elongation=10.0,
                           hot_pixel_ratio=1.1, gain_e_per_dn=1.0)
    errors = []
    bounds = []
    found = 0
    for _ in range(n):
        off = rng.uniform(-0.5, 0.5, 2)
        img, (tx, ty) = render_single_star(rng, flux, sigma_psf, background_e, read_noise_e, offset=off)
        res = find_stars(img, opts, saturation=1e12)
        bounds.append(cramer_rao_bound(flux, sigma_psf, background_e, read_noise_e, off[0], off[1]))
        if not res.stars:
            continue
        best = min(res.stars, key=lambda s: (s["x"] - tx) ** 2 + (s["y"] - ty) ** 2)
        if math.hypot(best["x"] - tx, best["y"] - ty) > 3 * sigma_psf:
            continue
        found += 1
        errors.extend([best["x"] - tx, best["y"] - ty])
    rms = math.sqrt(float(np.mean(np.square(errors)))) if errors else float("nan")
    return rms, float(np.mean(bounds)), found / n
