import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from startrack import rotations as rot

angles = st.floats(-np.pi, np.pi, allow_nan=False)
ras = st.one_of(st.floats(0, 2 * np.pi, allow_nan=False, exclude_max=True),
                st.sampled_from([0.0, 1e-12, 2 * np.pi - 1e-12, np.pi]))
decs = st.one_of(st.floats(-np.pi / 2, np.pi / 2, allow_nan=False),
                 st.sampled_from([np.pi / 2, -np.pi / 2, np.pi / 2 - 1e-9, -np.pi / 2 + 1e-9, 0.0]))
quats = st.lists(st.floats(-1, 1, allow_nan=False), min_size=4, max_size=4).filter(
    lambda q: np.linalg.norm(q) > 1e-3)


@settings(max_examples=300, deadline=None)
@given(quats)
def test_quaternion_dcm_round_trip(q):
    q = rot.normalize_quaternion(q)
    a = rot.quaternion_to_dcm(q)
    np.testing.assert_allclose(a @ a.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(a) == pytest.approx(1.0, abs=1e-12)
    q2 = rot.dcm_to_quaternion(a)
    assert q2[3] >= 0
    # q and -q are the same attitude; only at q4 = 0 may the sign differ.
    assert min(np.abs(q2 - q).max(), np.abs(q2 + q).max()) < 1e-9


def test_quaternion_formula_matches_formats_md():
    # A(q) = (q4^2 - |q|^2) I + 2 q q^T - 2 q4 [q x]: a rotation of +90 deg about z
    # (q = [0, 0, sin 45, cos 45]) maps inertial x to camera -y (passive rotation).
    q = np.array([0, 0, np.sin(np.pi / 4), np.cos(np.pi / 4)])
    a = rot.quaternion_to_dcm(q)
    np.testing.assert_allclose(a @ [1, 0, 0], [0, -1, 0], atol=1e-15)
    np.testing.assert_allclose(a, rot.elementary_rotation(3, np.pi / 2), atol=1e-15)


@settings(max_examples=300, deadline=None)
@given(ras, decs, angles)
def test_radec_roll_round_trip(ra, dec, roll):
    a = rot.radec_roll_to_dcm(ra, dec, roll)
    np.testing.assert_allclose(a @ a.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(a) == pytest.approx(1.0, abs=1e-12)
    ra2, dec2, roll2 = rot.dcm_to_radec_roll(a)
    # The matrix is reproduced exactly, poles included (where ra is undefined).
    np.testing.assert_allclose(rot.radec_roll_to_dcm(ra2, dec2, roll2), a, atol=1e-9)
    assert dec2 == pytest.approx(dec, abs=1e-9)
    if abs(dec) < np.pi / 2 - 1e-6:
        dra = (ra2 - ra + np.pi) % (2 * np.pi) - np.pi
        assert abs(dra) < 1e-9
        droll = (roll2 - roll + np.pi) % (2 * np.pi) - np.pi
        assert abs(droll) < 1e-9


@settings(max_examples=200, deadline=None)
@given(quats)
def test_dcm_radec_roll_dcm(q):
    a = rot.quaternion_to_dcm(q)
    np.testing.assert_allclose(rot.radec_roll_to_dcm(*rot.dcm_to_radec_roll(a)), a, atol=1e-9)


@settings(max_examples=200, deadline=None)
@given(quats)
def test_euler123_round_trip(q):
    a = rot.quaternion_to_dcm(q)
    np.testing.assert_allclose(rot.euler123_to_dcm(*rot.dcm_to_euler123(a)), a, atol=1e-9)


def test_euler123_gimbal_lock():
    a = rot.euler123_to_dcm(0.3, np.pi / 2, 0.2)
    np.testing.assert_allclose(rot.euler123_to_dcm(*rot.dcm_to_euler123(a)), a, atol=1e-12)


@settings(max_examples=200, deadline=None)
@given(quats, quats)
def test_composition_and_inverse(q, p):
    aq, ap = rot.quaternion_to_dcm(q), rot.quaternion_to_dcm(p)
    np.testing.assert_allclose(rot.quaternion_to_dcm(rot.quaternion_multiply(q, p)), aq @ ap, atol=1e-12)
    np.testing.assert_allclose(rot.quaternion_to_dcm(rot.quaternion_inverse(q)), aq.T, atol=1e-12)


def test_roll_zero_is_north_up_east_left():
    ra, dec = np.radians(83.8), np.radians(-1.2)
    a = rot.radec_roll_to_dcm(ra, dec, 0.0)
    bore = rot.radec_to_vector(ra, dec)
    north_star = rot.radec_to_vector(ra, dec + 1e-3)
    east_star = rot.radec_to_vector(ra + 1e-3, dec)
    n_cam = a @ north_star
    e_cam = a @ east_star
    np.testing.assert_allclose(a[2], bore)
    assert n_cam[1] < 0 and abs(n_cam[0]) < 1e-12      # north is up (-y)
    assert e_cam[0] < 0 and abs(e_cam[1]) < 1e-6       # east is left (-x)
    # roll = 90 deg turns image up toward east.
    a90 = rot.radec_roll_to_dcm(ra, dec, np.pi / 2)
    assert (a90 @ east_star)[1] < 0


def test_random_quaternions_uniform_and_seeded():
    q1 = rot.random_quaternions(20000, np.random.default_rng(5))
    q2 = rot.random_quaternions(20000, np.random.default_rng(5))
    np.testing.assert_array_equal(q1, q2)
    bores = rot.quaternion_to_dcm(q1)[:, 2, :]
    # Uniform boresights: the mean of each coordinate is 0 and z is uniform in [-1, 1].
    assert np.all(np.abs(bores.mean(axis=0)) < 0.02)
    hist, _ = np.histogram(bores[:, 2], bins=10, range=(-1, 1))
    assert hist.min() > 1800 and hist.max() < 2200


def test_attitude_error_split():
    a = rot.radec_roll_to_dcm(1.0, 0.5, 0.3)
    roll_only = rot.elementary_rotation(3, 1e-4) @ a
    total, cross, roll = rot.attitude_error(roll_only, a)
    assert total == pytest.approx(1e-4, rel=1e-6)
    assert cross == pytest.approx(0.0, abs=1e-12)
    assert roll == pytest.approx(1e-4, rel=1e-6)
    tilt = rot.elementary_rotation(1, 2e-5) @ a
    total, cross, roll = rot.attitude_error(tilt, a)
    assert cross == pytest.approx(2e-5, rel=1e-6)
    assert abs(roll) < 1e-12


def test_readme_roll_example(catalog):
    # README: boresight (83.8, -1.2), roll 30 deg -> Betelgeuse straight above the centre.
    from startrack.camera import Camera

    a = rot.radec_roll_to_dcm(np.radians(83.8), np.radians(-1.2), np.radians(30.0))
    cam = Camera.from_fov(30, 1024, 1024)
    betel = catalog.subset(catalog.id == 27989).vectors()[0]
    x, y = cam.vectors_to_pixels(a @ betel)
    assert y < cam.cy - 300
    assert abs(x - cam.cx) < 0.1 * (cam.cy - y)
