"""All-sky frames: the horizon nuisance of `render`, and the blind all-sky solve through the real CLI."""
import json
import math

import numpy as np
import pytest

from startrack.camera import Camera


def test_binomial_tail_of_thousands_of_stars():
    """An all-sky frame verifies over 1000+ detections: the tail must not overflow (it did: math.comb -> float).
    The oracle: the same sum in 60-digit decimal arithmetic with exact binomial coefficients."""
    import decimal

    from startrack.identify.verify import _binomial_sf

    decimal.getcontext().prec = 60
    for m, n, p in [(40, 1500, 0.01), (700, 1500, 0.3), (5, 2000, 1e-4), (1, 1200, 0.5), (1200, 1200, 0.999)]:
        dp = decimal.Decimal(p)
        want = sum(decimal.Decimal(math.comb(n, k)) * dp ** k * (1 - dp) ** (n - k) for k in range(m, n + 1))
        assert _binomial_sf(m, n, p) == pytest.approx(float(want), rel=1e-9, abs=1e-300)


def test_horizon_profile():
    from startrack.nuisance import horizon_altitude, horizon_profile

    assert np.all(horizon_profile("flat", np.random.default_rng(0)) == 0)
    for seed in range(30):
        alt = horizon_profile("random", np.random.default_rng(seed))
        again = horizon_profile("random", np.random.default_rng(seed))
        assert np.array_equal(alt, again)
        assert np.all(alt >= 0) and np.all(alt < math.radians(90))
        assert np.quantile(alt, 2 / 3) <= math.radians(15.0) + 1e-12
    # Interpolation wraps around azimuth 0 = 2 pi.
    prof = np.arange(720, dtype=float)
    assert horizon_altitude(prof, 2 * math.pi - 1e-12) == pytest.approx(0.0, abs=1e-6)
    assert horizon_altitude(prof, 0.5 * 2 * math.pi / 720) == pytest.approx(0.5)


def test_ground_mask_follows_the_skyline():
    from startrack.nuisance import below_skyline, ground_mask

    cam = Camera.from_fov(180.0, 201, 201, projection="equidistant")
    profile = np.zeros(720)
    profile[:180] = math.radians(30.0)          # a wall over azimuths 0-90 deg
    mask = ground_mask(cam, profile, soft_px=1.0)
    vec = cam.pixels_to_vectors(*np.meshgrid(np.arange(201.0), np.arange(201.0)))
    inside = np.all(np.isfinite(vec), axis=-1)
    below = np.zeros(mask.shape, dtype=bool)
    below[inside] = below_skyline(vec[inside], profile)
    # Away from the soft edge the mask is the rule: 1 below the skyline or off the model, 0 above.
    theta = np.degrees(np.arccos(np.clip(vec[..., 2], -1, 1)))
    az = np.degrees(np.arctan2(vec[..., 1], vec[..., 0])) % 360
    edge = np.where(az < 90, 60.0, 90.0)
    clear = inside & (np.abs(theta - edge) > 2.0) & (np.abs(az - 90) > 2) & (np.abs(az) % 360 > 2)
    assert np.all(mask[clear & below] == 1.0) and np.all(mask[clear & ~below] == 0.0)
    assert np.all(mask[~inside] == 1.0)
    assert np.count_nonzero(clear & below) > 1000 and np.count_nonzero(clear & ~below) > 1000


def test_render_fisheye_draws_only_the_sky(tmp_path, cli):
    proc = cli("render", "--projection", "equisolid", "--fov-deg", "170", "--size", "300x240", "--ra", "10",
               "--dec", "50", "--mag-max", "5", "--horizon", "random", "--no-aberration", "--seed", "3",
               "-o", tmp_path / "f.png", check=True)
    doc = json.loads(proc.stdout)
    cam = Camera.from_dict(doc["camera"])
    assert cam.projection == "equisolid" and cam.fov_deg[0] == pytest.approx(170.0)
    from startrack.rotations import quaternion_to_dcm

    a = quaternion_to_dcm(doc["truth"]["quaternion"])
    hidden = set(doc["truth"]["horizon"]["hidden_star_ids"])
    assert hidden and doc["truth"]["horizon"]["kind"] == "random"
    from startrack.catalog import load_catalog

    cat = load_catalog().propagate(doc["truth"]["epoch"])
    rows = cat.rows_by_id()
    vec = cat.vectors()
    for s in doc["truth"]["stars"]:
        assert s["id"] not in hidden
        v = a @ vec[rows[s["id"]]]
        assert v[2] > 0                                            # nothing below the horizon
        x, y = cam.vectors_to_pixels(v)
        assert (x, y) == pytest.approx((s["x"], s["y"]), abs=1e-6)
    assert doc["render"]["params"]["scene"]["horizon"] == "random"


def test_blind_allsky_solve_end_to_end(tmp_path, cli, solve_cache):
    """A 180 deg equidistant frame with a random horizon: `solve` with no hint finds it, its projection, focal
    length and centre, and writes an ARC WCS that astropy reads back to the same sky."""
    proc = cli("render", "--projection", "equidistant", "--fov-deg", "180", "--size", "640x640", "--ra", "250",
               "--dec", "-20", "--roll", "40", "--mag-max", "5.5", "--horizon", "random", "--extinction-mag", "0.2",
               "--no-aberration", "--seed", "8", "-o", tmp_path / "sky.png", check=True)
    truth = json.loads(proc.stdout)
    solved = cli("solve", tmp_path / "sky.png", "--no-aberration", "--wcs", tmp_path / "sky.wcs.fits", env=solve_cache,
                 timeout=600)
    assert solved.returncode == 0, solved.stderr
    doc = json.loads(solved.stdout)
    assert doc["solve"]["status"] == "ok"
    cam = Camera.from_dict(doc["camera"])
    assert cam.projection == "equidistant" and doc["solve"]["allsky"]["projection"] == "equidistant"
    assert cam.focal_length_px == pytest.approx(truth["camera"]["focal_length_px"], rel=1e-3)
    from startrack.rotations import attitude_error, quaternion_to_dcm

    _, cross, roll = attitude_error(quaternion_to_dcm(doc["attitude"]["quaternion"]),
                                    quaternion_to_dcm(truth["truth"]["quaternion"]))
    assert cross < 0.05 and abs(roll) < 0.1
    from astropy.io import fits
    from astropy.wcs import WCS

    hdr = fits.getheader(tmp_path / "sky.wcs.fits")
    assert hdr["CTYPE1"] in ("RA---ARC", "RA---ZPN")
    ra, dec = WCS(hdr).all_pix2world([[319.5, 319.5]], 0)[0]
    assert ra == pytest.approx(doc["solve"]["center_ra"], abs=1e-6) and dec == pytest.approx(doc["solve"]["center_dec"],
                                                                                             abs=1e-6)


def test_pinhole_only_leaves_a_fisheye_frame_unsolved(tmp_path, cli, solve_cache):
    """`--projection pinhole` is today's search alone: an all-sky frame is a failure with a reason, never a guess."""
    cli("render", "--projection", "stereographic", "--fov-deg", "150", "--size", "480x480", "--ra", "30",
        "--dec", "10", "--mag-max", "5.5", "--no-aberration", "--seed", "2", "-o", tmp_path / "sky.png", check=True)
    solved = cli("solve", tmp_path / "sky.png", "--projection", "pinhole", "--no-aberration", env=solve_cache,
                 timeout=600)
    assert solved.returncode == 1
    assert json.loads(solved.stdout)["solve"]["status"] == "failed"
