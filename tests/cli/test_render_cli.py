"""startrack render through the real entry point."""
import hashlib
import json
import math
import os

import numpy as np
import pytest
from conftest import assert_refused, run_cli


def sha(path):
    return hashlib.sha256(open(path, "rb").read()).hexdigest()


def test_same_seed_same_bytes(tmp_path):
    docs = []
    for name in ("a", "b"):
        out = tmp_path / f"{name}.png"
        proc = run_cli("render", "--fov-deg", "15", "--size", "320x240", "--seed", "7", "--hot-pixels", "5",
                       "--false-stars", "2", "--mag-noise", "0.2", "--prnu", "0.01", "-o", out, check=True)
        docs.append(json.loads(proc.stdout))
    assert sha(tmp_path / "a.png") == sha(tmp_path / "b.png")
    assert docs[0]["truth"] == docs[1]["truth"]
    proc = run_cli("render", "--fov-deg", "15", "--size", "320x240", "--seed", "8", "-o", tmp_path / "c.png", check=True)
    assert sha(tmp_path / "c.png") != sha(tmp_path / "a.png")


def test_frame_seed_reproduces_one_frame_of_a_set():
    a = run_cli("render", "--stars-only", "--count", "5", "--fov-deg", "20", "--mag-max", "5", "--sigma-px", "0.3",
                "--seed", "3", check=True).stdout.splitlines()
    third = json.loads(a[2])
    again = json.loads(run_cli("render", "--stars-only", "--fov-deg", "20", "--mag-max", "5", "--sigma-px", "0.3",
                               "--frame-seed", third["render"]["frame_seed"], check=True).stdout)
    assert again["stars"] == third["stars"] and again["truth"]["quaternion"] == third["truth"]["quaternion"]


def test_orion_truth_agrees_with_astropy_tan_projection(tmp_path):
    from astropy.wcs import WCS

    out = tmp_path / "orion.png"
    # The projection alone: a camera at rest (aberration moves the stars by up to 20.5", tests/test_apparent.py).
    doc = json.loads(run_cli("render", "--fov-deg", "20", "--size", "1024x1024", "--ra", "83.8", "--dec", "-1.2",
                             "--seed", "1", "--no-aberration", "-o", out, check=True).stdout)
    from startrack.catalog import load_catalog

    cat = load_catalog()
    f = doc["camera"]["focal_length_px"]
    w = WCS(naxis=2)
    w.wcs.ctype = ["RA---TAN", "DEC--TAN"]
    w.wcs.crval = [83.8, -1.2]
    w.wcs.crpix = [doc["camera"]["cx"] + 1, doc["camera"]["cy"] + 1]
    scale = math.degrees(1.0 / f)
    # Roll 0: north up (-y, decreasing row), east left (-x).
    w.wcs.cd = [[-scale, 0.0], [0.0, -scale]]
    stars = {s["id"]: s for s in doc["truth"]["stars"]}
    for hip, name in ((27989, "Betelgeuse"), (24436, "Rigel")):
        row = cat.subset(cat.id == hip)
        px, py = w.wcs_world2pix([[row.ra[0], row.dec[0]]], 0)[0]
        assert hip in stars, name
        assert stars[hip]["x"] == pytest.approx(px, abs=1e-6), name
        assert stars[hip]["y"] == pytest.approx(py, abs=1e-6), name
    # Betelgeuse is up-left (north-east) of the centre, Rigel down-right.
    assert stars[27989]["x"] < 512 and stars[27989]["y"] < 512
    assert stars[24436]["x"] > 512 and stars[24436]["y"] > 512


def test_sequence_numbered_images(tmp_path):
    out = tmp_path / "seq" / "frame.png"
    lines = run_cli("render", "--fov-deg", "12", "--size", "256x192", "--frames", "3", "--rate-deg-s", "0,0.5,0",
                    "--frame-interval-s", "0.5", "--time", "2026-11-21T22:10:00Z", "--seed", "2", "-o", out,
                    check=True).stdout.splitlines()
    docs = [json.loads(l) for l in lines]
    assert [d["image"]["path"] for d in docs] == [str(tmp_path / "seq" / f"frame-{i:04d}.png") for i in range(3)]
    assert all(os.path.exists(d["image"]["path"]) for d in docs)
    assert docs[1]["image"]["time"] == "2026-11-21T22:10:00.500Z"
    from startrack.rotations import _attitude_error_rad, quaternion_to_dcm

    a0 = quaternion_to_dcm(docs[0]["truth"]["quaternion"])
    a2 = quaternion_to_dcm(docs[2]["truth"]["quaternion"])
    total, _, _ = _attitude_error_rad(a2, a0)
    assert math.degrees(total) == pytest.approx(0.5, rel=1e-9)




@pytest.mark.parametrize("args, needle", [
    (["--fov-deg", "0", "--size", "64x64"], "--fov-deg"),
    (["--fov-deg", "-5", "--size", "64x64"], "--fov-deg"),
    (["--fov-deg", "10", "--size", "0x64"], "--size"),
    (["--fov-deg", "10", "--size", "64x64", "--quaternion", "0.5,0.5,0.5,0.6"], "unit quaternion"),
    (["--fov-deg", "10", "--size", "64x64", "--quaternion", "nan,0,0,1"], "--quaternion"),
    (["--fov-deg", "10", "--size", "64x64", "--quaternion", "1,0,0"], "--quaternion"),
])
def test_bad_input_refused_and_nothing_written(tmp_path, args, needle):
    out = tmp_path / "x.png"
    assert_refused(run_cli("render", *args, "-o", out), needle)
    assert not out.exists()
    assert os.listdir(tmp_path) == []


def test_unknown_extensionassert_refused(tmp_path):
    out = tmp_path / "x.gif"
    assert_refused(run_cli("render", "--fov-deg", "10", "--size", "64x64", "-o", out), "x.gif", "unknown image extension")
    assert os.listdir(tmp_path) == []


def test_fits_and_tiff_outputs(tmp_path):
    from astropy.io import fits

    from startrack.imageio import read_image

    run_cli("render", "--fov-deg", "10", "--size", "64x48", "--seed", "1", "-o", tmp_path / "a.fits", check=True)
    run_cli("render", "--fov-deg", "10", "--size", "64x48", "--seed", "1", "-o", tmp_path / "a.tiff", check=True)
    run_cli("render", "--fov-deg", "10", "--size", "64x48", "--seed", "1", "--bit-depth", "8", "-o", tmp_path / "a.png",
            check=True)
    fdata = fits.getdata(tmp_path / "a.fits")
    tdata, info = read_image(str(tmp_path / "a.tiff"))
    assert fdata.shape == (48, 64) and info["bit_depth"] == 16
    np.testing.assert_array_equal(fdata.astype(np.float32), tdata)
    pdata, pinfo = read_image(str(tmp_path / "a.png"))
    assert pinfo["bit_depth"] == 8 and pdata.max() <= 255
