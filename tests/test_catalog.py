import math

import numpy as np
import pytest
from naive import count_in_fov_naive, pairs_within_naive

from startrack.camera import Camera
from startrack.catalog import Catalog, field_statistics, load_catalog, star_pairs, write_catalog
from startrack.errors import BadInputError
from startrack.rotations import quaternion_to_dcm, random_quaternions


def test_shipped_catalog(catalog):
    # The whole Hipparcos 2 catalogue (catalogs/README.md): 117,955 stars, Hp -1.09 to 14.56.
    assert len(catalog) == 117955
    assert catalog.mag.max() == pytest.approx(14.5622, abs=1e-3)
    assert int(np.sum(catalog.mag <= 8.0)) == 37622
    assert catalog.epoch == 1991.25
    assert np.all(np.diff(catalog.mag) >= 0)            # brightest first
    assert len(np.unique(catalog.id)) == len(catalog)
    sirius = catalog.subset(catalog.id == 32349)
    assert sirius.ra[0] == pytest.approx(101.2885, abs=1e-3) and sirius.dec[0] == pytest.approx(-16.7131, abs=1e-3)


def test_counts_per_magnitude_match_paper_003_table_2(catalog):
    # Paper 003 Table 2 counts Hipparcos stars per Hp bin: 165 / 315 / 991 / 3088 / 9381.
    hist, _ = np.histogram(catalog.mag, bins=[-5, 3, 4, 5, 6, 7, 9])
    assert hist[:5].tolist() == [165, 315, 991, 3088, 9381]


def test_filter_magnitude(catalog):
    f = catalog.filter_magnitude(2.5, 6.59)
    assert len(f) == int(np.sum((catalog.mag >= 2.5) & (catalog.mag <= 6.59)))
    assert f.mag.min() >= 2.5 and f.mag.max() <= 6.59
    with pytest.raises(BadInputError, match="larger than"):
        catalog.filter_magnitude(6, 3)


def test_proper_motion_barnards_star(catalog):
    # Groombridge 1830 (HIP 57939, Hp 6.6) moves about 7 arcsec per year, mostly south.
    b = catalog.subset(catalog.id == 57939)
    later = b.propagate(b.epoch + 10.0)
    sep = math.degrees(math.acos(np.clip(b.vectors()[0] @ later.vectors()[0], -1, 1))) * 3600
    expected = math.hypot(b.pm_ra[0], b.pm_dec[0]) * 10 / 1000
    assert sep == pytest.approx(expected, rel=1e-3)
    assert sep > 69
    assert later.dec[0] < b.dec[0]
    back = later.propagate(b.epoch)
    assert back.dec[0] == pytest.approx(b.dec[0], abs=1e-10)
    assert back.ra[0] == pytest.approx(b.ra[0], abs=1e-10)
    assert back.pm_dec[0] == pytest.approx(b.pm_dec[0], abs=1e-6)


def _toy(ra, dec, mag):
    n = len(ra)
    return Catalog(np.arange(1, n + 1), np.array(ra, float), np.array(dec, float), np.array(mag, float),
                   np.zeros(n), np.zeros(n), np.full(n, np.nan), 2000.0)


def test_merge_close_combines_brightness():
    cat = _toy([10.0, 10.0 + 5 / 3600, 50.0], [20.0, 20.0, 0.0], [3.0, 3.0, 4.0])
    merged = cat.merge_close(10.0)
    assert len(merged) == 2
    assert merged.mag[0] == pytest.approx(3.0 - 2.5 * math.log10(2))
    assert merged.ra[0] == pytest.approx(10.0 + 2.5 / 3600 * 1, abs=1e-6)
    assert merged.params["merged_groups"] == 1


def test_thin_uniform_caps_each_cell(catalog):
    thin = catalog.filter_magnitude(None, 7.0).thin_uniform(5, cell_deg=6.0)
    assert 0 < len(thin) < len(catalog)
    # The brightest star of the sky survives any thinning.
    assert 32349 in thin.id


