"""Attitude mathematics: quaternions, direction cosine matrices and angles.

Conventions (``docs/formats.md``, "Attitude"):

* The attitude matrix ``A`` maps ICRS unit vectors to camera-frame unit vectors,
  ``v_cam = A @ v_icrs``; its rows are the camera axes expressed in ICRS, so its
  third row is the boresight.
* Quaternions are ``[q1, q2, q3, q4]``, scalar last, and
  ``A(q) = (q4**2 - |q_v|**2) I + 2 q_v q_v^T - 2 q4 [q_v x]``
  (paper 000 Eqs. 20-22; Shuster 1993).  Every quaternion returned here has
  ``q4 >= 0``.
* ``(ra, dec, roll)``: ``ra``/``dec`` are the boresight's.  ``roll`` is the
  position angle of the image's "up" direction (``-y``, toward row 0) measured
  from celestial north through east, the same angle astrometry.net reports as
  "up, degrees east of north".  ``roll = 0`` puts north up and east to the left,
  as on a sky chart.  Formally ``A = R3(-roll) @ A0(ra, dec)`` with ``A0``'s rows
  ``(-east, -north, boresight)``.
* ``(yaw, pitch, roll)`` Euler angles: the 1-2-3 sequence
  ``A = R3(roll) @ R2(pitch) @ R1(yaw)`` (passive elementary rotations), so the
  last rotation is about the boresight.  Paper 000 (Eqs. 27-29) reports
  attitudes as roll/pitch/yaw without naming its sequence; this is ours.

Every public function takes and returns angles in **degrees** (rates in degrees
per second), as everywhere at startrack's public boundary; the radian forms the
library computes with are private (``_radec_roll_to_dcm_rad`` and so on).  All
functions broadcast over leading dimensions: a quaternion array has shape
``(..., 4)`` and a DCM array ``(..., 3, 3)``.
"""
from __future__ import annotations

import math

import numpy as np

__all__ = [
    "normalize_quaternion",
    "quaternion_to_dcm",
    "dcm_to_quaternion",
    "quaternion_multiply",
    "quaternion_inverse",
    "radec_roll_to_dcm",
    "dcm_to_radec_roll",
    "euler123_to_dcm",
    "dcm_to_euler123",
    "elementary_rotation",
    "random_quaternions",
    "propagate_attitude",
    "east_north",
    "radec_to_vector",
    "vector_to_radec",
    "rotation_vector",
    "attitude_error",
]


def normalize_quaternion(q):
    """Return ``q`` scaled to unit norm with a non-negative scalar part."""
    q = np.asarray(q, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., 3:4] < 0.0, -q, q)


def _cross_matrix(v):
    """Skew-symmetric ``[v x]`` with ``[v x] w = v x w``; shape ``(..., 3, 3)``."""
    zero = np.zeros_like(v[..., 0])
    return np.stack(
        [
            np.stack([zero, -v[..., 2], v[..., 1]], axis=-1),
            np.stack([v[..., 2], zero, -v[..., 0]], axis=-1),
            np.stack([-v[..., 1], v[..., 0], zero], axis=-1),
        ],
        axis=-2,
    )


def quaternion_to_dcm(q):
    """Attitude matrix of a scalar-last quaternion (paper 000 Eq. 22; Shuster).

    Parameters
    ----------
    q : array_like, shape (..., 4)
        Quaternion ``[q1, q2, q3, q4]``; normalised here.

    Returns
    -------
    ndarray, shape (..., 3, 3)
        ``A(q) = (q4^2 - |q_v|^2) I + 2 q_v q_v^T - 2 q4 [q_v x]``.
    """
    if type(q) is np.ndarray and q.shape == (4,) and q.dtype == np.float64:
        dcm = _quaternion_to_dcm_one(q.tolist())
        if dcm is not None:
            return dcm
    q = normalize_quaternion(q)
    qv = q[..., :3]
    q4 = q[..., 3]
    eye = np.eye(3)
    scal = (q4**2 - np.sum(qv * qv, axis=-1))[..., None, None]
    return (
        scal * eye
        + 2.0 * qv[..., :, None] * qv[..., None, :]
        - 2.0 * q4[..., None, None] * _cross_matrix(qv)
    )


