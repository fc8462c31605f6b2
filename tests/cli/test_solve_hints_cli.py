"""Issue 40 through the real CLI: `solve --ra/--dec/--radius`, `--scale-low/--scale-high/--scale-units`,
`--target-pixel`/`--target-radec`, astrometry.net's corr and axy tables, `--fits-out` in the image's own type,
and a wrong hint that says it may be wrong.  Each failed on main before the change."""
import csv
import glob
import json
import math
import os

import numpy as np
import pytest
from conftest import DATA, assert_refused, run_cli

REAL = sorted(glob.glob(os.path.join(DATA, "real", "*.tiff")))
ESA = REAL[0]
REF = {r["file"]: r for r in csv.DictReader(open(os.path.join(DATA, "real", "solutions.csv")))}[os.path.basename(ESA)]


def _solve(cache, *args, ok=(0,)):
    proc = run_cli("solve", ESA, "-q", "--no-aberration", *args, env=cache)
    assert proc.returncode in ok, proc.stderr
    return json.loads(proc.stdout), proc


@pytest.fixture(scope="module")
def tables(solve_cache, tmp_path_factory):
    out = tmp_path_factory.mktemp("tables")
    ra, dec = float(REF["ra_deg"]), float(REF["dec_deg"])
    doc, _ = _solve(solve_cache, "--ra", ra + 2, "--dec", dec - 3, "--radius", 6, "--scale-low", 10,
                    "--scale-high", 13, "--target-pixel", "100,200", "--target-pixel", "0,0", "--target-radec",
                    f"{ra},{dec}", "--corr-out", out / "corr.fits", "--axy-out", out / "field.axy", "--fits-out",
                    out / "new.fits", "--wcs", out / "w.fits")
    return doc, out


def test_hints_are_recorded_and_the_answer_is_the_blind_one(tables, solve_cache):
    doc, _ = tables
    blind, _ = _solve(solve_cache)
    assert doc["solve"]["status"] == "ok"
    assert doc["attitude"]["quaternion"] == pytest.approx(blind["attitude"]["quaternion"], abs=1e-12)
    ra, dec = float(REF["ra_deg"]), float(REF["dec_deg"])
    assert doc["solve"]["hint"] == pytest.approx({"ra": ra + 2, "dec": dec - 3, "radius": 6.0, "fov_min": 10.0,
                                                  "fov_max": 13.0})


def test_targets_answer_pixels_and_sky_positions(tables):
    from astropy.io import fits
    from astropy.wcs import WCS

    doc, out = tables
    t = doc["solve"]["targets"]
    assert [x["given"] for x in t] == ["pixel", "pixel", "radec"]
    wcs = WCS(fits.getheader(out / "w.fits"))
    for target in t[:2]:
        sky = wcs.pixel_to_world(target["x"], target["y"])
        assert sky.separation(_coord(target["ra"], target["dec"])).arcsec < 1e-6
        assert target["in_image"]
    # The reference solution's centre (astrometry.net) is the image's middle pixel, within a pixel or two.
    centre = t[2]
    assert centre["in_image"]
    assert math.hypot(centre["x"] - 511.5, centre["y"] - 383.5) < 3


def _coord(ra, dec):
    from astropy.coordinates import SkyCoord

    return SkyCoord(ra, dec, unit="deg")


