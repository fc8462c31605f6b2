"""Tracking mode: predictive windows, smear-aware centroids, a Kalman filter on attitude and rate,
single-star attitude (paper 001 Case 2) and fall-back to lost in space.

Per frame at time ``t`` (seconds; exposure ``T``):

1. **Predict** (when an attitude is known and the last one is at most
   ``max_gap_s`` old).  The filter (:class:`AttitudeRateFilter`) propagates
   the attitude with its rate estimate and grows its covariance; catalog stars
   are projected with the predicted attitude (from the catalog's neighbourhood
   of the boresight, kept until the boresight has moved by
   ``Tracker.NEIGHBOURHOOD_MARGIN_DEG``), each with the streak the rate draws
   during the exposure (the chord between its positions half an exposure
   before and after).
2. **Windowed centroiding** around each prediction (half-size: a base
   ``window_px`` plus 3 sigma of the predicted position plus half the
   expected smear), all predicted stars in one numba kernel
   (:func:`startrack._kernels.track.track_windows`: projection, window
   centroid and, for streaks, the capsule centroid along the expected streak).
   When the expected smear is at least ``streak_min_px`` and the filter's rate
   is still uncertain, the brightest found stars are instead measured by the
   **line-segment PSF fit** (:mod:`startrack.streak`), giving the
   mid-exposure position, its sigma, and the streak (a rate measurement).  Right after an
   acquisition whose rate came from streaks (known only up to its sign), both
   signs are tried and the one whose windows find more stars, closer to their
   predictions, is kept.
3. **Match by prediction**, outliers dropped (offsets from the median offset
   beyond ``outlier_px``).
4. **Attitude**: with ``min_stars`` (2) or more, QUEST with per-star sigmas and
   its chi-square gate (:func:`startrack.attitude.estimate_attitude`), mode
   ``tracking``; with one star, paper 001's **single-star** attitude (Case 2:
   the other predicted stars shifted by the observed star's offset act as
   "empirical" stars, weighted QUEST), mode ``single-star``.
5. **Filter update** with the measured attitude (and, with streaks, the rate
   measured from them).
6. **Fall-back**: no attitude yet, a gap since the last attitude longer than
   ``max_gap_s`` (a blackout), or a failed tracking step -> **lost in space**:
   detection, streak fits, the angular rate from the streaks
   (:func:`startrack.streak.rate_from_streaks`), identification by
   :func:`startrack.identify.identify_stars` with identify's own defaults and the
   stars' per-star sigmas (the machinery of ``startrack identify``, the same
   database), QUEST; mode ``lost-in-space``.  If that fails too the frame is
   ``lost``: no attitude (the filter coasts, its covariance grows).

The filter (:class:`AttitudeRateFilter`) is a multiplicative extended Kalman
filter with state ``x = [dtheta, w]`` (attitude error and body rate, rad and
rad/s, camera frame), ``A_true = exp(-[dtheta x]) A_est``; constant-rate model
with white angular-acceleration noise of spectral density ``q`` (rad^2/s^3):

.. math::

    A^- = \\exp(-[\\hat w \\times] \\Delta t) A, \\quad
    F = \\begin{bmatrix} I & \\Delta t I \\\\ 0 & I \\end{bmatrix}, \\quad
    Q = q \\begin{bmatrix} \\Delta t^3/3 \\, I & \\Delta t^2/2 \\, I \\\\
                           \\Delta t^2/2 \\, I & \\Delta t \\, I \\end{bmatrix}, \\quad
    P^- = F P F^T + Q

    z = \\mathrm{rotvec}(A_{meas} A^{-T}), \\ H = [I \\ 0], \\ R = P_{QUEST}; \\quad
    K = P^- H^T (H P^- H^T + R)^{-1}, \\ \\delta x = K z, \\ P = (I - K H) P^-

    A = \\exp(-[\\delta\\theta \\times]) A^-, \\quad \\hat w \\mathrel{+}= \\delta w

A rate measured from streaks updates with ``H = [0 I]``, ``R`` its covariance;
a single star ``b`` (unit vector) with ``z = b_meas - A^- r``,
``H = [[b x] 0]``, ``R = sigma^2 (I - b b^T)`` (regularised).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from startrack.errors import BadInputError, ParameterError

__all__ = ["MODES", "AttitudeRateFilter", "Tracker", "TrackerConfig", "empirical_stars", "single_star_attitude",
           "track_state"]

#: The modes a frame can be in, in the order summaries list them.
MODES = ("tracking", "single-star", "lost-in-space", "lost")


@dataclass
class TrackerConfig:
    """Tracking settings (pixels, seconds, arcseconds, degrees per second).

    ``rate_noise_deg_s2``: spectral density of the angular acceleration the
    filter allows, as (deg/s)/sqrt(s) (a constant-rate model with this much
    random walk of the rate).  ``rate_sigma0_deg_s``: 1-sigma rate uncertainty
    after an acquisition without a rate from streaks.  ``streak_rate_until_deg_s``:
    while tracking, rates from streaks update the filter only while its rate
    sigma is above this (then the attitude differences dominate).
    """

    mag_limit: float | None = None
    window_px: int = 8
    min_stars: int = 2
    outlier_px: float = 3.0
    sigma_px: float = 0.3
    sigma_floor_px: float = 0.05
    max_rms_arcsec: float | None = None
    max_gap_s: float = 0.5
    exposure_s: float = 0.1
    rate_noise_deg_s2: float = 0.01
    rate_sigma0_deg_s: float = 0.5
    single_star_weight: float = 10.0
    empirical_stars: int = 3
    k_sigma: float = 5.0
    algorithm: str = "pyramid"
    max_predicted: int = 40
    streak_min_px: float = 3.0
    max_streaks: int = 8
    max_window_px: int = 160
    streak_rate_until_deg_s: float = 0.02


def empirical_stars(observed_xy, predicted_xy, others_predicted_xy):
    """Paper 001 Case 2: empirical image stars = other stars' predictions + the observed offset.

    ``dx = x_obs - x_pred``; each other predicted star ``(x_i, y_i)`` becomes
    ``(x_i + dx, y_i + dy)``.
    """
    obs = np.asarray(observed_xy, dtype=np.float64)
    pred = np.asarray(predicted_xy, dtype=np.float64)
    return np.asarray(others_predicted_xy, dtype=np.float64) + (obs - pred)


def single_star_attitude(camera, observed_xy, predicted_xy, ref_vector, others_predicted_xy, others_ref_vectors,
                         weight: float = 10.0):
    """Attitude from one identified star plus empirical stars (paper 001 Sec. 3, Case 2), by weighted QUEST."""
    from startrack.attitude import quest

    emp = empirical_stars(observed_xy, predicted_xy, others_predicted_xy)
    xs = np.concatenate([[observed_xy[0]], emp[:, 0]])
    ys = np.concatenate([[observed_xy[1]], emp[:, 1]])
    body = camera.pixels_to_vectors(xs, ys)
    ref = np.vstack([ref_vector, others_ref_vectors])
    w = np.concatenate([[weight], np.ones(len(emp))])
    return quest(body, ref, w / w.sum())


_I3 = np.eye(3)


def _cross(v):
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def _exp_minus(phi):
    """``exp(-[phi x])`` (Rodrigues): the passive rotation by ``|phi|`` about ``phi`` (as
    :func:`startrack.rotations.propagate_attitude`); numba kernel :func:`startrack._kernels.track.exp_minus`."""
    from startrack._kernels.track import exp_minus

    return exp_minus(np.asarray(phi, dtype=np.float64))


_H_ATT = np.hstack([np.eye(3), np.zeros((3, 3))])
_H_RATE = np.hstack([np.zeros((3, 3)), np.eye(3)])


class AttitudeRateFilter:
    """Multiplicative EKF on attitude and body rate (equations in the module docstring).

    Parameters
    ----------
    dcm : ndarray (3, 3)
        Initial attitude (ICRS to camera).
    rate : ndarray (3,)
        Initial body rate (rad/s).
    cov : ndarray (6, 6)
        Initial covariance of ``[dtheta, w]`` (rad^2, rad^2/s^2).
    q : float
        Angular-acceleration spectral density (rad^2/s^3).
    """

    def __init__(self, dcm, rate, cov, q):
        self.dcm = np.ascontiguousarray(dcm, dtype=np.float64)
        self.rate = np.array(rate, dtype=np.float64)
        self.P = np.array(cov, dtype=np.float64)
        self.q = float(q)

    def predicted(self, dt, rate=None):
        """``(A^-, P^-)`` after ``dt`` seconds, without changing the state (optionally with another rate)."""
        from startrack._kernels.track import filter_predict

        w = self.rate if rate is None else np.asarray(rate, dtype=np.float64)
        return filter_predict(self.dcm, self.P, w, float(dt), self.q)

    def predict(self, dt):
        self.dcm, self.P = self.predicted(dt)

    def _update(self, z, h, r):
        from startrack._kernels.track import filter_update

        self.dcm, self.P, self.rate, nis = filter_update(self.dcm, self.P, self.rate, z, h, r)
        return float(nis)

    def update_attitude(self, dcm_meas, cov):
        """Update with a measured attitude and its covariance (rad^2, camera frame); returns the NIS."""
        from startrack._kernels.track import attitude_residual

        z = attitude_residual(np.ascontiguousarray(dcm_meas, dtype=np.float64), self.dcm)
        return self._update(z, _H_ATT, np.ascontiguousarray(cov, dtype=np.float64))

    def update_rate(self, rate_meas, cov):
        """Update with a measured body rate (rad/s) and its covariance."""
        z = np.asarray(rate_meas, dtype=np.float64) - self.rate
        return self._update(z, _H_RATE, np.ascontiguousarray(cov, dtype=np.float64))

    def update_star(self, body, ref, sigma_rad):
        """Update with one star: measured camera-frame unit vector ``body``, catalog vector ``ref``."""
        b_pred = self.dcm @ np.asarray(ref, dtype=np.float64)
        z = np.asarray(body, dtype=np.float64) - b_pred
        h = np.hstack([_cross(b_pred), np.zeros((3, 3))])
        r = sigma_rad ** 2 * (np.eye(3) - np.outer(b_pred, b_pred)) + (sigma_rad * 1e-3) ** 2 * np.eye(3)
        return self._update(z, h, r)


def _significant(fit):
    """A fitted streak whose length is clear of zero (twice its sigma, and more than 1 px)."""
    return fit is not None and fit.length_px > 2.0 * max(fit.sigma_length_px, 0.5)


def _sign_score(res):
    """How well windows at one sign of the rate fit: stars found, then closeness to their predictions."""
    ok = res[:, 11] > 0
    if not ok.any():
        return (0, -math.inf)
    off = np.hypot(res[ok, 3] - res[ok, 1], res[ok, 4] - res[ok, 2])
    return (int(ok.sum()), -float(np.median(off)))


_STATE_FIELDS = ("mode", "t_s", "dt_s", "window_px", "predicted", "found", "used", "stars", "rate_deg_s",
                 "fallback_reason", "empirical_stars", "time_ms")


def track_state(track: dict):
    """The :class:`startrack.records.TrackState` of one frame (fields beyond its schema go to ``details``)."""
    from startrack.records import TrackState

    known = {k: track[k] for k in _STATE_FIELDS if k in track}
    if known.get("rate_deg_s") is not None:
        known["rate_deg_s"] = np.asarray(known["rate_deg_s"], dtype=np.float64)
    return TrackState(**known, details={k: v for k, v in track.items() if k not in _STATE_FIELDS})


class Tracker:
    """Stateful tracker; :meth:`step` processes one frame (image in memory) at time ``t`` (seconds)."""

    #: Margin (deg) of the catalog neighbourhood kept around the boresight (see :meth:`_neighbourhood`).
    NEIGHBOURHOOD_MARGIN_DEG = 2.0

    def __init__(self, catalog, camera, database, config: TrackerConfig | None = None, initial_dcm=None,
                 initial_rate=None, parity: str = "auto"):
        from startrack.parity import parities_to_try

        parities_to_try(parity)
        self.config = config or TrackerConfig()
        # Parity (startrack.parity): a mirrored sequence is tracked on its frames flipped left-right, seen by the
        # camera whose principal point is flipped too (x' = W-1-x sees what the un-mirrored camera sees at
        # 2 cx - x), and every position reported is flipped back; auto settles it at the first acquisition.
        self.parity = parity
        self._parity_known = parity != "auto"
        self._mirrored = parity == "mirrored"
        self._camera_normal = camera
        if not camera.is_pinhole:
            raise ParameterError("camera", f"tracking models a pinhole camera only, not a {camera.projection} one "
                                 "(solve each frame instead)", "Tracker")
        self._camera_flipped = camera.replace(cx=camera.width - 1 - camera.cx)
        if self._mirrored:
            camera = self._camera_flipped
        cat = catalog if self.config.mag_limit is None else catalog.filter_magnitude(None, self.config.mag_limit)
        self.catalog = cat.sorted_by_magnitude()
        self.vectors = self.catalog.vectors()
        self.astrometric = self.vectors      # the catalog's directions; self.vectors the frame's apparent ones
        self.ids = self.catalog.id
        self.row_of_id = self.catalog.rows_by_id()
        self._sky = None            # the catalog's sky index (startrack.skyindex), made at the first neighbourhood
        self.camera = camera
        self.db = database
        self.filter = None
        self.sign_ambiguous = False
        self.last_t = None
        self.last_fix_t = None
        self.mode = None
        self.rate_prior = None if initial_rate is None else np.asarray(initial_rate, dtype=np.float64)
        self.r_max = math.hypot(camera.width, camera.height) / 2.0
        self._cos_limit = math.cos(math.radians(min(89.0, camera.max_off_axis_deg + 1.0)))
        # The catalog's neighbourhood of the boresight: the field's cone plus a margin, kept until the
        # boresight has moved by the margin.
        margin = math.radians(self.NEIGHBOURHOOD_MARGIN_DEG)
        self._cos_margin = math.cos(margin)
        self._cos_near = math.cos(min(math.pi, math.acos(self._cos_limit) + margin))
        self._near = None
        self._max_r2 = camera.max_valid_r2
        from startrack._kernels.track import N_COLUMNS

        self._out = np.empty((self.config.max_predicted, N_COLUMNS))
        self.psf_sigma_px = 1.0       # updated from the streak fits of each acquisition
        if initial_dcm is not None:
            rate = np.zeros(3) if initial_rate is None else np.asarray(initial_rate, dtype=np.float64)
            s_rate = 1e-4 if initial_rate is not None else math.radians(self.config.rate_sigma0_deg_s)
            s_att = math.radians(60.0 / 3600.0)
            self.filter = AttitudeRateFilter(initial_dcm, rate, np.diag([s_att ** 2] * 3 + [s_rate ** 2] * 3),
                                             self._q())

    def _q(self):
        return math.radians(self.config.rate_noise_deg_s2) ** 2

    def set_directions(self, vectors):
        """Use these unit vectors (rows of ``self.catalog``: ``self.astrometric`` moved to the coming frame's
        apparent places, :mod:`startrack.apparent`) for the catalog stars from the next step on."""
        self.vectors = np.ascontiguousarray(vectors, dtype=np.float64)
        if self._near is not None:
            self._near = (self._near[0], self._near[1], np.ascontiguousarray(self.vectors[self._near[1]]))

    # ------------------------------------------------------------------ helpers
    def _neighbourhood(self, dcm):
        """Catalog rows (brightest first) and their unit vectors within ``max_off_axis + 1 + margin`` degrees
        of the boresight, recomputed only when the boresight has moved more than the margin since (every star
        the field can hold is in it)."""
        bore = np.asarray(dcm)[2]
        if self._near is None or float(bore @ self._near[0]) < self._cos_margin:
            if self._sky is None:
                from startrack.skyindex import SkyIndex

                self._sky = SkyIndex(self.vectors)
            rows = self._sky.cone(bore, self._cos_near)
            self._near = (bore.copy(), rows, np.ascontiguousarray(self.vectors[rows]))
        return self._near[1], self._near[2]

    def predict_stars(self, dcm):
        """Predicted pixel positions and catalog rows of the stars in the field (brightest first).

        As :func:`startrack.render.project_stars` with a 2 px inner margin, its
        field-of-view cone computed once.
        """
        rows, vec = self._neighbourhood(dcm)
        cam_vec = vec @ np.asarray(dcm).T
        front = np.flatnonzero(cam_vec[:, 2] > self._cos_limit)
        x, y = self.camera.vectors_to_pixels(cam_vec[front])
        inside = self.camera.in_image(x, y, margin=2.0) & np.isfinite(x)
        rows = rows[front[inside][: self.config.max_predicted]]
        n = len(rows)
        return rows, x[inside][:n], y[inside][:n]

    def _sigma_px(self, p_theta):
        """1-sigma predicted position (px) at the edge of the field from the attitude covariance."""
        f = self.camera.focal_length_px
        return math.sqrt(f * f * max(p_theta[0, 0], p_theta[1, 1]) + self.r_max ** 2 * p_theta[2, 2])

    def _windows(self, img, dcm, rate, exposure_s, half, box, segment, max_shift):
        """All predicted stars of the frame in one kernel (:func:`startrack._kernels.track.track_windows`):
        the prediction at ``dcm``, the streak a body rate ``rate`` draws in ``exposure_s``, the window
        centroids and, with ``segment``, the capsule centroids along the streaks.  Returns the catalog rows
        and the kernel's output rows (columns :data:`startrack._kernels.track.COLUMNS`)."""
        from startrack._kernels.track import track_windows

        cam = self.camera
        rows, vec = self._neighbourhood(dcm)
        half_turn = _exp_minus(np.asarray(rate, dtype=np.float64) * (0.5 * exposure_s))
        out = self._out
        n = track_windows(img, vec, np.ascontiguousarray(dcm, dtype=np.float64), half_turn, cam.focal_length_px,
                          cam.cx, cam.cy, cam.k1, cam.k2, self._max_r2, cam.width, cam.height, 2.0, self._cos_limit,
                          self.config.max_predicted, half, self.config.k_sigma, 3, box, segment,
                          3.0 * self.psf_sigma_px + 1.0, 3, max_shift, out)
        res = out[:n]
        return rows[res[:, 0].astype(np.int64)], res

    def _acquire(self, img, saturation, exposure_s):
        """Lost in space: detection, streak fits, rate from streaks, identify's search, QUEST."""
        from startrack.attitude import estimate_attitude
        from startrack.centroid import CentroidOptions, find_stars
        from startrack.formats.sections import to_section
        from startrack.identify import IdentifyParams, identify_stars
        from startrack.streak import fit_streaks, rate_from_streaks

        cfg = self.config
        res = find_stars(img, CentroidOptions(), saturation=saturation)
        trails = [r for r in res.rejected if str(r.get("reason", "")).startswith("elongated")]
        prior = self.filter.rate if self.filter is not None else self.rate_prior
        expect = 0.0 if prior is None else float(np.linalg.norm(prior)) * self.camera.focal_length_px * exposure_s
        probe = res.stars[: cfg.max_streaks]
        fits = fit_streaks(img, [s["x"] for s in probe], [s["y"] for s in probe]) if probe else []
        long_fits = [ft for ft in fits if ft is not None and ft.length_px > cfg.streak_min_px
                     and ft.length_px > 3.0 * ft.sigma_length_px]
        streaky = bool(trails) or expect >= cfg.streak_min_px or len(long_fits) >= max(1, len(probe) // 2)
        info = {"detected": len(res.stars), "streaks": 0, "streak_detection": streaky}
        if streaky:
            # Streaks: a matched filter (their signal is spread along them), no deblending (a streak's noisy
            # ridge is not two stars) and no elongation cut; then the line-segment fits on the brightest.
            res = find_stars(img, CentroidOptions(deblend=False, max_elongation=1e9, matched_filter=True,
                                                  filter_sigma_px=2.0), saturation=saturation)
            info["detected"] = len(res.stars)
            n_fit = min(len(res.stars), max(cfg.max_streaks, 12))
            fits = fit_streaks(img, [s["x"] for s in res.stars[:n_fit]], [s["y"] for s in res.stars[:n_fit]])
        stars = [dict(s) for s in res.stars]
        rate_est = rate_from_streaks(self.camera, fits[: cfg.max_streaks], exposure_s) if fits else None
        if streaky and rate_est is not None and np.all(np.isfinite(rate_est.cov)):
            # All stars move with one body rate: streaks the moments could not start (no fit, no significant
            # length) or found only in part (off the common motion) are fitted again from the streak the rate
            # predicts, and the rate is estimated again from the result (twice).
            from startrack.streak import refit_off_motion

            xs = [s["x"] for s in stars[: len(fits)]]
            ys = [s["y"] for s in stars[: len(fits)]]
            for _ in range(2):
                fits, n_new = refit_off_motion(img, self.camera, fits, xs, ys, rate_est.rate, exposure_s,
                                               significant=_significant)
                info["streaks_refitted"] = info.get("streaks_refitted", 0) + n_new
                again = rate_from_streaks(self.camera, [ft if _significant(ft) else None for ft in fits][
                    : cfg.max_streaks], exposure_s)
                if n_new == 0 or again is None or not np.all(np.isfinite(again.cov)):
                    break
                rate_est = again
        for s, ft in zip(stars[: len(fits)], fits, strict=True):
            if not _significant(ft):
                continue
            # A significant streak: its mid-exposure position and sigma replace the point-source centroid.
            st = ft.as_star()
            s.update(x=st["x"], y=st["y"], sigma_px=st["sigma_px"], streak=st["streak"])
            info["streaks"] += 1
        widths = [ft.psf_sigma_px for ft in fits if ft is not None]
        if widths:
            # The fitted width (PSF and pixel, sigma^2 + 1/12) sizes the tracking apertures.
            self.psf_sigma_px = float(np.clip(np.median(widths), 0.5, 5.0))
        if len(stars) < 3:
            return None, {"status": "failed", "algorithm": cfg.algorithm, "matches": [],
                          "reason": res.reason or f"{len(stars)} star(s) found: at least 3 are needed"}, stars, None, info
        if self._parity_known:
            ident = identify_stars(stars, self.camera, self.db, cfg.algorithm, IdentifyParams())
        else:
            from startrack.parity import identify_either_parity

            # Until the parity is known: normal first, then the frame's stars flipped left-right (the flipped
            # camera's view), each with half the false-match budget and half the time budget (a sequence's
            # field is rich: a search that finds nothing runs until its budget is spent), the second also
            # what the first left.
            default = IdentifyParams()
            half = IdentifyParams(max_false_probability=default.max_false_probability / 2,
                                  max_time_ms=default.max_time_ms / 2)
            ident, _ = identify_either_parity(stars, self.camera, self.db, cfg.algorithm, half, parity="normal")
            left_ms = default.max_time_ms - (ident.time_ms or 0.0)
            if ident.status != "ok" and left_ms > 0:
                flipped = [{**s, "x": self.camera.width - 1 - s["x"]} for s in stars]
                half.max_time_ms = left_ms
                again, _ = identify_either_parity(flipped, self._camera_flipped, self.db, cfg.algorithm, half,
                                                  parity="normal")
                if again.status == "ok":
                    ident, stars = again, flipped
                    self._mirrored, self.camera = True, self._camera_flipped
                    rate_est = None          # measured on the frame as given: not the flipped camera's
                    info["streaks"] = 0
            if ident.status == "ok":
                self._parity_known = True
        if ident.status != "ok":
            return None, to_section(ident), stars, rate_est, info
        body, ref, labels, sig = [], [], [], []
        f = self.camera.focal_length_px
        for m in ident.matches:
            k = self.row_of_id.get(int(m.id))
            if k is None:
                continue
            s = stars[m.star]
            body.append(self.camera.pixels_to_vectors(s["x"], s["y"]))
            ref.append(self.vectors[k])
            labels.append((m.star, int(m.id)))
            sp = s.get("sigma_px")
            sp = sp if isinstance(sp, (int, float)) and sp > 0 else 0.5
            sig.append(max(sp, cfg.sigma_floor_px) / f)
        att = estimate_attitude(np.array(body).reshape(-1, 3), np.array(ref).reshape(-1, 3), np.array(sig),
                                "quest", labels)
        if att.status != "ok":
            return None, to_section(ident), stars, rate_est, info
        return att, to_section(ident), stars, rate_est, info

    def _track(self, img, dcm_pred, p_pred, exposure_s, track, details=True):
        """Windowed tracking at the predicted attitude; returns ``(result, stars, reason)``."""
        from startrack.attitude import AttitudeResult, estimate_attitude

        cfg = self.config
        f = self.camera.focal_length_px
        rate = self.filter.rate
        speed = math.sqrt(float(rate @ rate)) * f
        smear = speed * exposure_s
        sig_pos = self._sigma_px(p_pred[:3, :3])
        half = int(min(cfg.max_window_px, math.ceil(cfg.window_px + 3.0 * sig_pos + smear / 2.0)))
        box = int(max(2, math.ceil(1.0 + smear / 2.0)))
        rate_sigma = math.sqrt(max(self.filter.P[3, 3], self.filter.P[4, 4], self.filter.P[5, 5]))
        fit_rate = rate_sigma > math.radians(cfg.streak_rate_until_deg_s)
        streaky = smear >= cfg.streak_min_px
        # A box centroid of a long streak is not its mid-exposure position: the found stars are measured
        # again knowing the streak's shape from the rate.  While the filter's rate is uncertain the
        # brightest are fitted with the line-segment PSF (position, sigma, and a rate measurement);
        # afterwards a capsule-aperture centroid along the predicted segment does (fast, in the kernel).
        segment = streaky and not fit_rate
        max_shift = smear / 2.0 + 3.0
        rows, res = self._windows(img, dcm_pred, rate, exposure_s, half, box, segment, max_shift)
        if self.sign_ambiguous:
            res = res.copy()       # the kernel's output buffer is reused by the other sign's windows
            alt, _ = self.filter.predicted(track["dt_s"], rate=-rate)
            rows2, res2 = self._windows(img, alt, -rate, exposure_s, half, box, segment, max_shift)
            if _sign_score(res2) > _sign_score(res):
                # The streaks' rate had the other sign: the filter's state and its prediction turn with it.
                rows, res = rows2, res2
                self.filter.rate = -self.filter.rate
                self._pred = self.filter.predicted(track["dt_s"])
                track["rate_sign"] = "flipped"
            self.sign_ambiguous = False
        px, py, mx, my = res[:, 1], res[:, 2], res[:, 3].copy(), res[:, 4].copy()
        flux, snr = res[:, 5], res[:, 6]
        found = res[:, 8] > 0
        ok = np.flatnonzero(res[:, 11] > 0)
        sig = np.full(len(rows), max(cfg.sigma_px, cfg.sigma_floor_px))
        streaks = []
        if streaky and len(ok):
            if fit_rate:
                from startrack.streak import _streak, fit_streaks_array

                use = ok[np.argsort(-flux[ok], kind="stable")][: cfg.max_streaks]
                length = 2.0 * np.hypot(res[use, 9], res[use, 10])
                angle = np.arctan2(res[use, 10], res[use, 9])
                fits = fit_streaks_array(img, mx[use], my[use], max_half_px=math.ceil(smear + 12),
                                         lengths_px=length, angles_rad=angle)
                fitted = []
                for j, k in enumerate(use):
                    st = _streak(fits[j])
                    if st is not None and math.hypot(st.x - mx[k], st.y - my[k]) < max_shift:
                        mx[k], my[k] = st.x, st.y
                        sig[k] = max(math.sqrt(0.5 * (st.sigma_x ** 2 + st.sigma_y ** 2)), cfg.sigma_floor_px)
                        fitted.append(k)
                        streaks.append(st)
                ok = np.array(sorted(fitted), dtype=np.int64)
            else:
                sig[ok] = np.maximum(res[ok, 7], cfg.sigma_floor_px)
                track["centroid"] = "segment"
        # Outliers: offsets far from the common offset (a false star or a neighbour in the window).
        if len(ok) >= 3:
            from startrack._kernels.track import offset_inliers

            ok = offset_inliers(mx, my, px, py, ok.astype(np.int64), float(max(cfg.outlier_px, 3 * cfg.sigma_px)))
        track.update(window_px=half, predicted=len(rows), found=int(found.sum()), used=len(ok))
        stars = []
        if details:
            ids = self.ids[rows].tolist()
            pxl, pyl, mxl, myl = (np.round(v, 3).tolist() for v in (px, py, mx, my))
            fl = found.tolist()
            track["stars"] = [{"id": ids[k], "predicted": [pxl[k], pyl[k]],
                               "measured": [mxl[k], myl[k]] if fl[k] else None} for k in range(len(ids))]
            stars = [{"x": x, "y": y, "flux": fx, "snr": sn, "sigma_px": sg} for x, y, fx, sn, sg in
                     zip(mx[ok].tolist(), my[ok].tolist(), flux[ok].tolist(), snr[ok].tolist(), sig[ok].tolist(),
                         strict=True)]
        if len(streaks) >= 2 and fit_rate:
            from startrack.streak import rate_from_streaks

            track["streaks"] = len(streaks)
            est = rate_from_streaks(self.camera, streaks, exposure_s)
            if est is not None and np.all(np.isfinite(est.cov)):
                w = est.resolved(self.filter.rate)
                track["streak_rate_deg_s"] = [round(float(v), 5) for v in np.degrees(w)]
                track["streak_rate_sigma_deg_s"] = [round(float(v), 5) for v in np.degrees(np.sqrt(np.diag(est.cov)))]
                self._streak_rate = (w, est.cov)
        if len(ok) >= max(cfg.min_stars, 2):
            body = self.camera.pixels_to_vectors(mx[ok], my[ok])
            ref = self.vectors[rows[ok]]
            labels = [(i, int(self.ids[rows[k]])) for i, k in enumerate(ok)]
            att = estimate_attitude(body, ref, sig[ok] / f, "quest", labels)
            if att.status != "ok":
                return None, stars, att.reason or "attitude failed"
            rms = math.sqrt(math.fsum(x * x for x in att.residuals_arcsec) / len(att.residuals_arcsec))
            scale = self.camera.pixel_scale_arcsec
            limit = cfg.max_rms_arcsec if cfg.max_rms_arcsec is not None else \
                max(10.0, 5.0 * float(np.max(sig[ok])) * scale + 0.1 * smear * scale)
            if rms > limit:
                return None, stars, f"tracking residuals {rms:.1f} arcsec above {limit:.1f}"
            track["mode"] = "tracking"
            return att, stars, None
        if len(ok) == 1:
            k = ok[0]
            others = [j for j in range(len(rows)) if j != k][: cfg.empirical_stars]
            if not others:
                return None, stars, "one star and no other predicted star for empirical stars"
            dcm1 = single_star_attitude(self.camera, (mx[k], my[k]), (px[k], py[k]), self.vectors[rows[k]],
                                        np.column_stack([px[others], py[others]]), self.vectors[rows[others]],
                                        cfg.single_star_weight)
            track["mode"] = "single-star"
            track["empirical_stars"] = len(others)
            body = self.camera.pixels_to_vectors(mx[k], my[k]).reshape(3)
            self._single = (body, self.vectors[rows[k]], sig[k] / f)
            return AttitudeResult("ok", "single-star", dcm1, None, [(0, int(self.ids[rows[k]]))], [], [0.0]), stars, None
        return None, stars, f"{len(ok)} stars found in the prediction windows"

    # --------------------------------------------------------------------- step
    def step(self, image, t: float, saturation: float | None = None, exposure_s: float | None = None,
             details: bool = True) -> dict:
        """Process one frame; returns ``{"stars", "identification", "attitude", "track"}`` sections.

        With ``details=False`` (a tracking loop in memory) it returns
        ``{"mode", "dcm", "rate_rad_s", "result", "track"}`` instead: the attitude
        (ICRS to camera, or ``None``), the filter's rate, the
        :class:`~startrack.attitude.AttitudeResult`, and the
        :class:`~startrack.records.TrackState` without the per-star list; no
        document section is built.

        Parameters
        ----------
        image : ndarray (height, width)
        t : float
            Mid-exposure time (s) on any fixed origin; must increase.
        saturation : float, optional
            The image's saturation level (DN).
        exposure_s : float, optional
            This frame's exposure (s); default ``config.exposure_s``.
        """
        t0 = time.perf_counter()
        if self.last_t is not None and t <= self.last_t:
            raise BadInputError("image.time", None, f"time {t:.6f} s is not after the previous frame's "
                                f"{self.last_t:.6f} s (out-of-order or repeated time stamps)")
        img = np.ascontiguousarray(image[:, ::-1] if self._mirrored else image, dtype=np.float32)
        cfg = self.config
        exposure = cfg.exposure_s if exposure_s is None else float(exposure_s)
        dt = None if self.last_t is None else t - self.last_t
        track = {"mode": None, "dt_s": dt}
        self._streak_rate = None
        self._single = None
        result, stars_out, reason_lis, ident_section = None, [], None, None
        since_fix = None if self.last_fix_t is None else t - self.last_fix_t
        self._pred = None
        if self.filter is not None and dt is not None:
            dcm_pred, p_pred = self.filter.predicted(dt)
            self._pred = (dcm_pred, p_pred)
            if since_fix is not None and since_fix <= cfg.max_gap_s:
                result, stars_out, reason_lis = self._track(img, dcm_pred, p_pred, exposure, track, details)
            else:
                reason_lis = f"{since_fix:.3f} s since the last attitude (above {cfg.max_gap_s:g} s)" \
                    if since_fix is not None else "no attitude yet"
        elif self.filter is not None:
            # A given initial attitude: track from it on the first frame.
            dcm_pred, p_pred = self.filter.dcm, self.filter.P
            result, stars_out, reason_lis = self._track(img, dcm_pred, p_pred, exposure, track, details)
        else:
            reason_lis = "no attitude yet"
        rate_est = None
        if result is None:
            att, ident_section, lis_stars, rate_est, info = self._acquire(img, saturation, exposure)
            stars_out = lis_stars
            track.update(info)
            track["fallback_reason"] = reason_lis
            if att is not None:
                result = att
                track["mode"] = "lost-in-space"
            else:
                track["mode"] = "lost"
        elif details:
            labels = result.used
            ident_section = {"status": "ok", "algorithm": f"track-{track['mode']}",
                             "matches": [{"star": int(s), "id": int(i)} for s, i in labels]}
        self._update_filter(result, track, dt, rate_est)
        self.last_t = t
        if result is not None:
            self.last_fix_t = t
        self.mode = track["mode"]
        if not details:
            track["time_ms"] = (time.perf_counter() - t0) * 1000
            track["t_s"] = t
            return {"mode": track["mode"], "dcm": None if result is None else result.dcm,
                    "rate_rad_s": None if self.filter is None else self.filter.rate.copy(), "result": result,
                    "track": track_state(track)}
        if self.filter is not None:
            track["rate_deg_s"] = [float(v) for v in np.degrees(self.filter.rate)]
            track["rate_sigma_deg_s"] = [float(v) for v in np.degrees(np.sqrt(np.diag(self.filter.P)[3:]))]
            if self.sign_ambiguous:
                track["rate_sign_known"] = False
        track["time_ms"] = round((time.perf_counter() - t0) * 1000, 4)
        if result is None:
            att_section = {"status": "failed", "method": "quest",
                           "reason": "lost: no attitude in this frame"
                           + (f" ({ident_section.get('reason')})" if ident_section and ident_section.get("reason") else "")}
        else:
            att_section = result.section()
            att_section["mode"] = track["mode"]
            if track["mode"] == "single-star" and self.filter is not None:
                arcsec = math.degrees(1.0) * 3600.0
                p = self.filter.P
                att_section["sigma_cross_boresight_arcsec"] = float(math.sqrt((p[0, 0] + p[1, 1]) / 2.0) * arcsec)
                att_section["sigma_roll_arcsec"] = float(math.sqrt(p[2, 2]) * arcsec)
        from startrack.formats.sections import to_section

        track["t_s"] = t
        track_section = to_section(track_state(track))
        if self._mirrored:
            # Positions in the frame as given: flipped back.
            w1 = self.camera.width - 1
            for s in stars_out:
                s["x"] = w1 - s["x"]
            for s in track_section.get("stars") or []:
                for key in ("predicted", "measured"):
                    if s.get(key) is not None:
                        s[key] = [w1 - s[key][0], s[key][1]]
            if ident_section is not None and ident_section.get("status") == "ok":
                ident_section["parity"] = "mirrored"
        elif ident_section is not None and ident_section.get("status") == "ok" and self._parity_known:
            ident_section["parity"] = "normal"
        return {"stars": stars_out, "identification": ident_section, "attitude": att_section,
                "track": track_section}

    def _update_filter(self, result, track, dt, rate_est):
        cfg = self.config
        mode = track["mode"]
        if mode == "lost-in-space":
            # (Re)start the filter at the acquired attitude; the rate from the streaks (sign unknown) or the
            # previous estimate.
            cov_att = result.cov_rad2 if result.cov_rad2 is not None else np.eye(3) * math.radians(60 / 3600) ** 2
            s0 = math.radians(cfg.rate_sigma0_deg_s)
            if self.filter is None and self.rate_prior is not None:
                # A rate given by the caller (a gyro): its sign is known.
                rate, cov_rate = self.rate_prior, np.eye(3) * math.radians(0.01) ** 2
                self.sign_ambiguous = False
            elif rate_est is not None and np.all(np.isfinite(rate_est.cov)):
                rate, cov_rate = rate_est.rate, rate_est.cov + np.eye(3) * 1e-8
                sig = np.sqrt(np.diag(cov_rate))
                self.sign_ambiguous = bool(np.linalg.norm(rate) > 3.0 * np.linalg.norm(sig))
                track["streak_rate_deg_s"] = [round(float(v), 5) for v in np.degrees(rate)]
                track["streak_rate_sigma_deg_s"] = [round(float(v), 5) for v in np.degrees(np.sqrt(np.diag(rate_est.cov)))]
                if not self.sign_ambiguous:
                    cov_rate = cov_rate + np.outer(rate, rate)     # a rate not clear of zero: either sign
            elif self.filter is not None and dt is not None and self.last_fix_t is not None:
                rate, cov_rate = self.filter.rate, self.filter.P[3:, 3:]
                self.sign_ambiguous = False
            else:
                rate, cov_rate = np.zeros(3), np.eye(3) * s0 ** 2
                self.sign_ambiguous = False
            cov = np.zeros((6, 6))
            cov[:3, :3] = cov_att
            cov[3:, 3:] = cov_rate
            prev = self.filter
            self.filter = AttitudeRateFilter(result.dcm, rate, cov, self._q())
            # Consecutive fixes: the attitude difference measures the rate (resolving the streak sign).
            if prev is not None and dt is not None and self.last_fix_t is not None and self.mode is not None \
                    and self.mode != "lost" and dt <= cfg.max_gap_s:
                from startrack.rotations import _rotation_vector_rad

                measured = _rotation_vector_rad(result.dcm @ prev.dcm.T) / dt
                cov_m = (cov_att + prev.P[:3, :3]) / dt ** 2
                if self.sign_ambiguous and np.dot(measured, rate) < 0:
                    self.filter.rate = -rate
                self.sign_ambiguous = False
                self.filter.update_rate(measured, cov_m)
            return
        if self.filter is None:
            return
        if dt is not None:
            if self._pred is not None:
                self.filter.dcm, self.filter.P = self._pred
            else:
                self.filter.predict(dt)
        if mode == "tracking":
            cov = result.cov_rad2 if result.cov_rad2 is not None else np.eye(3) * math.radians(10 / 3600) ** 2
            track["nis"] = round(self.filter.update_attitude(result.dcm, cov), 3)
        elif mode == "single-star" and self._single is not None:
            body, ref, sig = self._single
            track["nis"] = round(self.filter.update_star(body, ref, sig), 3)
        if mode in ("tracking", "single-star") and self._streak_rate is not None:
            w, cov_w = self._streak_rate
            self.filter.update_rate(w, cov_w + np.eye(3) * 1e-10)
