"""Line-segment PSF fits and the rate from one frame's streaks, against the renderer's truth."""
import math

import numpy as np
import pytest

from startrack.camera import Camera
from startrack.catalog import Catalog
from startrack.render import Scene, Sensor, render_image
from startrack.rotations import _radec_roll_to_dcm_rad, _radec_to_vector_rad, radec_roll_to_dcm
from startrack.streak import (
    fit_streaks,
    predicted_streaks,
    rate_from_streaks,
    segment_centroids,
    streak_jacobians,
)


def _one_star_catalog(cam, dcm, x, y, mag):
    """A catalog with one star that lands at pixel (x, y) at attitude ``dcm``."""
    b = cam.pixels_to_vectors(np.array([x]), np.array([y])).reshape(3)
    r = dcm.T @ b
    ra = math.degrees(math.atan2(r[1], r[0])) % 360
    dec = math.degrees(math.asin(r[2]))
    return Catalog(np.array([1]), np.array([ra]), np.array([dec]), np.array([mag]), np.zeros(1), np.zeros(1),
                   np.zeros(1), 2000.0)


@pytest.mark.parametrize("rate, seed", [((0.0, 0.0, 0.0), 1), ((1.5, -1.0, 0.0), 2), ((0.0, 3.0, 0.0), 3),
                                        ((2.0, 2.0, 0.0), 4)])
def test_streak_position_length_and_direction(rate, seed):
    cam = Camera.from_fov(12, 256, 256)
    dcm = _radec_roll_to_dcm_rad(0.3, 0.2, 0.1)
    rng = np.random.default_rng(seed)
    x0, y0 = rng.uniform(100, 156, 2)
    cat = _one_star_catalog(cam, dcm, x0, y0, 3.0)
    sensor = Sensor()
    errs, pulls, seg = [], [], []
    for trial in range(12):
        img, truth = render_image(cat, cam, dcm, sensor, Scene(rate_deg_s=rate), np.random.default_rng([seed, trial]))
        s = truth["stars"][0]
        fit = fit_streaks(img, [s["x"] + 0.7], [s["y"] - 0.6])[0]
        assert fit is not None
        errs.append((fit.x - s["x"], fit.y - s["y"]))
        pulls.append(((fit.x - s["x"]) / fit.sigma_x, (fit.y - s["y"]) / fit.sigma_y))
        # Tracking's fast path: a capsule centroid along the streak the rate predicts.
        length, angle = predicted_streaks(cam, [s["x"]], [s["y"]], np.radians(rate), sensor.exposure_s)
        c = segment_centroids(img, [s["x"] + 0.7], [s["y"] - 0.6], length, angle)[0]
        assert c[4] == 1
        seg.append((c[0] - s["x"], c[1] - s["y"]))
    assert np.sqrt(np.mean(np.square(seg))) < 0.15, seg
    errs = np.array(errs)
    # Mid-exposure position: unbiased and precise to a small fraction of a pixel.
    assert np.abs(errs.mean(axis=0)).max() < 0.05, errs.mean(axis=0)
    assert np.sqrt(np.mean(errs ** 2)) < 0.1
    # The sigmas are honest (pulls of order 1, not 10).
    assert 0.3 < np.std(np.array(pulls)) < 2.5
    # Length and direction of the trail: the image motion over the exposure.
    m = streak_jacobians(cam, [s["x"]], [s["y"]])[0]
    v = m @ np.radians(rate) * sensor.exposure_s
    length = float(np.hypot(*v))
    # (below ~1 px a segment and a wider PSF are hard to tell apart: the fit trades length for width)
    assert fit.length_px == pytest.approx(length, abs=max(1.0, 0.03 * length))
    if length > 5:
        d_ang = (fit.angle_rad - math.atan2(v[1], v[0]) + math.pi / 2) % math.pi - math.pi / 2
        assert abs(d_ang) < math.radians(2)


