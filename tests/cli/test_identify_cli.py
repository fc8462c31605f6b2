"""identify and evaluate through the real entry point: pipes, real images, bad input."""
import csv
import glob
import json
import math
import os

import numpy as np
import pytest
from conftest import CHART_COLOURS, DATA, assert_chart_draws, assert_refused, run_cli

REAL = sorted(glob.glob(os.path.join(DATA, "real", "*.tiff")))
ESA_CAMERA = os.path.join(DATA, "real", "camera.json")


@pytest.fixture(scope="module")
def db20(tmp_path_factory):
    out = tmp_path_factory.mktemp("db") / "p003.h5"
    run_cli("build-kvector", "--fov-deg", "20", "--mag-max", "5.0", "-o", out, check=True)
    return out


@pytest.fixture(scope="module")
def esa_db(tmp_path_factory):
    out = tmp_path_factory.mktemp("db") / "esa.h5"
    run_cli("build-kvector", "--camera", ESA_CAMERA, "--mag-max", "6.5", "-o", out, check=True)
    return out


def test_pipe_render_identify(db20):
    frames = run_cli("render", "--stars-only", "--count", "30", "--fov-deg", "20", "--size", "1024x1024",
                     "--mag-max", "5", "--sigma-px", "0.2", "--max-stars", "10", "--seed", "5", check=True).stdout
    proc = run_cli("identify", "--database", db20, input=frames)
    docs = [json.loads(l) for l in proc.stdout.splitlines()]
    assert len(docs) == 30
    ok = [d for d in docs if d["identification"]["status"] == "ok"]
    assert len(ok) >= 29
    # Honest exit status: 1 as soon as one frame failed, and the summary counts them.
    assert proc.returncode == (0 if len(ok) == 30 else 1), proc.stderr
    assert f"{len(ok)} ok, {30 - len(ok)} failed, 0 bad input" in proc.stderr
    for d in ok:
        blends = {t["id"]: set(t.get("blended", [])) for t in d["truth"]["stars"]}
        for m in d["identification"]["matches"]:
            true_id = d["truth"]["star_ids"][m["star"]]
            assert true_id == m["id"] or m["id"] in blends[true_id]   # a blend may take either name
        assert d["identification"]["false_match_probability"] < 1e-4


def test_real_esa_images_identified(esa_db):
    """centroid -> identify on the 8 real images: all identified, boresight within 0.05 deg of the reference."""
    from startrack.rotations import _dcm_to_radec_roll_rad, _radec_to_vector_rad, quaternion_to_dcm

    cent = run_cli("centroid", *REAL, "--camera", ESA_CAMERA, check=True).stdout
    proc = run_cli("identify", "-d", esa_db, input=cent, check=True)
    ref = {r["file"]: r for r in csv.DictReader(open(os.path.join(DATA, "real", "solutions.csv")))}
    docs = [json.loads(l) for l in proc.stdout.splitlines()]
    assert len(docs) == 8
    for d in docs:
        ident = d["identification"]
        assert ident["status"] == "ok", ident
        assert len(ident["matches"]) >= 6
        ra, dec, _ = _dcm_to_radec_roll_rad(quaternion_to_dcm(ident["quaternion_estimate"]))
        r = ref[os.path.basename(d["image"]["path"])]
        sep = math.degrees(math.acos(np.clip(_radec_to_vector_rad(ra, dec) @ _radec_to_vector_rad(
            math.radians(float(r["ra_deg"])), math.radians(float(r["dec_deg"]))), -1, 1)))
        assert sep < 0.05, (d["image"]["path"], sep)




def test_database_for_another_fov_is_refused(db20):
    frame = run_cli("render", "--stars-only", "--fov-deg", "40", "--size", "1024x1024", "--seed", "1",
                    check=True).stdout
    assert_refused(run_cli("identify", "-d", db20, input=frame), "max_angle_deg", "rebuild")
    frame = run_cli("render", "--stars-only", "--fov-deg", "6", "--size", "1024x1024", "--seed", "1",
                    check=True).stdout
    assert_refused(run_cli("identify", "-d", db20, input=frame), "max_angle_deg")


