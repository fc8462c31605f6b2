"""Cramér-Rao bounds (startrack.accuracy) and attitude's checks of its input (issue 17, 21)."""
import math

import numpy as np
import pytest

from startrack.accuracy import (
    attitude_crb,
    centroid_crb,
    centroid_crb_px,
    stars_crb_from_frame,
    summarise,
)
from startrack.attitude import covariance, estimate_attitude
from startrack.camera import Camera
from startrack.rotations import _rotation_vector_rad, quaternion_to_dcm, random_quaternions


def test_centroid_bound_limits():
    # Shot noise only, wide PSF: the pixelated Gaussian tends to var = (s^2 + 1/12) / F (box-blurred Gaussian).
    f, s = 1e5, 3.0
    assert centroid_crb_px(f, s, 0.0, 0.3, 0.1) == pytest.approx(math.sqrt((s * s + 1 / 12) / f), rel=2e-3)
    # Background limited, wide PSF: var = 8 pi s^4 v / F^2 (the matched-filter limit).
    f, v = 1e4, 1e6
    assert centroid_crb_px(f, s, v) == pytest.approx(math.sqrt(8 * math.pi * (s * s + 1 / 12) ** 2 * v) / f, rel=1e-2)
    # Unknown flux never tightens the bound; more background always widens it.
    c_known = centroid_crb(2000, 0.7, 40, 0.31, -0.2, flux_known=True)
    c = centroid_crb(2000, 0.7, 40, 0.31, -0.2)
    assert np.all(np.diag(c) >= np.diag(c_known) * (1 - 1e-12))
    assert centroid_crb_px(2000, 0.7, 80) > centroid_crb_px(2000, 0.7, 40)


def test_attitude_bound_is_quest_covariance_for_a_narrow_pinhole_field():
    cam = Camera.from_fov(2.0, 1000, 1000)
    rng = np.random.default_rng(0)
    x, y = rng.uniform(0, 999, 6), rng.uniform(0, 999, 6)
    b = cam.pixels_to_vectors(x, y)
    s_px = rng.uniform(0.05, 0.3, 6)
    p = attitude_crb(cam, b, s_px**2).cov_rad2
    q = covariance(b, s_px / cam.focal_length_px)
    assert np.allclose(p, q, rtol=2e-3)


def test_an_efficient_estimator_reaches_the_bound():
    """Truth + noise drawn from each star's centroid bound: the errors match the per-frame bound (normalised RMS 1)."""
    cam = Camera.from_fov(15.0, 1024, 1024)
    rng = np.random.default_rng(7)
    z, phis, bounds = [], [], []
    for _ in range(400):
        a = quaternion_to_dcm(random_quaternions(1, rng)[0])
        n = int(rng.integers(4, 20))
        x, y = rng.uniform(0, 1023, n), rng.uniform(0, 1023, n)
        covs = np.array([centroid_crb(e, s, 60.0, u, v) for e, s, u, v in
                         zip(rng.uniform(500, 50000, n), rng.uniform(0.6, 2.0, n), x, y)])
        r = cam.pixels_to_vectors(x, y) @ a
        noise = np.array([rng.multivariate_normal([0, 0], c) for c in covs])
        bound = attitude_crb(cam, cam.pixels_to_vectors(x, y), covs)
        sig = np.sqrt(0.5 * (covs[:, 0, 0] + covs[:, 1, 1])) / cam.focal_length_px
        res = estimate_attitude(cam.pixels_to_vectors(x + noise[:, 0], y + noise[:, 1]), r, sig, gate=1e9)
        phi = _rotation_vector_rad(res.dcm @ a.T)
        z.append(phi / np.sqrt(np.diag(bound.cov_rad2)))
        phis.append(phi)
        bounds.append(np.diag(bound.cov_rad2))
    rms = np.sqrt(np.mean(np.square(z), axis=0))
    s = summarise(phis, bounds)
    for axis in ("cross", "roll"):
        lo, hi = s[f"ratio_{axis}_band"]
        assert lo <= s[f"ratio_{axis}"] <= hi and 1 < s[f"ratio_{axis}_n_eff"] < 800
    # 400 frames: the RMS of unit normals is 1 +- 0.035 (1 sigma)
    assert np.all(np.abs(rms - 1.0) < 0.12), rms


def test_stars_crb_from_frame_uses_what_centroid_writes():
    stars = [{"x": 10.2, "y": 5.7, "flux": 3000.0, "fwhm_px": 2.3548, "noise_dn": 10.0},
             {"x": 1.0, "y": 2.0, "flux": 3000.0}]
    out = stars_crb_from_frame(stars, gain_e_per_dn=2.0)
    assert out[1] is None
    assert math.sqrt(out[0][0, 0]) == pytest.approx(math.sqrt(centroid_crb(6000, 1.0, 400.0, 10.2, 5.7)[0, 0]))