def _quaternion_to_dcm_one(q):
    """:func:`quaternion_to_dcm` of one finite quaternion (a list of four floats) in Python floats, to the bit: the
    same operations in the same order (numpy's sums of squares run left to right; its ``q4 ** 2`` is ``q4 * q4``),
    without the array path's stacking (called per frame).  None when an entry or the
    norm is not finite or the norm is 0 (the array path decides)."""
    if not all(map(math.isfinite, q)):
        return None
    n = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    if not 0.0 < n < math.inf:
        return None
    q1, q2, q3, q4 = (v / n for v in q)
    if q4 < 0.0:
        q1, q2, q3, q4 = -q1, -q2, -q3, -q4
    scal = q4 * q4 - (q1 * q1 + q2 * q2 + q3 * q3)
    t1, t2, t3, t4 = 2.0 * q1, 2.0 * q2, 2.0 * q3, 2.0 * q4
    # scal I + 2 q_v q_v^T - 2 q4 [q_v x], entry by entry as the arrays add them (the off-diagonal scal * 0).
    z = scal * 0.0
    return np.array([
        [(scal + t1 * q1) - t4 * 0.0, (z + t1 * q2) - t4 * -q3, (z + t1 * q3) - t4 * q2],
        [(z + t2 * q1) - t4 * q3, (scal + t2 * q2) - t4 * 0.0, (z + t2 * q3) - t4 * -q1],
        [(z + t3 * q1) - t4 * -q2, (z + t3 * q2) - t4 * q1, (scal + t3 * q3) - t4 * 0.0],
    ])


def dcm_to_quaternion(dcm):
    """Quaternion of an attitude matrix, by Shepperd's method (stable everywhere).

    Parameters
    ----------
    dcm : array_like, shape (..., 3, 3)
        A proper rotation matrix.

    Returns
    -------
    ndarray, shape (..., 4)
        Scalar-last unit quaternion with ``q4 >= 0``.
    """
    if type(dcm) is np.ndarray and dcm.shape == (3, 3) and dcm.dtype == np.float64:
        q = _dcm_to_quaternion_one(dcm.tolist())
        if q is not None:
            return q
    a = np.asarray(dcm, dtype=np.float64)
    tr = a[..., 0, 0] + a[..., 1, 1] + a[..., 2, 2]
    # Four candidate forms; pick, per matrix, the one with the largest pivot.
    cands = np.stack(
        [
            np.stack([1 + 2 * a[..., 0, 0] - tr, a[..., 0, 1] + a[..., 1, 0],
                      a[..., 0, 2] + a[..., 2, 0], a[..., 1, 2] - a[..., 2, 1]], axis=-1),
            np.stack([a[..., 1, 0] + a[..., 0, 1], 1 + 2 * a[..., 1, 1] - tr,
                      a[..., 1, 2] + a[..., 2, 1], a[..., 2, 0] - a[..., 0, 2]], axis=-1),
            np.stack([a[..., 2, 0] + a[..., 0, 2], a[..., 2, 1] + a[..., 1, 2],
                      1 + 2 * a[..., 2, 2] - tr, a[..., 0, 1] - a[..., 1, 0]], axis=-1),
            np.stack([a[..., 1, 2] - a[..., 2, 1], a[..., 2, 0] - a[..., 0, 2],
                      a[..., 0, 1] - a[..., 1, 0], 1 + tr], axis=-1),
        ],
        axis=-2,
    )
    pivots = np.stack(
        [a[..., 0, 0], a[..., 1, 1], a[..., 2, 2], tr], axis=-1
    )
    best = np.argmax(pivots, axis=-1)
    q = np.take_along_axis(cands, best[..., None, None], axis=-2)[..., 0, :]
    return normalize_quaternion(q)


