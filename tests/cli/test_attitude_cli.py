"""attitude through the real entry point: the shell pipeline on real images, WCS, bad input."""
import csv
import glob
import json
import math
import os

import pytest
from conftest import DATA, run_cli

REAL = sorted(glob.glob(os.path.join(DATA, "real", "*.tiff")))
ESA_CAMERA = os.path.join(DATA, "real", "camera.json")


@pytest.fixture(scope="module")
def esa_db(tmp_path_factory):
    out = tmp_path_factory.mktemp("db") / "esa.h5"
    run_cli("build-kvector", "--camera", ESA_CAMERA, "--mag-max", "6.5", "-o", out, check=True)
    return out


def test_real_image_end_to_end_with_wcs(esa_db, tmp_path):
    """centroid | identify | attitude on a real ESA image: RA/Dec within 0.02 deg; the WCS agrees."""
    from astropy.io import fits
    from astropy.wcs import WCS

    cent = run_cli("centroid", REAL[2], "--camera", ESA_CAMERA, check=True).stdout
    ident = run_cli("identify", "-d", esa_db, input=cent, check=True).stdout
    wcs_path = tmp_path / "sky.wcs.fits"
    doc = json.loads(run_cli("attitude", "--wcs", wcs_path, input=ident, check=True).stdout)
    att = doc["attitude"]
    ref = {r["file"]: r for r in csv.DictReader(open(os.path.join(DATA, "real", "solutions.csv")))}
    r = ref[os.path.basename(REAL[2])]
    dra = (att["ra"] - float(r["ra_deg"])) * math.cos(math.radians(att["dec"]))
    assert math.hypot(dra, att["dec"] - float(r["dec_deg"])) < 0.02
    rolls = {x["file"]: float(x["roll_deg"]) for x in csv.DictReader(open(os.path.join(DATA, "real", "roll_centre.csv")))}
    assert abs((att["roll"] - rolls[os.path.basename(REAL[2])] + 180) % 360 - 180) < 0.05
    assert att["sigma_cross_boresight_arcsec"] > 0 and att["sigma_roll_arcsec"] > att["sigma_cross_boresight_arcsec"]
    # astropy's pixel -> sky on the written header puts each identified star within
    # its residual of the catalog position.
    w = WCS(fits.getheader(wcs_path))
    from startrack.camera import Camera
    from startrack.catalog import load_catalog, merge_radius_arcsec

    cat = load_catalog()
    pos = {int(i): (ra, dec) for i, ra, dec in zip(cat.id, cat.ra, cat.dec)}
    # A star with companions closer than 2 px is referred to their photocentre (attitude --merge-px).
    merged = cat.merge_close(merge_radius_arcsec(Camera.from_dict(doc["camera"]), 2.0))
    pos.update({int(i): (ra, dec) for i, ra, dec in zip(merged.id, merged.ra, merged.dec) if int(i) in merged.merged})
    resid = {x["id"]: x["residual_arcsec"] for x in att["residuals"]}
    for m in doc["identification"]["matches"]:
        if m["id"] not in resid:
            continue
        s = doc["stars"][m["star"]]
        ra, dec = w.all_pix2world([[s["x"], s["y"]]], 0)[0]
        cra, cdec = pos[m["id"]]
        sep = math.hypot((ra - cra) * math.cos(math.radians(dec)), dec - cdec) * 3600
        assert sep <= resid[m["id"]] + 0.5


def test_methods_and_rendered_truth(tmp_path):
    """render -> identify -> attitude, every method: the truth within a few arcsec."""
    db = tmp_path / "db.h5"
    run_cli("build-kvector", "--fov-deg", "20", "--mag-max", "5.5", "-o", db, check=True)
    frames = run_cli("render", "--stars-only", "--count", "5", "--fov-deg", "20", "--size", "1024x1024",
                     "--mag-max", "5.5", "--sigma-px", "0.1", "--seed", "9", check=True).stdout
    ident = run_cli("identify", "-d", db, "--sigma-px", "0.1", input=frames, check=True).stdout
    from startrack.rotations import _attitude_error_rad, quaternion_to_dcm

    for method in ("quest", "q-method", "svd", "foam", "esoq2", "triad"):
        out = run_cli("attitude", "--method", method, "--sigma-px", "0.1", input=ident, check=True).stdout
        for line in out.splitlines():
            d = json.loads(line)
            assert d["attitude"]["status"] == "ok" and d["attitude"]["method"] == method
            _, cross, _ = _attitude_error_rad(quaternion_to_dcm(d["attitude"]["quaternion"]),
                                         quaternion_to_dcm(d["truth"]["quaternion"]))
            limit = 60 if method == "triad" else 5
            assert math.degrees(cross) * 3600 < limit, method


def test_bad_frames(tmp_path):
    db = tmp_path / "db.h5"
    run_cli("build-kvector", "--fov-deg", "20", "--mag-max", "5.0", "-o", db, check=True)
    frames = run_cli("render", "--stars-only", "--count", "6", "--fov-deg", "20", "--size", "1024x1024",
                     "--mag-max", "5", "--sigma-px", "0.1", "--seed", "2", check=True).stdout
    proc = run_cli("identify", "-d", db, input=frames)
    ident = [json.loads(l) for l in proc.stdout.splitlines()]
    n_failed = sum(d["identification"]["status"] == "failed" for d in ident)
    assert len(ident) == 6 and proc.returncode == (1 if n_failed else 0), proc.stderr
    ident = [d for d in ident if d["identification"]["status"] == "ok"][:2]
    one = json.loads(json.dumps(ident[0]))
    one["identification"]["matches"] = one["identification"]["matches"][:1]
    failed = json.loads(json.dumps(ident[0]))
    failed["identification"] = {"status": "failed", "algorithm": "pyramid", "matches": [], "reason": "x"}
    no_cam = json.loads(json.dumps(ident[1]))
    del no_cam["camera"]
    nan = json.loads(json.dumps(ident[1]))
    nan["stars"][0]["x"] = float("nan")
    stream = "\n".join(json.dumps(d) for d in (one, failed, no_cam, ident[1])) + "\n"
    stream += json.dumps(nan) + "\n"
    proc = run_cli("attitude", input=stream)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert "5 frame(s), 1 ok, 2 failed, 2 bad input" in proc.stderr
    docs = [json.loads(l) for l in proc.stdout.splitlines()]
    assert len(docs) == 5
    assert docs[0]["attitude"]["status"] == "failed" and "at least 2" in docs[0]["attitude"]["reason"]
    assert docs[1]["attitude"]["status"] == "failed" and "identification failed" in docs[1]["attitude"]["reason"]
    assert docs[2]["attitude"]["status"] == "failed" and "camera" in docs[2]["attitude"]["reason"]
    assert docs[3]["attitude"]["status"] == "ok"
    assert docs[4]["attitude"]["status"] == "failed" and "JSON" in docs[4]["attitude"]["reason"]
