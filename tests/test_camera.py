import math

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from startrack.camera import Camera, parse_size
from startrack.errors import BadInputError


@settings(max_examples=300, deadline=None)
@given(
    fov=st.floats(2.0, 40.0),
    width=st.integers(16, 4096),
    height=st.integers(16, 4096),
    k1=st.floats(-0.3, 0.3),
    k2=st.floats(-0.1, 0.1),
    fx=st.floats(0.0, 1.0),
    fy=st.floats(0.0, 1.0),
)
def test_pixel_vector_pixel_round_trip(fov, width, height, k1, k2, fx, fy):
    assume(0.25 <= height / width <= 4)
    cam = Camera.from_fov(fov, width, height, k1=k1, k2=k2)
    # The lens model must be invertible over the image: r_d(r) increasing.
    r2 = ((width / 2) ** 2 + (height / 2) ** 2) / cam.focal_length_px**2
    assume(1 + 3 * k1 * r2 + 5 * k2 * r2 * r2 > 0.2)
    # ... and the corners lie within the range the lens model reaches (barrel distortion
    # has a largest distorted radius, beyond which no direction maps).
    s_max = min(cam.max_valid_r2, 100.0)
    rd_max = math.sqrt(s_max) * (1 + k1 * s_max + k2 * s_max**2)
    assume(math.sqrt(r2) < 0.9 * rd_max)
    x = -0.5 + fx * width
    y = -0.5 + fy * height
    v = cam.pixels_to_vectors(x, y)
    assert np.linalg.norm(v) == pytest.approx(1.0, abs=1e-12)
    x2, y2 = cam.vectors_to_pixels(v)
    assert abs(x2 - x) < 1e-9 and abs(y2 - y) < 1e-9


def test_eq13_pinhole():
    # Paper 000 Eq. 13 with f in pixels: W = (x - cx, y - cy, f) / norm.
    cam = Camera(752, 480, 41.1e-3 / 6e-6, 375.5, 239.5)
    v = cam.pixels_to_vectors(np.array([295.0]), np.array([355.0]))[0]
    w = np.array([295 - 375.5, 355 - 239.5, 41.1e-3 / 6e-6])
    np.testing.assert_allclose(v, w / np.linalg.norm(w), atol=1e-15)


def test_fov_from_model():
    cam = Camera.from_fov(20.0, 1024, 1024)
    fx, fy = cam.fov_deg
    assert fx == pytest.approx(20.0, abs=1e-9) and fy == pytest.approx(20.0, abs=1e-9)
    assert cam.diagonal_fov_deg == pytest.approx(2 * math.degrees(math.atan(math.sqrt(2) * math.tan(math.radians(10)))))
    cam = Camera.from_focal_length_mm(41.1, 6.0, 752, 480)
    assert cam.focal_length_px == pytest.approx(6850.0)
    assert cam.fov_deg[0] == pytest.approx(2 * math.degrees(math.atan(376 / 6850)), abs=1e-9)


@settings(max_examples=200, deadline=None)
@given(st.integers(8, 6000), st.integers(8, 6000), st.floats(5.0, 1e5), st.floats(-0.5, 1.5), st.floats(-0.5, 1.5))
def test_undistorted_field_of_view_is_the_angle_between_its_edges(w, h, f, fx, fy):
    """An undistorted pinhole's fov_deg (from the edges' angles off the boresight) is the angle between the unit
    vectors of its two edges through the principal point, from their cross and dot products, principal points
    outside the image included."""
    cam = Camera(w, h, f, fx * w, fy * h)
    got = cam.fov_deg
    for edges in ((np.array([-0.5, w - 0.5]), np.full(2, cam.cy)), (np.full(2, cam.cx), np.array([-0.5, h - 0.5]))):
        a, b = cam.pixels_to_vectors(*edges)
        want = math.degrees(math.atan2(np.linalg.norm(np.cross(a, b)), float(a @ b)))
        assert got[0 if edges[1][0] == edges[1][1] else 1] == pytest.approx(want, rel=1e-12, abs=1e-12)


def test_distortion_moves_corners_outward():
    plain = Camera.from_fov(20, 1000, 1000)
    barrel = Camera.from_fov(20, 1000, 1000, k1=-0.1)
    assert barrel.fov_deg[0] > plain.fov_deg[0]


def test_dict_round_trip_and_validation():
    cam = Camera.from_focal_length_mm(41.1, 6.0, 752, 480, k1=0.01)
    doc = cam.to_dict(standalone=True)
    assert doc["format"] == "startrack.camera/1"
    assert Camera.from_dict(doc) == cam
    bad = dict(doc, focal_length_px=float("nan"))
    with pytest.raises(BadInputError, match="camera.focal_length_px"):
        Camera.from_dict(bad, "cam.json")
    with pytest.raises(BadInputError, match="camera.cx: is missing"):
        Camera.from_dict({k: v for k, v in doc.items() if k != "cx"}, "cam.json")