def _dcm_to_quaternion_one(rows):
    """:func:`dcm_to_quaternion` of one finite 3 x 3 matrix (nested lists) in Python floats, to the bit: the same
    operations in the same order (numpy's sum of four squares runs left to right), ~10x faster than the array
    path for a single matrix (called per frame).  None when an entry or the norm is not finite or the norm is 0 (the array path decides)."""
    (a00, a01, a02), (a10, a11, a12), (a20, a21, a22) = rows
    if not all(map(math.isfinite, (a00, a01, a02, a10, a11, a12, a20, a21, a22))):
        return None
    tr = a00 + a11 + a22
    # np.argmax: the first of equal pivots.
    best, piv = 0, a00
    if a11 > piv:
        best, piv = 1, a11
    if a22 > piv:
        best, piv = 2, a22
    if tr > piv:
        best = 3
    if best == 0:
        q = (1 + 2 * a00 - tr, a01 + a10, a02 + a20, a12 - a21)
    elif best == 1:
        q = (a10 + a01, 1 + 2 * a11 - tr, a12 + a21, a20 - a02)
    elif best == 2:
        q = (a20 + a02, a21 + a12, 1 + 2 * a22 - tr, a01 - a10)
    else:
        q = (a12 - a21, a20 - a02, a01 - a10, 1 + tr)
    n = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    if not 0.0 < n < math.inf:
        return None
    q = [v / n for v in q]
    if q[3] < 0.0:
        q = [-v for v in q]
    return np.array(q, dtype=np.float64)


def quaternion_multiply(q, p):
    """Compose attitudes: ``A(quaternion_multiply(q, p)) == A(q) @ A(p)``.

    This is Shuster's product in "natural order" (Shuster 1993, Eq. 171):
    ``q (x) p = [q4 p_v + p4 q_v - q_v x p_v,  q4 p4 - q_v . p_v]``.
    """
    q = np.asarray(q, dtype=np.float64)
    p = np.asarray(p, dtype=np.float64)
    qv, q4 = q[..., :3], q[..., 3:4]
    pv, p4 = p[..., :3], p[..., 3:4]
    vec = q4 * pv + p4 * qv - np.cross(qv, pv)
    scal = q4 * p4 - np.sum(qv * pv, axis=-1, keepdims=True)
    return normalize_quaternion(np.concatenate([vec, scal], axis=-1))


def quaternion_inverse(q):
    """Inverse (conjugate) attitude: ``A(quaternion_inverse(q)) == A(q).T``."""
    q = normalize_quaternion(q)
    return normalize_quaternion(np.concatenate([-q[..., :3], q[..., 3:]], axis=-1))


def _elementary_rotation_rad(axis: int, angle):
    """Passive rotation ``R_axis(angle)`` about axis 1, 2 or 3; shape ``(..., 3, 3)``.

    ``R3(t) = [[c, s, 0], [-s, c, 0], [0, 0, 1]]`` and likewise for 1 and 2.
    """
    angle = np.asarray(angle, dtype=np.float64)
    c, s = np.cos(angle), np.sin(angle)
    one, zero = np.ones_like(c), np.zeros_like(c)
    if axis == 1:
        rows = [[one, zero, zero], [zero, c, s], [zero, -s, c]]
    elif axis == 2:
        rows = [[c, zero, -s], [zero, one, zero], [s, zero, c]]
    elif axis == 3:
        rows = [[c, s, zero], [-s, c, zero], [zero, zero, one]]
    else:
        raise ValueError("axis must be 1, 2 or 3")
    return np.stack([np.stack(r, axis=-1) for r in rows], axis=-2)


def _radec_to_vector_rad(ra, dec):
    """ICRS unit vector ``(cos a cos d, sin a cos d, sin d)`` (paper 000 Eq. 14).

    Parameters
    ----------
    ra, dec : array_like
        Right ascension and declination in radians.

    Returns
    -------
    ndarray, shape (..., 3)
    """
    ra = np.asarray(ra, dtype=np.float64)
    dec = np.asarray(dec, dtype=np.float64)
    cd = np.cos(dec)
    return np.stack([np.cos(ra) * cd, np.sin(ra) * cd, np.sin(dec)], axis=-1)


