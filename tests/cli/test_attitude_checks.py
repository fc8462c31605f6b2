"""attitude checks the identification it is given (issue 17), through the real CLI.

Each case is a frame whose identification is wrong in one way; the frame must
come out ``failed`` with a reason code (exit status 1: a frame failed), never
``ok``, and never an internal error.
"""
import json
import math

import numpy as np
import pytest
from conftest import assert_refused, run_cli


@pytest.fixture(scope="module")
def frame():
    """One rendered star list (12 deg, 0.1 px noise) identified from its truth: the correct identification."""
    doc = json.loads(run_cli("render", "--stars-only", "--fov-deg", "12", "--size", "1024x1024", "--mag-max", "6",
                             "--sigma-px", "0.1", "--seed", "21", "--ra", "286", "--dec", "20", "--roll", "10",
                             check=True).stdout)
    matches = []
    for i, s in enumerate(doc["stars"]):
        t = min(doc["truth"]["stars"], key=lambda t: math.hypot(t["x"] - s["x"], t["y"] - s["y"]))
        if math.hypot(t["x"] - s["x"], t["y"] - s["y"]) < 1.0:
            matches.append({"star": i, "id": t["id"]})
    assert len(matches) >= 8
    doc["identification"] = {"status": "ok", "algorithm": "truth", "matches": matches}
    return doc


def _attitude(doc, *args):
    proc = run_cli("attitude", "--sigma-px", "0.1", *args, input=json.dumps(doc) + "\n")
    assert "Traceback" not in proc.stderr and "internal error" not in proc.stderr, proc.stderr
    return proc, json.loads(proc.stdout)["attitude"]


def _failed(proc, att, code):
    """The frame is failed with ``code`` and the batch says so (exit 1; 0 before the batch machinery counted it)."""
    assert proc.returncode in (0, 1) and "attitude: 1 frame(s), 0 ok, 1 failed" in proc.stderr, proc.stderr
    assert att["status"] == "failed" and att["reason_code"] == code, att
    assert "quaternion" not in att and "sigma_cross_boresight_arcsec" not in att


def _copy(doc):
    return json.loads(json.dumps(doc))


def test_correct_identification_is_ok(frame):
    proc, att = _attitude(frame)
    assert proc.returncode == 0 and att["status"] == "ok"
    assert abs((att["ra"] - 286 + 180) % 360 - 180) < 0.01 and att["rms_residual_arcsec"] < 30


def test_permuted_ids_fail(frame):
    doc = _copy(frame)
    ids = [m["id"] for m in doc["identification"]["matches"]]
    for m, i in zip(doc["identification"]["matches"], ids[1:] + ids[:1]):
        m["id"] = i
    proc, att = _attitude(doc)
    _failed(proc, att, "residuals_too_large")


def test_one_wrong_id_of_two_fails(frame):
    doc = _copy(frame)
    m = doc["identification"]["matches"]
    # the second star given the id of the third: a wrong but plausible catalog star
    doc["identification"]["matches"] = [m[0], {"star": m[1]["star"], "id": m[2]["id"]}]
    proc, att = _attitude(doc)
    _failed(proc, att, "residuals_too_large")


def test_corrupted_catalog_fails(frame, tmp_path):
    import h5py

    cat = tmp_path / "cat.h5"
    run_cli("catalog-filter", "--mag-max", "6.5", "-o", cat, check=True)
    with h5py.File(cat, "r+") as f:
        name = next(k for k in ("ra", "ra_deg", "stars/ra") if k in f)
        ra = f[name][...]
        ra += np.random.default_rng(1).uniform(-0.5, 0.5, ra.shape)   # every star moved up to half a degree
        f[name][...] = ra
    # the file's sha256 map catches the edit first: refused, not wrong
    proc = run_cli("attitude", "--sigma-px", "0.1", "--catalog", cat, input=json.dumps(frame) + "\n")
    assert_refused(proc, "cat.h5: ra: does not match the file's sha256")
    with h5py.File(cat, "r+") as f:
        del f.attrs["sha256"]       # as a catalog written before checksums: the residuals must still catch it
    proc, att = _attitude(frame, "--catalog", cat)
    _failed(proc, att, "residuals_too_large")


