import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from startrack import rotations as rot

# The public functions take and return degrees (README "Conventions": degrees at every public boundary).
angles = st.floats(-180.0, 180.0, allow_nan=False)
ras = st.one_of(st.floats(0, 360.0, allow_nan=False, exclude_max=True),
                st.sampled_from([0.0, 1e-10, 360.0 - 1e-10, 180.0]))
decs = st.one_of(st.floats(-90.0, 90.0, allow_nan=False),
                 st.sampled_from([90.0, -90.0, 90.0 - 1e-7, -90.0 + 1e-7, 0.0]))
quats = st.lists(st.floats(-1, 1, allow_nan=False), min_size=4, max_size=4).filter(
    lambda q: np.linalg.norm(q) > 1e-3)


def _expected_dcm(ra_deg, dec_deg, roll_deg):
    """README "Roll", written out from scratch: A = R3(-roll) A0, A0's rows (-east, -north, boresight)."""
    a, d, r = (math.radians(v) for v in (ra_deg, dec_deg, roll_deg))
    east = np.array([-math.sin(a), math.cos(a), 0.0])
    north = np.array([-math.sin(d) * math.cos(a), -math.sin(d) * math.sin(a), math.cos(d)])
    bore = np.array([math.cos(a) * math.cos(d), math.sin(a) * math.cos(d), math.sin(d)])
    a0 = np.array([-east, -north, bore])
    r3 = np.array([[math.cos(-r), math.sin(-r), 0.0], [-math.sin(-r), math.cos(-r), 0.0], [0.0, 0.0, 1.0]])
    return r3 @ a0


@settings(max_examples=300, deadline=None)
@given(ras, decs, angles)
def test_radec_roll_to_dcm_takes_degrees(ra, dec, roll):
    """Degrees in -> the matrix of the documented convention (and the boresight row is (ra, dec))."""
    a = rot.radec_roll_to_dcm(ra, dec, roll)
    np.testing.assert_allclose(a, _expected_dcm(ra, dec, roll), atol=1e-12)
    np.testing.assert_allclose(a[2], rot.radec_to_vector(ra, dec), atol=1e-15)
    # the same numbers read as radians would be another attitude entirely
    if abs(ra) > 1e-3 or abs(dec) > 1e-3 or abs(roll) > 1e-3:
        assert not np.allclose(a, rot._radec_roll_to_dcm_rad(ra, dec, roll), atol=1e-6)


def test_radec_roll_to_dcm_known_values():
    # ra 90, dec 0, roll 0: boresight +Y; north (+Z) is image up (-y), east (-X) image left (-x).
    np.testing.assert_allclose(rot.radec_roll_to_dcm(90.0, 0.0, 0.0), [[1, 0, 0], [0, 0, -1], [0, 1, 0]], atol=1e-15)
    # roll 90 turns image up toward east: up (-y row) is east (-X), and north (+Z) is image right.
    np.testing.assert_allclose(rot.radec_roll_to_dcm(90.0, 0.0, 90.0), [[0, 0, 1], [1, 0, 0], [0, 1, 0]],
                               atol=1e-15)
    # broadcasting: arrays of angles give a stack of matrices
    stack = rot.radec_roll_to_dcm([0.0, 90.0], [0.0, 0.0], [0.0, 90.0])
    assert stack.shape == (2, 3, 3)
    np.testing.assert_allclose(stack[1], rot.radec_roll_to_dcm(90.0, 0.0, 90.0), atol=1e-15)


def test_public_functions_are_degrees():
    np.testing.assert_allclose(rot.elementary_rotation(3, 90.0), [[0, 1, 0], [-1, 0, 0], [0, 0, 1]], atol=1e-15)
    np.testing.assert_allclose(rot.radec_to_vector(90.0, 0.0), [0, 1, 0], atol=1e-15)
    ra, dec = rot.vector_to_radec([0.0, -1.0, 1.0])
    assert (float(ra), float(dec)) == pytest.approx((270.0, 45.0))
    east, north = rot.east_north(90.0, 0.0)
    np.testing.assert_allclose(east, [-1, 0, 0], atol=1e-15)
    np.testing.assert_allclose(north, [0, 0, 1], atol=1e-15)
    yaw, pitch, roll = rot.dcm_to_euler123(rot.euler123_to_dcm(10.0, -20.0, 30.0))
    assert (float(yaw), float(pitch), float(roll)) == pytest.approx((10.0, -20.0, 30.0))
    a = rot.radec_roll_to_dcm(40.0, 10.0, 5.0)
    # 0.5 deg/s about the boresight for 2 s: a pure roll of 1 deg
    b = rot.propagate_attitude(a, [0.0, 0.0, 0.5], 2.0)
    total, cross, roll_err = rot.attitude_error(b, a)
    assert float(total) == pytest.approx(1.0, rel=1e-9)
    assert float(cross) == pytest.approx(0.0, abs=1e-9)
    assert abs(float(roll_err)) == pytest.approx(1.0, rel=1e-9)
    np.testing.assert_allclose(np.abs(rot.rotation_vector(b @ a.T)), [0, 0, 1.0], atol=1e-9)
    # a positive turn of the camera about its boresight lowers the roll angle (A = R3(-roll) A0)
    assert float(rot.dcm_to_radec_roll(b)[2]) == pytest.approx(4.0, abs=1e-9)


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
    np.testing.assert_allclose(a, rot.elementary_rotation(3, 90.0), atol=1e-15)


