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
