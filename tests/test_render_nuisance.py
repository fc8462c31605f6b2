"""render's nuisances (issue 37): each is there, of the stated size, and reproducible."""
import json
import math
from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest
from conftest import assert_refused, run_cli

from startrack.camera import Camera
from startrack.catalog import Catalog, load_catalog
from startrack.nuisance import foreground_mask
from startrack.render import Scene, Sensor, background_dn_cdf, render_image, star_list
from startrack.rotations import radec_roll_to_dcm

CAM = Camera.from_fov(12, 400, 300)
ORION = radec_roll_to_dcm(83.8, -1.2, 20.0)
EMPTY = Catalog([], [], [], [], [], [], [], 2000.0)


@pytest.fixture(scope="module")
def catalog():
    return load_catalog().filter_magnitude(None, 8.0)


def render(cat, sensor=None, scene=None, seed=1):
    return render_image(cat, CAM, ORION, sensor or Sensor(), scene or Scene(), np.random.default_rng(seed))


def test_dark_subtracted_8bit_frame_is_clipped_like_the_issue():
    # Sky 4 e + dark 2 e at 2 e/DN, read noise 6 e: the sky is 2 DN above 0 with ~3.3 DN of noise.
    sensor = Sensor(bit_depth=8, gain_e_per_dn=2.0, read_noise_e=6.0, background_e_per_s=40.0,
                    dark_current_e_per_s=20.0, dark_subtracted=True)
    image, _ = render(EMPTY, sensor)
    assert image.dtype == np.uint8
    # The oracle: the exact distribution of a pixel with the bias and the dark's mean removed.
    cdf, lo = background_dn_cdf(SimpleNamespace(background_e=sensor.background_e, gain=2.0,
                                                bias=-sensor.dark_current_e_per_s * sensor.exposure_s / 2.0,
                                                read_noise_e=6.0))
    p_zero = cdf[-lo] if lo <= 0 else 0.0
    n = image.size
    assert 0.2 < p_zero < 0.5
    assert np.mean(image == 0) == pytest.approx(p_zero, abs=4 * math.sqrt(p_zero * (1 - p_zero) / n))
    assert np.median(image) == 2
    plain, _ = render(EMPTY, replace(sensor, dark_subtracted=False))
    assert np.mean(plain == 0) < 0.05 and np.median(plain) == np.median(image) + 5 + 1   # bias 5 DN, dark 1 DN


def test_hot_pixels_are_single_pixels_some_saturated():
    sensor = Sensor(hot_pixels=400, noise=False)
    image, truth = render(EMPTY, sensor)
    sky = np.median(image)
    hot = truth["hot_pixels"]
    assert len(hot) == 400
    levels = np.array([h["electrons"] for h in hot])
    assert levels.min() >= 0.01 * sensor.full_well_e and levels.max() <= 2.0 * sensor.full_well_e
    charge = np.zeros(image.shape)
    np.add.at(charge, ([h["y"] for h in hot], [h["x"] for h in hot]), levels)
    lit = charge > 0
    # Each hot pixel holds exactly its charge (clipped at the full well and the ADC's top).
    expected = np.minimum(sensor.max_dn, np.floor(np.minimum(charge[lit] + sensor.background_e, sensor.full_well_e)
                                                  / sensor.gain + sensor.bias + 0.5))
    assert np.array_equal(image[lit], expected)
    saturated = np.mean(levels + sensor.background_e >= sensor.full_well_e)
    assert 0.05 < saturated < 0.25            # log-uniform 1-200 %: log(2)/log(200) = 13 %
    assert np.sum(image == sensor.max_dn) >= saturated * 400 - 2
    img = image.astype(float)
    # Everything else is the flat sky: nothing bleeds into the neighbours.
    assert np.all(img[~lit] == sky) and np.all(img[lit] > sky)


def test_cosmic_rays_are_sharp_tracks_on_their_pixels_only():
    base, _ = render(EMPTY, Sensor(noise=False))
    image, truth = render(EMPTY, Sensor(noise=False, cosmic_rays=20))
    assert len(truth["cosmic_rays"]) == 20
    changed = image != base
    assert 20 <= changed.sum() <= 20 * 4 * 31
    hit = np.zeros(image.shape, bool)
    for ray in truth["cosmic_rays"]:
        a = math.radians(ray["angle_deg"])
        for t in np.linspace(0, ray["length_px"], 200):
            c, r = round(ray["x"] + t * math.cos(a)), round(ray["y"] + t * math.sin(a))
            if 0 <= r < image.shape[0] and 0 <= c < image.shape[1]:
                hit[r, c] = True
    assert np.all(hit[changed])
    starts = [(round(r["y"]), round(r["x"])) for r in truth["cosmic_rays"]]
    assert all(changed[r, c] for r, c in starts if 0 <= r < image.shape[0] and 0 <= c < image.shape[1])


