import math

import numpy as np
import pytest

from startrack.camera import Camera
from startrack.catalog import Catalog
from startrack.render import (
    Scene,
    Sensor,
    electrons_from_magnitude,
    frame_seed,
    render_image,
    star_list,
)
from startrack.rotations import (
    _propagate_attitude_rad,
    quaternion_to_dcm,
    radec_roll_to_dcm,
    random_quaternions,
)


def one_star_catalog(dx_px, dy_px, camera, mag=3.0):
    """A catalog whose only star lands at (cx + dx, cy + dy) for the identity attitude."""
    v = camera.pixels_to_vectors(camera.cx + dx_px, camera.cy + dy_px)
    ra = math.degrees(math.atan2(v[1], v[0])) % 360
    dec = math.degrees(math.asin(v[2]))
    return Catalog([1], [ra], [dec], [mag], [0.0], [0.0], [np.nan], 2000.0)


IDENTITY = np.eye(3)


@pytest.mark.parametrize("sigma", [0.6, 1.0, 2.0])
@pytest.mark.parametrize("phase", [(0.0, 0.0), (0.25, -0.4), (0.5, 0.5), (-0.13, 0.37)])
def test_noise_free_centroid_is_truth(sigma, phase):
    cam = Camera.from_fov(10, 128, 128)
    cat = one_star_catalog(3 + phase[0], -2 + phase[1], cam)
    sensor = Sensor(psf_sigma_px=sigma, noise=False, full_well_e=1e9, gain_e_per_dn=0.2)
    image, truth = render_image(cat, cam, IDENTITY, sensor, Scene(), np.random.default_rng(0))
    star = truth["stars"][0]
    bg = sensor.bias + sensor.background_e / sensor.gain
    img = image.astype(float) - bg
    half = int(6 * sigma) + 2
    x0, y0 = int(round(star["x"])), int(round(star["y"]))
    win = img[y0 - half:y0 + half + 1, x0 - half:x0 + half + 1]
    yy, xx = np.mgrid[y0 - half:y0 + half + 1, x0 - half:x0 + half + 1]
    cx = (win * xx).sum() / win.sum()
    cy = (win * yy).sum() / win.sum()
    assert abs(cx - star["x"]) < 0.02 and abs(cy - star["y"]) < 0.02


@pytest.mark.parametrize("mag", [2.0, 4.0, 6.0])
def test_total_signal_follows_magnitude_law(mag):
    cam = Camera.from_fov(10, 96, 96)
    cat = one_star_catalog(0.3, 0.2, cam, mag=mag)
    sensor = Sensor(noise=False, full_well_e=1e9, gain_e_per_dn=0.05, psf_sigma_px=1.3)
    image, truth = render_image(cat, cam, IDENTITY, sensor, Scene(), np.random.default_rng(0))
    bg = sensor.bias + sensor.background_e / sensor.gain
    total_e = (image.astype(float) - bg).sum() * sensor.gain
    expected = sensor.zero_point_e_per_s * sensor.exposure_s * 2.512 ** (-mag)
    assert total_e == pytest.approx(expected, rel=0.01)
    # A factor 2.512 per magnitude (paper 003 Eqs. 7-8).
    assert electrons_from_magnitude(mag, sensor) / electrons_from_magnitude(mag + 1, sensor) == pytest.approx(2.512, rel=1e-3)


@pytest.mark.parametrize("read_noise, background", [(5.0, 50.0), (2.0, 500.0), (10.0, 0.0)])
def test_dark_frame_statistics_match_noise_model(read_noise, background):
    cam = Camera.from_fov(10, 512, 512)
    empty = Catalog([], [], [], [], [], [], [], 2000.0)
    sensor = Sensor(read_noise_e=read_noise, background_e_per_s=background, dark_current_e_per_s=30.0,
                    gain_e_per_dn=0.8, bias_dn=100)
    image, _ = render_image(empty, cam, IDENTITY, sensor, Scene(), np.random.default_rng(3))
    b = sensor.background_e
    mean = sensor.bias + b / sensor.gain
    var = (b + read_noise**2) / sensor.gain**2 + 1 / 12
    assert image.mean() == pytest.approx(mean, abs=4 * math.sqrt(var / image.size) + 1e-3)
    assert image.var() == pytest.approx(var, rel=0.02)


def test_full_path_noise_matches_table_path():
    """Pixels drawn the slow way (with PRNU 0+) and by table agree in distribution."""
    cam = Camera.from_fov(10, 512, 512)
    empty = Catalog([], [], [], [], [], [], [], 2000.0)
    fast = Sensor(gain_e_per_dn=0.5, bias_dn=50)
    slow = Sensor(gain_e_per_dn=0.5, bias_dn=50, prnu=1e-9)
    a, _ = render_image(empty, cam, IDENTITY, fast, Scene(), np.random.default_rng(1))
    b, _ = render_image(empty, cam, IDENTITY, slow, Scene(), np.random.default_rng(2))
    assert a.mean() == pytest.approx(b.mean(), abs=0.05)
    assert a.var() == pytest.approx(b.var(), rel=0.02)


