"""Fisheye projections of :class:`startrack.camera.Camera`: round trips, known points, monotonic radius,
OpenCV's fisheye model, the field of view, the camera document, and the kernels' projection."""
import math

import numpy as np
import pytest
from hypothesis import assume, example, given, settings
from hypothesis import strategies as st

from startrack.camera import PROJECTIONS, Camera, projection_angle, projection_radius
from startrack.errors import BadInputError, ParameterError

FISHEYES = [p for p in PROJECTIONS if p != "pinhole"]
# The radius over f of each projection, written out independently of startrack.camera.
G = {"equidistant": lambda t: t, "equisolid": lambda t: 2 * math.sin(t / 2),
     "stereographic": lambda t: 2 * math.tan(t / 2), "orthographic": math.sin}


def _unit(theta, azimuth):
    return np.array([math.sin(theta) * math.cos(azimuth), math.sin(theta) * math.sin(azimuth), math.cos(theta)])


@pytest.mark.parametrize("projection", FISHEYES)
@pytest.mark.parametrize("theta_deg", [0.0, 1.0, 30.0, 60.0, 89.0, 90.0, 120.0, 179.0])
def test_known_points(projection, theta_deg):
    cam = Camera(1000, 800, 300.0, 510.0, 395.0, projection=projection)
    theta = math.radians(theta_deg)
    if theta > cam.max_theta:
        x, y = cam.vectors_to_pixels(_unit(theta, 0.3))
        assert math.isnan(x) and math.isnan(y)
        return
    az = 0.3
    x, y = cam.vectors_to_pixels(_unit(theta, az))
    r = 300.0 * G[projection](theta)
    assert x == pytest.approx(510.0 + r * math.cos(az), abs=1e-9)
    assert y == pytest.approx(395.0 + r * math.sin(az), abs=1e-9)
    v = cam.pixels_to_vectors(x, y)
    assert v == pytest.approx(_unit(theta, az), abs=1e-12)


@settings(max_examples=200, deadline=None)
@given(projection=st.sampled_from(FISHEYES), fov=st.floats(100.0, 200.0), k1=st.floats(-0.05, 0.05),
       k2=st.floats(-0.01, 0.01), k3=st.floats(-0.003, 0.003), k4=st.floats(-0.001, 0.001),
       fx=st.floats(0.0, 1.0), fy=st.floats(0.0, 1.0))
@example(projection="orthographic", fov=180.0, k1=0.0, k2=0.0, k3=0.0, k4=0.0, fx=0.0, fy=0.5)  # on the rim
def test_pixel_vector_pixel_round_trip(projection, fov, k1, k2, k3, k4, fx, fy):
    assume(projection != "orthographic" or fov <= 180.0)
    cam = Camera.from_fov(fov, 900, 700, projection=projection, k1=k1, k2=k2, k3=k3, k4=k4)
    x, y = -0.5 + fx * 900, -0.5 + fy * 700
    v = cam.pixels_to_vectors(x, y)
    rho = np.hypot(x - cam.cx, y - cam.cy)
    if abs(rho - cam.max_radius_px) <= 1e-9 * cam.max_radius_px:
        return                              # on the image circle's rim itself (90 deg orthographic): either answer
    if rho > cam.max_radius_px:
        assert np.all(np.isnan(v))          # outside the image circle: no direction
        return
    assert np.linalg.norm(v) == pytest.approx(1.0, abs=1e-12)
    x2, y2 = cam.vectors_to_pixels(v)
    assert abs(x2 - x) < 1e-7 and abs(y2 - y) < 1e-7


@settings(max_examples=100, deadline=None)
@given(projection=st.sampled_from(FISHEYES), k1=st.floats(-0.2, 0.2), k2=st.floats(-0.05, 0.05),
       k3=st.floats(-0.01, 0.01), k4=st.floats(-0.005, 0.005))
