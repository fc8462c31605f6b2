"""Mirrored images (issue 37): solve, identify and track try both parities, and write WCS of the right sign."""
import json
import math

import numpy as np
import pytest
from conftest import run_cli

from startrack.attitude import wcs_header
from startrack.camera import Camera
from startrack.catalog import load_catalog
from startrack.rotations import quaternion_to_dcm, radec_roll_to_dcm

SIZE = ("--fov-deg", "12", "--size", "640x480")


def _render(tmp_path, name, *extra, seed=3):
    out = tmp_path / f"{name}.png"
    doc = json.loads(run_cli("render", *SIZE, "--seed", seed, "-o", out, "-q", *extra, check=True).stdout)
    return out, doc


def _angle_arcsec(a, b):
    return math.degrees(math.acos(max(-1.0, min(1.0, (np.trace(np.asarray(a) @ np.asarray(b).T) - 1) / 2)))) * 3600


def _sky_errors_arcsec(header, doc, fits_xy):
    """Angular errors of the WCS at each truth star: FITS pixel ``fits_xy(star)`` against its catalog position."""
    from astropy.wcs import WCS

    cat = load_catalog()
    rows = cat.rows_by_id()
    w = WCS(header)
    errors = []
    for s in doc["truth"]["stars"][:15]:
        fx, fy = fits_xy(s)
        ra, dec = w.all_pix2world([[fx, fy]], 1)[0]
        r = rows[s["id"]]
        d = math.degrees(math.acos(min(1.0, math.sin(math.radians(dec)) * math.sin(math.radians(cat.dec[r]))
                                       + math.cos(math.radians(dec)) * math.cos(math.radians(cat.dec[r]))
                                       * math.cos(math.radians(ra - cat.ra[r])))))
        errors.append(d * 3600)
    return errors