def _vector_to_radec_rad(v):
    """Right ascension in ``[0, 2 pi)`` and declination of vectors ``(..., 3)``."""
    v = np.asarray(v, dtype=np.float64)
    ra = np.mod(np.arctan2(v[..., 1], v[..., 0]), 2 * np.pi)
    dec = np.arctan2(v[..., 2], np.hypot(v[..., 0], v[..., 1]))
    return ra, dec


def _east_north_rad(ra, dec):
    """Unit vectors of local east and north (ICRS) at right ascension ``ra`` and declination ``dec`` (radians).

    ``east = (-sin a, cos a, 0)`` and ``north = (-sin d cos a, -sin d sin a, cos d)``,
    the derivatives of the unit vector (paper 000 Eq. 14) along ``a`` (divided by
    ``cos d``) and ``d``.

    Returns
    -------
    east, north : ndarray, shape (..., 3)
    """
    ra = np.asarray(ra, dtype=np.float64)
    dec = np.asarray(dec, dtype=np.float64)
    east = np.stack([-np.sin(ra), np.cos(ra), np.zeros_like(ra)], axis=-1)
    north = np.stack(
        [-np.sin(dec) * np.cos(ra), -np.sin(dec) * np.sin(ra), np.cos(dec)], axis=-1
    )
    return east, north


def _radec_roll_to_dcm_rad(ra, dec, roll):
    """Attitude matrix from boresight ``(ra, dec)`` and ``roll`` (radians).

    Rows of the result: camera ``+x`` (image right), ``+y`` (image down) and
    ``+z`` (boresight) in ICRS.  With ``roll = 0`` image up is north and image
    left is east; ``roll`` turns image up from north toward east.
    """
    east, north = _east_north_rad(ra, dec)
    bore = _radec_to_vector_rad(ra, dec)
    roll = np.asarray(roll, dtype=np.float64)[..., None]
    c, s = np.cos(roll), np.sin(roll)
    # image up (-y) = cos(roll) N + sin(roll) E;  +x = y x z.
    y_axis = -(c * north + s * east)
    x_axis = np.cross(y_axis, bore)
    return np.stack([x_axis, y_axis, bore], axis=-2)


def _dcm_to_radec_roll_rad(dcm):
    """Inverse of :func:`_radec_roll_to_dcm_rad`: ``(ra, dec, roll)`` in radians.

    ``ra`` is in ``[0, 2 pi)``, ``roll`` in ``(-pi, pi]``.  At a pole ``ra`` is
    undefined; the returned triple then still reproduces ``dcm`` exactly.
    """
    a = np.asarray(dcm, dtype=np.float64)
    if a.shape == (3, 3):
        return _dcm_to_radec_roll_one(a)
    bore = a[..., 2, :]
    ra, dec = _vector_to_radec_rad(bore)
    east, north = _east_north_rad(ra, dec)
    up = -a[..., 1, :]
    roll = np.arctan2(np.sum(up * east, axis=-1), np.sum(up * north, axis=-1))
    return ra, dec, roll


def _boresight_one(a):
    """``ra`` (in ``[0, 2 pi)``) and ``dec`` (radians) of one 3 x 3 matrix's boresight row: the ufuncs of
    :func:`_dcm_to_radec_roll_rad` on the same values."""
    bore = a[..., 2, :]
    return (np.mod(np.arctan2(bore[..., 1], bore[..., 0]), 2 * np.pi),
            np.arctan2(bore[..., 2], np.hypot(bore[..., 0], bore[..., 1])))


def _east_north_one(ra, dec):
    """:func:`_east_north_rad` of one ``ra``, ``dec`` (radians), to the bit: each sine and cosine once, east and north
    built directly rather than stacked (``zeros_like`` of a 0-d value is +0.0)."""
    sr, cr, sd = np.sin(ra), np.cos(ra), np.sin(dec)
    return np.array([-sr, cr, 0.0]), np.array([-sd * cr, -sd * sr, np.cos(dec)])


