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
    """A 180 deg equidistant frame with a random horizon and lights on the ground: `solve` with no hint finds
    it, its projection, focal length and centre, the ground, and writes an ARC WCS that astropy reads back to
    the same sky."""
    proc = cli("render", "--projection", "equidistant", "--fov-deg", "180", "--size", "640x640", "--ra", "250",
               "--dec", "-20", "--roll", "40", "--mag-max", "5.5", "--horizon", "random", "--extinction-mag", "0.2",
               "--ground-lights", "30", "--no-aberration", "--seed", "8", "-o", tmp_path / "sky.png", check=True)
    truth = json.loads(proc.stdout)
    solved = cli("solve", tmp_path / "sky.png", "--no-aberration", "--wcs", tmp_path / "sky.wcs.fits", env=solve_cache,
                 timeout=600)
    assert solved.returncode == 0, solved.stderr
    doc = json.loads(solved.stdout)
    assert doc["solve"]["status"] == "ok"
    cam = Camera.from_dict(doc["camera"])
    assert cam.projection == "equidistant" and doc["solve"]["allsky"]["projection"] == "equidistant"
    assert cam.focal_length_px == pytest.approx(truth["camera"]["focal_length_px"], rel=1e-3)
    # The ground found in the pixels (below the skyline, outside the image circle) and its 30 lights dropped.
    sky = doc["solve"]["allsky"]["sky"]
    assert sky["masked_fraction"] == pytest.approx(truth["truth"]["horizon"]["ground_fraction"], abs=0.03)
    assert sky["image_circle"] is not None
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


def test_match_is_the_naive_nearest_neighbour_rule():
    """The grid-binned match of the ring growth against the full distance matrix (tests/naive.py), on random
    detections near and away from predicted stars, radii varied, some not finite."""
    from naive import allsky_match_naive

    from startrack.allsky import _match

    rng = np.random.default_rng(5)
    for trial in range(60):
        n, m = int(rng.integers(0, 150)), int(rng.integers(0, 200))
        px, py = rng.uniform(0, 400, m), rng.uniform(0, 400, m)
        k = min(n, m)
        xs = np.concatenate([px[:k] + rng.normal(0, 2, k), rng.uniform(0, 400, n - k)])
        ys = np.concatenate([py[:k] + rng.normal(0, 2, k), rng.uniform(0, 400, n - k)])
        radius = rng.uniform(0.5, 20, n)
        radius[rng.random(n) < 0.05] = np.inf if trial % 2 else np.nan
        got, want = _match(xs, ys, radius, px, py), allsky_match_naive(xs, ys, radius, px, py)
        assert np.array_equal(got[0], want[0]) and np.array_equal(got[1], want[1])


def _rendered_with_ground(projection, fov, seed, monkeypatch, horizon="random", lights=0, size=480):
    """A zenith-pointing frame rendered in-process, with the skyline profile render drew (to compute the truth)."""
    from startrack import nuisance
    from startrack.catalog import load_catalog
    from startrack.render import Scene, Sensor, render_image
    from startrack.rotations import radec_roll_to_dcm

    drawn = []
    real = nuisance.horizon_profile

    def spy(kind, rng, *a, **k):
        drawn.append(real(kind, rng, *a, **k))
        return drawn[-1]

    monkeypatch.setattr(nuisance, "horizon_profile", spy)
    cam = Camera.from_fov(fov, size, size, projection=projection)
    cat = load_catalog().filter_magnitude(None, 5.5)
    rng = np.random.default_rng(seed)
    image, truth = render_image(cat, cam, radec_roll_to_dcm(rng.uniform(0, 360), rng.uniform(-60, 60), 20.0),
                                Sensor(), Scene(5.5, horizon=horizon, extinction_mag=0.2, ground_lights=lights), rng)
    ground = nuisance.ground_mask(cam, drawn[-1]) >= 0.5 if drawn else np.zeros(image.shape, dtype=bool)
    return image, truth, ground, cam


@pytest.mark.parametrize("projection,fov,seed", [("equidistant", 180, 1), ("equisolid", 150, 2),
                                                 ("stereographic", 180, 3), ("orthographic", 120, 4),
                                                 ("equidistant", 150, 6)])
