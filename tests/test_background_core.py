"""The background's level and noise from the normal core of its distribution, and the deblend kernel."""
import numpy as np
import pytest
from naive import split_blob_naive

from startrack._kernels.background import _probit, core_stats_of_sorted
from startrack._kernels.centroid import split_blob


def _sample(rng, mu, sigma, n, *, integer=False, floor=None, star_fraction=0.01):
    x = rng.normal(mu, sigma, n)
    stars = rng.random(n) < star_fraction
    x[stars] += rng.exponential(30 * sigma + 5, stars.sum())
    if integer:
        x = np.floor(x + 0.5)
    if floor is not None:
        x = np.maximum(x, floor)
    return np.sort(x)


@pytest.mark.parametrize("p", [1e-6, 0.001, 0.02425, 0.1, 0.5, 0.8, 0.97575, 0.999])
def test_probit_inverts_the_normal_cdf(p):
    from statistics import NormalDist

    assert _probit(p) == pytest.approx(NormalDist().inv_cdf(p), rel=1e-6)


@pytest.mark.parametrize("mu, sigma, integer, floor", [
    (100.0, 5.0, False, None),      # a plain frame
    (100.0, 5.0, True, None),       # whole DN
    (2.0, 4.0, True, 0.0),          # dark-subtracted and clipped at 0: ~31 % zeros
    (-1.5, 4.0, True, 0.0),         # clipped: ~65 % zeros, the median is 0
    (1.2, 0.3, True, None),         # 8-bit, a third of a DN of noise: two grey levels
    (20.0, 2.0, True, None),
])
def test_core_stats_recover_the_normal_background(mu, sigma, integer, floor):
    rng = np.random.default_rng(7)
    est = np.array([core_stats_of_sorted(_sample(rng, mu, sigma, 10000, integer=integer, floor=floor))
                    for _ in range(20)])
    assert np.mean(est[:, 0]) == pytest.approx(mu, abs=0.05 * sigma)
    assert np.mean(est[:, 1]) == pytest.approx(sigma, rel=0.05)


@pytest.mark.parametrize("mu, sigma", [(-1.5, 4.0), (2.0, 4.0), (1.2, 0.3)])
def test_core_stats_where_a_median_and_mad_fail(mu, sigma):
    """Clipped at 0 (65 % and 31 % zeros) and 8-bit at a third of a DN: the median and MAD (main's estimator)
    miss the noise by over a fifth (0 where half the sample is one value); the core fit lands within 5 %."""
    rng = np.random.default_rng(3)
    s = _sample(rng, mu, sigma, 10000, integer=True, floor=0.0 if mu < 1 or sigma > 1 else None)
    mad_sigma = 1.4826 * np.median(np.abs(s - np.median(s)))
    assert abs(mad_sigma - sigma) > 0.2 * sigma, mad_sigma
    assert core_stats_of_sorted(s)[1] == pytest.approx(sigma, rel=0.05)


def test_core_stats_of_constant_and_two_level_samples():
    assert core_stats_of_sorted(np.full(100, 7.0)) == (7.0, 0.0)
    level, sigma = core_stats_of_sorted(np.sort(np.r_[np.full(99, 3.0), 4.0]))
    assert level == 3.0 and sigma == 0.0


@pytest.mark.parametrize("seed", range(8))
def test_split_blob_matches_the_naive_deblend(seed):
    from startrack._kernels.centroid import label_blobs

    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:40, 0:50]
    img = rng.normal(0, 1, (40, 50))
    for _ in range(4):
        x0, y0, a, s = rng.uniform(5, 45), rng.uniform(5, 35), rng.uniform(20, 200), rng.uniform(0.8, 3)
        img += a * np.exp(-((xx - x0) ** 2 + (yy - y0) ** 2) / (2 * s * s))
    residual = img.astype(np.float32)
    mask = (residual > 3).astype(np.uint8)
    labels, table, n = label_blobs(residual, mask, residual, np.inf, 10000)
    out = np.empty((64, 2), dtype=np.int64)
    for lab in range(1, n + 1):
        row = table[lab]
        box = (int(row[12]), int(row[13]), int(row[14] - row[12] + 1), int(row[15] - row[13] + 1))
        ref = split_blob_naive(residual, labels, lab, box)
        k = split_blob(residual, labels.astype(np.int32), lab, *box, 2.5, 0.7, out)
        assert [tuple(p) for p in out[:k].tolist()] == [tuple(p) for p in ref]


@pytest.mark.parametrize("kind", ["normal", "whole DN", "NaN tiles", "zeros of either sign"])
def test_median3_is_each_cells_sorted_middle(kind):
    """median3 (a sorting network for nine finite values) gives, bit for bit, what a stable sort of each cell's
    finite 3 x 3 neighbours (edges replicated) gives: the middle value, or the mean of the middle two, NaN when
    none is finite; a zero keeps the sign the sort meets it with."""
    from startrack._kernels.background import median3

    rng = np.random.default_rng(len(kind))
    a = rng.normal(100.0, 5.0, (9, 13))
    if kind == "whole DN":
        a = np.round(a / 3.0)           # many ties
    elif kind == "NaN tiles":
        a[rng.random(a.shape) < 0.35] = np.nan
        a[0:3, 0:3] = np.nan            # a cell without a finite neighbour
    elif kind == "zeros of either sign":
        a = np.where(rng.random(a.shape) < 0.5, 0.0, a)
        a[rng.random(a.shape) < 0.3] = -0.0
    got = median3(a)
    ny, nx = a.shape
    for j in range(ny):
        for i in range(nx):
            vals = [float(a[min(max(j + dj, 0), ny - 1), min(max(i + di, 0), nx - 1)])
                    for dj in (-1, 0, 1) for di in (-1, 0, 1)]
            vals = sorted(v for v in vals if v == v)
            k = len(vals)
            want = np.nan if k == 0 else vals[k // 2] if k & 1 else 0.5 * (vals[k // 2 - 1] + vals[k // 2])
            assert np.float64(got[j, i]).tobytes() == np.float64(want).tobytes(), (j, i, got[j, i], want)