def _dcm_to_radec_roll_one(a):
    """:func:`_dcm_to_radec_roll_rad` of one 3 x 3 matrix, to the bit (called per frame)."""
    ra, dec = _boresight_one(a)
    east, north = _east_north_one(ra, dec)
    up = -a[..., 1, :]
    roll = np.arctan2(np.sum(up * east, axis=-1), np.sum(up * north, axis=-1))
    return ra, dec, roll


def _boresight_east_north_one(a):
    """``ra, dec = dcm_to_radec_roll(a)[:2]`` (degrees) and ``east, north = east_north(ra, dec)`` of one 3 x 3
    float64 matrix, to the bit, without the roll (:func:`startrack.attitude.wcs_keywords`, per solved frame)."""
    ra, dec = _boresight_one(a)
    ra, dec = np.mod(np.degrees(ra), 360.0), np.degrees(dec)
    return (ra, dec, *_east_north_one(_deg(ra), _deg(dec)))


def _euler123_to_dcm_rad(yaw, pitch, roll):
    """``A = R3(roll) R2(pitch) R1(yaw)``: the roll/pitch/yaw of our reports."""
    return (
        _elementary_rotation_rad(3, roll)
        @ _elementary_rotation_rad(2, pitch)
        @ _elementary_rotation_rad(1, yaw)
    )


def _dcm_to_euler123_rad(dcm):
    """Inverse of :func:`_euler123_to_dcm_rad`: ``(yaw, pitch, roll)`` in radians.

    ``pitch`` is in ``[-pi/2, pi/2]``.  At ``|pitch| = pi/2`` (gimbal lock) only
    ``roll -/+ yaw`` is defined; the returned triple still reproduces ``dcm``.
    """
    a = np.asarray(dcm, dtype=np.float64)
    if a.shape == (3, 3):
        return _dcm_to_euler123_one(a)
    # A = R3(r) R2(p) R1(y) has third row (sin p, -cos p sin y, cos p cos y).
    pitch = np.arctan2(a[..., 2, 0], np.hypot(a[..., 2, 1], a[..., 2, 2]))
    yaw = np.arctan2(-a[..., 2, 1], a[..., 2, 2])
    # Roll from what is left once pitch and yaw are undone: stable near gimbal
    # lock (|pitch| -> 90 deg), where any error in yaw is absorbed by roll.
    rest = a @ np.swapaxes(_elementary_rotation_rad(2, pitch) @ _elementary_rotation_rad(1, yaw), -1, -2)
    roll = np.arctan2(rest[..., 0, 1], rest[..., 0, 0])
    return yaw, pitch, roll


def _dcm_to_euler123_one(a):
    """:func:`_dcm_to_euler123_rad` of one 3 x 3 matrix, to the bit: the same ufuncs on the same values and the
    same matrix products (the rotations built directly, not stacked), ~3x faster (called per frame)."""
    pitch = np.arctan2(a[..., 2, 0], np.hypot(a[..., 2, 1], a[..., 2, 2]))
    yaw = np.arctan2(-a[..., 2, 1], a[..., 2, 2])
    cp, sp, cy, sy = np.cos(pitch), np.sin(pitch), np.cos(yaw), np.sin(yaw)
    r2 = np.array([[cp, 0.0, -sp], [0.0, 1.0, 0.0], [sp, 0.0, cp]])
    r1 = np.array([[1.0, 0.0, 0.0], [0.0, cy, sy], [0.0, -sy, cy]])
    rest = a @ np.swapaxes(r2 @ r1, -1, -2)
    roll = np.arctan2(rest[..., 0, 1], rest[..., 0, 0])
    return yaw, pitch, roll