def test_find_sky_recovers_the_rendered_ground(projection, fov, seed, monkeypatch):
    """The ground found in the pixels against the ground rendered (below a random skyline, outside the image
    circle): intersection over union of the ground >= 0.9; the sky it keeps is sky (>= 98 %)."""
    from startrack.allsky import find_sky

    image, truth, ground, _ = _rendered_with_ground(projection, fov, seed, monkeypatch, size=960)
    region = find_sky(image)
    assert region is not None
    found = region.pixel_mask()
    iou = np.count_nonzero(found & ground) / np.count_nonzero(found | ground)
    print(f"{projection} {fov} deg: ground {ground.mean():.3f}, IoU {iou:.3f}")
    assert iou >= 0.9, iou
    assert np.count_nonzero(~found & ~ground) / np.count_nonzero(~found) >= 0.98
    assert region.record()["masked_fraction"] == pytest.approx(float(found.mean()), abs=1e-4)


def test_find_sky_image_circle_and_a_frame_without_ground(monkeypatch):
    """A flat horizon at 180 deg: the sky's edge is the lens's image circle, centred on the principal point,
    radius f pi / 2.  An ordinary frame (a 20 deg pinhole, no ground) has no ground and no circle."""
    from startrack.allsky import find_sky

    image, _, _, cam = _rendered_with_ground("equidistant", 180, 9, monkeypatch, horizon="flat")
    region = find_sky(image)
    cx, cy, r = region.circle
    assert math.hypot(cx - cam.cx, cy - cam.cy) < 0.5 * region.tile_px
    assert r == pytest.approx(cam.focal_length_px * math.pi / 2, abs=region.tile_px)
    image, _, _, _ = _rendered_with_ground("pinhole", 20, 9, monkeypatch, horizon=None)
    assert find_sky(image) is None


def test_lights_on_the_ground_are_dropped(monkeypatch):
    """`render`'s ground lights are bright point sources: find_stars detects them; the sky mask (one block's
    margin, as the all-sky search uses it) drops at least 90 % of them and keeps at least 97 % of the rendered
    stars' detections."""
    from startrack.allsky import find_sky
    from startrack.centroid import CentroidOptions, find_stars

    image, truth, _, _ = _rendered_with_ground("equisolid", 160, 12, monkeypatch, lights=40, size=960)
    lights = truth["horizon"]["lights"]
    assert len(lights) == 40
    det = find_stars(image, CentroidOptions(max_stars=1500)).stars
    dx, dy = np.array([s["x"] for s in det]), np.array([s["y"] for s in det])

    def nearest(x, y):
        return np.argmin(np.hypot(dx - x, dy - y)), np.min(np.hypot(dx - x, dy - y))

    hit_lights = [nearest(li["x"], li["y"]) for li in lights]
    hit_lights = [i for i, d in hit_lights if d < 1.5]
    assert len(hit_lights) >= 30                # the lights are detected: they would enter the search
    region = find_sky(image)
    keep = region.in_sky(dx, dy, margin=1)
    assert np.count_nonzero(~keep[hit_lights]) >= 0.9 * len(hit_lights)
    stars = [i for i, d in (nearest(s["x"], s["y"]) for s in truth["stars"] if s["mag_rendered"] < 5) if d < 1.0]
    print(f"lights dropped {np.count_nonzero(~keep[hit_lights])} of {len(hit_lights)}; stars kept "
          f"{np.count_nonzero(keep[stars])} of {len(stars)}")
    assert len(stars) > 100 and np.count_nonzero(keep[stars]) >= 0.97 * len(stars)


def test_extincted_magnitudes():
    """k (X - 1): nothing at the zenith, k at an air mass of 2 (60 deg), the most at the horizon; monotonic."""
    from startrack.allsky import EXTINCTION_K, extincted_mag

    theta = np.radians([0.0, 60.0, 80.0, 90.0])
    got = extincted_mag(np.full(4, 5.0), theta, 0.2)
    assert got[0] == pytest.approx(5.0, abs=1e-3)
    assert got[1] == pytest.approx(5.2, abs=0.002)
    assert np.all(np.diff(got) > 0) and got[3] == pytest.approx(5.0 + 0.2 * (38.0 - 1), abs=0.2)
    assert EXTINCTION_K == 0.0          # off by default (see its comment)


