"""Rendering kernels: pixel-integrated Gaussian stars and the sensor's noise.

Random numbers come from a counter-based generator (SplitMix64 keyed by the
frame seed and the row), so an image is the same bytes whatever the number of
threads, and rows can be drawn in parallel.
"""
import math

import numpy as np

from startrack._kernels._jit import njit, prange

_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_M1 = np.uint64(0xBF58476D1CE4E5B9)
_M2 = np.uint64(0x94D049BB133111EB)
_S30 = np.uint64(30)
_S27 = np.uint64(27)
_S31 = np.uint64(31)
_S11 = np.uint64(11)
_INV53 = 1.0 / 9007199254740992.0


@njit(cache=True, inline="always")
def _mix(z):
    z = (z ^ (z >> _S30)) * _M1
    z = (z ^ (z >> _S27)) * _M2
    return z ^ (z >> _S31)


@njit(cache=True, inline="always")
def _uniform(state):
    """Next uniform in (0, 1) from a one-element uint64 state array."""
    state[0] += _GOLDEN
    return ((_mix(state[0]) >> _S11) + 0.5) * _INV53


@njit(cache=True)
def _normal(state):
    u1 = _uniform(state)
    u2 = _uniform(state)
    return math.sqrt(-2.0 * math.log(u1)) * math.cos(2.0 * math.pi * u2)


@njit(cache=True)
def _poisson(state, lam):
    """Poisson deviate: inversion below 10, Hormann's PTRS rejection above."""
    if lam <= 0.0:
        return 0.0
    if lam < 10.0:
        u = _uniform(state)
        p = math.exp(-lam)
        cdf = p
        k = 0
        while u > cdf and k < 1000:
            k += 1
            p *= lam / k
            cdf += p
        return float(k)
    slam = math.sqrt(lam)
    loglam = math.log(lam)
    b = 0.931 + 2.53 * slam
    a = -0.059 + 0.02483 * b
    invalpha = 1.1239 + 1.1328 / (b - 3.4)
    vr = 0.9277 - 3.6224 / (b - 2.0)
    while True:
        u = _uniform(state) - 0.5
        v = _uniform(state)
        us = 0.5 - abs(u)
        k = math.floor((2.0 * a / us + b) * u + lam + 0.43)
        if us >= 0.07 and v <= vr:
            return k
        if k < 0.0 or (us < 0.013 and v > us):
            continue
        if (math.log(v) + math.log(invalpha) - math.log(a / (us * us) + b)
                <= -lam + k * loglam - math.lgamma(k + 1.0)):
            return k


@njit(cache=True)
def _pixel_fractions(centre, sigma, lo, n, out):
    """Fraction of a 1-D Gaussian falling in pixels lo..lo+n-1 (paper 003 Eq. 5)."""
    inv = 1.0 / (math.sqrt(2.0) * sigma)
    prev = math.erf((lo - 0.5 - centre) * inv)
    for i in range(n):
        cur = math.erf((lo + i + 0.5 - centre) * inv)
        out[i] = 0.5 * (cur - prev)
        prev = cur


@njit(cache=True)
def add_stars(signal, xs, ys, electrons, sigma):
    """Add pixel-integrated Gaussian stars to ``signal`` (electrons).

    ``xs``, ``ys`` have shape ``(n_stars, n_sub)``: each star's positions at
    ``n_sub`` instants of the exposure (one for a still camera; many along a
    smear trail), each carrying ``electrons[s] / n_sub``.  The Gaussian is
    integrated over each pixel's area with the error function (paper 003
    Eqs. 4-5), not sampled at pixel centres.
    """
    height, width = signal.shape
    n_stars, n_sub = xs.shape
    half = int(math.ceil(5.0 * sigma)) + 1
    fx = np.empty(2 * half + 1)
    fy = np.empty(2 * half + 1)
    for s in range(n_stars):
        e = electrons[s] / n_sub
        if e <= 0.0:
            continue
        for t in range(n_sub):
            x = xs[s, t]
            y = ys[s, t]
            x0 = int(math.floor(x + 0.5)) - half
            y0 = int(math.floor(y + 0.5)) - half
            if x0 + 2 * half < 0 or y0 + 2 * half < 0 or x0 >= width or y0 >= height:
                continue
            _pixel_fractions(x, sigma, x0, 2 * half + 1, fx)
            _pixel_fractions(y, sigma, y0, 2 * half + 1, fy)
            for j in range(2 * half + 1):
                row = y0 + j
                if row < 0 or row >= height:
                    continue
                wy = fy[j] * e
                for i in range(2 * half + 1):
                    col = x0 + i
                    if col < 0 or col >= width:
                        continue
                    signal[row, col] += wy * fx[i]