def _r2_r1(cp, sp, cy, sy):
    """``R2(pitch) @ R1(yaw)`` (cosines and sines, Python floats) as numpy's matmul of the two makes it, to the bit.

    ``[[cp, 0, -sp], [0, 1, 0], [sp, 0, cp]] @ [[1, 0, 0], [0, cy, sy], [0, -sy, cy]]``: each entry a sum of three
    products of which at most one is not an exact zero, so any matmul (fused or not, in any order) gives that product
    rounded once; when all three are zeros one is +0 (``0 * 0``, or ``cp * 0`` / ``0 * cy`` when ``sp`` or ``sy``
    is 0), so the sum is +0: each entry is its product ``+ 0.0``.  A product of two non-zero factors that underflows
    to zero is the exception: a fused multiply-add rounds the exact tiny product once with the sum and keeps its sign
    (-0.0), a separate multiply and add make +0.0, and which numpy's matmul does depends on the machine (angles below
    ~1e-154 rad): numpy's matmul itself then."""
    p01, p02, p21, p22 = (-sp) * (-sy), (-sp) * cy, cp * (-sy), cp * cy
    if (p01 == 0.0 and sp != 0.0 and sy != 0.0) or (p02 == 0.0 and sp != 0.0 and cy != 0.0) \
            or (p21 == 0.0 and cp != 0.0 and sy != 0.0) or (p22 == 0.0 and cp != 0.0 and cy != 0.0):
        return np.array([[cp, 0.0, -sp], [0.0, 1.0, 0.0], [sp, 0.0, cp]]) @ \
            np.array([[1.0, 0.0, 0.0], [0.0, cy, sy], [0.0, -sy, cy]])
    return np.array([[cp + 0.0, p01 + 0.0, p02 + 0.0],
                     [0.0, cy + 0.0, sy + 0.0],
                     [sp + 0.0, p21 + 0.0, p22 + 0.0]])


_RAD_TO_DEG = 180.0 / math.pi        # np.degrees' factor (numpy's rad2deg is x * (180.0 / NPY_PI))


def _angles_deg_one(a, rows):
    """``dcm_to_radec_roll(a) + dcm_to_euler123(a)``, six Python floats (degrees), to the bit, for an attitude
    record (once per solved frame): ``a`` one 3 x 3 float64 ndarray, ``rows`` its ``a.tolist()``.  None unless
    every entry's square is finite and their sum is below 1e300 (then no product or sum below overflows; the
    callers take the public functions, which decide).

    Bit for bit the single-matrix paths' arithmetic (:func:`_dcm_to_radec_roll_one`, :func:`_dcm_to_euler123_one`):
    the transcendental functions are still numpy's (``arctan2`` and ``hypot`` are not libm's everywhere: numpy's
    SIMD ``arctan2`` differs from ``math.atan2`` in the last bit for ~4% of arguments on an AVX-512 machine), one
    ufunc call for each stage's arguments together (a ufunc treats each element alike, whatever its neighbours); the
    euler roll's last matrix product is numpy's ``@`` on the same arrays (BLAS, fused: not Python's sums).  In
    Python floats: products, sums of three from +0.0 left to right (numpy's sum of fewer than 8 values), ``%``
    (``np.mod``'s fmod and sign fix) and ``x * (180 / pi)`` (``np.degrees``)."""
    (a00, a01, a02), (a10, a11, a12), (a20, a21, a22) = rows
    size2 = (a00 * a00 + a01 * a01 + a02 * a02) + (a10 * a10 + a11 * a11 + a12 * a12) + (a20 * a20 + a21 * a21
                                                                                          + a22 * a22)
    if not size2 < 1e300:       # NaN, inf or a huge entry
        return None
    # Boresight (a20, a21, a22): ra = mod(atan2(a21, a20), 2 pi), dec = atan2(a22, hypot(a20, a21)); euler:
    # pitch = atan2(a20, hypot(a21, a22)), yaw = atan2(-a21, a22).
    h_bore, h_pitch = np.hypot((a20, a21), (a21, a22)).tolist()
    ra, dec, pitch, yaw = np.arctan2((a21, a22, a20, -a21), (a20, h_bore, h_pitch, a22)).tolist()
    ra = ra % (2 * math.pi)
    angles = (ra, dec, pitch, yaw)
    sr, sd, sp, sy = np.sin(angles).tolist()
    cr, cd, cp, cy = np.cos(angles).tolist()
    # roll: up = -a[1], east = (-sin ra, cos ra, 0), north = (-sin dec cos ra, -sin dec sin ra, cos dec).
    # np.sum of three values: ((0.0 + x0) + x1) + x2 (numpy's reduction starts at the identity +0.0, so a sum of
    # zeros is +0; the angle of a zero row then is atan2(+0, +0) = 0, not 180).
    up_e = ((0.0 + (-a10) * (-sr)) + (-a11) * cr) + (-a12) * 0.0
    up_n = ((0.0 + (-a10) * (-sd * cr)) + (-a11) * (-sd * sr)) + (-a12) * cd
    rest = a @ _r2_r1(cp, sp, cy, sy).T         # np.swapaxes(m, -1, -2) of a 3 x 3: the same view
    roll, roll123 = np.arctan2((up_e, rest[0, 1]), (up_n, rest[0, 0])).tolist()
    d = _RAD_TO_DEG
    return (ra * d) % 360.0, dec * d, roll * d, yaw * d, pitch * d, roll123 * d


