"""Bias, dark and flat frames (issue 37): combined, checked, applied; a fixed pattern solves only calibrated."""
import hashlib
import json
import math

import numpy as np
import pytest
from conftest import assert_refused, run_cli

from startrack.calibration_frames import hot_pixel_map, load_calibration_frames
from startrack.errors import BadInputError
from startrack.nuisance import vignetting_map


def _fits(path, data):
    from astropy.io import fits

    fits.PrimaryHDU(np.asarray(data)).writeto(path)
    return str(path)


@pytest.fixture
def sensor_frames(tmp_path):
    """A sensor of bias 100 DN, a dark current pattern with 40 hot pixels, a vignetted flat; lights of it."""
    rng = np.random.default_rng(0)
    h, w = 120, 160
    hot_rows, hot_cols = rng.integers(0, h, 40), rng.integers(0, w, 40)
    dark_current = np.full((h, w), 5.0)
    dark_current[hot_rows, hot_cols] = rng.uniform(200, 3000, 40)
    response = vignetting_map(h, w, 0.4) * (1 + 0.05 * rng.standard_normal((h, w)))
    files = {"bias": [], "dark": [], "flat": []}
    for k in range(3):
        files["bias"].append(_fits(tmp_path / f"bias{k}.fits", 100 + rng.normal(0, 3, (h, w))))
        dark = 100 + dark_current + rng.normal(0, 3, (h, w))
        if k == 1:
            dark[50:53, 20:80] += 5000          # a cosmic ray / satellite in one dark: voted out
        files["dark"].append(_fits(tmp_path / f"dark{k}.fits", dark))
        files["flat"].append(_fits(tmp_path / f"flat{k}.fits", 100 + 20000 * response + rng.normal(0, 20, (h, w))))
    return files, dark_current, response, (hot_rows, hot_cols)


def test_calibration_removes_the_fixed_pattern(sensor_frames):
    files, dark_current, response, hot = sensor_frames
    cal = load_calibration_frames(files["bias"], files["dark"], files["flat"])
    # Every hot pixel found, nothing else (the cosmic ray of one dark voted out by the median).
    truth = np.zeros(response.shape, bool)
    truth[hot] = True
    assert np.array_equal(cal.hot, truth)
    assert np.median(cal.flat) == pytest.approx(1.0) and np.corrcoef(cal.flat.ravel(), response.ravel())[0, 1] > 0.99
    rng = np.random.default_rng(1)
    sky = 400.0
    light = 100 + dark_current + sky * response + rng.normal(0, 2, response.shape)
    out, saturation = cal.apply(light, 65535.0)
    # A flat sky again: the vignetting divided out, the hot pixels gone.
    assert np.std(out) < 0.03 * sky and abs(np.median(out) - sky * np.median(response)) < 0.03 * sky
    assert np.max(out) < 1.2 * sky * np.median(response)
    assert saturation > np.max(out)
    record = cal.record()
    assert record["hot_pixels"] == 40 and len(record["files"]) == 9
    first = record["files"][0]
    assert first["kind"] == "bias" and first["sha256"] == hashlib.sha256(open(first["path"], "rb").read()).hexdigest()


def test_hot_pixel_map_of_pure_noise_flags_almost_nothing():
    rng = np.random.default_rng(2)
    flagged = [hot_pixel_map(1000 + rng.normal(0, 7, (300, 400)))[0].sum() for _ in range(10)]
    assert sum(flagged) <= 4                  # 0.1 false pixel a frame expected
    # An 8-bit clipped dark (few grey levels, mostly 0) is not all "hot".
    clipped = np.clip(np.rint(rng.normal(0.5, 1.0, (300, 400))), 0, 255)
    assert hot_pixel_map(clipped)[0].mean() < 1e-3


def test_saturated_pixels_stay_the_top(sensor_frames):
    files, dark_current, response, _ = sensor_frames
    cal = load_calibration_frames(dark=files["dark"], flat=files["flat"])
    light = 100 + dark_current + 400 * response
    light[60, 60] = 4095
    out, saturation = cal.apply(light, 4095.0)
    assert out[60, 60] == saturation and np.sum(out >= saturation) == 1


def test_bad_calibration_inputs_are_refused(tmp_path, sensor_frames):
    files, *_ = sensor_frames
    small = _fits(tmp_path / "small.fits", np.ones((10, 10)))
    with pytest.raises(BadInputError, match="small.fits"):
        load_calibration_frames(dark=[files["dark"][0], small])
    zero = np.full((120, 160), 500.0)
    zero[3, 4] = 0.0
    with pytest.raises(BadInputError, match="zero"):
        load_calibration_frames(flat=[_fits(tmp_path / "zero.fits", zero)])
    negative = _fits(tmp_path / "negative.fits", np.full((120, 160), 50.0))
    with pytest.raises(BadInputError, match="negative.fits"):
        load_calibration_frames(bias=files["bias"], flat=[negative])      # 50 - 100: below zero
    cal = load_calibration_frames(dark=files["dark"])
    with pytest.raises(BadInputError, match="light.png"):
        cal.apply(np.zeros((10, 10)), 255.0, "light.png")