@pytest.mark.parametrize("text", ["0x10", "10", "axb", "10x-4", ""])
def test_parse_size_refuses(text):
    with pytest.raises(BadInputError):
        parse_size(text)


def test_parse_size():
    assert parse_size("1024x768") == (1024, 768)


@pytest.mark.parametrize("fov", [3.0, 11.4, 40.0])
def test_cached_field_of_view_follows_every_changed_camera(fov):
    """fov_deg and max_off_axis_deg are computed once per camera: a changed camera (a new frozen object) has its
    own, equal to a fresh camera's, and the cached values do not enter equality."""
    import pickle

    cam = Camera.from_fov(fov, 1024, 768)
    first = cam.fov_deg
    assert first[0] == pytest.approx(fov, rel=1e-9)
    for other in (cam.with_focal_length(cam.focal_length_px * 1.1), cam.replace(k1=0.05),
                  cam.replace(cx=cam.cx + 40.0)):
        fresh = Camera(**{f: getattr(other, f) for f in ("width", "height", "focal_length_px", "cx", "cy", "k1")})
        assert other.fov_deg == fresh.fov_deg != first
        assert other.max_off_axis_deg == fresh.max_off_axis_deg
        assert other.cone_cos(0.5) == fresh.cone_cos(0.5)
    assert cam == Camera.from_fov(fov, 1024, 768) and hash(cam) == hash(Camera.from_fov(fov, 1024, 768))
    assert pickle.loads(pickle.dumps(cam)).fov_deg == first


@pytest.mark.parametrize("k1, k2", [(0.0, 0.0), (-0.05, 0.01)])
@pytest.mark.parametrize("shape", [(), (1,), (7,), (300,), (6, 5)])
def test_pixels_to_vectors_the_normalised_stack_to_the_bit(k1, k2, shape):
    """A pinhole's unit vectors are (u, v, 1) divided by numpy's norm of them, bit for bit."""
    rng = np.random.default_rng(len(shape) * 10 + int(k1 != 0))
    cam = Camera(1024, 768, 900.0, 511.5, 383.5, k1=k1, k2=k2)
    x = rng.uniform(-100, 1124, shape)
    y = rng.uniform(-100, 868, shape)
    u, v = cam.undistort((x - cam.cx) / cam.focal_length_px, (y - cam.cy) / cam.focal_length_px)
    stacked = np.stack([u, v, np.ones_like(u)], axis=-1)
    expected = stacked / np.linalg.norm(stacked, axis=-1, keepdims=True)
    got = cam.pixels_to_vectors(x, y)
    assert got.shape == expected.shape and got.dtype == np.float64
    assert got.tobytes() == expected.tobytes()


def test_replace_is_dataclasses_replace_and_checks():
    import dataclasses

    cam = Camera(1024, 768, 900.0, 511.5, 383.5, k1=0.01, pixel_pitch_um=3.45, extra={"a": 1})
    new = cam.replace(focal_length_px=950.0, cy=380.0)
    assert new == dataclasses.replace(cam, focal_length_px=950.0, cy=380.0)
    assert new.extra == cam.extra and new.extra is not cam.extra
    assert cam.with_focal_length(800) == dataclasses.replace(cam, focal_length_px=800.0)
    with pytest.raises(TypeError):
        cam.replace(focal=1.0)


@pytest.mark.parametrize("changes, field", [({"focal_length_px": math.nan}, "focal_length_px"),
                                            ({"focal_length_px": -5.0}, "focal_length_px"),
                                            ({"focal_length_px": 1e12}, "focal_length_px"),
                                            ({"cx": math.inf}, "cx"), ({"cx": 5000.0}, "cx"),
                                            ({"cy": -2000.0}, "cy"), ({"k1": math.nan}, "k1"),
                                            ({"k1": 50.0}, "distortion"), ({"width": 0}, "width"),
                                            ({"width": 2_000_000}, "width"), ({"height": 10.5}, "height"),
                                            ({"k3": 0.1}, "k3")])
def test_every_camera_is_checked(changes, field):
    """The common case's quick test lets no absurd value through: each is refused naming its parameter."""
    from startrack.errors import ParameterError

    values = {"width": 1024, "height": 768, "focal_length_px": 900.0, "cx": 511.5, "cy": 383.5}
    Camera(**values)
    with pytest.raises(ParameterError) as err:
        Camera(**{**values, **changes})
    assert err.value.parameter == field