def test_ring_growth_predicts_only_stars_the_atmosphere_lets_through():
    """Ring growth on a 180 deg star list whose stars are those brighter than 5.5 after 0.2 mag per air mass:
    every match is the detection's own star, no star dimmed past the growth's limit is predicted, and more
    stars are matched than when the growth ignores the extinction."""
    from startrack.allsky import AllSkyOptions, _grow, extincted_mag
    from startrack.catalog import load_catalog
    from startrack.rotations import radec_roll_to_dcm

    cam = Camera.from_fov(180.0, 800, 800, projection="equidistant")
    cat = load_catalog().filter_magnitude(None, 6.5)
    vec = cat.vectors()
    dcm = radec_roll_to_dcm(120.0, 30.0, 10.0)
    v = vec @ dcm.T
    theta = np.arccos(np.clip(v[:, 2], -1, 1))
    x, y = cam.vectors_to_pixels(v)
    seen = np.isfinite(x) & cam.in_image(x, y) & (extincted_mag(cat.mag, theta, 0.2) <= 5.5) & (theta < np.pi / 2)
    rows = np.flatnonzero(seen)
    rng = np.random.default_rng(3)
    stars = [{"x": float(x[r] + rng.normal(0, 0.1)), "y": float(y[r] + rng.normal(0, 0.1)), "sigma_px": 0.1}
             for r in rows]
    opts = AllSkyOptions(mag_max=6.0, extinction_k=0.2)
    # a slightly wrong start (focal length 1 % off), as the centre's pinhole solve gives
    _, _, det, got = _grow(stars, 800, 800, cam.focal_length_px * 1.01, dcm, vec, opts, 0.1, np.radians(15),
                           "equidistant", cat.mag)
    assert len(det) > 0.7 * len(rows)
    assert np.array_equal(got, rows[det])                        # each detection matched to its own star
    v_got = vec[got] @ dcm.T
    assert np.all(extincted_mag(cat.mag[got], np.arccos(np.clip(v_got[:, 2], -1, 1)), 0.2) <= 6.0)
    # Without the extinction, the stars it hides crowd the low rings: fewer unambiguous matches (550 here).
    _, _, det_plain, got_plain = _grow(stars, 800, 800, cam.focal_length_px * 1.01, dcm, vec, opts, 0.1,
                                       np.radians(15), "equidistant", None)
    assert np.array_equal(got_plain, rows[det_plain]) and len(det) > 1.1 * len(det_plain)


