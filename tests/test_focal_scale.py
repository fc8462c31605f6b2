"""The focal-length scale's standard error (``scale_sigma``) against Monte Carlo, the verification
re-verifying only for a scale its matches can tell from 1, and what a fitted scale pays (``scale_cells``)."""
import numpy as np
import pytest

from startrack._kernels.common import pixels_to_unit
from startrack._kernels.focal import SCALE_Z, focal_scale, scale_sigma

FOCAL, CX, CY = 6000.0, 639.5, 479.5


def _similarity_scale(x, y, u, v):
    """Least-squares scale of a similarity transform (scale, rotation, shift) taking (u, v) to (x, y)."""
    a = np.stack([u - u.mean(), v - v.mean()])
    b = np.stack([x - x.mean(), y - y.mean()])
    m = b @ a.T
    return float(np.hypot(m[0, 0] + m[1, 1], m[1, 0] - m[0, 1])
                 / np.sum(a * a))


@pytest.mark.parametrize("n, sigma", [(5, 0.3), (12, 1.0)])
def test_scale_sigma_is_the_spread_of_a_fitted_scale(n, sigma):
    rng = np.random.default_rng(7 + n)
    u = rng.uniform(0, 1279, n)
    v = rng.uniform(0, 959, n)
    sig = np.full(n, sigma)
    predicted = scale_sigma(u, v, sig, np.arange(n, dtype=np.int64))
    fits, chords = [], []
    truth = pixels_to_unit(u, v, FOCAL, CX, CY)
    for _ in range(3000):
        x = u + rng.normal(0, sigma, n)
        y = v + rng.normal(0, sigma, n)
        fits.append(_similarity_scale(x, y, u, v))
        b = pixels_to_unit(x, y, FOCAL, CX, CY)
        chords.append(focal_scale(b, np.arange(n, dtype=np.int64), truth, np.arange(n, dtype=np.int64)))
    # The optimal (similarity) fit scatters as predicted; the chord estimate the verification uses no less.
    assert np.std(fits) == pytest.approx(predicted, rel=0.08)
    assert np.std(chords) >= 0.9 * predicted


def test_scale_sigma_weights_and_degenerate_cases():
    idx = np.arange(4, dtype=np.int64)
    x = np.array([0.0, 100.0, 0.0, 100.0])
    y = np.array([0.0, 0.0, 100.0, 100.0])
    # Four corners of a square 100 px on a side, sigma 1: sum |x - c|^2 = 4 * 50^2 * 2.
    assert scale_sigma(x, y, np.ones(4), idx) == pytest.approx(1 / np.sqrt(20000.0))
    # Doubling every sigma doubles the standard error.
    assert scale_sigma(x, y, 2 * np.ones(4), idx) == pytest.approx(2 / np.sqrt(20000.0))
    assert scale_sigma(x, y, np.ones(4), idx[:1]) == np.inf
    assert scale_sigma(np.zeros(4), np.zeros(4), np.ones(4), idx) == np.inf
    assert SCALE_Z >= 2.0


def _field(rng, n, sigma_true, scale):
    """Tentative matches of a frame: detections (pixels, noise ``sigma_true``) and their stars' vectors seen
    through a focal length ``scale`` times the nominal; the pairs' chords in ``_field_scale_of``'s order."""
    u = rng.uniform(0, 1279, n)
    v = rng.uniform(0, 959, n)
    stars = pixels_to_unit(u, v, FOCAL * scale, CX, CY)       # catalog chords = scale x measured ones
    xs = u + rng.normal(0, sigma_true, n)
    ys = v + rng.normal(0, sigma_true, n)
    b = pixels_to_unit(xs, ys, FOCAL, CX, CY)
    iu = np.triu_indices(n, 1)
    mea = np.linalg.norm(b[:, None] - b[None, :], axis=2)[iu]
    ang = np.linalg.norm(stars[:, None] - stars[None, :], axis=2)[iu]
    return xs, ys, b, stars, np.ascontiguousarray(ang), np.ascontiguousarray(mea)