def test_star_pairs_match_brute_force(catalog):
    sub = catalog.filter_magnitude(None, 4.5)
    vec = sub.vectors()
    for deg in (0.5, 5.0, 21.0):
        a, b, cosine = star_pairs(vec, math.radians(deg))
        got = set(zip(a.tolist(), b.tolist()))
        assert got == pairs_within_naive(vec, math.radians(deg))
        np.testing.assert_allclose(cosine, np.sum(vec[a] * vec[b], axis=1), atol=1e-15)


def test_field_statistics_match_naive(catalog):
    cat = catalog.filter_magnitude(None, 5.0)
    cam = Camera.from_fov(20, 1024, 768, k1=-0.02)
    stats = field_statistics(cat, cam, 300, np.random.default_rng(3))
    dcms = quaternion_to_dcm(random_quaternions(300, np.random.default_rng(3)))
    vec = cat.vectors()
    for k in range(300):
        n, brightest = count_in_fov_naive(vec, cat.mag, dcms[k], cam)
        assert stats.counts[k] == n
        if n:
            assert stats.brightest_mag[k] == brightest


def test_write_formats(tmp_path, catalog):
    sub = catalog.filter_magnitude(None, 2.0)
    p = tmp_path / "c.h5"
    write_catalog(sub, str(p))
    back = load_catalog(str(p))
    np.testing.assert_array_equal(back.id, sub.id)
    np.testing.assert_allclose(back.ra, sub.ra)
    assert back.checksum() == load_catalog(str(p)).checksum()
    assert back.params["mag_max"] == 2.0
    csv = tmp_path / "c.csv"
    write_catalog(sub, str(csv))
    lines = csv.read_text().splitlines()
    assert lines[0].startswith("# startrack") and lines[1].startswith("id,ra_deg")
    assert len(lines) == len(sub) + 2
    with pytest.raises(BadInputError, match="unknown output extension"):
        write_catalog(sub, str(tmp_path / "c.txt"))


def test_load_catalog_mag_max_reads_only_the_bright_stars(catalog):
    bright = load_catalog(mag_max=6.0)
    ref = catalog.filter_magnitude(None, 6.0)
    assert len(bright) == len(ref) == 4559
    assert np.array_equal(bright.id, ref.id) and np.array_equal(bright.ra, ref.ra)
    assert np.array_equal(bright.mag, ref.mag)


def test_merge_close_names_the_brighter_and_lists_the_others(tmp_path):
    # A chain: 1 (mag 5) - 6" - 2 (mag 4) - 6" - 3 (mag 6); an 8" radius joins all three.
    d = 6.0 / 3600.0
    cat = _toy([10.0, 10.0 + d, 10.0 + 2 * d, 40.0], [0.0, 0.0, 0.0, 0.0], [5.0, 4.0, 6.0, 3.0])
    merged = cat.merge_close(8.0)
    assert sorted(merged.id.tolist()) == [2, 4]
    assert merged.merged == {2: [1, 3]}
    flux = 10 ** (-0.4 * np.array([5.0, 4.0, 6.0]))
    k = int(np.flatnonzero(merged.id == 2)[0])
    assert merged.mag[k] == pytest.approx(-2.5 * math.log10(flux.sum()), abs=1e-9)
    assert merged.ra[k] == pytest.approx(10.0 + d * (flux[1] + 2 * flux[2]) / flux.sum(), abs=1e-9)
    # The merged list survives a round trip through the catalog file.
    path = str(tmp_path / "m.h5")
    write_catalog(merged, path)
    assert load_catalog(path).merged == {2: [1, 3]}