def _frame(n, rng, spread=0.08):
    a = quaternion_to_dcm(random_quaternions(1, rng)[0])
    cam = np.column_stack([rng.uniform(-spread, spread, (n, 2)), np.ones(n)])
    cam /= np.linalg.norm(cam, axis=1, keepdims=True)
    return a, cam, cam @ a


def test_duplicates_and_degenerate_geometry_fail():
    rng = np.random.default_rng(2)
    a, b, r = _frame(5, rng)
    res = estimate_attitude(np.vstack([b, b]), np.vstack([r, r]), np.full(10, 1e-5),
                            labels=[(i % 5, 100 + i % 5) for i in range(10)])
    assert res.status == "failed" and res.reason_code == "duplicate_match"
    # two stars 0.2" apart with 2" sigmas: the roll is not determined
    b2 = np.array([[0.0, 0.0, 1.0], [1e-6, 0.0, 1.0]])
    res = estimate_attitude(b2, b2 @ a, np.full(2, 1e-5))
    assert res.status == "failed" and res.reason_code == "degenerate_geometry"
    # the same match repeated without labels is degenerate too, never a math error
    res = estimate_attitude(np.repeat(b[:1], 10, axis=0), np.repeat(r[:1], 10, axis=0), np.full(10, 1e-5))
    assert res.status == "failed" and res.reason_code == "degenerate_geometry"


def test_wrong_identifications_fail():
    rng = np.random.default_rng(3)
    _, b, r = _frame(8, rng)
    sig = np.full(8, 5e-6)
    b = b + rng.normal(size=b.shape) * 5e-6
    assert estimate_attitude(b, r, sig).status == "ok"
    perm = estimate_attitude(b, np.roll(r, 1, axis=0), sig)
    assert perm.status == "failed" and perm.reason_code == "residuals_too_large"
    two = estimate_attitude(b[:2], np.vstack([r[0], r[2]]), sig[:2])
    assert two.status == "failed" and two.reason_code == "residuals_too_large"


def test_star_covariance_prefers_the_fit_s_own():
    from startrack.accuracy import star_covariance

    s = {"x": 10.2, "y": 5.7, "flux": 3000.0, "fwhm_px": 2.3548, "noise_dn": 10.0,
         "cov_px2": [[0.01, 0.001], [0.001, 0.02]]}
    assert np.allclose(star_covariance(s, 2.0), [[0.01, 0.001], [0.001, 0.02]])
    bad = dict(s, cov_px2=[[0.01, 0.5], [0.5, 0.02]])          # not positive definite: the bound instead
    assert np.allclose(star_covariance(bad, 2.0), centroid_crb(6000, 1.0, 400.0, 10.2, 5.7))


def test_blended_references_sit_at_the_photocentre():
    from startrack.accuracy import blended_references
    from startrack.catalog import Catalog

    cam = Camera.from_fov(10.0, 1000, 1000)                       # 36"/px: a 2 px merge radius is 72"
    d = 40.0 / 3600.0
    nan = np.full(3, np.nan)
    cat = Catalog(np.array([1, 2, 3]), np.array([10.0, 10.0 + d, 20.0]), np.array([0.0, 0.0, 0.0]),
                  np.array([5.0, 7.0, 5.0]), nan, nan, nan, 2000.0)
    refs = blended_references(cat.filter_magnitude(None, 6.0), cat, cam)
    assert sorted(refs.id.tolist()) == [1, 3]
    one = refs.ra[refs.id.tolist().index(1)]
    w = 10 ** (-0.4 * 2.0)                                        # the companion is 2 mag fainter
    assert one == pytest.approx(10.0 + d * w / (1 + w), abs=1e-7)


def test_evaluate_accuracy_goes_on_from_the_records_of_an_earlier_call(catalog):
    """evaluate_accuracy(done=...): the records on_frame gave for the first frames are taken, not rendered again;
    only the rest reach on_frame, and the result is the uninterrupted call's.  A record out of order is refused."""
    from startrack.accuracy import evaluate_accuracy
    from startrack.errors import ParameterError

    cam = Camera.from_fov(20, 256, 256)
    cat = catalog.filter_magnitude(None, 4.0)
    first = []
    whole = evaluate_accuracy(cam, cat, 14, 5, on_frame=first.append)
    assert [r["frame"] for r in first] == list(range(14)) and whole["frames"] >= 3
    assert {r["outcome"] for r in first} <= {"ok", "far", "wrong", "failed", "no_bound"}
    rest = []
    assert evaluate_accuracy(cam, cat, 14, 5, done=iter(first[:9]), on_frame=rest.append) == whole
    assert rest == first[9:]
    with pytest.raises(ParameterError) as info:
        evaluate_accuracy(cam, cat, 14, 5, done=first[1:3])
    assert info.value.field == "done" and "record 0 is not frame 0's" in info.value.problem
