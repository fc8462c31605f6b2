"""startrack centroid through the real entry point, on rendered and real images."""
import glob
import json
import os

import numpy as np
from conftest import DATA, assert_refused, run_cli

REAL = sorted(glob.glob(os.path.join(DATA, "real", "*.tiff")))


def test_real_esa_images_with_defaults(tmp_path):
    assert len(REAL) == 8
    proc = run_cli("centroid", *REAL, "--plot", tmp_path / "esa.png", check=True)
    docs = [json.loads(l) for l in proc.stdout.splitlines()]
    assert len(docs) == 8
    for doc, path in zip(docs, REAL):
        assert doc["image"]["path"] == path and doc["image"]["width"] == 1024 and doc["image"]["height"] == 768
        assert len(doc["stars"]) >= 12, path
        assert doc["centroid"]["time_ms"] > 0
    assert len(list(tmp_path.glob("esa-*.png"))) == 8


def test_pipeline_from_render(tmp_path):
    img = tmp_path / "sky.png"
    render = run_cli("render", "--fov-deg", "20", "--size", "512x512", "--ra", "83.8", "--dec", "-1.2",
                     "--psf-sigma-px", "1.2", "--seed", "3", "-o", img, check=True)
    proc = run_cli("centroid", "--max-stars", "15", input=render.stdout, check=True)
    doc = json.loads(proc.stdout)
    assert doc["truth"] == json.loads(render.stdout)["truth"]          # sections pass through
    # The render section's gain is used (shot noise in the fit's weights), and the fit reports its covariance.
    gain = json.loads(render.stdout)["render"]["params"]["sensor"]["gain_e_per_dn"]
    assert doc["centroid"]["params"]["gain_e_per_dn"] == gain
    assert all("cov_px2" in s and s["fit_dof"] > 0 for s in doc["stars"] if not s["saturated"])
    given = json.loads(run_cli("centroid", "--gain-e-per-dn", "2.5", input=render.stdout, check=True).stdout)
    assert given["centroid"]["params"]["gain_e_per_dn"] == 2.5
    assert len(doc["stars"]) == 15
    truth = np.array([(s["x"], s["y"]) for s in doc["truth"]["stars"]])
    for s in doc["stars"]:
        assert np.hypot(*(truth - [s["x"], s["y"]]).T).min() < 1.0
    # Windowed mode around the truth positions.
    win = json.loads(run_cli("centroid", "--windows-from", "truth", "--window-px", "6", input=render.stdout,
                             check=True).stdout)
    assert win["centroid"]["mode"] == "windows" and len(win["stars"]) >= 15




def test_bad_images(tmp_path):
    import cv2

    empty = tmp_path / "empty.png"
    empty.write_bytes(b"")
    assert_refused(run_cli("centroid", empty), "empty.png", "empty")
    good = tmp_path / "good.png"
    cv2.imwrite(str(good), np.full((40, 40), 10, np.uint8))
    truncated = tmp_path / "trunc.png"
    truncated.write_bytes(good.read_bytes()[:40])
    assert_refused(run_cli("centroid", truncated), "trunc.png", "not a readable image")
    assert_refused(run_cli("centroid", tmp_path / "missing.tiff"), "missing.tiff", "no such file")
    text = tmp_path / "notes.png"
    text.write_text("this is not an image")
    assert_refused(run_cli("centroid", text), "notes.png")
    # A 32-bit integer TIFF is not a depth we read.
    deep = tmp_path / "deep.tiff"
    cv2.imwrite(str(deep), np.full((20, 20), 7, np.int32))
    assert_refused(run_cli("centroid", deep), "deep.tiff", "unsupported pixel type int32")


def test_degenerate_images_give_empty_lists_with_reasons(tmp_path):
    import cv2

    cases = {
        "black.png": np.zeros((64, 64), np.uint8),
        "saturated.png": np.full((64, 64), 65535, np.uint16),
        "noise.png": np.random.default_rng(0).normal(2000, 30, (256, 256)).astype(np.uint16),
    }
    for name, arr in cases.items():
        cv2.imwrite(str(tmp_path / name), arr)
    from astropy.io import fits

    fits.PrimaryHDU(np.zeros((0, 0), np.int16)).writeto(tmp_path / "zero.fits")
    proc = run_cli("centroid", *(tmp_path / n for n in cases))
    assert proc.returncode == 0, proc.stderr
    docs = [json.loads(l) for l in proc.stdout.splitlines()]
    assert docs[0]["stars"] == [] and docs[0]["centroid"]["reason"]
    assert docs[1]["stars"] == [] and "saturated" in docs[1]["centroid"]["reason"]
    assert len(docs[2]["stars"]) <= 2
    assert_refused(run_cli("centroid", tmp_path / "zero.fits"), "zero.fits")


def test_batch_goes_on_past_a_bad_image(tmp_path):
    empty = tmp_path / "empty.png"
    empty.write_bytes(b"")
    proc = run_cli("centroid", REAL[0], empty, REAL[1])
    assert proc.returncode == 2
    docs = [json.loads(l) for l in proc.stdout.splitlines()]
    assert len(docs) == 3
    assert docs[1]["centroid"]["status"] == "failed" and "empty" in docs[1]["centroid"]["reason"]
    assert len(docs[0]["stars"]) > 10 and len(docs[2]["stars"]) > 10
    assert "1 bad input" in proc.stderr and "empty.png: is empty" in proc.stderr
