import math

import numpy as np
import pytest

from startrack.camera import Camera
from startrack.errors import BadInputError
from startrack.kvector import build_kvector, max_separation_deg
from startrack.render import RenderRun, Scene, Sensor
from startrack.rotations import _attitude_error_rad, _radec_roll_to_dcm_rad, quaternion_to_dcm, radec_roll_to_dcm
from startrack.track import (
    Tracker,
    TrackerConfig,
    empirical_stars,
    single_star_attitude,
)


def test_paper_001_case_2():
    """Paper 001 Case 2: the empirical star and the attitude A' (||A' - A|| = 0.00289)."""
    from startrack.attitude import quest

    # The empirical star: star 2's predicted position shifted by star 1's observed offset.
    emp = empirical_stars((264.1069, 345.19025), (254.823628, 344.43765), [(219.6527, 289.0390)])[0]
    assert emp[0] == pytest.approx(228.93597, abs=1e-4) and emp[1] == pytest.approx(289.79160, abs=1e-4)
    r = np.array([[0.005121, 0.999940, 0.009651], [0.011252, 0.999937, 0.000481]])
    b1 = [0.011976, -0.02364, 0.999613]
    a_case1 = quest(np.array([b1, [0.0002935, -0.038253, 0.9994907]]), r)
    a_case2 = quest(np.array([b1, [0.0003692, -0.038245, 0.9994892]]), r)
    printed = np.array([[-0.99652, 0.013915, 0.082138], [0.081583, -0.036653, 0.99599], [0.01687, 0.99923, 0.03539]])
    assert np.abs(a_case2 - printed).max() < 2e-4
    # The paper's "Euclidean norm" 0.00289 is the spectral norm (the Frobenius norm would be 0.0041).
    assert np.linalg.norm(a_case2 - a_case1, 2) == pytest.approx(0.00289, abs=0.00005)


def test_single_star_attitude_recovers_a_pure_shift():
    cam = Camera.from_fov(12, 1024, 768)
    a = _radec_roll_to_dcm_rad(1.0, 0.4, 0.2)
    rng = np.random.default_rng(0)
    cam_dirs = cam.pixels_to_vectors(rng.uniform(100, 900, 4), rng.uniform(100, 700, 4))
    ref = cam_dirs @ a
    # The camera turned slightly about its x and y axes: all stars shift about alike.
    from startrack.rotations import _propagate_attitude_rad

    a2 = _propagate_attitude_rad(a, np.radians([0.01, -0.02, 0.0]), 1.0)
    x2, y2 = cam.vectors_to_pixels(ref @ a2.T)
    x1, y1 = cam.vectors_to_pixels(ref @ a.T)
    est = single_star_attitude(cam, (x2[0], y2[0]), (x1[0], y1[0]), ref[0], np.column_stack([x1[1:], y1[1:]]), ref[1:])
    _, cross, _ = _attitude_error_rad(est, a2)
    assert math.degrees(cross) * 3600 < 5


@pytest.fixture(scope="module")
def world(catalog):
    cam = Camera.from_fov(12, 1024, 768)
    db = build_kvector(catalog.filter_magnitude(None, 6.0), max_separation_deg(camera=cam))
    return catalog, cam, db


def _sequence(catalog, cam, n, rate, seed, start=(100.0, 20.0, 10.0), blackout=(), exposure_ms=100.0):
    a0 = radec_roll_to_dcm(*start)
    run = RenderRun(catalog.filter_magnitude(None, 7.0), cam, Sensor(exposure_ms=exposure_ms), Scene(rate_deg_s=rate),
                    seed, a0, 1, n, 0.1, blackout=blackout)
    return list(run.frames_iter())


def _errors(doc, out):
    _, cross, roll = _attitude_error_rad(quaternion_to_dcm(out["attitude"]["quaternion"]),
                                    quaternion_to_dcm(doc["truth"]["quaternion"]))
    return math.degrees(cross) * 3600, abs(math.degrees(roll)) * 3600