@pytest.mark.parametrize("kind", ["disc", "edge", "branches"])
@pytest.mark.parametrize("fraction", [0.3, 0.5])
def test_foreground_covers_its_fraction_and_hides_the_stars_behind(catalog, kind, fraction):
    mask, texture = foreground_mask(300, 400, kind, fraction, np.random.default_rng(5))
    assert mask.mean() == pytest.approx(fraction, abs=0.01)
    assert mask.min() == 0 and mask.max() == 1 and texture.min() > 0
    scene = Scene(foreground=kind, foreground_fraction=fraction, foreground_e_per_s=0.0)
    sensor = Sensor(noise=False, background_e_per_s=5000.0, dark_current_e_per_s=0.0)
    plain_image, plain = render(catalog, sensor, seed=5)
    image, truth = render(catalog, sensor, scene, seed=5)
    fg = truth["foreground"]
    assert fg["kind"] == kind and fg["fraction"] == pytest.approx(fraction, abs=0.01)
    hidden = set(fg["hidden_star_ids"])
    shown = {s["id"] for s in truth["stars"]}
    assert hidden and shown and not hidden & shown
    assert hidden | shown == {s["id"] for s in plain["stars"]}
    # A dark body: where it covers, only the bias remains (no sky, no star); its soft edge half-way.
    sky_dn = sensor.background_e / sensor.gain
    assert np.mean(image < sensor.bias + 0.5 * sky_dn) == pytest.approx(fraction, abs=0.02)
    assert fraction - 0.15 < np.mean(image == sensor.bias) <= fraction
    inside = [s for s in plain["stars"] if 0 <= round(s["x"]) < 400 and 0 <= round(s["y"]) < 300]
    for s in inside:
        r, c = round(s["y"]), round(s["x"])
        if s["id"] in hidden:
            # Opacity >= 0.5 there: at most half of the sky and the star get through.
            assert image[r, c] - sensor.bias <= 0.5 * (float(plain_image[r, c]) - sensor.bias) + 1


def test_bright_disc_is_saturated_by_default(catalog):
    sensor = Sensor(noise=False)
    image, truth = render(catalog, sensor, Scene(foreground="disc", foreground_fraction=0.3), seed=2)
    assert truth["foreground"]["e_per_s"] == pytest.approx(2 * sensor.full_well_e / sensor.exposure_s)
    full = min(sensor.max_dn, round(sensor.full_well_e / sensor.gain + sensor.bias))
    assert np.mean(image == full) > 0.2


def test_nebulosity_has_its_peak_and_structure():
    sensor = Sensor(noise=False, gain_e_per_dn=0.1, full_well_e=1e7, dark_current_e_per_s=0.0)
    base, _ = render(EMPTY, sensor)
    image, truth = render(EMPTY, sensor, Scene(nebulosity_e_per_s=2000.0), seed=3)
    extra = (image.astype(float) - base) * sensor.gain / sensor.exposure_s
    assert extra.max() == pytest.approx(2000.0, rel=0.01)
    assert extra.min() >= -1.0 and truth["nebulosity_e_per_s"] == 2000.0
    # Structured: neither flat nor noise (neighbouring pixels alike).
    assert np.std(extra) > 100 and np.corrcoef(extra[:, 1:].ravel(), extra[:, :-1].ravel())[0, 1] > 0.99


@pytest.mark.parametrize("ratio", [3.0, 10.0])
def test_gradient_spans_its_ratio(ratio):
    sensor = Sensor(noise=False, gain_e_per_dn=1.0, full_well_e=1e6, dark_current_e_per_s=0.0,
                    background_e_per_s=20000.0, bias_dn=100)
    image, truth = render(EMPTY, sensor, Scene(gradient=ratio), seed=4)
    sky = image.astype(float) - 100
    assert sky.max() / sky.min() == pytest.approx(ratio, rel=0.01)
    assert sky.mean() == pytest.approx(2000.0, rel=0.01)
    assert truth["gradient"] == ratio


def test_vignetting_dims_corners_stars_and_sky():
    sensor = Sensor(noise=False, gain_e_per_dn=1.0, full_well_e=1e6, dark_current_e_per_s=0.0,
                    background_e_per_s=20000.0, bias_dn=100, vignetting=0.5)
    image, _ = render(EMPTY, sensor)
    sky = image.astype(float) - 100
    assert sky[0, 0] / sky[150, 200] == pytest.approx(0.5, rel=0.01)
    assert sky[149:151, 199:201].max() == sky.max()