def test_cli_refuses_bad_calibration_files(tmp_path, sensor_frames):
    files, *_ = sensor_frames
    img = tmp_path / "light.fits"
    _fits(img, np.full((120, 160), 300.0))
    small = _fits(tmp_path / "small.fits", np.ones((10, 10)))
    text = tmp_path / "notes.fits"
    text.write_text("not an image\n")
    zero = _fits(tmp_path / "zero.fits", np.zeros((120, 160)))
    for command in ("centroid", "solve"):
        assert_refused(run_cli(command, img, "--dark", files["dark"][0], "--dark", small), "small.fits", "pixels")
        assert_refused(run_cli(command, img, "--flat", zero), "zero.fits", "zero")
        assert_refused(run_cli(command, img, "--bias", text), "notes.fits")
    # A light of another size than the frames.
    assert_refused(run_cli("centroid", small, "--dark", files["dark"][0]), "small.fits", "calibration frames")


def test_centroid_records_the_calibration(tmp_path, sensor_frames):
    files, dark_current, response, _ = sensor_frames
    img = _fits(tmp_path / "light.fits", 100 + dark_current + 400 * response)
    proc = run_cli("centroid", img, "--dark", files["dark"][0], "--flat", files["flat"][0], "--flat", files["flat"][1],
                   check=True)
    doc = json.loads(proc.stdout)
    cal = doc["image"]["calibration"]
    assert [f["kind"] for f in cal["files"]] == ["dark", "flat", "flat"] and cal["hot_pixels"] > 30
    # Calibrated, the image is a flat sky: no hot pixel and no vignetting edge is detected as a star.
    assert doc["stars"] == []


def test_fixed_pattern_frame_solves_only_after_calibration(tmp_path, solve_cache):
    """A bright sky through a strong flat-field pattern (20 % PRNU, vignetting 0.5) and 1000 hot pixels."""
    sensor = ("--fov-deg", "12", "--size", "640x480", "--prnu", "0.2", "--vignetting", "0.5", "--hot-pixels", "1000",
              "--zero-point", "2e7", "-q")
    lights = run_cli("render", *sensor, "--background-e-per-s", "30000", "--count", "2", "--seed", "1",
                     "-o", tmp_path / "light.png", check=True).stdout.splitlines()
    run_cli("render", *sensor, "--background-e-per-s", "0", "--frames", "2", "--blackout", "0:2", "--seed", "2",
            "-o", tmp_path / "dark.png", check=True)
    run_cli("render", *sensor[:-3], "--hot-pixels", "0", "-q", "--background-e-per-s", "100000", "--frames", "2",
            "--blackout", "0:2", "--seed", "3", "-o", tmp_path / "flat.png", check=True)
    images = [tmp_path / "light-0000.png", tmp_path / "light-0001.png"]
    raw = run_cli("solve", *images, env=solve_cache, timeout=600)
    assert raw.returncode == 1
    assert all(json.loads(line)["solve"]["status"] == "failed" for line in raw.stdout.splitlines())
    frames = [a for k in range(2) for a in ("--dark", tmp_path / f"dark-000{k}.png", "--flat",
                                            tmp_path / f"flat-000{k}.png")]
    calibrated = run_cli("solve", *images, *frames, env=solve_cache, timeout=600)
    assert calibrated.returncode == 0, calibrated.stderr
    for line, light in zip(calibrated.stdout.splitlines(), lights):
        doc, truth = json.loads(line), json.loads(light)["truth"]
        assert doc["solve"]["status"] == "ok"
        assert doc["image"]["calibration"]["hot_pixels"] >= 900
        a = doc["attitude"]
        sep = math.hypot((a["ra"] - truth["ra"] + 180) % 360 - 180, a["dec"] - truth["dec"])
        assert sep * 3600 < 60 * max(1.0, 1 / math.cos(math.radians(a["dec"])))


def test_track_applies_and_records_the_calibration(tmp_path):
    sensor = ("--fov-deg", "12", "--size", "640x480", "--hot-pixels", "500", "-q")
    db = tmp_path / "db.h5"
    run_cli("build-kvector", "--fov-deg", "12", "--size", "640x480", "--mag-max", "6.0", "-o", db, "-q", check=True)
    seq = run_cli("render", *sensor, "--frames", "3", "--rate-deg-s", "0.1,0,0.2", "--seed", "7",
                  "-o", tmp_path / "seq" / "f.png", check=True).stdout
    run_cli("render", *sensor, "--background-e-per-s", "0", "--frames", "2", "--blackout", "0:2", "--seed", "8",
            "-o", tmp_path / "dark.png", check=True)
    proc = run_cli("track", "--database", db, "--dark", tmp_path / "dark-0000.png", "--dark", tmp_path / "dark-0001.png",
                   "-q", input=seq)
    assert proc.returncode == 0, proc.stderr
    for line in proc.stdout.splitlines():
        doc = json.loads(line)
        assert doc["attitude"]["status"] == "ok"
        cal = doc["image"]["calibration"]
        assert [f["kind"] for f in cal["files"]] == ["dark", "dark"] and cal["hot_pixels"] >= 450
