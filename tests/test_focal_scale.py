"""The focal-length scale's standard error (``scale_sigma``) against Monte Carlo, and the verification
re-verifying only for a scale its matches can tell from 1."""
import numpy as np
import pytest

from startrack._kernels.identify import SCALE_Z, focal_scale, pixels_to_unit, scale_sigma

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
    from startrack._kernels.identify import scale_significant

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


@pytest.mark.parametrize("n, m", [(6, 20), (40, 300)])     # every star looked at; columns of stars
def test_field_tentative_matches_are_the_brute_force_ones(n, m):
    """The field's tentative matches (each detection's one projected star within its widened radius, none
    when two are; a star once) are those of a scan of every star, also when the stars are looked up by
    columns (many detections and stars): some detections near a star, some between two, some far."""
    from startrack._kernels.identify import field_tentative_matches

    rng = np.random.default_rng(4)
    dcm = np.eye(3)
    for _ in range(30):
        u = rng.uniform(-50, 1330, m)
        v = rng.uniform(-50, 1010, m)
        stars = pixels_to_unit(u, v, FOCAL, CX, CY)
        pick = rng.choice(m, size=n, replace=False)
        xs = u[pick] + rng.normal(0, rng.choice([0.3, 3.0, 30.0]), n)
        ys = v[pick] + rng.normal(0, 0.5, n)
        xs[:2] = rng.uniform(0, 1279, 2)                  # two anywhere
        radius = rng.uniform(1.0, 3.0, n)
        core = np.arange(min(4, n), dtype=np.int64)
        front = np.arange(m, dtype=np.int64)
        got = field_tentative_matches(xs, ys, stars, dcm, FOCAL, CX, CY, 0.0, 0.0, core, radius, 0.02, front, m)
        # The scan of every star.
        allowed = radius + 0.02 * np.hypot(xs - xs[core].mean(), ys - ys[core].mean())
        d = np.hypot(xs[:, None] - u[None, :], ys[:, None] - v[None, :])
        srt = np.sort(d, axis=1)
        img, cat = [], []
        for i in range(n):
            if srt[i, 0] <= allowed[i] and srt[i, 1] > allowed[i]:
                s = int(np.argmin(d[i]))
                if s not in cat:
                    img.append(i)
                    cat.append(s)
        assert got[0].tolist() == img and got[1].tolist() == cat
