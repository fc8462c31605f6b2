"""A proposal whose focal-length scale makes the camera's lens no camera (its terms, fitted at one focal length, move
the farthest corner by over 100 % at the other) is a rejected proposal, never a ParameterError out of the
identification (the all-sky search's 90 deg k1 -0.15 frames ended in an 'internal error')."""
import math
from types import SimpleNamespace

import numpy as np
import pytest

import startrack._kernels.focal as focal
from startrack.camera import Camera
from startrack.errors import ParameterError
from startrack.identify.params import IdentifyParams
from startrack.identify.verify import _scaled_camera, _verify_with_focal


def _near_the_limit(fov, effect):
    """A camera whose k1 moves its farthest corner by ``effect`` (a fraction, under 1) of its radius."""
    cam = Camera.from_fov(fov, 1280, 960)
    x = math.hypot(cam.cx, cam.cy) / cam.focal_length_px
    return cam.replace(k1=-effect / x ** 2)


@pytest.mark.parametrize("fov,effect", [(20, 0.5), (60, 0.9), (90, 0.95)])
def test_scaled_camera_is_none_exactly_when_camera_refuses_the_lens(fov, effect):
    cam = _near_the_limit(fov, effect)
    for scale in np.linspace(0.6, 1.6, 41):
        try:
            want = cam.with_focal_length(cam.focal_length_px / scale)
        except ParameterError:
            want = None
        got = _scaled_camera(cam, scale)
        assert (got is None) == (want is None), scale
        if got is not None:
            assert got.focal_length_px == pytest.approx(cam.focal_length_px / scale)
            assert got.k1 == cam.k1
    # The corner moves as k1 (x s)^2: effect s^2, over 1 beyond s = 1/sqrt(effect).
    assert _scaled_camera(cam, 1.01 / math.sqrt(effect)) is None
    assert _scaled_camera(cam, 0.99 / math.sqrt(effect)) is not None


def test_a_proposal_whose_scale_is_no_camera_is_rejected(monkeypatch):
    cam = _near_the_limit(60, 0.9)
    scale = 1.2         # within max_focal_error below; 0.9 * 1.2^2 = 1.3: no camera
    monkeypatch.setattr(focal, "focal_scale", lambda *_: scale)
    proposal = SimpleNamespace(image=[0, 1, 2, 3], catalog=[10, 11, 12, 13])
    db = SimpleNamespace(star_vector=np.eye(3)[[0, 1, 2, 0]].repeat(4, axis=0).astype(float))
    xs, ys = np.array([600.0, 700.0, 500.0, 640.0]), np.array([400.0, 500.0, 450.0, 300.0])
    params = IdentifyParams(max_focal_error=0.5)
    v, got = _verify_with_focal(proposal, xs, ys, np.zeros((4, 3)), None, np.ones(4), cam, db, 1e-3, params, 1,
                                False, None)
    assert v.matches is None and got is None
    assert "no camera" in v.reason