def test_corr_and_axy_tables_in_astrometry_net_layout(tables):
    from astropy.table import Table

    doc, out = tables
    corr = Table.read(out / "corr.fits")
    for name in ("field_x", "field_y", "field_ra", "field_dec", "index_x", "index_y", "index_ra", "index_dec",
                 "index_id", "field_id", "match_weight", "FLUX"):
        assert name in corr.colnames, name
    assert len(corr) == len(doc["identification"]["matches"])
    stars = doc["stars"]
    for row in corr:
        star = stars[int(row["field_id"])]
        # FITS (astrometry.net) pixels are ours plus one.
        assert row["field_x"] == pytest.approx(star["x"] + 1) and row["field_y"] == pytest.approx(star["y"] + 1)
    # A matched detection and its catalog star agree: in pixels (the catalog star projected) and on the sky.
    dpx = np.hypot(corr["field_x"] - corr["index_x"], corr["field_y"] - corr["index_y"])
    assert np.median(dpx) < 0.5 and np.max(dpx) < 3
    sep = _coord(corr["field_ra"], corr["field_dec"]).separation(_coord(corr["index_ra"], corr["index_dec"])).arcsec
    assert np.median(sep) < 10
    ids = {m["star"]: m["id"] for m in doc["identification"]["matches"]}
    assert all(ids[int(r["field_id"])] == int(r["index_id"]) for r in corr)
    used = {(r["star"], r["id"]) for r in doc["attitude"]["residuals"]}
    assert [bool(w) for w in corr["match_weight"]] == [(int(f), int(i)) in used
                                                      for f, i in zip(corr["field_id"], corr["index_id"])]
    axy = Table.read(out / "field.axy")
    assert axy.colnames[:3] == ["X", "Y", "FLUX"] and len(axy) == len(stars)
    assert axy.meta["IMAGEW"] == 1024 and axy.meta["IMAGEH"] == 768
    assert np.asarray(axy["X"]) == pytest.approx([s["x"] + 1 for s in stars])
    assert doc["solve"]["corr_path"] == str(out / "corr.fits") and doc["solve"]["axy_path"] == str(out / "field.axy")


def test_fits_out_keeps_the_images_type(tables):
    from astropy.io import fits

    from startrack.imageio import read_image

    _, out = tables
    data = fits.getdata(out / "new.fits")
    image, meta = read_image(ESA)
    assert meta["bit_depth"] == 16 and data.dtype == np.uint16
    np.testing.assert_array_equal(data, image.astype(np.uint16))


def test_arcsec_per_pixel_is_the_same_field(solve_cache):
    """--scale-units arcsecperpix is the scale at the image centre: a pinhole camera of the reference field (its
    focal length from Camera.from_fov) has atan(1 / f) per pixel there, and that scale gives back the field."""
    from startrack.camera import Camera

    fov = float(REF["fov_x_deg"])
    scale = math.degrees(math.atan(1.0 / Camera.from_fov(fov, 1024, 768).focal_length_px)) * 3600
    doc, _ = _solve(solve_cache, "--scale-low", scale * 0.999, "--scale-high", scale * 1.001, "--scale-units",
                    "arcsecperpix")
    assert doc["solve"]["status"] == "ok"
    lo, hi = doc["solve"]["hint"]["fov_min"], doc["solve"]["hint"]["fov_max"]
    assert lo < fov < hi and (lo, hi) == pytest.approx((fov * 0.999, fov * 1.001), rel=1e-4)


@pytest.mark.parametrize("args, says", [
    (("--ra", "50", "--dec", "-40", "--radius", "5"), "boresight within 5 deg of RA 50, Dec -40"),
    (("--scale-low", "30", "--scale-high", "40"), "field of view 30 to 40 deg"),
    (("--fov-deg", "40"), "field of view 36 to 44 deg"),
])
def test_a_wrong_hint_says_it_may_be_wrong(solve_cache, args, says):
    doc, proc = _solve(solve_cache, *args, "--timeout-s", "3", ok=(1,))
    reason = doc["solve"]["reason"]
    assert doc["solve"]["status"] == "failed" and f"the hint ({says}) may be wrong" in reason, reason
    assert "may be wrong" in proc.stderr


def test_hint_options_are_checked():
    assert_refused(run_cli("solve", ESA, "--ra", "10", "--dec", "20"), "--radius", "go together")
    assert_refused(run_cli("solve", ESA, "--dec", "95", "--ra", "1", "--radius", "1"), "--dec")
    proc = run_cli("solve", ESA, "--scale-low", "12", "--scale-high", "10")
    assert proc.returncode == 2 and "larger than" in proc.stderr
    proc = run_cli("solve", ESA, "--fov-deg", "11", "--scale-low", "10")
    assert proc.returncode == 2 and "exclude each other" in proc.stderr
    assert_refused(run_cli("solve", ESA, "--target-pixel", "1"), "--target-pixel")