def test_bad_frames_in_a_batch(db20):
    good = run_cli("render", "--stars-only", "--count", "3", "--fov-deg", "20", "--size", "1024x1024",
                   "--mag-max", "5", "--sigma-px", "0.2", "--seed", "2", check=True).stdout.splitlines()
    bad_x = json.loads(good[1])
    del bad_x["stars"][0]["x"]
    empty = json.loads(good[2])
    empty["stars"] = []
    stream = "\n".join([good[0], json.dumps(bad_x), "{not json", json.dumps(empty), good[0]]) + "\n"
    proc = run_cli("identify", "-d", db20, input=stream)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    docs = [json.loads(l) for l in proc.stdout.splitlines()]
    assert len(docs) == 5
    assert docs[0]["identification"]["status"] == "ok" and docs[4]["identification"]["status"] == "ok"
    assert docs[1]["identification"]["status"] == "failed" and "stars[0].x" in docs[1]["identification"]["reason"]
    assert docs[2]["identification"]["status"] == "failed" and "JSON" in docs[2]["identification"]["reason"]
    assert docs[3]["identification"]["status"] == "failed" and "at least 3" in docs[3]["identification"]["reason"]
    assert "stars[0].x" in proc.stderr
    # A single bad document is refused outright.
    assert_refused(run_cli("identify", "-d", db20, input=json.dumps(bad_x)), "stars[0].x", "missing")


def test_wrong_database_file(tmp_path):
    cat = tmp_path / "c.h5"
    run_cli("catalog-filter", "--mag-max", "2", "-o", cat, check=True)
    assert_refused(run_cli("identify", "-d", cat, input="{}"), "c.h5", "format")


def test_evaluate_table_csv_json_plot(db20, tmp_path):
    proc = run_cli("evaluate", "-d", db20, "-a", "pyramid,voting", "--fov-deg", "20", "--size", "1024x1024",
                   "--mag-max", "5", "--sigma-px", "0.2", "--false-stars", "0,2", "--count", "60", "--seed", "3",
                   "--csv", tmp_path / "e.csv", "--json", "-o", tmp_path / "e.json", "--plot", tmp_path / "e.png",
                   "-j", "2", check=True)
    assert "pyramid" in proc.stdout and "bad match" in proc.stdout
    rows = json.load(open(tmp_path / "e.json"))["rows"]
    assert len(rows) == 4 and all(r["success"] + r["failure"] + r["bad"] == 60 for r in rows)
    assert_chart_draws(tmp_path / "e.png", CHART_COLOURS[:2])         # pyramid and voting
    assert open(tmp_path / "e.csv").readline().startswith("# startrack")


def test_evaluate_speaks_the_users_unit_of_noise(db20, tmp_path):
    """--sigma-arcsec 1.667: the conditions say 1.667 arcsec (not 0.0235 px); the rows keep both."""
    proc = run_cli("evaluate", "-d", db20, "-a", "pyramid", "--fov-deg", "20", "--size", "1024x1024",
                   "--mag-max", "5", "--sigma-arcsec", "1.667", "--count", "10", "--seed", "3",
                   "--json", "-o", tmp_path / "e.json", check=True)
    assert "sigma 1.667 arcsec" in proc.stdout and "px" not in proc.stdout.split("sigma", 1)[1].split("\n")[0]
    (row,) = json.load(open(tmp_path / "e.json"))["rows"]
    assert row["condition"] == "sigma 1.667 arcsec" and row["sigma_arcsec"] == 1.667
    assert abs(row["sigma_px"] - 1.667 / (20 * 3600 / 1024)) < 1e-3        # about 0.0237 px at 70 arcsec/px
    px = json.loads(run_cli("evaluate", "-d", db20, "-a", "pyramid", "--fov-deg", "20", "--size", "1024x1024",
                            "--mag-max", "5", "--sigma-px", "0.2", "--count", "10", "--seed", "3", "--json",
                            check=True).stdout)["rows"][0]
    assert px["condition"] == "sigma 0.2px" and px["sigma_arcsec"] is None
