import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from naive import pairs_within_naive

from startrack.camera import Camera
from startrack.errors import DatabaseMismatchError
from startrack.kvector import build_kvector, check_database, load_kvector, max_separation_deg, save_kvector
from startrack.labels import build_labels, label_from_distances, load_labels, save_labels


@pytest.fixture(scope="module")
def db20(catalog):
    return build_kvector(catalog.filter_magnitude(None, 5.0), max_separation_deg(20.0))


def test_pairs_are_exactly_the_close_pairs(db20):
    pairs = set(zip(db20.pair_i.tolist(), db20.pair_j.tolist()))
    assert pairs == pairs_within_naive(db20.star_vector, math.radians(db20.max_angle_deg))
    assert np.all(np.diff(db20.pair_cos) >= 0)
    # Brighter star first (paper 003 Sec. 4.2.1).
    assert np.all(db20.star_mag[db20.pair_i] <= db20.star_mag[db20.pair_j])
    np.testing.assert_allclose(np.sum(db20.star_vector[db20.pair_i] * db20.star_vector[db20.pair_j], axis=1),
                               db20.pair_cos, atol=1e-15)


def test_neighbour_lists(db20):
    for s in (0, 17, 500, db20.n_stars - 1):
        nb = set(db20.neighbor_idx[db20.neighbor_ptr[s]:db20.neighbor_ptr[s + 1]].tolist())
        expected = set(db20.pair_j[db20.pair_i == s].tolist()) | set(db20.pair_i[db20.pair_j == s].tolist())
        assert nb == expected


@settings(max_examples=3000, deadline=None)
@given(centre=st.floats(0.0, 0.999), width=st.floats(1e-7, 3e-3))
def test_kvector_returns_exactly_the_brute_force_pairs(db20, centre, width):
    cos_centre = math.cos(math.radians(db20.max_angle_deg)) + centre * (1 - math.cos(math.radians(db20.max_angle_deg)))
    lo, hi = cos_centre - width, min(cos_centre + width, 1.0)
    truth = np.flatnonzero((db20.pair_cos >= lo) & (db20.pair_cos <= hi))
    s1, e1 = db20.range_linear(lo, hi)
    s2, e2 = db20.range_quadratic(lo, hi)
    s3, e3 = db20.range_quadratic_pure(lo, hi)
    for s, e in ((s1, e1), (s2, e2), (s3, e3)):
        got = np.arange(s, e)
        got = got[(db20.pair_cos[got] >= lo) & (db20.pair_cos[got] <= hi)]
        np.testing.assert_array_equal(got, truth)
    assert e2 - s2 <= e1 - s1


def test_kvector_scans_about_one_extra_pair(db20):
    rng = np.random.default_rng(5)
    extra = []
    for _ in range(5000):
        angle = rng.uniform(0.5, db20.max_angle_deg - 0.5)
        half = rng.uniform(1, 60) / 3600
        lo, hi = math.cos(math.radians(angle + half)), math.cos(math.radians(angle - half))
        s, e = db20.range_linear(lo, hi)
        extra.append((e - s) - np.sum((db20.pair_cos >= lo) & (db20.pair_cos <= hi)))
    assert np.mean(extra) < 2.0 and np.percentile(extra, 99) <= 6


def test_pairs_between_angles(db20):
    idx = db20.pairs_between(math.radians(10.0), math.radians(10.01))
    ang = np.degrees(np.arccos(db20.pair_cos[idx]))
    assert len(idx) > 0 and np.all((ang >= 10.0 - 1e-9) & (ang <= 10.01 + 1e-9))


def test_save_load_and_mismatch_checks(tmp_path, db20, catalog):
    p = str(tmp_path / "db.h5")
    db20.path = ""
    save_kvector(db20, p)
    back = load_kvector(p)
    np.testing.assert_array_equal(back.pair_cos, db20.pair_cos)
    np.testing.assert_array_equal(back.kvector, db20.kvector)
    assert back.line == db20.line and back.catalog_sha256 == db20.catalog_sha256
    check_database(back, Camera.from_fov(20, 1024, 1024), catalog.filter_magnitude(None, 5.0))
    with pytest.raises(DatabaseMismatchError, match="max_angle_deg.*rebuild"):
        check_database(back, Camera.from_fov(30, 1024, 1024))
    with pytest.raises(DatabaseMismatchError, match="another, wider|built for a field"):
        check_database(back, Camera.from_fov(5, 1024, 1024))
    with pytest.raises(DatabaseMismatchError, match="catalog_sha256"):
        check_database(back, None, catalog.filter_magnitude(None, 5.5))


def test_label_table_1():
    # Paper 004 Table 1: 452, 385, 276 px with r = 2 -> sub-labels 85, 61 -> 8561.
    assert label_from_distances([452, 385, 276], 2) == 8561
    assert label_from_distances([276, 452, 385], 2) == 8561      # order does not matter
    assert label_from_distances([452, 385, 276], 3) == 852611


@pytest.fixture(scope="module")
def labels24(catalog):
    return build_labels(catalog.filter_magnitude(None, 5.2), 24.0, step_deg=2.0)


def test_label_database_lookup_and_order(labels24):
    db = labels24
    assert np.all(np.diff(db.label) >= 0)
    rng = np.random.default_rng(0)
    for k in rng.integers(0, len(db.label), 3000):
        s, e = db.lookup(int(db.label[k]))
        assert s <= k < e
        assert np.all(db.label[s:e] == db.label[k])
    assert db.lookup(int(db.label.max()) + 1) == (len(db.label), len(db.label)) or \
        db.lookup(int(db.label.max()) + 1)[0] == db.lookup(int(db.label.max()) + 1)[1]
    # No duplicate groups.
    assert len(np.unique(np.sort(db.members, axis=1), axis=0)) == len(db.members)


def test_stored_labels_recompute_from_the_stars(labels24):
    db = labels24
    for k in np.random.default_rng(1).integers(0, len(db.label), 200):
        members = db.members[k]
        v = db.star_vector[members]
        d = [math.acos(np.clip(v[a] @ v[b], -1, 1)) for a in range(4) for b in range(a + 1, 4)]
        assert label_from_distances(d, 2) == db.label[k]
        sums = [sum(math.acos(np.clip(v[a] @ v[b], -1, 1)) for b in range(4) if b != a) for a in range(4)]
        assert sums == sorted(sums, reverse=True)        # Sec. 2.3 order


def test_labels_save_load(tmp_path, labels24):
    p = str(tmp_path / "labels.h5")
    save_labels(labels24, p)
    back = load_labels(p)
    np.testing.assert_array_equal(back.label, labels24.label)
    np.testing.assert_array_equal(back.members, labels24.members)
    k = 1234
    assert back.lookup(int(back.label[k]))[0] <= k