def test_merge_close_unresolved_doubles_of_the_issue(catalog):
    # Pairs 20-35" apart that a 15 deg 1280 px sensor (42"/px) sees as one star.
    merged = catalog.filter_magnitude(None, 6.0).merge_close(2 * 15 * 3600 / 1280)
    for bright, faint in ((86614, 86620), (63003, 63005), (5131, 5132)):
        assert bright in merged.id and faint not in merged.id
        assert faint in merged.merged[bright]


def test_thin_for_field_gives_every_field_about_the_same_stars(catalog):
    from startrack.catalog import thin_for_field

    cam = Camera.from_fov(6.0, 1392, 1040)
    thin = thin_for_field(catalog, *cam.fov_deg, stars_per_field=30)
    limit = thin.params["depth_mag_max"]
    assert thin.mag.max() <= limit and 8.0 < limit < 10.5
    counts = field_statistics(thin, cam, 300, np.random.default_rng(3)).counts
    full = field_statistics(catalog.filter_magnitude(None, limit), cam, 300, np.random.default_rng(3)).counts
    p5, p95 = np.percentile(counts, [5, 95])
    # 95 % of the sky holds at least about two thirds of the wanted 30 stars ...
    assert p5 >= 20
    # ... and thinning evens out the Milky Way: the spread is far below the unthinned catalog's.
    assert p95 / p5 < 2.0 and np.percentile(full, 95) / np.percentile(full, 5) > 2.0


def test_photocentres_around_stars_agree_with_the_merged_catalog():
    """The local photocentre of a star and its companions is merge_close's entry for that group (pairs)."""
    from startrack.catalog import load_catalog

    cat = load_catalog().filter_magnitude(mag_max=8.0)
    radius = 60.0
    merged = cat.merge_close(radius)
    rows = cat.rows_by_id()
    pairs = [i for i, others in merged.merged.items() if len(others) == 1]
    assert len(pairs) > 20
    local = cat.photocentres([rows[i] for i in pairs], radius)
    mrows, mvec = merged.rows_by_id(), merged.vectors()
    worst = max(float(np.degrees(np.arccos(min(1.0, local[i] @ mvec[mrows[i]])))) * 3600 for i in pairs)
    assert worst < 0.01, worst        # arcsec (merge_close averages in float32 magnitudes)
    grouped = set(merged.merged) | {int(j) for others in merged.merged.values() for j in others}
    lonely = [r for r in range(len(cat)) if int(cat.id[r]) not in grouped][:200]
    assert cat.photocentres(lonely, radius) == {}


def test_rows_and_vectors_are_built_once_and_match_a_fresh_computation(catalog):
    """rows_by_id and vectors are kept on the catalog (issue 38: rebuilt per solve they were 70 % of it),
    equal to what they were computed as, the id index read-only, and rebuilt when a column is replaced."""
    import pickle

    from startrack.rotations import radec_to_vector

    sub = catalog.subset(np.arange(0, len(catalog), 7))
    rows, vec = sub.rows_by_id(), sub.vectors()
    assert sub.rows_by_id() is rows and sub.vectors() is vec
    assert dict(rows) == {int(i): k for k, i in enumerate(sub.id)}
    np.testing.assert_array_equal(vec, radec_to_vector(sub.ra, sub.dec))
    assert vec.flags.c_contiguous and vec.flags.writeable      # numba takes it as it takes any array
    with pytest.raises(TypeError):
        rows[1] = 2
    # A replaced column is noticed (the arrays are the cache's key).
    sub.ra = sub.ra + 1.0
    np.testing.assert_array_equal(sub.vectors(), radec_to_vector(sub.ra, sub.dec))
    # Workers get the catalog without its derived tables, and rebuild the same.
    back = pickle.loads(pickle.dumps(sub))
    assert not any(k.startswith("_cache_") for k in back.__dict__)
    np.testing.assert_array_equal(back.vectors(), sub.vectors())
    # Derived catalogs do not inherit the tables.
    later = sub.propagate(2030.0)
    assert later.vectors() is not sub.vectors() and not np.array_equal(later.vectors(), sub.vectors())