@pytest.fixture(scope="module")
def frames(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("parity")
    return tmp, {m: _render(tmp, m, *(("--mirror", m) if m != "none" else ())) for m in ("none", "x", "y")}


def test_mirrored_frames_solve_mirrored_with_the_right_attitude_and_wcs(frames, solve_cache):
    from astropy.io import fits

    tmp, rendered = frames
    paths = [rendered[m][0] for m in ("none", "x", "y")]
    proc = run_cli("solve", *paths, "--wcs", str(tmp / "wcs") + "/", env=solve_cache, timeout=600)
    assert proc.returncode == 0, proc.stderr
    docs = {m: json.loads(line) for m, line in zip(("none", "x", "y"), proc.stdout.splitlines())}
    dets = {}
    for m, d in docs.items():
        truth = rendered[m][1]["truth"]
        assert d["solve"]["status"] == "ok" and d["solve"]["parity"] == ("normal" if m == "none" else "mirrored")
        assert d["identification"]["parity"] == d["solve"]["parity"]
        a = quaternion_to_dcm(np.array(d["attitude"]["quaternion"]))
        t = quaternion_to_dcm(np.array(truth["quaternion"]))
        if m == "y":
            # A row flip is the column flip and half a turn about the boresight.
            t = radec_roll_to_dcm(truth["ra"], truth["dec"], truth["roll"] + 180.0)
        assert _angle_arcsec(a, t) < 60, m
        header = fits.getheader(tmp / "wcs" / f"{m}.wcs.fits")
        dets[m] = header["CD1_1"] * header["CD2_2"] - header["CD1_2"] * header["CD2_1"]
        # The WCS puts every star of the written image on its catalog position.
        assert max(_sky_errors_arcsec(header, rendered[m][1], lambda s: (s["x"] + 1, s["y"] + 1))) < 20, m
    assert np.sign(dets["x"]) == np.sign(dets["y"]) == -np.sign(dets["none"])


def test_parity_normal_does_not_solve_a_mirrored_frame_and_says_so(frames, solve_cache):
    _, rendered = frames
    proc = run_cli("solve", rendered["x"][0], "--parity", "normal", env=solve_cache, timeout=600)
    assert proc.returncode == 1
    doc = json.loads(proc.stdout)
    assert doc["solve"]["status"] == "failed" and "normal parity only" in doc["solve"]["reason"]
    proc = run_cli("solve", rendered["none"][0], "--parity", "mirrored", env=solve_cache, timeout=600)
    assert proc.returncode == 1 and "mirrored parity only" in json.loads(proc.stdout)["solve"]["reason"]


def test_fits_stored_bottom_up_round_trips_to_the_same_sky(frames, solve_cache):
    """A FITS file written bottom-up (its first row the scene's bottom row, as FITS displays it): solved as a
    mirrored image, its WCS in the file's own pixels puts each star on the sky where the PNG's does."""
    import cv2
    from astropy.io import fits

    tmp, rendered = frames
    png, doc = rendered["none"]
    image = cv2.imread(str(png), cv2.IMREAD_UNCHANGED)
    height = image.shape[0]
    fits.PrimaryHDU(image[::-1]).writeto(tmp / "bottom-up.fits")
    proc = run_cli("solve", tmp / "bottom-up.fits", "--wcs", tmp / "bottom-up.wcs.fits", env=solve_cache, timeout=600)
    assert proc.returncode == 0, proc.stderr
    solved = json.loads(proc.stdout)
    assert solved["solve"]["parity"] == "mirrored"
    header = fits.getheader(tmp / "bottom-up.wcs.fits")
    # Our row y of the PNG is the file's row height - 1 - y, FITS pixel height - y.
    assert max(_sky_errors_arcsec(header, doc, lambda s: (s["x"] + 1, height - s["y"]))) < 20
    # The centre of the picture is the same sky either way.
    a = solved["solve"]
    plain = json.loads(run_cli("solve", png, env=solve_cache, check=True, timeout=600).stdout)["solve"]
    assert a["center_ra"] == pytest.approx(plain["center_ra"], abs=2e-3)
    assert a["center_dec"] == pytest.approx(plain["center_dec"], abs=2e-3)


def test_calibrate_refuses_mirrored_frames(frames, solve_cache):
    from conftest import assert_refused

    _, rendered = frames
    solved = run_cli("solve", rendered["x"][0], env=solve_cache, check=True, timeout=600).stdout
    assert_refused(run_cli("calibrate", "-", "-o", rendered["x"][0].with_suffix(".json"), input=solved), "mirrored")


def test_noise_frames_still_fail(tmp_path, solve_cache):
    run_cli("render", *SIZE, "--frames", "3", "--blackout", "0:3", "--false-stars", "40", "--seed", "4",
            "-o", tmp_path / "noise.png", "-q", check=True)
    proc = run_cli("solve", *sorted(tmp_path.glob("noise-*.png")), env=solve_cache, timeout=600)
    assert proc.returncode == 1
    docs = [json.loads(line) for line in proc.stdout.splitlines()]
    assert len(docs) == 3 and all(d["solve"]["status"] == "failed" for d in docs)
    assert all("either parity" in d["solve"]["reason"] or "within" in d["solve"]["reason"] for d in docs)


def test_identify_and_track_find_the_parity(tmp_path):
    db = tmp_path / "db.h5"
    run_cli("build-kvector", *SIZE, "--mag-max", "6.0", "-o", db, "-q", check=True)
    lists = {}
    for m in ("none", "x"):
        text = run_cli("render", "--stars-only", "--count", "5", *SIZE, "--mag-max", "6", "--sigma-px", "0.2",
                       "--seed", "5", *(("--mirror", m) if m != "none" else ()), check=True).stdout
        lists[m] = tmp_path / f"{m}.jsonl"
        lists[m].write_text(text)
        proc = run_cli("identify", "-d", db, lists[m], "-q")
        assert proc.returncode == 0, proc.stderr
        for line in proc.stdout.splitlines():
            d = json.loads(line)
            ident = d["identification"]
            assert ident["parity"] == ("normal" if m == "none" else "mirrored")
            ids = d["truth"]["star_ids"]
            assert all(ids[k["star"]] == k["id"] for k in ident["matches"])
        # `attitude` reads the parity: the un-mirrored camera's attitude, a WCS of the image's sign.
        att = run_cli("attitude", "-q", input=proc.stdout)
        assert att.returncode == 0, att.stderr
        for line in att.stdout.splitlines():
            d = json.loads(line)
            a = d["attitude"]
            # 0.2 px of centroid noise at 67"/px over a few stars: the roll is good to a few arcminutes, a
            # reflection's attitude would be degrees off.
            assert _angle_arcsec(np.array(a["dcm"]), quaternion_to_dcm(np.array(d["truth"]["quaternion"]))) < 300
            det = a["wcs"]["CD1_1"] * a["wcs"]["CD2_2"] - a["wcs"]["CD1_2"] * a["wcs"]["CD2_1"]
            assert (det > 0) == (m == "none")    # a normal image's CD (y down) has a positive determinant
    proc = run_cli("identify", "-d", db, lists["x"], "--parity", "normal", "-q")
    assert proc.returncode == 1
    # A mirrored tracking sequence: acquired mirrored, tracked, positions in the frames as given.
    seq = run_cli("render", *SIZE, "--frames", "4", "--rate-deg-s", "0.2,-0.1,0.3", "--seed", "6", "--mirror", "x",
                  "-o", tmp_path / "seq" / "f.png", "-q", check=True).stdout
    proc = run_cli("track", "--database", db, "-q", input=seq)
    assert proc.returncode == 0, proc.stderr
    truth = [json.loads(line) for line in seq.splitlines()]
    for d, t in zip((json.loads(line) for line in proc.stdout.splitlines()), truth):
        assert d["attitude"]["status"] == "ok" and d["identification"]["parity"] == "mirrored"
        a = np.array(d["attitude"]["dcm"])
        assert _angle_arcsec(a, quaternion_to_dcm(np.array(t["truth"]["quaternion"]))) < 120
        tx = np.array([s["x"] for s in t["truth"]["stars"]])
        ty = np.array([s["y"] for s in t["truth"]["stars"]])
        near = [np.min(np.hypot(tx - s["x"], ty - s["y"])) for s in d["stars"][:8]]
        assert np.median(near) < 1.0


@pytest.mark.parametrize("k1", [0.0, -0.05])
def test_mirrored_wcs_is_the_normal_one_seen_flipped(k1):
    """Property: the mirrored WCS at FITS pixel (2 cx - x + 1, y + 1) is the normal WCS at (x + 1, y + 1)."""
    from astropy.wcs import WCS

    rng = np.random.default_rng(0)
    cam = Camera(800, 600, 1500.0, 410.3, 290.7, k1=k1)
    dcm = radec_roll_to_dcm(40.0, 30.0, 25.0)
    normal, mirrored = WCS(wcs_header(dcm, cam)), WCS(wcs_header(dcm, cam, mirrored=True))
    x, y = rng.uniform(0, 799, 50), rng.uniform(0, 599, 50)
    a = normal.all_pix2world(np.c_[x + 1, y + 1], 1)
    b = mirrored.all_pix2world(np.c_[2 * cam.cx - x + 1, y + 1], 1)
    assert np.allclose(a[:, 1], b[:, 1], atol=1e-7)
    assert np.allclose((a[:, 0] - b[:, 0] + 180) % 360 - 180, 0, atol=1e-7)
    assert np.linalg.det(normal.wcs.cd) * np.linalg.det(mirrored.wcs.cd) < 0