def test_tracking_sequence_with_loss_and_recovery(world):
    catalog, cam, db = world
    frames = _sequence(catalog, cam, 40, (0.3, 0.4, 0.0), 3, blackout=tuple(range(15, 25)))
    tr = Tracker(catalog, cam, db, TrackerConfig(mag_limit=6.0))
    modes = []
    for k, (doc, img, _) in enumerate(frames):
        out = tr.step(img, 0.1 * k, 65535)
        modes.append(out["track"]["mode"])
        if out["attitude"]["status"] == "ok":
            cross, roll = _errors(doc, out)
            assert cross < 20 and roll < 200, (k, out["track"]["mode"], cross, roll)
    assert modes[0] == "lost-in-space"
    assert modes[1:15] == ["tracking"] * 14
    assert set(modes[15:25]) == {"lost"}
    # 1 s without an attitude: lost in space on the first frame with light, tracking from the next.
    assert modes[25] == "lost-in-space" and modes[26:] == ["tracking"] * 14
    assert np.allclose(out["track"]["rate_deg_s"], [0.3, 0.4, 0.0], atol=0.02)


def _stretch(catalog, cam, n, rate, seed, keep, start=(100.0, 20.0, 10.0)):
    """Frames rendered with only the ``keep`` brightest stars of the field (the rest occluded)."""
    frames = _sequence(catalog, cam, n, rate, seed, start=start)
    ids = [s["id"] for s in frames[0][0]["truth"]["stars"][:keep]]
    sub = catalog.subset(np.isin(catalog.id, ids))
    return frames, _sequence(sub, cam, n, rate, seed, start=start)


@pytest.mark.parametrize("keep, mode", [(1, "single-star"), (2, "tracking")])
def test_few_stars_keep_lock(world, keep, mode):
    """Two stars keep tracking; one star is paper 001's single-star mode (empirical stars), and says so."""
    catalog, cam, db = world
    full, few = _stretch(catalog, cam, 14, (0.05, -0.05, 0.02), 11, keep)
    tr = Tracker(catalog, cam, db, TrackerConfig(mag_limit=6.0))
    for k in range(14):
        doc, img = (full[k][0], full[k][1]) if k < 6 else (few[k][0], few[k][1])
        out = tr.step(img, 0.1 * k, 65535)
        if k >= 6:
            assert out["track"]["mode"] == mode, (k, out["track"])
            assert out["attitude"]["status"] == "ok" and out["attitude"]["mode"] == mode
            cross, _ = _errors(doc, out)
            assert cross < 30, (k, cross)
    if mode == "single-star":
        assert out["track"]["empirical_stars"] >= 1 and out["attitude"]["method"] == "single-star"


def test_rate_filter_converges_on_noisy_attitudes():
    """The Kalman filter's rate from 20 noisy attitudes (10 arcsec, 0.1 s apart) beats the per-frame difference."""
    from startrack.rotations import _propagate_attitude_rad
    from startrack.track import AttitudeRateFilter

    rng = np.random.default_rng(4)
    w = np.radians([0.5, -1.0, 2.0])
    a = _radec_roll_to_dcm_rad(0.4, -0.3, 1.0)
    s = math.radians(10 / 3600)
    f = AttitudeRateFilter(a, np.zeros(3), np.diag([s ** 2] * 3 + [math.radians(3.0) ** 2] * 3), 1e-8)
    errs = []
    for k in range(1, 21):
        truth = _propagate_attitude_rad(a, w, 0.1 * k)
        meas = _propagate_attitude_rad(truth, rng.normal(0, s, 3), 1.0)
        f.predict(0.1)
        f.update_attitude(meas, np.eye(3) * s ** 2)
        errs.append(np.degrees(f.rate - w))
    single_diff = math.degrees(s * math.sqrt(2) / 0.1)
    assert np.abs(errs[-1]).max() < 0.25 * single_diff, (errs[-1], single_diff)
    sig = np.degrees(np.sqrt(np.diag(f.P)[3:]))
    assert np.all(np.abs(errs[-1]) < 4 * sig)


