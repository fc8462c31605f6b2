"""Frames without a star field (daylight, cloud, texture): the deeper, matched-filter detection finds no stars in a
background the mesh does not follow, so that such a frame fails at once with a reason instead of a blind search on
the background's bumps (a daylight frame: 0 detections, then 51 through the filter and a 5 s search)."""
import json

import cv2
import numpy as np
import pytest
from conftest import run_cli

import startrack.centroid as centroid
from startrack.centroid import CentroidOptions, find_stars


def _textured(shape, seed, period=(23.0, 17.0), noise=8.0):
    """An 8-bit frame of a smooth texture (the blind bench's daylight frame at other sizes and periods) and noise."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:shape[0], 0:shape[1]]
    day = 120 + 60 * np.sin(xx / period[0]) * np.cos(yy / period[1]) + rng.normal(0, noise, shape)
    return day.clip(0, 255).astype(np.uint8)


def _cloud(shape, seed):
    """An 8-bit frame of smoothed noise (clouds a few pixels to a cell wide) over white noise."""
    rng = np.random.default_rng(seed)
    sky = cv2.GaussianBlur(rng.normal(0, 1, shape), (0, 0), 6) * 300 + 100 + rng.normal(0, 3, shape)
    return sky.clip(0, 255).astype(np.uint8)


@pytest.mark.parametrize("make,shape,seed", [(_textured, (768, 1024), 0), (_textured, (480, 640), 1),
                                             (_cloud, (600, 800), 2), (_cloud, (768, 1024), 3)])
def test_matched_filter_finds_no_stars_in_a_background_the_mesh_does_not_follow(make, shape, seed, monkeypatch):
    image = make(shape, seed)
    for band_min in (10**12, 0):        # the whole frame, then in bands of rows
        monkeypatch.setattr(centroid, "_BAND_MIN_PIXELS", band_min)
        if band_min == 0:
            monkeypatch.setattr(centroid, "_BAND_BYTES", 4 * shape[1] * 128)
        res = find_stars(image, CentroidOptions(matched_filter=True, max_stars=60))
        assert len(res.stars) < 4, (band_min, len(res.stars))


@pytest.mark.parametrize("sigma", [0.8, 1.0, 1.6])
def test_filtered_noise_is_the_norm_on_white_noise_and_measured_on_structure(sigma):
    """The oracle: the smoothed frame's spread over the pixel's, computed here directly on the whole frame."""
    rng = np.random.default_rng(int(sigma * 10))
    k = max(3, int(2 * np.ceil(3 * sigma) + 1))
    g1 = cv2.getGaussianKernel(k, sigma)
    norm = float(np.sqrt(np.sum((g1 @ g1.T) ** 2)))
    for shape in ((480, 640), (128, 1024), (1200, 1600)):
        white = rng.normal(0, 5, shape).astype(np.float32)
        assert centroid._filtered_noise(white, cv2.GaussianBlur(white, (k, k), sigma), norm) == norm
        yy, xx = np.mgrid[0:shape[0], 0:shape[1]]
        tex = (white + 10 * np.sin(xx / 11.0) * np.cos(yy / 7.0)).astype(np.float32)
        smooth = cv2.GaussianBlur(tex, (k, k), sigma)
        got = centroid._filtered_noise(tex, smooth, norm)

        def mad(a):
            return np.median(np.abs(a - np.median(a)))
        assert got > 1.2 * norm
        assert got == pytest.approx(mad(smooth) / mad(tex), rel=0.05)


def test_matched_filter_still_finds_faint_stars_on_white_noise():
    """Stars whose peaks are 3.5 sigma of a pixel's noise (under the 5 sigma threshold of one pixel) are found through
    the filter on white noise, as before."""
    rng = np.random.default_rng(5)
    shape = (600, 800)
    yy, xx = np.mgrid[0:shape[0], 0:shape[1]]
    image = rng.normal(200, 4, shape)
    pos = [(60 + 90 * i, 50 + 60 * (i % 8)) for i in range(8)]
    for x, y in pos:
        image += 14 * np.exp(-((xx - x) ** 2 + (yy - y) ** 2) / (2 * 1.2 ** 2))
    image = image.astype(np.float32)
    assert len(find_stars(image, CentroidOptions()).stars) < len(pos)
    deep = find_stars(image, CentroidOptions(matched_filter=True, filter_sigma_px=1.2))
    found = sum(any(abs(s["x"] - x) < 1 and abs(s["y"] - y) < 1 for s in deep.stars) for x, y in pos)
    assert found == len(pos)


def test_daylight_frame_fails_with_a_detection_reason_through_the_cli(tmp_path):
    """The blind bench's daylight frame: no stars, a no-stars reason, no pattern search (main searched the filter's
    51 detections of the texture until the 5 s limit)."""
    path = tmp_path / "daylight.png"
    cv2.imwrite(str(path), _textured((768, 1024), 0))
    proc = run_cli("solve", path, "-q")
    assert proc.returncode == 1, proc.stderr
    doc = json.loads(proc.stdout.splitlines()[0])
    assert doc["solve"]["status"] == "failed"
    assert doc["solve"]["reason_code"] in ("no_stars", "too_few_stars"), doc["solve"]
    assert "hypotheses" not in doc["solve"] or not doc["solve"]["hypotheses"]