@njit(cache=True, parallel=True)
def expose(signal, out, background_cdf, background_guide, background_lo, background_e, prnu, full_well,
           read_noise, gain, bias, max_dn, seed, with_noise):
    """Turn expected electrons into digital numbers, with the sensor's noise.

    ``signal`` holds the expected electrons per pixel above ``background_e``,
    the flat sky + dark of every pixel: stars and hot pixels, and the
    nuisances' departures from the flat sky, which may be negative (the sky
    behind a dark foreground body, a vignetted corner).  A pixel
    with no such signal (exactly 0) draws its DN straight from ``background_cdf``, the
    exact distribution of ``round((Poisson(background_e) + N(0, read_noise)) /
    gain + bias)`` (one uniform deviate and a guide-table look-up: Chen &
    Asau's indexed search, ``background_guide[b]`` being the first entry with
    ``cdf >= b / len(guide)``); any other pixel is
    drawn in full: Poisson photo-electrons, PRNU gain, full-well clipping, read
    noise, gain, bias, quantisation and clipping to ``[0, max_dn]``.
    ``prnu`` is empty or a per-pixel relative gain map; with it every pixel
    takes the full path.
    """
    height, width = signal.shape
    n_guide = background_guide.shape[0]
    has_prnu = prnu.shape[0] == height
    for row in prange(height):
        state = np.empty(1, dtype=np.uint64)
        state[0] = _mix(np.uint64(seed) * np.uint64(0x2545F4914F6CDD1D) + np.uint64(row) + np.uint64(1))
        for col in range(width):
            s = signal[row, col]
            if not with_noise:
                e = min(s + background_e, full_well)
                dn = math.floor(e / gain + bias + 0.5)
            elif s == 0.0 and not has_prnu:
                u = _uniform(state)
                i = background_guide[int(u * n_guide)]
                while background_cdf[i] < u:
                    i += 1
                dn = background_lo + i
            else:
                e = _poisson(state, s + background_e)
                if has_prnu:
                    e *= prnu[row, col]
                e = min(e, full_well) + read_noise * _normal(state)
                dn = math.floor(e / gain + bias + 0.5)
            if dn < 0.0:
                dn = 0.0
            elif dn > max_dn:
                dn = max_dn
            out[row, col] = dn


@njit(cache=True)
def background_cdf(upper, pk, kmin, rn):
    """``out[i] = sum_j pk[j] Phi((upper[i] - kmin - j) / rn)``: P(Poisson count + read noise < upper[i]).

    Counts more than 9 read-noise sigmas below ``upper[i]`` add their whole probability (a
    running sum), those more than 9 sigmas above none; only the band between is evaluated.
    ``rn == 0``: the counts below ``upper[i]`` exactly.
    """
    n = upper.size
    m = pk.size
    cum = np.empty(m + 1)
    cum[0] = 0.0
    for j in range(m):
        cum[j + 1] = cum[j] + pk[j]
    out = np.empty(n)
    if rn <= 0.0:
        for i in range(n):
            a = int(math.ceil(upper[i] - kmin))     # counts kmin + j < upper[i]
            out[i] = cum[min(max(a, 0), m)]
        return out
    w = 9.0 * rn
    s2 = math.sqrt(2.0) * rn
    for i in range(n):
        u = upper[i] - kmin
        a = min(max(int(math.ceil(u - w)), 0), m)
        b = min(max(int(math.floor(u + w)) + 1, a), m)
        acc = cum[a]
        for j in range(a, b):
            acc += pk[j] * 0.5 * (1.0 + math.erf((u - j) / s2))
        out[i] = acc
    return out