@pytest.mark.parametrize("axis", ["x", "y"])
def test_mirror_flips_the_written_image_and_the_truth(catalog, axis):
    image, truth = render(catalog, Sensor(hot_pixels=5, cosmic_rays=3), seed=6)
    flipped, ftruth = render(catalog, Sensor(hot_pixels=5, cosmic_rays=3), Scene(mirror=axis), seed=6)
    assert np.array_equal(flipped, image[:, ::-1] if axis == "x" else image[::-1, :])
    assert ftruth["mirror"] == axis and ftruth["quaternion"] == truth["quaternion"]
    size = CAM.width if axis == "x" else CAM.height
    for name in ("stars", "hot_pixels", "cosmic_rays"):
        for a, b in zip(truth[name], ftruth[name]):
            assert b[axis] == pytest.approx(size - 1 - a[axis])
    stars, st = star_list(catalog, CAM, ORION, Sensor(), Scene(mag_limit=6.0), np.random.default_rng(1))
    fstars, fst = star_list(catalog, CAM, ORION, Sensor(), Scene(mag_limit=6.0, mirror=axis), np.random.default_rng(1))
    assert fst["mirror"] == axis and len(stars) == len(fstars)
    for a, b in zip(stars, fstars):
        assert b[axis] == pytest.approx(size - 1 - a[axis])


def test_every_nuisance_is_reproducible(catalog):
    sensor = Sensor(hot_pixels=20, cosmic_rays=5, vignetting=0.7, bit_depth=8, dark_subtracted=True,
                    gain_e_per_dn=2.0)
    scene = Scene(foreground="branches", nebulosity_e_per_s=300.0, gradient=5.0, mirror="y")
    a, ta = render(catalog, sensor, scene, seed=9)
    b, tb = render(catalog, sensor, scene, seed=9)
    c, tc = render(catalog, sensor, scene, seed=10)
    assert np.array_equal(a, b) and ta == tb
    assert not np.array_equal(a, c) and ta["foreground"] != tc["foreground"]


def test_no_nuisance_draws_nothing_more(catalog):
    # A frame without nuisances is what it was before they existed: the same random draws.
    sensor = Sensor()
    a, _ = render(catalog, sensor, seed=11)
    b, _ = render(catalog, sensor, Scene(foreground_fraction=0.7, gradient=1.0), seed=11)
    assert np.array_equal(a, b)


def test_render_cli_nuisances(tmp_path):
    out = tmp_path / "n.fits"
    proc = run_cli("render", "--fov-deg", "10", "--size", "320x240", "--seed", "3", "--bit-depth", "8",
                   "--gain-e-per-dn", "2", "--dark-subtracted", "--hot-pixels", "10", "--cosmic-rays", "2",
                   "--vignetting", "0.6", "--gradient", "4", "--nebulosity-e-per-s", "200", "--foreground", "edge",
                   "--foreground-fraction", "0.4", "--mirror", "x", "-o", out, check=True)
    doc = json.loads(proc.stdout)
    truth, params = doc["truth"], doc["render"]["params"]
    assert truth["mirror"] == "x" and truth["foreground"]["kind"] == "edge"
    assert truth["foreground"]["fraction"] == pytest.approx(0.4, abs=0.01)
    assert len(truth["hot_pixels"]) == 10 and len(truth["cosmic_rays"]) == 2 and truth["gradient"] == 4
    assert params["sensor"]["dark_subtracted"] is True and params["sensor"]["vignetting"] == 0.6
    assert params["scene"]["foreground"] == "edge" and params["scene"]["mirror"] == "x"
    assert params["scene"]["nebulosity_e_per_s"] == 200
    assert_refused(run_cli("render", "--stars-only", "--fov-deg", "10", "--foreground", "disc"), "--foreground")
    assert_refused(run_cli("render", "--fov-deg", "10", "--gradient", "0.5", "-o", tmp_path / "x.png"), "--gradient")


def test_false_stars_with_a_magnitude_limit_below_zero():
    # Was "internal error: ValueError: high - low < 0" (false stars drawn between max(0, limit - 5) and the limit).
    proc = run_cli("render", "--stars-only", "--fov-deg", "20", "--mag-max", "-1", "--false-stars", "5", "--seed", "2",
                   check=True)
    doc = json.loads(proc.stdout)
    assert doc["truth"]["star_ids"].count(None) == 5 and len(doc["stars"]) == len(doc["truth"]["star_ids"])