def _propagate_attitude_rad(dcm, rate_rad_s, dt):
    """Attitude after ``dt`` seconds at constant body rate ``rate_rad_s`` (camera frame).

    ``A(t) = exp(-[w x] t) A(0)``: the camera turns by ``w t`` about the
    body-frame axis ``w``, so fixed stars appear to turn the other way.
    """
    w = np.asarray(rate_rad_s, dtype=np.float64)
    angle = float(np.linalg.norm(w)) * dt
    if angle == 0.0:
        return np.array(dcm, dtype=np.float64)
    axis = w / np.linalg.norm(w)
    # Quaternion of a passive rotation by `angle` about `axis` (A = I - [phi x] + ...).
    dq = np.concatenate([axis * math.sin(angle / 2.0), [math.cos(angle / 2.0)]])
    return quaternion_to_dcm(quaternion_multiply(dq, dcm_to_quaternion(dcm)))


def random_quaternions(n: int, rng: np.random.Generator):
    """``n`` attitudes uniformly distributed over SO(3), shape ``(n, 4)``.

    Normalised 4-D Gaussian vectors are uniform on the unit 3-sphere, hence
    uniform (Haar) attitudes.
    """
    q = rng.standard_normal((int(n), 4))
    return normalize_quaternion(q)


def _rotation_vector_rad(dcm):
    """Rotation vector ``phi`` (radians) with ``A ~ I - [phi x]`` for small angles."""
    q = dcm_to_quaternion(dcm)
    qv = q[..., :3]
    sin_half = np.linalg.norm(qv, axis=-1, keepdims=True)
    angle = 2.0 * np.arctan2(sin_half, q[..., 3:4])
    scale = np.where(sin_half > 1e-300, angle / np.maximum(sin_half, 1e-300), 2.0)
    return qv * scale


def _attitude_error_rad(dcm_estimate, dcm_truth):
    """Angle between two attitudes, split into cross-boresight and roll parts.

    Returns
    -------
    total, cross_boresight, roll : ndarray
        In radians.  ``total`` is the angle of ``A_est A_true^T``;
        ``cross_boresight`` the angle between the two boresights; ``roll`` the
        signed component of the error rotation vector about the true boresight.
        The x and y components (camera frame) are pitch and yaw errors.
    """
    a_est = np.asarray(dcm_estimate, dtype=np.float64)
    a_true = np.asarray(dcm_truth, dtype=np.float64)
    delta = a_est @ np.swapaxes(a_true, -1, -2)
    phi = _rotation_vector_rad(delta)
    total = np.linalg.norm(phi, axis=-1)
    cos_b = np.clip(np.sum(a_est[..., 2, :] * a_true[..., 2, :], axis=-1), -1, 1)
    sin_b = np.linalg.norm(np.cross(a_est[..., 2, :], a_true[..., 2, :]), axis=-1)
    cross = np.arctan2(sin_b, cos_b)
    return total, cross, phi[..., 2]


# ---------------------------------------------------------------------------------------------
# The public functions: degrees in, degrees out (the radian forms above are the library's own)
# ---------------------------------------------------------------------------------------------

def _deg(x):
    return np.radians(np.asarray(x, dtype=np.float64))


