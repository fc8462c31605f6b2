"""The sky index (startrack.skyindex) against the brute-force cone on random skies, poles, RA wrap, wide cones."""
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from naive import cone_naive

from startrack.errors import ParameterError
from startrack.skyindex import SkyIndex


def _unit(v):
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _sky(n, seed):
    """Random stars plus the awkward ones: both poles, RA exactly 0, just below 360 deg, on the equator."""
    rng = np.random.default_rng(seed)
    special = [[0, 0, 1], [0, 0, -1], [1, 0, 0], [1, -1e-12, 0], [math.cos(1e-9), -math.sin(1e-9), 0.3],
               [1e-13, 0, 1], [-1, 0, 0], [-1, -1e-15, 0.2]]
    return _unit(np.vstack([rng.normal(size=(n, 3)), special]))


SKY = _sky(20000, 38)
INDEX = SkyIndex(SKY)


def _axis(ra_deg, dec_deg):
    ra, dec = math.radians(ra_deg), math.radians(dec_deg)
    return np.array([math.cos(dec) * math.cos(ra), math.cos(dec) * math.sin(ra), math.sin(dec)])


@pytest.mark.parametrize("ra", [0.0, 1e-7, 359.9999999, 180.0, 90.0, 270.0, 33.3])
@pytest.mark.parametrize("dec", [90.0, -90.0, 89.99, -89.5, 85.0, -80.0, 0.0, 45.0, -30.0])
@pytest.mark.parametrize("radius", [0.01, 1.0, 5.0, 15.0, 35.0, 70.0, 89.9, 90.0, 120.0, 180.0])
def test_cone_is_the_brute_force_cone(ra, dec, radius):
    axis = _axis(ra, dec)
    c = math.cos(math.radians(radius))
    got = INDEX.cone(axis, c)
    want = cone_naive(SKY, axis, c)
    np.testing.assert_array_equal(got, want)
    assert got.dtype == np.int64


@settings(max_examples=300, deadline=None)
@given(st.floats(-1.5, 1.5), st.floats(-1.5, 1.5), st.floats(-1.5, 1.5), st.floats(0.0, math.pi))
def test_cone_on_random_axes(x, y, z, radius):
    if math.hypot(x, y, z) < 1e-3:
        return
    axis = _unit([x, y, z])
    c = math.cos(radius)
    np.testing.assert_array_equal(INDEX.cone(axis, c), cone_naive(SKY, axis, c))


def test_cone_limits_and_band_counts():
    axis = _axis(10.0, 20.0)
    assert INDEX.cone(axis, -1.5).tolist() == list(range(len(SKY)))          # beyond 180 deg: everything
    assert INDEX.cone(axis, 1.0).size == 0                                   # nothing is strictly inside 0 deg
    for nb in (1, 2, 7, 500):
        idx = SkyIndex(SKY, n_bands=nb)
        np.testing.assert_array_equal(idx.cone(axis, math.cos(0.3)), cone_naive(SKY, axis, math.cos(0.3)))
    # near() is a superset that holds the stars just outside by rounding.
    c = float(SKY[5] @ axis)
    assert 5 not in INDEX.cone(axis, c).tolist() and 5 in INDEX.near(axis, c).tolist()


def test_cone_on_the_shipped_catalog(catalog):
    vec = catalog.vectors()
    index = SkyIndex(vec)
    rng = np.random.default_rng(7)
    for axis in _unit(rng.normal(size=(40, 3))):
        for radius in (2.0, 10.6, 40.0, 100.0):
            c = math.cos(math.radians(radius))
            np.testing.assert_array_equal(index.cone(axis, c), cone_naive(vec, axis, c))


def test_bad_input_is_refused():
    with pytest.raises(ParameterError, match="shape"):
        SkyIndex(np.zeros((4, 2)))
    with pytest.raises(ParameterError, match="n_bands"):
        SkyIndex(SKY, n_bands=0)


@pytest.mark.parametrize("damage", ["row", "offset", "bands", "ra"])
def test_an_index_from_arrays_is_checked_before_a_query(damage):
    """SkyIndex.from_arrays (a cache's copy of an index) takes the arrays a SkyIndex made, and refuses offsets or rows
    that would make a cone query read outside the vectors."""
    rng = np.random.default_rng(3)
    vec = rng.normal(size=(500, 3))
    vec /= np.linalg.norm(vec, axis=1, keepdims=True)
    made = SkyIndex(vec)
    again = SkyIndex.from_arrays(vec, made.cells.copy(), made.ra.copy())
    axis = np.array([0.0, 0.6, 0.8])
    assert np.array_equal(again.cone(axis, 0.9), made.cone(axis, 0.9))
    cells, ra = made.cells.copy(), made.ra.copy()
    nb = int(cells[0])
    if damage == "row":
        cells[nb + 2 + 7] = len(vec)
    elif damage == "offset":
        cells[3] = 2 * len(vec)
    elif damage == "bands":
        cells[0] = nb + 1
    else:
        ra = ra[:-1]
    with pytest.raises(ParameterError):
        SkyIndex.from_arrays(vec, cells, ra)