def test_false_star_inside_a_window_and_washed_out_half(world):
    catalog, cam, db = world
    frames = _sequence(catalog, cam, 12, (0.2, 0.0, 0.0), 5)
    tr = Tracker(catalog, cam, db, TrackerConfig(mag_limit=6.0))
    for k, (doc, img, _) in enumerate(frames):
        img = img.astype(np.float32)
        if k >= 4:
            # A false star next to a tracked star.
            s = doc["truth"]["stars"][0]
            yy, xx = np.mgrid[0:img.shape[0], 0:img.shape[1]]
            img += 20000.0 * np.exp(-((xx - s["x"] - 4.0) ** 2 + (yy - s["y"] - 3.0) ** 2) / 2.0)
        if k >= 8:
            img[:, : img.shape[1] // 2] = 65535.0          # a bright body washes out the left half
        out = tr.step(img, 0.1 * k, 65535)
        assert out["attitude"]["status"] == "ok", (k, out["track"])
        cross, _ = _errors(doc, out)
        assert cross < 30, (k, cross, out["track"]["mode"])


def test_star_leaving_the_field_is_dropped(world):
    catalog, cam, db = world
    # A 2 deg/s slew, 20 ms exposures (3.4 px trails), the rate known from a gyro.
    frames = _sequence(catalog, cam, 30, (0.0, 2.0, 0.0), 7, exposure_ms=20.0)
    tr = Tracker(catalog, cam, db, TrackerConfig(mag_limit=6.0, exposure_s=0.02),
                 initial_rate=np.radians([0.0, 2.0, 0.0]))
    seen = []
    for k, (_doc, img, _) in enumerate(frames):
        out = tr.step(img, 0.1 * k, 65535)
        if out["track"]["mode"] == "tracking":
            seen.append({s["id"] for s in out["track"]["stars"]})
    assert len(seen) >= 25
    assert seen[0] - seen[-1] and seen[-1] - seen[0]     # some stars left, others came in


def test_out_of_order_time_is_refused(world):
    catalog, cam, db = world
    frames = _sequence(catalog, cam, 2, (0.0, 0.0, 0.0), 1)
    tr = Tracker(catalog, cam, db, TrackerConfig(mag_limit=6.0))
    tr.step(frames[0][1], 1.0, 65535)
    with pytest.raises(BadInputError, match="out-of-order"):
        tr.step(frames[1][1], 0.5, 65535)


@pytest.mark.parametrize("k1, rate", [(0.0, (0.1, 0.0, 0.0)), (-0.3, (1.5, -1.0, 0.5))])
def test_window_kernel_matches_its_parts(catalog, k1, rate):
    """The one-call kernel predicts as the camera model does and measures as the window and capsule
    centroids do (lens distortion included)."""
    from startrack._kernels.centroid import window_centroids
    from startrack.streak import predicted_streaks, segment_centroids

    cam = Camera.from_fov(12, 1024, 768, k1=k1)
    cat = catalog.filter_magnitude(None, 6.5)
    a0 = radec_roll_to_dcm(100.0, 20.0, 10.0)
    doc, img, _ = next(iter(RenderRun(cat, cam, Sensor(exposure_ms=100.0), Scene(rate_deg_s=rate), 3, a0, 1, 1,
                                      0.1).frames_iter()))
    img = img.astype(np.float32)
    tr = Tracker(cat, cam, None, TrackerConfig(mag_limit=6.5))
    dcm = quaternion_to_dcm(doc["truth"]["quaternion"])
    w = np.radians(rate)
    rows_py, px, py = tr.predict_stars(dcm)
    half, box = 14, 6
    smear = float(np.linalg.norm(w)) * cam.focal_length_px * 0.1
    for segment in (False, True):
        rows, res = tr._windows(img, dcm, w, 0.1, half, box, segment, smear / 2 + 3)
        assert len(rows) >= 8 and np.array_equal(rows, rows_py)
        assert np.allclose(res[:, 1], px, atol=1e-9) and np.allclose(res[:, 2], py, atol=1e-9)
        mx, my, flux, _, _, found = window_centroids(img, px, py, half, tr.config.k_sigma, 3, box)
        assert np.array_equal(res[:, 8] > 0, found) and np.allclose(res[found, 5], flux[found])
        if not segment:
            assert np.allclose(res[found, 3], mx[found]) and np.allclose(res[found, 4], my[found])
            continue
        # The expected streak: the chord between half an exposure before and after.
        length = 2 * np.hypot(res[:, 9], res[:, 10])
        lin, ang = predicted_streaks(cam, px, py, w, 0.1)      # the image motion to first order
        assert np.allclose(length, lin, rtol=0.01)
        d_ang = (np.arctan2(res[:, 10], res[:, 9]) - ang + np.pi / 2) % np.pi - np.pi / 2
        assert np.abs(d_ang).max() < 0.01
        seg = segment_centroids(img, mx[found], my[found], length[found], np.arctan2(res[found, 10], res[found, 9]),
                                3.0 * tr.psf_sigma_px + 1.0)
        near = np.hypot(seg[:, 0] - mx[found], seg[:, 1] - my[found]) < smear / 2 + 3
        ok = np.flatnonzero(found)[(seg[:, 4] > 0) & near]
        assert np.array_equal(np.flatnonzero(res[:, 11] > 0), ok)
        assert np.allclose(res[ok, 3], seg[(seg[:, 4] > 0) & near, 0]) and np.allclose(res[ok, 7],
                                                                                    seg[(seg[:, 4] > 0) & near, 3])


@pytest.mark.parametrize("fov", [12.0, 70.0, 120.0])
def test_predicted_stars_through_the_sky_index_are_the_brute_force_ones(catalog, fov):
    """The tracker's predicted stars (its neighbourhood from the sky index) are those of projecting the whole
    catalog, attitude after attitude as the boresight moves, across the poles and right ascension 0."""
    from startrack.rotations import random_quaternions

    cam = Camera.from_fov(fov, 1024, 768)
    tracker = Tracker(catalog, cam, None, TrackerConfig(mag_limit=7.0))
    vec = catalog.filter_magnitude(None, 7.0).sorted_by_magnitude().vectors()
    cos_limit = math.cos(math.radians(min(89.0, cam.max_off_axis_deg + 1.0)))
    dcms = [radec_roll_to_dcm(ra, dec, roll) for ra, dec, roll in
            ((0.0, 90.0, 0.0), (359.9, 89.0, 30.0), (0.1, 88.0, 60.0), (180.0, -90.0, 10.0), (359.99, 0.0, 0.0),
             (0.01, -45.0, 5.0), (359.0, -1.0, 0.0))]
    dcms += [quaternion_to_dcm(q) for q in random_quaternions(20, np.random.default_rng(38))]
    for dcm in dcms:
        rows, x, y = tracker.predict_stars(dcm)
        cam_vec = vec @ np.asarray(dcm).T
        front = np.flatnonzero(cam_vec[:, 2] > cos_limit)
        bx, by = cam.vectors_to_pixels(cam_vec[front])
        inside = cam.in_image(bx, by, margin=2.0) & np.isfinite(bx)
        want = front[inside][: tracker.config.max_predicted]
        np.testing.assert_array_equal(rows, want)
        np.testing.assert_allclose(x, bx[inside][: len(want)], rtol=0, atol=1e-9)
        np.testing.assert_allclose(y, by[inside][: len(want)], rtol=0, atol=1e-9)