def test_poisson_kernel_moments():
    """Bright pixels use PTRS rejection: mean and variance of Poisson."""
    cam = Camera.from_fov(10, 256, 256)
    empty = Catalog([], [], [], [], [], [], [], 2000.0)
    for lam in (3.0, 37.0, 900.0):
        sensor = Sensor(read_noise_e=0.0, background_e_per_s=lam * 10, dark_current_e_per_s=0.0,
                        gain_e_per_dn=1.0, bias_dn=0, prnu=1e-12)
        img, _ = render_image(empty, cam, IDENTITY, sensor, Scene(), np.random.default_rng(5))
        assert img.mean() == pytest.approx(lam, rel=0.01)
        assert img.var() == pytest.approx(lam, rel=0.03)


def test_smear_trail_length():
    cam = Camera.from_fov(10, 256, 256)
    cat = one_star_catalog(0.0, 0.0, cam, mag=1.0)
    rate = (0.0, 2.0, 0.0)   # deg/s about camera y: the star runs along x
    sensor = Sensor(noise=False, exposure_ms=200.0, full_well_e=1e12, gain_e_per_dn=5.0, psf_sigma_px=1.0)
    image, truth = render_image(cat, cam, IDENTITY, sensor, Scene(rate_deg_s=rate), np.random.default_rng(0))
    img = image.astype(float) - np.median(image)
    star = truth["stars"][0]
    x0, y0 = int(round(star["x"])), int(round(star["y"]))
    win = img[y0 - 8:y0 + 9, x0 - 20:x0 + 21]
    profile = win.sum(axis=0)
    x = np.arange(x0 - 20, x0 + 21)
    mean = (profile * x).sum() / profile.sum()
    var = (profile * (x - mean) ** 2).sum() / profile.sum()
    # A uniform trail of length L blurred by the pixel-integrated Gaussian:
    # variance L^2 / 12 + sigma^2 + 1/12.
    length = math.sqrt(12 * (var - sensor.psf_sigma_px**2 - 1 / 12))
    expected = math.radians(2.0) * 0.2 * cam.focal_length_px
    assert length == pytest.approx(expected, rel=0.02)
    assert mean == pytest.approx(star["x"], abs=0.05)


def test_propagate_attitude_turns_at_the_rate():
    a = quaternion_to_dcm(random_quaternions(1, np.random.default_rng(1))[0])
    b = _propagate_attitude_rad(a, np.radians([0.1, -0.2, 0.3]), 2.0)
    from startrack.render import attitude_rate_check

    np.testing.assert_allclose(attitude_rate_check(a, b, 2.0), np.radians([0.1, -0.2, 0.3]), atol=1e-12)


def test_focal_error_moves_stars_radially(catalog):
    cam = Camera.from_fov(20, 1024, 1024)
    a = radec_roll_to_dcm(83.8, -1.2, 0.0)
    s0, t0 = star_list(catalog, cam, a, Sensor(), Scene(mag_limit=5), np.random.default_rng(0))
    s1, t1 = star_list(catalog, cam, a, Sensor(), Scene(mag_limit=5, focal_error_pct=1.0), np.random.default_rng(0))
    by_id = {s["id"]: s for s in t0["stars"]}
    for s in t1["stars"]:
        if s["id"] in by_id:
            r0 = math.hypot(by_id[s["id"]]["x"] - cam.cx, by_id[s["id"]]["y"] - cam.cy)
            r1 = math.hypot(s["x"] - cam.cx, s["y"] - cam.cy)
            assert r1 == pytest.approx(r0 * 1.01, rel=1e-9, abs=1e-9)


def test_star_list_noise_false_stars_and_ids(catalog):
    cam = Camera.from_fov(20, 1024, 1024)
    a = radec_roll_to_dcm(83.8, -1.2, 0.0)
    stars, truth = star_list(catalog, cam, a, Sensor(), Scene(mag_limit=5, false_stars=3), np.random.default_rng(4),
                             sigma_px=0.5, max_stars=10)
    assert len(stars) == 10 == len(truth["star_ids"])
    flux = [s["flux"] for s in stars]
    assert flux == sorted(flux, reverse=True)
    by_id = {s["id"]: s for s in truth["stars"]}
    for s, sid in zip(stars, truth["star_ids"]):
        if sid is not None:
            assert math.hypot(s["x"] - by_id[sid]["x"], s["y"] - by_id[sid]["y"]) < 3.0


def test_frame_seeds_are_distinct_and_the_same_in_another_process():
    """Each frame's recorded seed re-renders it alone, so it must not depend on the process (hash seeds, state)."""
    import subprocess
    import sys

    seeds = {frame_seed(seed, index) for seed in range(20) for index in range(50)}
    assert len(seeds) == 1000 and all(0 <= s < 2**63 for s in seeds)
    code = "from startrack.render import frame_seed; print(frame_seed(7, 3))"
    other = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                           env={**__import__("os").environ, "PYTHONHASHSEED": "123"}).stdout
    assert int(other) == frame_seed(7, 3)