def radec_to_vector(ra, dec):
    """ICRS unit vector ``(cos a cos d, sin a cos d, sin d)`` of right ascension ``ra`` and declination ``dec`` (degrees).

    Returns
    -------
    ndarray, shape (..., 3)
    """
    return _radec_to_vector_rad(_deg(ra), _deg(dec))


def vector_to_radec(v):
    """Right ascension in ``[0, 360)`` and declination (degrees) of vectors ``(..., 3)``."""
    ra, dec = _vector_to_radec_rad(v)
    return np.mod(np.degrees(ra), 360.0), np.degrees(dec)


def east_north(ra, dec):
    """Unit vectors (ICRS) of local east and north at ``ra``, ``dec`` (degrees); each shape ``(..., 3)``."""
    return _east_north_rad(_deg(ra), _deg(dec))


def radec_roll_to_dcm(ra, dec, roll):
    """Attitude matrix ``A`` (ICRS to camera) from boresight ``ra``, ``dec`` and ``roll``, all in degrees.

    Rows of the result: camera ``+x`` (image right), ``+y`` (image down) and
    ``+z`` (boresight) in ICRS.  With ``roll = 0`` image up is north and image
    left is east; ``roll`` turns image up from north toward east (see the
    README's "Roll").  Broadcasts over leading dimensions: shape ``(..., 3, 3)``.

    >>> a = radec_roll_to_dcm(83.8, -1.2, 30.0)
    >>> [round(float(v), 1) for v in dcm_to_radec_roll(a)]
    [83.8, -1.2, 30.0]
    """
    return _radec_roll_to_dcm_rad(_deg(ra), _deg(dec), _deg(roll))


def dcm_to_radec_roll(dcm):
    """Inverse of :func:`radec_roll_to_dcm`: ``(ra, dec, roll)`` in degrees.

    ``ra`` is in ``[0, 360)``, ``roll`` in ``[-180, 180]``.  At a pole ``ra`` is
    undefined; the returned triple then still reproduces ``dcm``.
    """
    ra, dec, roll = _dcm_to_radec_roll_rad(dcm)
    return np.mod(np.degrees(ra), 360.0), np.degrees(dec), np.degrees(roll)


def euler123_to_dcm(yaw, pitch, roll):
    """``A = R3(roll) R2(pitch) R1(yaw)`` (degrees): the roll/pitch/yaw of our reports."""
    return _euler123_to_dcm_rad(_deg(yaw), _deg(pitch), _deg(roll))


def dcm_to_euler123(dcm):
    """Inverse of :func:`euler123_to_dcm`: ``(yaw, pitch, roll)`` in degrees, ``pitch`` in ``[-90, 90]``."""
    return tuple(np.degrees(a) for a in _dcm_to_euler123_rad(dcm))


def elementary_rotation(axis: int, angle):
    """Passive rotation ``R_axis(angle)`` (``angle`` in degrees) about axis 1, 2 or 3; shape ``(..., 3, 3)``."""
    return _elementary_rotation_rad(axis, _deg(angle))


def propagate_attitude(dcm, rate_deg_s, dt):
    """Attitude after ``dt`` seconds at constant body rate ``rate_deg_s`` (degrees per second, camera axes)."""
    return _propagate_attitude_rad(dcm, _deg(rate_deg_s), dt)


def rotation_vector(dcm):
    """Rotation vector ``phi`` (degrees) of ``dcm``: ``A ~ I - [phi x]`` for small angles (phi in radians)."""
    return np.degrees(_rotation_vector_rad(dcm))


def attitude_error(dcm_estimate, dcm_truth):
    """Angle between two attitudes and its cross-boresight and roll parts, in degrees.

    Returns
    -------
    total, cross_boresight, roll : ndarray
        ``total`` is the angle of ``A_est A_true^T``; ``cross_boresight`` the
        angle between the two boresights; ``roll`` the signed rotation about the
        true boresight.
    """
    return tuple(np.degrees(a) for a in _attitude_error_rad(dcm_estimate, dcm_truth))