def test_radius_increases_up_to_max_theta(projection, k1, k2, k3, k4):
    cam = Camera(800, 800, 250.0, 399.5, 399.5, k1, k2, projection=projection, k3=k3, k4=k4)
    tmax = cam.max_theta
    assume(tmax > 0.05)
    theta = np.linspace(0.0, tmax, 2000)
    x, _ = cam.vectors_to_pixels(np.stack([np.sin(theta), np.zeros_like(theta), np.cos(theta)], axis=-1))
    assert np.all(np.isfinite(x))
    assert np.all(np.diff(x) > 0)
    # Beyond the largest angle the model maps, no pixel (NaN), never a fold back into the image.
    if tmax < math.pi - 1e-3:
        beyond = np.linspace(tmax + 1e-6, math.pi, 50)
        xb, _ = cam.vectors_to_pixels(np.stack([np.sin(beyond), np.zeros_like(beyond), np.cos(beyond)], axis=-1))
        assert np.all(np.isnan(xb))


def test_projection_angle_inverts_radius():
    for projection in PROJECTIONS:
        top = {"orthographic": math.pi / 2, "pinhole": 1.5}.get(projection, math.pi - 1e-6)
        theta = np.linspace(0.0, top, 500)
        assert projection_angle(projection, projection_radius(projection, theta)) == pytest.approx(theta, abs=1e-9)
    assert np.isnan(projection_angle("orthographic", 1.01))
    assert np.isnan(projection_angle("equisolid", 2.01))


def test_opencv_fisheye_model():
    cv2 = pytest.importorskip("cv2")
    f, cx, cy = 320.0, 640.3, 478.9
    ks = (0.03, -0.01, 0.002, -0.0004)
    cam = Camera(1280, 960, f, cx, cy, ks[0], ks[1], projection="equidistant", k3=ks[2], k4=ks[3])
    rng = np.random.default_rng(3)
    theta = rng.uniform(0.0, math.radians(89.0), 300)        # OpenCV divides by z: the front hemisphere
    az = rng.uniform(0.0, 2 * math.pi, 300)
    vec = np.stack([np.sin(theta) * np.cos(az), np.sin(theta) * np.sin(az), np.cos(theta)], axis=-1)
    k_matrix = np.array([[f, 0.0, cx], [0.0, f, cy], [0.0, 0.0, 1.0]])
    got, _ = cv2.fisheye.projectPoints(vec.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), k_matrix, np.array(ks))
    x, y = cam.vectors_to_pixels(vec)
    np.testing.assert_allclose(np.stack([x, y], axis=-1), got.reshape(-1, 2), atol=1e-6)
    # ... and back: cv2.fisheye.undistortPoints gives (X/Z, Y/Z).  Its fixed-count iteration loses
    # its way within ~10 deg of 90 (X/Z beyond ~6), so the inverse is compared below 75 deg.
    near = theta < math.radians(75.0)
    und = cv2.fisheye.undistortPoints(got[near].reshape(-1, 1, 2), k_matrix, np.array(ks)).reshape(-1, 2)
    v = cam.pixels_to_vectors(x[near], y[near])
    np.testing.assert_allclose(v[:, :2] / v[:, 2:], und, atol=1e-6)


@pytest.mark.parametrize("projection,fov", [("equidistant", 120.0), ("equidistant", 180.0), ("equidistant", 220.0),
                                            ("equisolid", 150.0), ("equisolid", 180.0), ("stereographic", 180.0),
                                            ("orthographic", 120.0), ("orthographic", 180.0)])
def test_fov_and_scale(projection, fov):
    cam = Camera.from_fov(fov, 1000, 600, projection=projection)
    assert cam.fov_deg[0] == pytest.approx(fov, abs=1e-6)
    assert cam.focal_length_px == pytest.approx(500.0 / G[projection](math.radians(fov / 2)))
    # Vertically the field is the angle at 300 px from the centre, twice.
    assert cam.fov_deg[1] == pytest.approx(2 * math.degrees(float(projection_angle(projection, 300 / cam.focal_length_px))))
    corner = math.degrees(float(projection_angle(projection, math.hypot(500, 300) / cam.focal_length_px)))
    expect = corner if not math.isnan(corner) else math.degrees(cam.max_theta)
    assert cam.max_off_axis_deg == pytest.approx(expect, abs=1e-6)
    # One pixel at the centre: 1/f rad for every projection (g'(0) = 1).
    x, _ = cam.vectors_to_pixels(_unit(math.radians(cam.pixel_scale_arcsec / 3600.0), 0.0))
    assert x - cam.cx == pytest.approx(1.0, rel=1e-5)       # g(t) = t + O(t^3): 1e-6 at f = 250