def _random_region(rng, n=24, tile=8):
    """A SkyRegion of ``n x n`` blocks (the image a few pixels wider than whole blocks): ground outside a
    circle about a random point near the centre, plus a few random rectangles of ground touching the border."""
    from startrack.allsky import SkyRegion

    w = h = n * tile + int(rng.integers(0, tile))
    yy, xx = np.mgrid[0:n, 0:n]
    c = n / 2 + rng.uniform(-3, 3, 2)
    ground = np.hypot(xx - c[0], yy - c[1]) > rng.uniform(0.35, 0.8) * n
    for _ in range(int(rng.integers(0, 4))):
        side, a, b = int(rng.integers(4)), *sorted(rng.integers(0, n, 2))
        depth = int(rng.integers(1, n // 2))
        if side == 0:
            ground[:depth, a:b + 1] = True
        elif side == 1:
            ground[n - depth:, a:b + 1] = True
        elif side == 2:
            ground[a:b + 1, :depth] = True
        else:
            ground[a:b + 1, n - depth:] = True
    return SkyRegion(ground, tile, w, h, 100.0, 10.0, None)


def test_sky_window_is_sky_and_cannot_grow():
    """The sky's window (the all-sky verification's frame, startrack.solve._allsky_verify) on random grounds, against
    SkyRegion.in_sky over pixels: every pixel of it is sky one block from the ground, it holds the principal point,
    and no side can move out by one pixel without taking in a pixel near the ground or leaving the image; None
    only when the principal point's own pixel is near the ground."""
    from startrack.allsky import sky_window

    rng = np.random.default_rng(43)
    seen = 0
    for _ in range(150):
        region = _random_region(rng)
        w, h = region.width, region.height
        cx, cy = rng.uniform(0.3, 0.7) * (w - 1), rng.uniform(0.3, 0.7) * (h - 1)
        win = sky_window(region, cx, cy)
        here = bool(region.in_sky(round(cx), round(cy), margin=1))
        if win is None:
            assert not here
            continue
        seen += 1
        x0, y0, x1, y1 = win
        assert 0 <= x0 and x1 <= w and 0 <= y0 and y1 <= h
        assert x0 - 0.5 <= cx < x1 - 0.5 and y0 - 0.5 <= cy < y1 - 0.5
        yy, xx = np.mgrid[y0:y1, x0:x1]
        assert region.in_sky(xx, yy, margin=1).all()
        for strip, at_edge in ((np.mgrid[y0:y1, x0 - 1:x0], x0 == 0), (np.mgrid[y0:y1, x1:x1 + 1], x1 == w),
                               (np.mgrid[y0 - 1:y0, x0:x1], y0 == 0), (np.mgrid[y1:y1 + 1, x0:x1], y1 == h)):
            assert at_edge or not region.in_sky(strip[1], strip[0], margin=1).all()
    assert seen >= 50


@pytest.mark.parametrize("mirrored", [False, True])
def test_allsky_verification_in_the_sky_window(mirrored, monkeypatch, solve_cache):
    """Step 4 (startrack.solve._allsky_verify) on a rendered 180 deg stereographic frame with a random horizon, with
    its true camera: identified in the sky's window, every match names the catalog star the truth puts at that
    detection (within 3 px, the median within 0.3 px) and lies in the window recorded (the image's pixels).  Mirrored: the image flipped left
    to right and searched as the mirrored parity is (the detections flipped back about the centre column)."""
    from startrack.allsky import find_sky
    from startrack.centroid import CentroidOptions, find_stars
    from startrack.parity import mirror_stars
    from startrack.solve import BandDatabases, SolveOptions, _allsky_verify, _pyramid_config, _SearchClock

    monkeypatch.setenv("STARTRACK_CACHE", solve_cache["STARTRACK_CACHE"])
    image, truth, _, cam = _rendered_with_ground("stereographic", 180, 5, monkeypatch, size=640)
    w, h = cam.width, cam.height
    seen = image[:, ::-1] if mirrored else image
    region = find_sky(seen)
    stars = find_stars(seen, CentroidOptions(max_stars=1500)).stars
    keep = region.in_sky([s["x"] for s in stars], [s["y"] for s in stars], margin=1)
    stars = [s for s, k in zip(stars, keep) if k]
    search = mirror_stars(stars, (w - 1) / 2.0) if mirrored else stars
    result, _, window = _allsky_verify(search, cam, region, w, h, SolveOptions(), _SearchClock(30.0),
                                       BandDatabases(), _pyramid_config("pyramid", 200), mirrored=mirrored)
    assert result is not None and window is not None and window != [0, 0, w, h]
    got_cam, _, res, _ = result
    assert got_cam is cam and len(res.matches) >= 50
    where = {s["id"]: (s["x"], s["y"]) for s in truth["stars"]}
    x0, y0, x1, y1 = window
    off = []
    for star, cid in res.matches:
        x, y = search[star]["x"], search[star]["y"]
        off.append(math.hypot(x - where[cid][0], y - where[cid][1]))
        ix = (w - 1) - x if mirrored else x          # the detection in the image's own pixels
        assert x0 - 0.5 <= ix < x1 - 0.5 and y0 - 0.5 <= y < y1 - 0.5
    # (a blend of two faint stars moves a centroid by a pixel or two; a wrong star is tens of pixels away)
    assert max(off) < 3.0 and np.median(off) < 0.3, (max(off), np.median(off))


def test_masked_fraction_is_the_pixel_masks_mean():
    """The ground's fraction from block pixel counts equals the mean of the whole-frame mask (partial last blocks
    included), on random grounds, block sizes and frames."""
    from startrack.allsky import SkyRegion

    rng = np.random.default_rng(1)
    for _ in range(200):
        w, h, tile = int(rng.integers(20, 300)), int(rng.integers(20, 300)), int(rng.integers(2, 17))
        ground = rng.random((max(1, h // tile), max(1, w // tile))) < 0.4
        region = SkyRegion(ground, tile, w, h, 1.0, 0.0, None)
        assert region.masked_fraction == pytest.approx(float(np.mean(region.pixel_mask())), abs=1e-12)
