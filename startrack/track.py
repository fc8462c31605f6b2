"""Tracking mode: predictive windows, angular rate, single-star attitude, fall-back to lost in space.

Per frame (papers 000 and 001; Samaan, Pollock & Junkins 2002):

1. **Predict.**  The last attitude is propagated with the estimated body rate
   over the time since the last frame (``A(t) = exp(-[w x] dt) A``); catalog
   stars are projected with it.  Stars entering the field are predicted as soon
   as they do; stars leaving it drop out.
2. **Windowed centroiding** around each predicted position (half-size: a
   base margin plus the image motion the rate uncertainty allows plus the
   smear), numba kernel :func:`startrack._kernels.centroid.window_centroids`.
3. **Match by prediction** and reject outliers: each star's offset from its
   prediction is compared with the median offset; a star off by more than
   ``outlier_px`` (a false star or a neighbour inside the window) is dropped.
4. **Attitude** by QUEST (:func:`startrack.attitude.estimate_attitude`, with
   its chi-square gate).  With one star left: paper 001's **single-star**
   attitude (Case 2): other catalog stars predicted in the field are shifted by
   the observed star's offset to make "empirical" image stars, and weighted
   QUEST solves with the real star weighted ``single_star_weight`` times more.
5. **Rate** from successive attitudes, ``w = rotvec(A_k A_{k-1}^T) / dt``,
   smoothed (``rate_smoothing``).
6. **Fall-back**: too few stars, residuals beyond ``max_rms_arcsec``, a
   washed-out frame, or a gap in time longer than ``max_gap_s`` -> lost-in-space
   on that frame (centroid + identify + attitude); tracking resumes once it
   solves; if it does not, the frame is ``lost``.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from startrack.errors import BadInputError

__all__ = ["TrackerConfig", "Tracker", "single_star_attitude", "empirical_stars"]


@dataclass
class TrackerConfig:
    """Tracking settings (pixels, seconds, arcseconds)."""

    mag_limit: float | None = None
    window_px: int = 8
    min_stars: int = 2
    outlier_px: float = 3.0
    sigma_px: float = 0.3
    max_rms_arcsec: float | None = None
    max_gap_s: float = 2.0
    rate_smoothing: float = 0.5
    exposure_s: float = 0.1
    single_star_weight: float = 10.0
    empirical_stars: int = 3
    k_sigma: float = 5.0
    algorithm: str = "pyramid"
    max_predicted: int = 40
    extra: dict = field(default_factory=dict)


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


class Tracker:
    """Stateful tracker; :meth:`step` processes one frame (image in memory) at time ``t`` (seconds)."""

    def __init__(self, catalog, camera, database, config: TrackerConfig | None = None, initial_dcm=None,
                 initial_rate=None):
        self.config = config or TrackerConfig()
        cat = catalog if self.config.mag_limit is None else catalog.filter_magnitude(None, self.config.mag_limit)
        self.catalog = cat.sorted_by_magnitude()
        self.vectors = np.ascontiguousarray(self.catalog.vectors())
        self.ids = self.catalog.id
        self.camera = camera
        self.db = database
        self.dcm = None if initial_dcm is None else np.asarray(initial_dcm, dtype=np.float64)
        self.rate = np.zeros(3) if initial_rate is None else np.asarray(initial_rate, dtype=np.float64)
        self.rate_known = initial_rate is not None
        self.last_t = None
        self.mode = "lis"

    # ------------------------------------------------------------------ helpers
    def predict(self, dcm):
        """Predicted pixel positions and catalog rows of the stars in the field (brightest first)."""
        from startrack.render import project_stars

        rows, x, y = project_stars(self.vectors, dcm, self.camera, margin_px=-2.0)
        return rows[: self.config.max_predicted], x[: self.config.max_predicted], y[: self.config.max_predicted]

    def _lis(self, image, saturation):
        from startrack.attitude import estimate_attitude
        from startrack.centroid import CentroidOptions, find_stars
        from startrack.identify import IdentifyParams, identify_stars

        # Smear expected from the current rate estimate: trails that long are stars, not defects.
        smear = float(np.linalg.norm(self.rate)) * self.camera.focal_length_px * self.config.exposure_s
        elong = max(2.5, 1.0 + smear / 2.0)
        res = find_stars(image, CentroidOptions(max_stars=40, max_elongation=elong,
                                                method="iwc" if smear > 3 else "gauss"), saturation=saturation)
        if len(res.stars) < 3:
            return None, {"status": "failed", "algorithm": self.config.algorithm, "matches": [],
                          "reason": res.reason or f"{len(res.stars)} stars found"}, res.stars
        ident = identify_stars(res.stars, self.camera, self.db, self.config.algorithm,
                               IdentifyParams(sigma_px=max(self.config.sigma_px, 0.2)))
        if ident.status != "ok":
            return None, ident.section(), res.stars
        rows = {int(i): k for k, i in enumerate(self.ids)}
        body, ref, labels = [], [], []
        for m in ident.matches:
            k = rows.get(int(m["id"]))
            if k is None:
                continue
            s = res.stars[m["star"]]
            body.append(self.camera.pixels_to_vectors(s["x"], s["y"]))
            ref.append(self.vectors[k])
            labels.append((m["star"], m["id"]))
        sig = np.full(len(body), max(self.config.sigma_px, 0.05) / self.camera.focal_length_px)
        att = estimate_attitude(np.array(body).reshape(-1, 3), np.array(ref).reshape(-1, 3), sig, "quest", labels)
        if att.status != "ok":
            return None, ident.section(), res.stars
        return att, ident.section(), res.stars

    # --------------------------------------------------------------------- step
    def step(self, image, t: float, saturation: float | None = None) -> dict:
        """Process one frame; returns ``{"stars", "identification", "attitude", "track"}`` sections."""
        from startrack._kernels.centroid import window_centroids
        from startrack.attitude import estimate_attitude
        from startrack.render import propagate_attitude
        from startrack.rotations import rotation_vector

        t0 = time.perf_counter()
        if self.last_t is not None and t <= self.last_t:
            raise BadInputError("image.time", None, f"time {t:.6f} s is not after the previous frame's "
                                f"{self.last_t:.6f} s (out-of-order or repeated time stamps)")
        img = np.ascontiguousarray(image, dtype=np.float32)
        cfg = self.config
        f = self.camera.focal_length_px
        dt = None if self.last_t is None else t - self.last_t
        track = {"mode": None, "dt_s": dt}
        reason_lis = None
        result = None
        stars_out = []
        if self.dcm is not None and dt is not None and dt <= cfg.max_gap_s:
            pred_dcm = propagate_attitude(self.dcm, self.rate, dt)
            rows, px, py = self.predict(pred_dcm)
            speed = float(np.linalg.norm(self.rate)) * f
            uncertainty = (0.5 if self.rate_known else 1.0) * speed * dt
            smear = speed * cfg.exposure_s
            half = int(math.ceil(cfg.window_px + uncertainty + smear / 2.0))
            box = int(max(2, math.ceil(1.0 + smear / 2.0)))
            mx, my, flux, peak, snr, found = window_centroids(img, px.astype(np.float64), py.astype(np.float64),
                                                              half, cfg.k_sigma, 3, box)
            ok = np.flatnonzero(found)
            # Outliers: offsets far from the common offset (false star or neighbour in the window).
            if len(ok) >= 3:
                off = np.column_stack([mx[ok] - px[ok], my[ok] - py[ok]])
                med = np.median(off, axis=0)
                dist = np.hypot(*(off - med).T)
                ok = ok[dist <= max(cfg.outlier_px, 3 * cfg.sigma_px)]
            track.update(window_px=half, predicted=len(rows), found=int(found.sum()), used=len(ok))
            track["stars"] = [{"id": int(self.ids[rows[k]]), "predicted": [round(float(px[k]), 3), round(float(py[k]), 3)],
                               "measured": [round(float(mx[k]), 3), round(float(my[k]), 3)] if found[k] else None}
                              for k in range(len(rows))]
            stars_out = [{"x": float(mx[k]), "y": float(my[k]), "flux": float(flux[k]), "peak": float(peak[k]),
                          "snr": float(snr[k])} for k in ok]
            if len(ok) >= max(cfg.min_stars, 2):
                body = self.camera.pixels_to_vectors(mx[ok], my[ok])
                ref = self.vectors[rows[ok]]
                labels = [(i, int(self.ids[rows[k]])) for i, k in enumerate(ok)]
                sig = np.full(len(ok), max(cfg.sigma_px, 0.05) / f)
                att = estimate_attitude(body, ref, sig, "quest", labels)
                rms = float(np.sqrt(np.mean(np.square(att.residuals_arcsec)))) if att.status == "ok" else None
                limit = cfg.max_rms_arcsec if cfg.max_rms_arcsec is not None else \
                    max(10.0, 5.0 * cfg.sigma_px * self.camera.pixel_scale_arcsec + 0.1 * smear * self.camera.pixel_scale_arcsec)
                if att.status == "ok" and rms <= limit:
                    result = att
                    track["mode"] = "track"
                else:
                    reason_lis = f"tracking residuals {rms:.1f} arcsec above {limit:.1f}" if rms else "attitude failed"
            elif len(ok) == 1:
                k = ok[0]
                others = [j for j in range(len(rows)) if j != k][: cfg.empirical_stars]
                if others:
                    dcm1 = single_star_attitude(self.camera, (mx[k], my[k]), (px[k], py[k]), self.vectors[rows[k]],
                                                np.column_stack([px[others], py[others]]), self.vectors[rows[others]],
                                                cfg.single_star_weight)
                    from startrack.attitude import AttitudeResult

                    result = AttitudeResult("ok", "quest-single-star", dcm1, None,
                                            [(0, int(self.ids[rows[k]]))], [], [0.0], None, None)
                    track["mode"] = "single-star"
                    track["empirical_stars"] = len(others)
                else:
                    reason_lis = "one star and no other predicted star for empirical stars"
            else:
                reason_lis = f"{len(ok)} stars found in the prediction windows"
        else:
            reason_lis = "no attitude yet" if self.dcm is None else \
                (f"gap of {dt:.3f} s above {cfg.max_gap_s:g} s" if dt is not None else "first frame")
        ident_section = None
        if result is None:
            att, ident_section, lis_stars = self._lis(img, saturation)
            stars_out = lis_stars
            if att is not None:
                result = att
                track["mode"] = "lis"
            else:
                track["mode"] = "lost"
            track["fallback_reason"] = reason_lis
        else:
            ident_section = {"status": "ok", "algorithm": f"track-{track['mode']}",
                             "matches": [{"star": i, "id": int(lbl[1])} for i, lbl in enumerate(result.used)]
                             if track["mode"] == "track" else [{"star": 0, "id": result.used[0][1]}]}
        # Rate and state.
        if result is not None:
            if self.dcm is not None and dt is not None and dt > 0 and track["mode"] in ("track", "single-star", "lis") \
                    and dt <= cfg.max_gap_s:
                measured = rotation_vector(result.dcm @ self.dcm.T) / dt
                if self.rate_known:
                    a = cfg.rate_smoothing
                    self.rate = a * self.rate + (1 - a) * measured
                else:
                    self.rate = measured
                    self.rate_known = True
            self.dcm = result.dcm
        else:
            # Lost: keep coasting on the last rate; the next frame tries again.
            if self.dcm is not None and dt is not None:
                self.dcm = propagate_attitude(self.dcm, self.rate, dt)
            self.rate_known = False
        self.last_t = t
        self.mode = track["mode"]
        track["rate_deg_s"] = [float(v) for v in np.degrees(self.rate)]
        track["time_ms"] = round((time.perf_counter() - t0) * 1000, 4)
        if result is None:
            att_section = {"status": "failed", "method": "quest", "reason": "lost: no attitude in this frame"}
        else:
            att_section = result.section()
        return {"stars": stars_out, "identification": ident_section, "attitude": att_section, "track": track}
