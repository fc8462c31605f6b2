"""solve, calibrate and plot through the real entry point, on the real images and on non-star images."""
import csv
import glob
import json
import math
import os
import time

import numpy as np
import pytest

from conftest import DATA, run_cli

REAL = sorted(glob.glob(os.path.join(DATA, "real", "*.tiff")))


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    env = {"STARTRACK_CACHE": str(tmp_path_factory.mktemp("cache"))}
    proc = run_cli("cache", "build", env=env, check=True, timeout=600)
    # The one-line notice is printed even though stderr is not a terminal here.
    assert "building the star index once" in proc.stderr
    listing = run_cli("cache", "list", env=env, check=True).stdout
    assert "patterns-" in listing
    return env


@pytest.fixture(scope="module")
def solved(cache, tmp_path_factory):
    out = tmp_path_factory.mktemp("solved")
    proc = run_cli("solve", *REAL, "-j", "2", "--wcs", out / "sky.wcs.fits", env=cache, check=True, timeout=600)
    return [json.loads(l) for l in proc.stdout.splitlines()], out


def test_blind_solve_of_the_real_images(solved):
    docs, out = solved
    ref = {r["file"]: r for r in csv.DictReader(open(os.path.join(DATA, "real", "solutions.csv")))}
    assert len(docs) == 8
    for d in docs:
        assert d["solve"]["status"] == "ok", d["solve"]
        a = d["attitude"]
        r = ref[os.path.basename(d["image"]["path"])]
        sep = math.hypot((a["ra"] - float(r["ra_deg"])) * math.cos(math.radians(a["dec"])), a["dec"] - float(r["dec_deg"]))
        assert sep * 3600 < 30
        assert d["solve"]["fov_deg"][0] == pytest.approx(float(r["fov_x_deg"]), abs=0.05)
    assert len(list(out.glob("sky.wcs-*.fits"))) == 8


def test_calibrate_then_solve_with_the_lens(solved, cache, tmp_path):
    docs, _ = solved
    frames = tmp_path / "solved.jsonl"
    frames.write_text("\n".join(json.dumps(d) for d in docs) + "\n")
    lens = tmp_path / "lens.json"
    proc = run_cli("calibrate", frames, "-o", lens, env=cache, check=True)
    assert "residual RMS" in proc.stderr
    cal = json.load(open(lens))
    c = cal["calibration"]
    assert c["rms_residual_after_px"] < c["rms_residual_before_px"]
    assert cal["fov_deg"][0] == pytest.approx(11.42, abs=0.02)
    assert all(v > 0 for v in c["sigma"].values())
    again = [json.loads(l) for l in run_cli("solve", *REAL[:3], "--camera", lens, env=cache, check=True).stdout.splitlines()]
    assert all(d["solve"]["status"] == "ok" for d in again)


def test_not_star_fields_fail_fast_and_cleanly(cache, tmp_path):
    import cv2

    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:480, 0:640]
    daylight = (120 + 60 * np.sin(xx / 23.0) * np.cos(yy / 17.0) + rng.normal(0, 8, (480, 640))).clip(0, 255)
    cv2.imwrite(str(tmp_path / "daylight.png"), daylight.astype(np.uint8))
    cv2.imwrite(str(tmp_path / "black.png"), np.zeros((480, 640), np.uint8))
    cv2.imwrite(str(tmp_path / "noise.png"), rng.normal(1000, 40, (480, 640)).astype(np.uint16))
    t0 = time.time()
    proc = run_cli("solve", tmp_path / "daylight.png", tmp_path / "black.png", tmp_path / "noise.png", env=cache)
    elapsed = time.time() - t0
    assert proc.returncode == 1 and "Traceback" not in proc.stderr, proc.stderr
    docs = [json.loads(l) for l in proc.stdout.splitlines()]
    assert [d["solve"]["status"] for d in docs] == ["failed"] * 3
    assert all(d["solve"]["reason"] and "attitude" not in d for d in docs)
    assert all(d["solve"]["time_ms"] < 5000 for d in docs)
    assert elapsed < 30


def test_plot_kinds(solved, tmp_path):
    docs, _ = solved
    one = tmp_path / "one.jsonl"
    one.write_text(json.dumps(docs[2]) + "\n")
    run_cli("plot", one, "--kind", "image", "-o", tmp_path / "img.png", check=True)
    run_cli("plot", one, "--kind", "residuals", "-o", tmp_path / "res.png", check=True)
    assert (tmp_path / "img.png").stat().st_size > 50000 and (tmp_path / "res.png").stat().st_size > 10000