@pytest.mark.parametrize("sigma_true, scale, expect", [
    (0.3, 1.0, "rarely"),       # the stated noise, the exact focal length
    (1.0, 1.0, "rarely"),       # stars three times noisier than stated: the scatter says so
    (0.3, 1.003, "always"),     # 0.3 % off: far beyond the noise
    (1.0, 1.01, "always"),      # 1 % off with noisy stars: the scatter is measured about the fitted scale
])
def test_scale_significant_only_when_the_matches_tell_the_scale_from_one(sigma_true, scale, expect):
    from startrack._kernels.focal import scale_significant

    rng = np.random.default_rng(11)
    hits = 0
    trials = 400
    for k in range(trials):
        n = 5 + k % 16
        xs, ys, b, stars, ang, mea = _field(rng, n, sigma_true, scale)
        idx = np.arange(n, dtype=np.int64)
        hits += bool(scale_significant(xs, ys, np.full(n, 0.3), FOCAL, idx, ang, mea))
    if expect == "rarely":
        assert hits <= 0.02 * trials
    else:
        assert hits == trials


def test_scale_cells_counts_the_scales_a_fit_could_choose():
    """The look-elsewhere factor of a proposal verified at a fitted focal-length scale: one cell per
    ``window`` over the scales the nominal search's windows allow the core's longest angle (at most the
    stated focal error), whatever scale the data fitted; never fewer than the fitted offset's own cells."""
    from startrack._kernels.focal import scale_cells

    theta, window, eps = 0.2, 7e-5, 3e-4
    want = 1.0 + 2.0 * eps / window
    for offset in (5e-4, 1e-3, 1.4e-3):
        assert scale_cells(theta, window, eps, offset, 0.05) == pytest.approx(want, rel=1e-12)
    # A focal error smaller than the windows allow bounds the range.
    assert scale_cells(theta, window, eps, 5e-4, 1e-3) == pytest.approx(1.0 + 2.0 * 1e-3 * theta / window)
    # A scale beyond the nominal windows (found with the focal length free) counts its own offset.
    assert scale_cells(theta, window, eps, 0.02, 0.05) == pytest.approx(1.0 + 0.02 * theta / window)


def test_a_fitted_scale_pays_the_same_whatever_its_value(sensor15):
    """verify() of a true proposal: at any fitted scale offset within the windows the false-match
    probability is the nominal one's times the same factor (the count of scales the fit could
    choose), at least three (the window never exceeds the search tolerance): a chance pattern is
    fitted to whichever scale suits it, so a small offset buys no confidence."""
    from startrack.evaluate import Condition, make_frames
    from startrack.identify import IdentifyParams, Proposal, identify_stars, verify
    from startrack.identify import params as identify_params

    cam, db, stars = sensor15
    params = IdentifyParams(sigma_px=0.3)
    index = {int(s): i for i, s in enumerate(db.star_id)}
    checked = 0
    for frame, _, _ in make_frames(stars, cam, Condition(sigma_px=0.3, min_catalog_stars=6), 10, 71, mag_limit=5.5):
        res = identify_stars(frame, cam, db, "pyramid", params)
        if res.status != "ok" or res.focal_scale is not None:
            continue
        img = [m.star for m in res.matches[:4]]
        prop = Proposal(img, [index[m.id] for m in res.matches[:4]])
        xs, ys, flux = identify_params._frame_arrays(frame)
        sig = identify_params.star_sigmas_px(frame, params)
        b_all = verify._pixels_to_vectors(cam, xs, ys)
        eps = float(np.sqrt(2.0) * 4.0 * 0.3 / cam.focal_length_px + np.radians(2.0 / 3600))
        p = [verify.verify(prop, b_all, flux, sig, cam, db, eps, params, 1, True, None, off).p_false
             for off in (0.0, 1e-4, 6e-4)]
        assert None not in p
        assert p[1] == pytest.approx(p[2], rel=1e-12)
        assert p[1] >= 3.0 * p[0]
        checked += 1
    assert checked >= 5