def test_rate_from_one_frame(catalog):
    cam = Camera.from_fov(12, 1024, 768)
    dcm = radec_roll_to_dcm(100.0, 20.0, 10.0)
    from startrack.centroid import CentroidOptions, find_stars

    for rate in [(1.5, -1.0, 0.5), (0.0, 0.0, 3.0), (2.0, 1.0, 1.0)]:
        img, _ = render_image(catalog.filter_magnitude(None, 6.5), cam, dcm, Sensor(), Scene(rate_deg_s=rate),
                              np.random.default_rng(7))
        res = find_stars(img, CentroidOptions(deblend=False, max_elongation=1e9))
        fits = fit_streaks(img, [s["x"] for s in res.stars[:8]], [s["y"] for s in res.stars[:8]])
        est = rate_from_streaks(cam, fits, 0.1)
        w = np.degrees(est.resolved(np.radians(rate)))
        sig = np.degrees(np.sqrt(np.diag(est.cov)))
        # Cross-boresight axes to a few hundredths of a deg/s, roll less well; within 5 sigma.
        assert np.abs(w[:2] - rate[:2]).max() < 0.05, (rate, w)
        assert abs(w[2] - rate[2]) < 0.3, (rate, w)
        assert np.all(np.abs(w - rate) < 5 * sig + 0.01), (rate, w, sig)


def test_rate_sign_is_ambiguous_but_resolved_by_a_prior():
    cam = Camera.from_fov(12, 1024, 768)
    from startrack.streak import RateEstimate

    est = RateEstimate(np.array([0.1, -0.2, 0.05]), np.eye(3), 3, 0.1)
    assert np.allclose(est.resolved(np.array([-0.1, 0.2, 0.0])), [-0.1, 0.2, -0.05])
    assert np.allclose(est.resolved(None), [0.1, -0.2, 0.05])
    # The Jacobian: a turn about the camera's y axis moves stars along image x (b x w).
    m = streak_jacobians(cam, [511.5], [383.5])[0]
    assert abs(m[0, 1]) == pytest.approx(cam.focal_length_px, rel=1e-4) and abs(m[1, 1]) < 1e-3
    assert _radec_to_vector_rad(0.0, 0.0)[0] == 1.0


def test_partial_streaks_are_fitted_again_from_the_common_motion(catalog):
    """At 3 deg/s (25 px streaks) the moments of faint streaks see only a piece of them; refitted from the
    streak the frame's rate predicts, they are whole again and the rate from the frame improves."""
    from startrack.centroid import CentroidOptions, find_stars
    from startrack.streak import refit_off_motion

    cam = Camera.from_fov(12, 1024, 768)
    cat = catalog.filter_magnitude(None, 6.5)
    rate = np.array([1.5, -1.0, 0.5]) / np.linalg.norm([1.5, -1.0, 0.5]) * 3.0
    dcm = radec_roll_to_dcm(6.1436, -0.5236, 0.6981)     # degrees (a field near RA 6 deg on the equator)
    img, _ = render_image(cat, cam, dcm, Sensor(), Scene(rate_deg_s=tuple(rate)), np.random.default_rng(11))
    res = find_stars(img, CentroidOptions(deblend=False, max_elongation=1e9, matched_filter=True, filter_sigma_px=2.0))
    xs, ys = [s["x"] for s in res.stars[:12]], [s["y"] for s in res.stars[:12]]
    fits = fit_streaks(img, xs, ys)

    def significant(ft):
        return ft is not None and ft.length_px > 2 * max(ft.sigma_length_px, 0.5)

    def length_errors(fs):
        ok = [ft for ft in fs if significant(ft)]
        true, _ = predicted_streaks(cam, [ft.x for ft in ok], [ft.y for ft in ok], np.radians(rate), 0.1)
        return np.abs(np.array([ft.length_px for ft in ok]) - true)

    est = rate_from_streaks(cam, [ft if significant(ft) else None for ft in fits][:8], 0.1)
    assert length_errors(fits).max() > 5 or sum(map(significant, fits)) < len(fits)   # pieces or no streak
    new, n = refit_off_motion(img, cam, fits, xs, ys, est.rate, 0.1, significant=significant)
    assert n >= 1
    # More whole streaks (length within 2 px of the truth) than before.
    assert np.sum(length_errors(new) < 2) >= np.sum(length_errors(fits) < 2) + 2
    assert np.median(length_errors(new)) < 1.0
    est2 = rate_from_streaks(cam, [ft if significant(ft) else None for ft in new][:8], 0.1)
    err1 = np.abs(np.degrees(est.resolved(np.radians(rate))) - rate)
    err2 = np.abs(np.degrees(est2.resolved(np.radians(rate))) - rate)
    assert np.linalg.norm(err2[:2]) < np.linalg.norm(err1[:2])      # cross-boresight (roll: see rate_from_streaks)
    assert np.all(err2 < 5 * np.degrees(np.sqrt(np.diag(est2.cov))) + 0.01)