def test_fov_limits():
    with pytest.raises(ParameterError):
        Camera.from_fov(181.0, 100, 100, projection="orthographic")
    with pytest.raises(ParameterError):
        Camera.from_fov(180.0, 100, 100)
    with pytest.raises(ParameterError):
        Camera.from_fov(360.0, 100, 100, projection="stereographic")
    assert Camera.from_fov(360.0, 100, 100, projection="equidistant").fov_deg[0] == pytest.approx(360.0)


def test_sky_fraction():
    # A circular orthographic fisheye inside a square sensor sees exactly one hemisphere.
    cam = Camera.from_fov(180.0, 600, 600, projection="orthographic")
    assert cam.sky_fraction == pytest.approx(0.5, abs=0.005)
    # An equidistant 180 deg across a square sensor sees the hemisphere plus the corners (to 127 deg).
    cam = Camera.from_fov(180.0, 600, 600, projection="equidistant")
    theta = np.radians(np.linspace(0, 180, 200001))
    r = np.degrees(theta) / 90.0        # radius in half-widths
    # Area of the square within radius r, per unit r: the arc of the circle inside the square.
    arc = np.where(r <= 1, 2 * np.pi * r, 8 * r * (np.pi / 4 - np.arccos(np.clip(1 / np.maximum(r, 1e-12), -1, 1))))
    # dOmega = sin(theta) dtheta dphi and the image area 2 pi r dr maps to 2 pi sin(theta) dtheta.
    omega = np.trapezoid(np.where(r <= math.sqrt(2), arc / (2 * np.pi * np.maximum(r, 1e-12)), 0) * 2 * np.pi
                         * np.sin(theta), theta)
    assert cam.sky_fraction == pytest.approx(omega / (4 * math.pi), abs=0.005)


def test_document_round_trip():
    cam = Camera(1280, 960, 330.5, 640.1, 480.2, 0.02, -0.003, 3.45, projection="equisolid", k3=1e-4, k4=-2e-5)
    doc = cam.to_dict(standalone=True)
    assert doc["projection"] == "equisolid"
    assert doc["distortion"] == {"k1": 0.02, "k2": -0.003, "k3": 1e-4, "k4": -2e-5}
    back = Camera.from_dict(doc)
    assert back == cam and back.projection == "equisolid"
    # A pinhole's document is unchanged: no projection, k1/k2 only.
    pin = Camera(100, 100, 500.0, 49.5, 49.5, 0.01)
    assert "projection" not in pin.to_dict() and pin.to_dict()["distortion"] == {"k1": 0.01, "k2": 0.0}
    assert Camera.from_dict(pin.to_dict()) == pin


@pytest.mark.parametrize("doc,field", [
    ({"projection": "fisheye"}, "camera.projection"),
    ({"distortion": {"k3": 0.1}}, "camera.distortion.k3"),
    ({"projection": "equidistant", "distortion": {"k5": 0.1}}, "camera.distortion.k5"),
    ({"projection": "equidistant", "distortion": {"k4": "x"}}, "camera.distortion.k4"),
])
def test_bad_documents(doc, field):
    base = {"width": 100, "height": 100, "focal_length_px": 50.0, "cx": 49.5, "cy": 49.5}
    with pytest.raises(BadInputError) as err:
        Camera.from_dict({**base, **doc}, "cam.json")
    assert err.value.field == field


def test_with_focal_length_keeps_projection():
    cam = Camera.from_fov(150.0, 800, 600, projection="stereographic", k1=0.01, k4=1e-4)
    other = cam.with_focal_length(200.0)
    assert other.projection == "stereographic" and other.k4 == 1e-4 and other.focal_length_px == 200.0


