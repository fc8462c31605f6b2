"""The focal-length scale's standard error (scale_sigma) against the scatter of the scale itself."""
import numpy as np
import pytest

from startrack._kernels.identify import focal_scale, pixels_to_unit, scale_sigma


@pytest.mark.parametrize("n, sigma", [(4, 0.3), (10, 1.0), (25, 0.5)])
def test_scale_sigma_matches_monte_carlo(n, sigma):
    """Stars on a 15 deg 1280x960 pinhole sensor, their pixel positions noisy by ``sigma``: the spread of
    focal_scale over 600 draws is scale_sigma within 15 % (a wrong formula, e.g. without the spread
    of the stars or the 1/sum normalisation, is off by far more)."""
    rng = np.random.default_rng(7 + n)
    focal, cx, cy = 4861.7, 639.5, 479.5
    x0 = rng.uniform(0, 1279, n)
    y0 = rng.uniform(0, 959, n)
    truth = pixels_to_unit(x0, y0, focal, cx, cy)           # the catalog directions
    idx = np.arange(n, dtype=np.int64)
    sig = np.full(n, sigma) * rng.uniform(0.5, 1.5, n)     # stars of different precision
    scales = []
    for _ in range(600):
        xs = x0 + rng.normal(0, 1, n) * sig
        ys = y0 + rng.normal(0, 1, n) * sig
        scales.append(focal_scale(pixels_to_unit(xs, ys, focal, cx, cy), idx, truth, idx))
    predicted = scale_sigma(x0, y0, idx, sig)
    assert np.std(scales) == pytest.approx(predicted, rel=0.15)


def test_scale_sigma_undefined_below_two_stars():
    assert np.isnan(scale_sigma(np.array([1.0]), np.array([2.0]), np.array([0], dtype=np.int64), np.array([0.5])))
