"""Stellar aberration end to end (issue 39): render simulates it, attitude corrects it, its WCS is astrometric."""
import json
import math

import numpy as np
import pytest
from conftest import run_cli

ARCSEC = math.degrees(1.0) * 3600


def _frames(*extra):
    proc = run_cli("render", "--stars-only", "--count", 4, "--fov-deg", 15, "--size", "1024x1024", "--seed", 5,
                   "--mag-max", 6, "--time", "2026-09-22T12:00:00Z", "-q", *extra, check=True)
    docs = [json.loads(line) for line in proc.stdout.splitlines()]
    for d in docs:
        # The identification from the truth: this test is about the attitude.
        d["identification"] = {"status": "ok", "algorithm": "truth",
                               "matches": [{"star": i, "id": sid} for i, sid in enumerate(d["truth"]["star_ids"])
                                           if sid is not None]}
    return docs


def _attitude(docs, *args):
    proc = run_cli("attitude", "-q", *args, input="".join(json.dumps(d) + "\n" for d in docs))
    assert proc.returncode == 0, proc.stderr
    return [json.loads(line) for line in proc.stdout.splitlines()], proc.stderr


def _error_arcsec(doc):
    from startrack.accuracy import error_vector
    from startrack.rotations import quaternion_to_dcm

    e = error_vector(quaternion_to_dcm(np.array(doc["attitude"]["quaternion"])),
                     quaternion_to_dcm(np.array(doc["truth"]["quaternion"])))
    return math.hypot(e[0], e[1]) * ARCSEC


def test_attitude_removes_the_aberration_render_simulated():
    docs = _frames("--velocity-km-s", "5,-5,2")
    assert docs[0]["observer"] == {"velocity_km_s": [5.0, -5.0, 2.0]}
    fixed, err = _attitude(docs)
    plain, _ = _attitude(docs, "--no-aberration")
    for a, b in zip(fixed, plain):
        rec = a["attitude"]["apparent"]
        assert rec["aberration"] == "corrected" and rec["time_source"] == "image.time"
        assert rec["velocity_source"] == "observer.velocity_km_s" and rec["observer_velocity_km_s"] == [5, -5, 2]
        assert 22 < np.linalg.norm(rec["velocity_km_s"]) < 40
        assert b["attitude"]["apparent"] == {"aberration": "disabled", "time": "2026-09-22T12:00:00.000Z",
                                             "time_source": "image.time"}
        # Noise-free stars: the corrected attitude is the rendered one, the other is off by the aberration.
        assert _error_arcsec(a) < 0.2
        assert _error_arcsec(b) > 8
    assert err == ""


def test_velocity_option_overrides_and_no_time_is_said_once():
    docs = _frames("--velocity-km-s", "5,-5,2")
    # A wrong velocity given on the command line wins over the frames' own, and shows in the error.
    wrong, _ = _attitude(docs, "--velocity-km-s", "-5,5,-2")
    assert wrong[0]["attitude"]["apparent"]["velocity_source"] == "given"
    assert all(_error_arcsec(d) > 2 for d in wrong)
    for d in docs:
        del d["image"]["time"]
        del d["truth"]["epoch"]
    out, err = _attitude(docs)
    assert all(d["attitude"]["apparent"]["aberration"] == "no_time" for d in out)
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "image.time" in lines[0] and "--time" in lines[0]
    # --time fills it in.
    out, err = _attitude(docs, "--time", "2026-09-22T12:00:00Z")
    assert err == "" and all(_error_arcsec(d) < 0.5 for d in out)   # the epoch: proper motion from 2026.7
    assert out[0]["attitude"]["apparent"]["time_source"] == "given"


def test_wcs_maps_pixels_to_catalog_positions():
    from astropy.wcs import WCS

    from startrack.catalog import load_catalog

    docs = _frames("--velocity-km-s", "7,0,0")
    out, _ = _attitude(docs)
    cat = load_catalog().propagate(out[0]["attitude"]["epoch"])
    rows = cat.rows_by_id()
    for d in out:
        # A TAN WCS holds the aberration to first order in the field angle; the rest is below (v/c) theta^2.
        beta = np.linalg.norm(d["attitude"]["apparent"]["velocity_km_s"]) / 299792.458
        limit = beta * (math.hypot(512, 512) / d["camera"]["focal_length_px"]) ** 2 * ARCSEC
        wcs = WCS({k: v for k, v in d["attitude"]["wcs"].items()})
        for s in d["truth"]["stars"]:
            if s.get("blended"):
                continue
            ra, dec = wcs.all_pix2world([[s["x"], s["y"]]], 0)[0]
            r = rows[s["id"]]
            dra = (ra - cat.ra[r] + 180) % 360 - 180
            sep = math.hypot(dra * math.cos(math.radians(dec)), dec - cat.dec[r]) * 3600
            assert sep < limit, (s["id"], sep)