@pytest.mark.parametrize("repeat", [600, 10])
def test_repeated_matches_fail(frame, repeat):
    doc = _copy(frame)
    m = doc["identification"]["matches"]
    doc["identification"]["matches"] = m * repeat if repeat == 600 else [m[0]] * repeat
    proc, att = _attitude(doc)
    _failed(proc, att, "duplicate_match")


def test_crb_beside_the_covariance(tmp_path):
    """render | centroid | attitude (identified from the truth): the frame's own bound is reported, the error near it."""
    from startrack.accuracy import error_vector
    from startrack.rotations import quaternion_to_dcm

    frames = run_cli("render", "--fov-deg", "15", "--size", "384x384", "--count", "2", "--seed", "4",
                     "--mag-max", "6.5", "-o", tmp_path / "f.png", "-q", check=True).stdout
    cent = run_cli("centroid", "--gain-e-per-dn", "0.3052", "-q", input=frames, check=True).stdout
    docs = []
    for line in cent.splitlines():
        d = json.loads(line)
        matches, used = [], set()
        for i, s in enumerate(d["stars"]):
            t = min(d["truth"]["stars"], key=lambda t: math.hypot(t["x"] - s["x"], t["y"] - s["y"]))
            if math.hypot(t["x"] - s["x"], t["y"] - s["y"]) < 1.0 and t["id"] not in used and not s["saturated"]:
                used.add(t["id"])
                matches.append({"star": i, "id": t["id"]})
        d["identification"] = {"status": "ok", "algorithm": "truth", "matches": matches}
        docs.append(json.dumps(d))
    out = run_cli("attitude", "--sigma-floor-px", "0", "-q", input="\n".join(docs) + "\n", check=True).stdout
    # A star marked misfit by centroid (its fit's chi-square failed) is left out and listed.
    first = json.loads(docs[0])
    k = first["identification"]["matches"][0]["star"]
    first["stars"][k]["misfit"] = True
    lone = json.loads(run_cli("attitude", "--sigma-floor-px", "0", "-q", input=json.dumps(first) + "\n",
                              check=True).stdout)["attitude"]
    assert lone["status"] == "ok" and lone["n_stars"] == len(first["identification"]["matches"]) - 1
    assert lone["rejected"][0]["star"] == k and "chi-square" in lone["rejected"][0]["reason"]
    for line in out.splitlines():
        d = json.loads(line)
        att = d["attitude"]
        assert att["status"] == "ok"
        assert 0 < att["crb_cross_boresight_arcsec"] < att["crb_roll_arcsec"]
        # each star weighted by its fit's own covariance, close to its bound (k = 1 here)
        assert att["sigma_cross_boresight_arcsec"] >= 0.9 * att["crb_cross_boresight_arcsec"]
        e = error_vector(quaternion_to_dcm(att["quaternion"]), quaternion_to_dcm(d["truth"]["quaternion"]))
        arcsec = math.degrees(1) * 3600
        assert abs(e[0]) * arcsec < 5 * att["crb_pitch_yaw_arcsec"][0]
        assert abs(e[2]) * arcsec < 5 * att["crb_roll_arcsec"]


def test_evaluate_accuracy_reports_error_over_bound(tmp_path):
    """evaluate --accuracy: rendered frames, identified by the database, error / bound per axis and NEES."""
    db = tmp_path / "db.h5"
    run_cli("build-kvector", "--fov-deg", "15", "--size", "384x384", "--mag-max", "5.5", "-o", db, check=True)
    out = tmp_path / "acc.json"
    proc = run_cli("evaluate", "-d", db, "--fov-deg", "15", "--size", "384x384", "--accuracy", "-n", "6", "--seed", "3",
                   "--json", "-o", out, "-q", check=True)
    assert "cross-boresight: RMS" in proc.stdout and "NEES mean" in proc.stdout
    s = json.loads(out.read_text())["accuracy"]
    assert s["frames"] + s["failed"] + s["wrong"] + s["no_bound"] == 6 and s["wrong"] == 0
    assert 0.2 < s["ratio_cross"] < 5 and 0.2 < s["ratio_roll"] < 5
