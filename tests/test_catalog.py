import math

import numpy as np
import pytest

from startrack.camera import Camera
from startrack.catalog import Catalog, field_statistics, load_catalog, star_pairs, write_catalog
from startrack.errors import BadInputError
from startrack.rotations import quaternion_to_dcm, random_quaternions

from naive import count_in_fov_naive, pairs_within_naive


def test_shipped_catalog(catalog):
    assert len(catalog) > 37000
    assert catalog.mag.max() <= 8.0
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