@pytest.mark.parametrize("bad", ["1,2", "1,2,x", "9000,0,0"])
def test_bad_velocity_is_exit_2(bad):
    proc = run_cli("attitude", "--velocity-km-s", bad, input="")
    assert proc.returncode == 2 and "--velocity-km-s" in proc.stderr and "Traceback" not in proc.stderr


@pytest.mark.parametrize("match,time", [("--match-all", "2026-09-22T12:00:00Z"),
                                        ("--database-only", "1991-04-02T13:30:00Z")])
def test_identify_quaternion_estimate_is_the_true_orientation(tmp_path, match, time):
    """identify's final match and quaternion_estimate use the apparent places (issue 39: "it applies in
    identify"), and with the catalog the database's stars moved to the frame's time; on main the estimate
    was the astrometric one at the database's epoch, 12" off the camera's orientation.  (--database-only
    has no catalog, so no proper motion: its frames are at the database's epoch.)"""
    db = tmp_path / "db.h5"
    run_cli("build-kvector", "--fov-deg", 15, "--size", "1024x1024", "--mag-max", 5.5, "-o", db, check=True)
    proc = run_cli("render", "--stars-only", "--count", 8, "--fov-deg", 15, "--size", "1024x1024", "--seed", 5,
                   "--mag-max", 6, "--time", time, "--velocity-km-s", "5,-5,2", "-q", check=True)
    got = {}
    for flag in ((), ("--no-aberration",)):
        out = run_cli("identify", "-d", db, "-q", match, *flag, input=proc.stdout)
        assert out.returncode == 0, out.stderr
        got[flag] = [json.loads(line) for line in out.stdout.splitlines()]
    errors = {True: [], False: []}
    for a, b in zip(got[()], got[("--no-aberration",)], strict=True):
        assert a["identification"]["apparent"]["aberration"] == "corrected"
        assert b["identification"]["apparent"]["aberration"] == "disabled"
        assert all(a["truth"]["star_ids"][m["star"]] == m["id"] for m in a["identification"]["matches"])
        for doc, corrected in ((a, True), (b, False)):
            doc["attitude"] = {"quaternion": doc["identification"]["quaternion_estimate"]}
            errors[corrected].append(_error_arcsec(doc))
    # Noise-free stars: the estimate is the rendered orientation (within the blends' photocentres); without the
    # correction it is off by the aberration.
    rms = {k: math.sqrt(np.mean(np.square(v))) for k, v in errors.items()}
    assert rms[True] < 2.0 and rms[False] > 8, rms


def test_render_and_attitude_place_sirius_with_its_parallax():
    """Parallax (issue 39: "parallax for the stars that have one"): render puts Sirius (HIP 32349, 379 mas) where
    astropy's GCRS puts a star at its distance, within 0.05" (without the parallax term 0.34" off on 2026-03-01),
    and attitude, applying the same, leaves it no residual.  (Not alpha Centauri: A and B blend into one image.)"""
    from astropy import units
    from astropy.coordinates import GCRS, SkyCoord
    from astropy.time import Time

    from startrack.camera import Camera
    from startrack.catalog import load_catalog
    from startrack.rotations import quaternion_to_dcm

    when = "2026-03-01T00:00:00Z"
    proc = run_cli("render", "--stars-only", "--count", 1, "--fov-deg", 10, "--size", "1024x1024", "--ra", 101.29,
                   "--dec", -16.71, "--roll", 0, "--mag-max", 4.5, "--time", when, "-q", check=True)
    doc = json.loads(proc.stdout)
    star = next(s for s in doc["truth"]["stars"] if s["id"] == 32349)
    cam = Camera.from_dict(doc["camera"])
    seen = quaternion_to_dcm(np.array(doc["truth"]["quaternion"])).T @ cam.pixels_to_vectors(star["x"], star["y"])
    cat = load_catalog()
    r = cat.rows_by_id()[32349]
    coord = SkyCoord(ra=cat.ra[r] * units.deg, dec=cat.dec[r] * units.deg, distance=(1000 / cat.plx[r]) * units.pc,
                     pm_ra_cosdec=cat.pm_ra[r] * units.mas / units.yr, pm_dec=cat.pm_dec[r] * units.mas / units.yr,
                     radial_velocity=0 * units.km / units.s, obstime=Time(cat.epoch, format="jyear"), frame="icrs")
    t = Time(when.replace("Z", ""), scale="utc")
    g = coord.apply_space_motion(new_obstime=t).transform_to(GCRS(obstime=t)).cartesian.xyz.value
    g /= np.linalg.norm(g)
    assert math.acos(min(1.0, float(seen @ g))) * ARCSEC < 0.05
    doc["identification"] = {"status": "ok", "algorithm": "truth",
                             "matches": [{"star": i, "id": sid} for i, sid in enumerate(doc["truth"]["star_ids"])
                                         if sid is not None]}
    (out,), _ = _attitude([doc])
    resid = {r_["id"]: r_["residual_arcsec"] for r_ in out["attitude"]["residuals"]}
    assert resid[32349] < 0.05
