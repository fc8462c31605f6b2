"""Smear-aware centroiding: line-segment PSF fits, and the angular rate from one frame's streaks.

A star seen by a rotating camera moves across the sensor during the exposure
and leaves a streak.  At a constant rate over the exposure ``T`` the star runs
at constant speed along a (nearly straight) segment of length ``L`` centred on
its position at **mid-exposure**, so the streak is a Gaussian PSF swept
uniformly along that segment.  With ``a`` the coordinate along the segment
(direction ``theta``) and ``d`` the distance across it, both from the centre
``(cx, cy)``, and ``l = L / 2``:

.. math::

    I(a, d) = B + \\frac{F}{2 l} \\, \\frac{e^{-d^2 / 2 s^2}}{\\sqrt{2 \\pi} s}
              \\left[\\Phi\\left(\\frac{a + l}{s}\\right) - \\Phi\\left(\\frac{a - l}{s}\\right)\\right]       (1)

(``Phi`` the standard normal distribution function), which tends to the
Gaussian PSF as ``l -> 0``.  The renderer integrates the Gaussian over each
pixel's area; Eq. (1) is evaluated at the pixel centre with a fitted width
``s``, which absorbs the pixel's box (``s^2 ~ sigma_psf^2 + 1/12``) and keeps
the model symmetric about the centre, so the mid-exposure position is unbiased
(the residual shape difference is below the noise; see tests/test_streak.py).

The 7 parameters ``cx, cy, l, theta, F, B, s`` are fitted by
Levenberg-Marquardt with analytic derivatives (numba kernel
:func:`startrack._kernels.streak.fit_streaks`) on the pixels within
``3 sigma + 2`` px of the segment found by thresholded second moments.  The
1-sigma uncertainties come from the sandwich (Huber-White) estimator
``(J^T J)^{-1} (sum_i r_i^2 J_i J_i^T) (J^T J)^{-1}``, which holds whatever the
noise model (shot noise makes the bright core noisier than the wings).

**Rate from one frame.**  A star at camera-frame direction ``b`` moves as
``db/dt = b x w`` for a body rate ``w`` (the attitude obeys
``A(t) = exp(-[w x] t) A``).  Its image moves by ``v = M w T`` pixels over the
exposure, ``M = (d pixel / d b) [b x]`` (2 x 3, from the camera model, lens
distortion included by finite differences).  A streak measures ``v`` up to its
sign: ``+-(2 l cos theta, 2 l sin theta)``.  :func:`rate_from_streaks`

1. finds the direction of ``w`` from the sign-free constraints
   ``n_i^T M_i w = 0`` (``n_i`` across streak ``i``): the right singular vector
   of the stacked, weighted rows with the smallest singular value;
2. picks each streak's sign to agree with ``M_i w``, and solves the weighted
   least squares ``min sum_i |s_i v_i - M_i w T|^2_{C_i^{-1}}`` for ``w``
   (``C_i`` the streak vector's covariance, from the fit), repeating the sign
   choice until it no longer changes; the streak farthest off the fit
   (more than 4 sigma, the sigmas scaled by the fit's own scatter measured
   robustly: the median chi-square) is dropped and the fit repeated, while
   more than 3 remain.

Cross-boresight rates come from the common motion of the streaks, the rate
about the boresight from how their directions turn across the field (a roll
sweeps stars around the centre; near the centre it moves them little, so the
roll rate is the least well determined).  A single frame cannot tell ``w``
from ``-w`` (a streak has no arrow of time): the result is ``+-w``; the
tracker resolves the sign with the next frame.

**Why the roll rate is weak.**  A cross-boresight rate moves every star by
``f w T`` pixels; a roll rate moves a star at distance ``r`` from the
principal point by ``r w_z T``, tangentially.  With the same streak-vector
noise on every star, the least squares above (which already weighs each
streak by its fitted length and direction sigmas, and whose covariance is
reported) gives ``sigma_z / sigma_xy ~ f / r_rms``; stars spread evenly over
a ``W x H`` sensor have ``r_rms = sqrt((W^2 + H^2) / 12)``, so for a 12 deg,
1024 x 768 camera ``f / r_rms = 4871 / 370 = 13``: roughly ``1 / tan(FOV/2)``.
No model of one frame's streaks escapes this lever arm; the attitude
differences of consecutive frames (the tracker's filter) measure the roll
rate with the full roll accuracy of the attitude instead.

**Partial streaks.**  A faint streak's thresholded moments may see only a
piece of it, and the fit started there converges on that piece: a streak
off the common motion.  :func:`refit_off_motion` fits such streaks (and
missing or insignificant ones) again from the streak the frame's rate
predicts, and the rate is estimated again.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["RateEstimate", "Streak", "fit_streaks", "fit_streaks_array", "predicted_streaks", "rate_from_streaks",
           "refit_off_motion", "segment_centroids", "streak_jacobians", "streak_residuals"]


@dataclass
class Streak:
    """One fitted streak (pixels, radians)."""

    x: float
    y: float
    sigma_x: float
    sigma_y: float
    length_px: float
    sigma_length_px: float
    angle_rad: float
    sigma_angle_rad: float
    flux: float
    background: float
    psf_sigma_px: float
    chi2_dof: float

    def as_star(self) -> dict:
        """A ``stars`` entry (mid-exposure position, its sigma, and the streak)."""
        sig = math.sqrt(0.5 * (self.sigma_x ** 2 + self.sigma_y ** 2))
        return {"x": self.x, "y": self.y, "flux": self.flux, "sigma_px": sig,
                "streak": {"length_px": self.length_px, "angle_deg": math.degrees(self.angle_rad),
                           "sigma_length_px": self.sigma_length_px,
                           "sigma_angle_deg": math.degrees(self.sigma_angle_rad)}}


def fit_streaks(image, xs, ys, psf_sigma_px: float = 1.0, half_px: int = 8, max_half_px: int = 128,
                k_sigma: float = 3.0, max_iter: int = 30, lengths_px=None, angles_rad=None):
    """Fit Eq. (1) to the streak around each start position.

    Parameters
    ----------
    image : ndarray (height, width)
        The frame (DN).
    xs, ys : array_like
        Start positions (px), e.g. detections or predictions; the streak is
        sought in a box of half-size ``half_px`` (doubled up to ``max_half_px``
        while it reaches the box's edge).
    psf_sigma_px : float
        Starting PSF width (px); fitted.
    k_sigma : float
        Threshold (background noise units) of the moments that start the fit.
    lengths_px, angles_rad : array_like, optional
        Predicted streak lengths and directions (e.g. from a known rate,
        :func:`predicted_streaks`); where finite they start the fit instead of
        the moments (faint streaks).

    Returns
    -------
    list of Streak or None
        ``None`` where no fit converged.
    """

    img = np.ascontiguousarray(image, dtype=np.float32)
    out = fit_streaks_array(img, xs, ys, psf_sigma_px, half_px, max_half_px, k_sigma, max_iter, lengths_px, angles_rad)
    return [_streak(row) for row in out]


def fit_streaks_array(image, xs, ys, psf_sigma_px=1.0, half_px=8, max_half_px=128, k_sigma=3.0, max_iter=30,
                      lengths_px=None, angles_rad=None):
    """:func:`fit_streaks` returning the raw ``(n, 14)`` array (for speed in loops)."""
    from startrack._kernels.streak import N_OUT
    from startrack._kernels.streak import fit_streaks as kernel

    xs = np.ascontiguousarray(xs, dtype=np.float64).reshape(-1)
    ys = np.ascontiguousarray(ys, dtype=np.float64).reshape(-1)
    n = len(xs)
    l0 = np.full(n, np.nan) if lengths_px is None else 0.5 * np.asarray(lengths_px, dtype=np.float64).reshape(-1)
    th0 = np.zeros(n) if angles_rad is None else np.asarray(angles_rad, dtype=np.float64).reshape(-1)
    out = np.empty((n, N_OUT))
    kernel(np.ascontiguousarray(image, dtype=np.float32), xs, ys, np.ascontiguousarray(l0), np.ascontiguousarray(th0),
           int(half_px), int(max_half_px), float(psf_sigma_px), float(k_sigma), int(max_iter), out)
    return out


def segment_centroids(image, xs, ys, lengths_px, angles_rad, radius_px: float = 4.0, iters: int = 3):
    """Mid-exposure positions of streaks of known shape by a capsule-aperture centroid (tracking's fast path).

    See :func:`startrack._kernels.streak.segment_centroids`.  Returns an
    ``(n, 5)`` array: ``x, y, flux, sigma_px, ok``.
    """
    from startrack._kernels.streak import segment_centroids as kernel

    xs = np.ascontiguousarray(xs, dtype=np.float64).reshape(-1)
    ys = np.ascontiguousarray(ys, dtype=np.float64).reshape(-1)
    half = 0.5 * np.asarray(lengths_px, dtype=np.float64).reshape(-1)
    ang = np.asarray(angles_rad, dtype=np.float64).reshape(-1)
    out = np.empty((len(xs), 5))
    kernel(np.ascontiguousarray(image, dtype=np.float32), xs, ys, np.ascontiguousarray(half * np.cos(ang)),
           np.ascontiguousarray(half * np.sin(ang)), float(radius_px), int(iters), out)
    return out


def predicted_streaks(camera, x, y, rate, exposure_s):
    """Length (px) and direction (rad) of the streaks a body rate ``rate`` (rad/s) draws at ``(x, y)``."""
    v = np.einsum("ijk,k->ij", streak_jacobians(camera, x, y), np.asarray(rate, dtype=np.float64)) * exposure_s
    return np.hypot(v[:, 0], v[:, 1]), np.arctan2(v[:, 1], v[:, 0])


def _streak(row):
    if not row[13] > 0 or not np.all(np.isfinite(row[:11])):
        return None
    return Streak(float(row[0]), float(row[1]), float(row[7]), float(row[8]), 2.0 * float(row[2]),
                  2.0 * float(row[9]), float(row[3]), float(row[10]), float(row[4]), float(row[5]),
                  float(row[6]), float(row[11]))


def streak_jacobians(camera, x, y, eps: float = 1e-6):
    """``M_i`` (n, 2, 3): image motion (px) per radian of body rotation about each camera axis.

    ``db = b x dphi`` (stars turn the other way), mapped to pixels by the
    camera model (finite differences, so lens distortion is included).
    """
    x = np.asarray(x, dtype=np.float64).reshape(-1)
    y = np.asarray(y, dtype=np.float64).reshape(-1)
    n = len(x)
    b = np.asarray(camera.pixels_to_vectors(x, y), dtype=np.float64).reshape(-1, 3)
    # b x (eps e_j) for the three axes, stacked: one camera call.
    zero = np.zeros(n)
    bx, by, bz = b[:, 0], b[:, 1], b[:, 2]
    d = eps * np.concatenate([np.column_stack([zero, bz, -by]), np.column_stack([-bz, zero, bx]),
                              np.column_stack([by, -bx, zero])])
    x2, y2 = camera.vectors_to_pixels(np.tile(b, (3, 1)) + d)
    m = np.empty((n, 2, 3))
    m[:, 0, :] = ((np.asarray(x2) - np.tile(x, 3)) / eps).reshape(3, n).T
    m[:, 1, :] = ((np.asarray(y2) - np.tile(y, 3)) / eps).reshape(3, n).T
    return m


@dataclass
class RateEstimate:
    """Body rate from one frame's streaks (rad/s, camera frame), up to its sign."""

    rate: np.ndarray
    cov: np.ndarray
    n_streaks: int
    rms_px: float

    def resolved(self, prior):
        """``+-rate``, whichever is closer to ``prior`` (rad/s)."""
        if prior is not None and float(np.dot(self.rate, prior)) < 0:
            return -self.rate
        return self.rate


def rate_from_streaks(camera, streaks, exposure_s: float, min_streaks: int = 2, floor_px: float = 0.05):
    """Angular rate (rad/s) from the streaks of one frame, by least squares (module docstring, steps 1-2).

    Parameters
    ----------
    camera : Camera
    streaks : list of Streak (``None`` entries are skipped)
    exposure_s : float
        The exposure ``T`` (s).
    floor_px : float
        Added in quadrature to each streak's fitted uncertainties (px): model
        error (curvature of long streaks, PSF shape).

    Returns
    -------
    RateEstimate or None
        ``None`` with fewer than ``min_streaks`` fitted streaks.
    """
    good = [s for s in streaks if s is not None and np.isfinite(s.sigma_length_px) and np.isfinite(s.sigma_angle_rad)]
    if len(good) < min_streaks or not exposure_s > 0:
        return None
    x = np.array([s.x for s in good])
    y = np.array([s.y for s in good])
    m = streak_jacobians(camera, x, y) * exposure_s          # px per (rad/s)
    length = np.array([s.length_px for s in good])
    ang = np.array([s.angle_rad for s in good])
    e = np.column_stack([np.cos(ang), np.sin(ang)])
    n = np.column_stack([-np.sin(ang), np.cos(ang)])
    sig_along = np.hypot(np.array([s.sigma_length_px for s in good]), floor_px)
    sig_across = np.hypot(length * np.array([s.sigma_angle_rad for s in good]), floor_px)
    # Step 1: direction of w from the sign-free cross-streak constraints n_i^T M_i w = 0.
    rows = np.einsum("ij,ijk->ik", n, m) / sig_across[:, None]
    scale_rows = np.einsum("ij,ijk->ik", e, m) / sig_along[:, None]
    _, _, vt = np.linalg.svd(rows, full_matrices=True)
    w_dir = vt[-1]
    proj = scale_rows @ w_dir
    target = length / sig_along
    mag = float(np.dot(np.abs(proj), target) / max(np.dot(proj, proj), 1e-300))
    w = w_dir * mag
    # Step 2: signs from the current w, weighted least squares, repeat.
    signs = None
    keep = np.ones(len(good), dtype=bool)
    for _ in range(6 + len(good)):
        pred = np.einsum("ijk,k->ij", m, w)
        new_signs = np.where(np.einsum("ij,ij->i", pred, e) >= 0, 1.0, -1.0)
        if signs is not None and np.array_equal(new_signs, signs):
            break
        signs = new_signs
        v = (signs * length)[:, None] * e                    # the streak vectors, signed
        # Whitened rows: along and across each streak.
        kw = keep.astype(np.float64)
        a = np.vstack([np.einsum("ij,ijk->ik", e, m) * (kw / sig_along)[:, None],
                       np.einsum("ij,ijk->ik", n, m) * (kw / sig_across)[:, None]])
        bvec = np.concatenate([np.einsum("ij,ij->i", e, v) * kw / sig_along, np.einsum("ij,ij->i", n, v) * kw / sig_across])
        w, *_ = np.linalg.lstsq(a, bvec, rcond=None)
        # Robust: a streak far off the common motion (a blend, a bad fit) is dropped and the fit repeated.
        resid_w = (a @ w - bvec).reshape(2, -1)
        r2 = np.sum(resid_w ** 2, axis=0)
        # The fit's own scatter, robustly: the median chi-square of the kept streaks (2 dof: median 1.386),
        # which one far-off streak cannot inflate (a mean would hide the outlier behind its own scatter).
        scale2 = max(1.0, float(np.median(r2[keep])) / 1.386)
        worst = int(np.argmax(np.where(keep, r2, -1.0)))
        if keep.sum() > 3 and r2[worst] / scale2 > 16.0 and r2[worst] > 25.0:
            keep[worst] = False
            signs = None
            continue
    info = a.T @ a
    try:
        cov = np.linalg.inv(info)
    except np.linalg.LinAlgError:
        cov = np.full((3, 3), np.inf)
    resid = np.einsum("ijk,k->ij", m, w) - (signs * length)[:, None] * e
    rms = float(np.sqrt(np.mean(np.sum(resid[keep] ** 2, axis=1))))
    chi2 = float(np.sum((a @ w - bvec) ** 2))
    dof = max(1, 2 * int(keep.sum()) - 3)
    if chi2 / dof > 1.0:
        cov = cov * (chi2 / dof)      # the fit's own scatter when the sigmas are too small
    return RateEstimate(w, cov, int(keep.sum()), rms)


def streak_residuals(camera, streaks, rate, exposure_s: float, floor_px: float = 0.05):
    """How far each streak is from the motion a body rate ``rate`` (rad/s) draws, in its own sigmas.

    The streak vector (signed to agree with the prediction ``M_i w T``) minus
    the prediction, along and across the streak over the streak's length and
    direction sigmas (with ``floor_px`` in quadrature, as
    :func:`rate_from_streaks`): ``sqrt(r_along^2 + r_across^2)``; NaN for a
    missing fit.
    """
    out = np.full(len(streaks), np.nan)
    idx = [j for j, st in enumerate(streaks) if st is not None]
    if not idx:
        return out
    good = [streaks[j] for j in idx]
    m = streak_jacobians(camera, [st.x for st in good], [st.y for st in good]) * exposure_s
    pred = np.einsum("ijk,k->ij", m, np.asarray(rate, dtype=np.float64))
    for j, st, p in zip(idx, good, pred, strict=True):
        e = np.array([math.cos(st.angle_rad), math.sin(st.angle_rad)])
        n = np.array([-e[1], e[0]])
        sign = 1.0 if float(p @ e) >= 0 else -1.0
        v = sign * st.length_px * e
        r_along = float((v - p) @ e) / math.hypot(st.sigma_length_px, floor_px)
        r_across = float((v - p) @ n) / math.hypot(st.length_px * st.sigma_angle_rad, floor_px)
        out[j] = math.hypot(r_along, r_across)
    return out


def refit_off_motion(image, camera, streaks, xs, ys, rate, exposure_s: float, k_sigma: float = 3.0,
                     significant=None):
    """Fit again, started from the streak ``rate`` predicts, every streak that is missing, not significant
    (``significant(fit)`` false) or more than ``k_sigma`` off that motion (:func:`streak_residuals`).

    All stars of a frame move with one body rate, so a faint streak whose fit
    found only part of it (its moments saw a piece above the threshold) is
    off the common motion; started from the predicted length and direction
    the fit finds the whole streak.  A refit replaces the old fit when it
    converges within half its length plus 3 px of the start ``(xs, ys)``, is
    significant, and is closer to the motion than the old one (in its own
    sigmas).  Returns ``(streaks, n_replaced)`` (a new list).
    """
    significant = significant or (lambda ft: ft is not None)
    out = list(streaks)
    res = streak_residuals(camera, out, rate, exposure_s)
    redo = [j for j, ft in enumerate(out) if not significant(ft) or not res[j] <= k_sigma]
    if not redo:
        return out, 0
    x = np.array([xs[j] for j in redo], dtype=np.float64)
    y = np.array([ys[j] for j in redo], dtype=np.float64)
    length, angle = predicted_streaks(camera, x, y, rate, exposure_s)
    new = fit_streaks(image, x, y, lengths_px=length, angles_rad=angle)
    new_res = streak_residuals(camera, new, rate, exposure_s)
    n = 0
    for t, (j, ft) in enumerate(zip(redo, new, strict=True)):
        if not significant(ft) or math.hypot(ft.x - x[t], ft.y - y[t]) >= 0.5 * ft.length_px + 3:
            continue
        if significant(out[j]) and not new_res[t] < res[j]:
            continue
        out[j] = ft
        n += 1
    return out, n