@pytest.mark.parametrize("projection", PROJECTIONS)
def test_kernel_projection_matches_camera(projection):
    """The kernels' projection (``project_to_pixel``) against :meth:`Camera.vectors_to_pixels`."""
    from naive import count_in_fov_naive

    from startrack._kernels.sphere import count_in_fov

    ks = (0.01, -0.002, 0.0, 0.0) if projection == "pinhole" else (0.02, -0.004, 3e-4, -2e-5)
    fov = 60.0 if projection == "pinhole" else 170.0
    cam = Camera.from_fov(fov, 640, 480, projection=projection, k1=ks[0], k2=ks[1],
                          **({} if projection == "pinhole" else {"k3": ks[2], "k4": ks[3]}))
    rng = np.random.default_rng(7)
    vec = rng.normal(size=(3000, 3))
    vec /= np.linalg.norm(vec, axis=1)[:, None]
    mags = rng.uniform(0, 6, len(vec))
    dec = np.arcsin(vec[:, 2])
    order = np.argsort(dec)
    from startrack.rotations import quaternion_to_dcm, random_quaternions

    dcms = np.ascontiguousarray(quaternion_to_dcm(random_quaternions(20, rng)))
    counts, brightest = count_in_fov(np.ascontiguousarray(vec[order]), np.ascontiguousarray(dec[order]),
                                     np.ascontiguousarray(mags[order]), dcms, float(cam.focal_length_px),
                                     float(cam.cx), float(cam.cy), float(cam.width), float(cam.height),
                                     *cam.lens_terms, math.acos(cam.cone_cos()) + 1e-9)
    for k in range(len(dcms)):
        n, b = count_in_fov_naive(vec, mags, dcms[k], cam)
        assert counts[k] == n
        assert (math.isnan(b) and math.isnan(brightest[k])) or brightest[k] == b


@pytest.mark.parametrize("projection,ks,fov", [
    ("equidistant", (0.0, 0.0, 0.0, 0.0), 180.0), ("equisolid", (0.0, 0.0, 0.0, 0.0), 180.0),
    ("stereographic", (0.0, 0.0, 0.0, 0.0), 150.0), ("orthographic", (0.0, 0.0, 0.0, 0.0), 120.0),
    ("equidistant", (0.03, -0.01, 0.002, -0.0004), 180.0), ("equisolid", (0.02, -0.004, 0.0, 0.0), 160.0)])
@pytest.mark.parametrize("mirrored", [False, True])
def test_wcs_maps_pixels_as_the_camera(projection, ks, fov, mirrored):
    """astropy.wcs's pixel -> sky of the written ARC / ZEA / STG / SIN / ZPN header against Camera.pixels_to_vectors."""
    from astropy.wcs import WCS

    from startrack.attitude import FITS_PROJECTIONS, wcs_header, zpn_coefficients
    from startrack.rotations import radec_roll_to_dcm

    cam = Camera.from_fov(fov, 800, 600, projection=projection, k1=ks[0], k2=ks[1], k3=ks[2], k4=ks[3])
    a = radec_roll_to_dcm(230.0, 64.0, 33.0)
    hdr = wcs_header(a, cam, mirrored=mirrored)
    assert hdr["CTYPE2"] == "DEC--" + ("ZPN" if any(ks) else FITS_PROJECTIONS[projection])
    w = WCS(hdr)
    rng = np.random.default_rng(6)
    xs = rng.uniform(-0.5, 799.5, 400)
    ys = rng.uniform(-0.5, 599.5, 400)
    vec = cam.pixels_to_vectors(xs, ys)
    seen = np.all(np.isfinite(vec), axis=1) & (vec[:, 2] > -0.98)
    xs, ys, vec = xs[seen], ys[seen], vec[seen]
    sky = w.all_pix2world(np.column_stack([cam.width - 1 - xs if mirrored else xs, ys]), 0)
    ra, dec = np.radians(sky[:, 0]), np.radians(sky[:, 1])
    want = vec @ a
    got = np.stack([np.cos(dec) * np.cos(ra), np.cos(dec) * np.sin(ra), np.sin(dec)], axis=-1)
    err_arcsec = np.degrees(np.arccos(np.clip(np.sum(got * want, axis=1), -1, 1))) * 3600
    # Exact projections (and the equidistant ZPN, exact too): rounding only; a fitted ZPN: its fit error.
    limit = 0.05 if projection == "equidistant" or not any(ks) else \
        0.05 + zpn_coefficients(cam)[1] * cam.pixel_scale_arcsec * 1.5
    assert np.max(err_arcsec) < limit