@settings(max_examples=300, deadline=None)
@given(ras, decs, angles)
def test_radec_roll_round_trip(ra, dec, roll):
    a = rot.radec_roll_to_dcm(ra, dec, roll)
    np.testing.assert_allclose(a @ a.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(a) == pytest.approx(1.0, abs=1e-12)
    ra2, dec2, roll2 = rot.dcm_to_radec_roll(a)
    assert 0.0 <= ra2 < 360.0 and -180.0 <= roll2 <= 180.0
    # The matrix is reproduced exactly, poles included (where ra is undefined).
    np.testing.assert_allclose(rot.radec_roll_to_dcm(ra2, dec2, roll2), a, atol=1e-9)
    assert dec2 == pytest.approx(dec, abs=1e-7)
    if abs(dec) < 90.0 - 1e-4:
        dra = (ra2 - ra + 180.0) % 360.0 - 180.0
        assert abs(dra) < 1e-7
        droll = (roll2 - roll + 180.0) % 360.0 - 180.0
        assert abs(droll) < 1e-7


@settings(max_examples=200, deadline=None)
@given(quats)
def test_dcm_radec_roll_dcm(q):
    a = rot.quaternion_to_dcm(q)
    np.testing.assert_allclose(rot.radec_roll_to_dcm(*rot.dcm_to_radec_roll(a)), a, atol=1e-9)
    np.testing.assert_allclose(rot._radec_roll_to_dcm_rad(*rot._dcm_to_radec_roll_rad(a)), a, atol=1e-9)


@settings(max_examples=200, deadline=None)
@given(quats)
def test_euler123_round_trip(q):
    a = rot.quaternion_to_dcm(q)
    np.testing.assert_allclose(rot.euler123_to_dcm(*rot.dcm_to_euler123(a)), a, atol=1e-9)


def test_euler123_gimbal_lock():
    a = rot.euler123_to_dcm(17.0, 90.0, 11.0)
    np.testing.assert_allclose(rot.euler123_to_dcm(*rot.dcm_to_euler123(a)), a, atol=1e-12)


@settings(max_examples=200, deadline=None)
@given(quats, quats)
def test_composition_and_inverse(q, p):
    aq, ap = rot.quaternion_to_dcm(q), rot.quaternion_to_dcm(p)
    np.testing.assert_allclose(rot.quaternion_to_dcm(rot.quaternion_multiply(q, p)), aq @ ap, atol=1e-12)
    np.testing.assert_allclose(rot.quaternion_to_dcm(rot.quaternion_inverse(q)), aq.T, atol=1e-12)


def test_roll_zero_is_north_up_east_left():
    ra, dec = 83.8, -1.2
    a = rot.radec_roll_to_dcm(ra, dec, 0.0)
    bore = rot.radec_to_vector(ra, dec)
    north_star = rot.radec_to_vector(ra, dec + 0.05)
    east_star = rot.radec_to_vector(ra + 0.05, dec)
    n_cam = a @ north_star
    e_cam = a @ east_star
    np.testing.assert_allclose(a[2], bore)
    assert n_cam[1] < 0 and abs(n_cam[0]) < 1e-12      # north is up (-y)
    assert e_cam[0] < 0 and abs(e_cam[1]) < 1e-6       # east is left (-x)
    # roll = 90 deg turns image up toward east.
    a90 = rot.radec_roll_to_dcm(ra, dec, 90.0)
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
    a = rot.radec_roll_to_dcm(57.0, 28.0, 17.0)
    roll_only = rot.elementary_rotation(3, 0.005) @ a
    total, cross, roll = rot.attitude_error(roll_only, a)
    assert total == pytest.approx(0.005, rel=1e-6)
    assert cross == pytest.approx(0.0, abs=1e-10)
    assert roll == pytest.approx(0.005, rel=1e-6)
    tilt = rot.elementary_rotation(1, 0.001) @ a
    total, cross, roll = rot.attitude_error(tilt, a)
    assert cross == pytest.approx(0.001, rel=1e-6)
    assert abs(roll) < 1e-10
    # the radian form the library uses internally agrees
    np.testing.assert_allclose(np.degrees(rot._attitude_error_rad(tilt, a)), (total, cross, roll), atol=1e-12)


def test_readme_roll_example(catalog):
    # README: boresight (83.8, -1.2), roll 30 deg -> Betelgeuse straight above the centre.
    from startrack.camera import Camera

    a = rot.radec_roll_to_dcm(83.8, -1.2, 30.0)
    cam = Camera.from_fov(30, 1024, 1024)
    betel = catalog.subset(catalog.id == 27989).vectors()[0]
    x, y = cam.vectors_to_pixels(a @ betel)
    assert y < cam.cy - 300
    assert abs(x - cam.cx) < 0.1 * (cam.cy - y)


def _array_path_quaternion(a):
    """dcm_to_quaternion's array path (a stack of one matrix never takes the single-matrix fast path)."""
    return rot.dcm_to_quaternion(np.asarray(a, dtype=np.float64)[None])[0]


@settings(max_examples=300, deadline=None)
@given(quats)
def test_dcm_to_quaternion_single_matrix_path_is_the_array_path_to_the_bit(q):
    a = rot.quaternion_to_dcm(rot.normalize_quaternion(q))
    fast = rot.dcm_to_quaternion(a)
    assert fast.shape == (4,) and fast.dtype == np.float64
    assert fast.tobytes() == _array_path_quaternion(a).tobytes()


def test_dcm_to_quaternion_single_matrix_path_every_pivot_ties_and_odd_matrices():
    rng = np.random.default_rng(38)
    cases = [np.eye(3), -np.eye(3), np.diag([1.0, -1.0, -1.0]), np.diag([-1.0, 1.0, -1.0]), np.diag([-1.0, -1.0, 1.0]),
             np.zeros((3, 3)), np.full((3, 3), 0.5), np.diag([0.2, 0.2, 0.2]), np.diag([-0.3, 0.4, 0.4])]
    # Rotations by ~180 degrees about each axis and about random axes (every pivot of Shepperd's method wins).
    for axis in range(1, 4):
        for ang in (179.9999, 180.0, 90.0, 1e-9):
            cases.append(rot.elementary_rotation(axis, ang))
    for _ in range(2000):
        cases.append(rot.quaternion_to_dcm(rot.normalize_quaternion(rng.normal(size=4) * [1, 1, 1, 1e-3])))
        cases.append(rng.normal(size=(3, 3)) * 10.0 ** rng.integers(-6, 6))   # not rotations: same arithmetic
    seen = set()
    for a in cases:
        a = np.ascontiguousarray(a, dtype=np.float64)
        with np.errstate(all="ignore"):
            fast, slow = rot.dcm_to_quaternion(a), _array_path_quaternion(a)
        assert fast.tobytes() == slow.tobytes(), a
        d = [a[0, 0], a[1, 1], a[2, 2], np.trace(a)]
        seen.add(int(np.argmax(d)))
    assert seen == {0, 1, 2, 3}
    # Not finite: the array path's answer (NaN), as before.
    bad = np.eye(3)
    bad[0, 1] = np.nan
    with np.errstate(all="ignore"):
        assert np.isnan(rot.dcm_to_quaternion(bad)).any()


def _euler123_reference(a):
    """_dcm_to_euler123_rad as it was before its single-matrix path (stacked elementary rotations)."""
    a = np.asarray(a, dtype=np.float64)
    pitch = np.arctan2(a[..., 2, 0], np.hypot(a[..., 2, 1], a[..., 2, 2]))
    yaw = np.arctan2(-a[..., 2, 1], a[..., 2, 2])
    rest = a @ np.swapaxes(rot._elementary_rotation_rad(2, pitch) @ rot._elementary_rotation_rad(1, yaw), -1, -2)
    return yaw, pitch, np.arctan2(rest[..., 0, 1], rest[..., 0, 0])


def _same_bits(x, y):
    return all(np.asarray(u, dtype=np.float64).tobytes() == np.asarray(v, dtype=np.float64).tobytes()
               for u, v in zip(x, y))


@settings(max_examples=300, deadline=None)
@given(quats)
def test_dcm_to_euler123_single_matrix_path_is_the_array_path_to_the_bit(q):
    a = rot.quaternion_to_dcm(rot.normalize_quaternion(q))
    assert _same_bits(rot._dcm_to_euler123_rad(a), _euler123_reference(a))
    assert _same_bits(rot.dcm_to_euler123(a), [np.degrees(v) for v in _euler123_reference(a)])
    # A stack of matrices still takes the array path, with the same numbers.
    np.testing.assert_allclose(np.ravel(rot.dcm_to_euler123(a[None])), rot.dcm_to_euler123(a), rtol=0, atol=1e-12)


def test_dcm_to_euler123_single_matrix_path_gimbal_lock_and_odd_matrices():
    rng = np.random.default_rng(38)
    cases = [np.eye(3), -np.eye(3), np.zeros((3, 3)), rot.euler123_to_dcm(10.0, 90.0, 20.0),
             rot.euler123_to_dcm(-30.0, -90.0, 5.0), rot.euler123_to_dcm(0.0, 89.9999999, 0.0)]
    cases += [rng.normal(size=(3, 3)) for _ in range(500)]
    cases += [rot.quaternion_to_dcm(rot.normalize_quaternion(rng.normal(size=4))) for _ in range(500)]
    for a in cases:
        assert _same_bits(rot._dcm_to_euler123_rad(a), _euler123_reference(a))
        assert _same_bits(rot._dcm_to_euler123_rad(a.tolist()), _euler123_reference(a))


def _radec_roll_reference(a):
    """_dcm_to_radec_roll_rad as it was before its single-matrix path (stacked east and north)."""
    a = np.asarray(a, dtype=np.float64)
    ra, dec = rot._vector_to_radec_rad(a[..., 2, :])
    east, north = rot._east_north_rad(ra, dec)
    up = -a[..., 1, :]
    return ra, dec, np.arctan2(np.sum(up * east, axis=-1), np.sum(up * north, axis=-1))


@settings(max_examples=300, deadline=None)
@given(ras, decs, angles)
def test_dcm_to_radec_roll_single_matrix_path_is_the_array_path_to_the_bit(ra, dec, roll):
    a = rot.radec_roll_to_dcm(ra, dec, roll)     # poles and RA 0/360 among the strategies
    assert _same_bits(rot._dcm_to_radec_roll_rad(a), _radec_roll_reference(a))
    ref = _radec_roll_reference(a)
    assert _same_bits(rot.dcm_to_radec_roll(a), (np.mod(np.degrees(ref[0]), 360.0), np.degrees(ref[1]),
                                                 np.degrees(ref[2])))


def test_dcm_to_radec_roll_single_matrix_path_odd_matrices():
    rng = np.random.default_rng(38)
    cases = [np.eye(3), -np.eye(3), np.zeros((3, 3)), rot.radec_roll_to_dcm(0.0, 90.0, 0.0),
             rot.radec_roll_to_dcm(359.9999999, -90.0, 180.0)]
    cases += [rng.normal(size=(3, 3)) for _ in range(500)]
    cases += [rot.quaternion_to_dcm(rot.normalize_quaternion(rng.normal(size=4))) for _ in range(500)]
    for a in cases:
        assert _same_bits(rot._dcm_to_radec_roll_rad(a), _radec_roll_reference(a))
        assert _same_bits(rot._dcm_to_radec_roll_rad(a.tolist()), _radec_roll_reference(a))


def test_one_quaternion_to_dcm_is_the_array_path_to_the_bit():
    """A single quaternion takes a scalar path: the same matrix, bit for bit, as a batch of them (the array path),
    for random quaternions, negative scalar parts, zero components and tiny or large norms."""
    rng = np.random.default_rng(11)
    qs = np.concatenate([rng.normal(size=(3000, 4)), rng.normal(size=(200, 4)) * 1e-150,
                         rng.normal(size=(200, 4)) * 1e140,
                         np.array([[0, 0, 0, 1], [0, 0, 0, -1], [1, 0, 0, 0], [0, -1, 0, 0], [-0.0, 0.0, -0.0, 1.0],
                                   [0.5, 0.5, 0.5, -0.5], [3, 4, 0, 0]], dtype=np.float64)])
    batch = rot.quaternion_to_dcm(qs)
    for q, expected in zip(qs, batch):
        assert rot.quaternion_to_dcm(q).tobytes() == expected.tobytes(), q
    # Not finite: the array path's NaNs.
    assert np.isnan(rot.quaternion_to_dcm(np.array([np.nan, 0.0, 0.0, 1.0]))).all()