def _calibration_frames(cam, n_frames=3, n_stars=150, sigma_px=0.1, seed=11):
    """Frames of ``cam``: random attitudes, random sky directions in its image, pixel noise ``sigma_px``."""
    from startrack.rotations import quaternion_to_dcm, random_quaternions

    rng = np.random.default_rng(seed)
    frames = []
    for a in quaternion_to_dcm(random_quaternions(n_frames, rng)):
        xs = rng.uniform(0, cam.width - 1, 4 * n_stars)
        ys = rng.uniform(0, cam.height - 1, 4 * n_stars)
        v = cam.pixels_to_vectors(xs, ys)
        ok = np.all(np.isfinite(v), axis=1) & (v[:, 2] > 0.02)
        xs, ys, v = xs[ok][:n_stars], ys[ok][:n_stars], v[ok][:n_stars]
        xy = np.column_stack([xs, ys]) + rng.normal(0, sigma_px, (len(xs), 2))
        frames.append((a, xy, v @ a))            # ref: ICRS directions, A ref = camera vectors
    return frames


@pytest.mark.parametrize("projection", FISHEYES)
def test_calibrate_chooses_the_projection(projection):
    from startrack.calibrate import calibrate_projection

    truth = Camera.from_fov(170.0 if projection != "orthographic" else 178.0, 900, 700, projection=projection)
    frames = _calibration_frames(truth)
    # Start from a pinhole of the wrong focal length: every projection is tried from its own start.
    start = Camera.from_fov(100.0, 900, 700)
    res = calibrate_projection(frames, start)
    assert res.camera.projection == projection, res.projections
    assert res.camera.focal_length_px == pytest.approx(truth.focal_length_px, rel=2e-4)
    assert res.rms_after_px < 0.2
    assert "pinhole" not in res.projections          # stars beyond 85 deg: no pinhole


def test_calibrate_fits_opencv_distortion():
    from startrack.calibrate import calibrate_projection

    truth = Camera.from_fov(180.0, 1000, 1000, projection="equidistant", k1=0.02, k2=-0.01)
    frames = _calibration_frames(truth, n_frames=4, n_stars=250)
    res = calibrate_projection(frames, Camera.from_fov(150.0, 1000, 1000, projection="equisolid"), ["equidistant"])
    assert res.camera.projection == "equidistant"
    assert res.camera.k1 == pytest.approx(0.02, abs=4 * res.sigma["k1"] + 1e-4)
    assert res.camera.k2 == pytest.approx(-0.01, abs=4 * res.sigma["k2"] + 1e-4)
    assert res.rms_after_px < 0.2


def test_max_theta_is_where_the_fisheye_model_stops_being_one_to_one():
    """Property (random lens terms, every projection): below max_theta the distorted angle increases and stays
    within the projection's limit; just above it (when it is below the limit) it does not.  The value is cached
    by the lens terms (a fit builds many cameras): the same for equal terms, whatever the focal length."""
    import dataclasses
    import math

    import numpy as np

    from startrack.camera import _THETA_MAX, Camera
    from startrack.errors import ParameterError

    rng = np.random.default_rng(11)
    kept = folded = 0
    for trial in range(400):
        proj = ("equidistant", "equisolid", "stereographic", "orthographic")[trial % 4]
        ks = rng.normal(0, [0.3, 0.1, 0.03, 0.01]) * (rng.random(4) < 0.7)
        try:
            cam = Camera(800, 800, 300.0, 399.5, 399.5, ks[0], ks[1], projection=proj, k3=ks[2], k4=ks[3])
        except ParameterError:  # terms that move a corner beyond its radius: no lens (camera.py's bound)
            continue
        kept += 1
        t = cam.max_theta
        folded += t < _THETA_MAX[proj] - 1e-9
        limit = _THETA_MAX[proj]
        below = np.linspace(0, t, 2001)[1:-1]
        td = cam.theta_distorted(below)
        assert np.all(np.diff(td) > 0) and np.all((td >= 0) & (td <= limit))
        if t < limit - 1e-9:
            above = t + 1e-7
            assert not (cam._theta_slope(above) > 0 and 0 <= float(cam.theta_distorted(above)) <= limit)
        again = Camera._probe({**dataclasses.asdict(cam), "width": 640, "height": 480, "focal_length_px": 211.0,
                               "cx": 300.0, "cy": 200.0, "extra": {}})
        assert again.max_theta == t and math.isfinite(t)
    # the draw must leave enough lenses, folded ones among them, for the property to say something
    assert kept >= 200 and folded >= 20, (kept, folded)
