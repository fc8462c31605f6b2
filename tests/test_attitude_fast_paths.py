"""The per-frame attitude glue's fast paths give the old code's bits (issue 38).

``AttitudeResult.record()`` / ``section()`` and ``estimate_attitude``'s input checks were made cheaper (Python floats
for one matrix, batched ufunc calls, one stacked finiteness check and normalisation).  The oracles here are the code
as it was before (260aad2), kept verbatim below: every field's type and bits must be the same, over random
attitudes and star sets and the edge cases (roll near +-180, dec near +-90, gimbal lock, matrices with exact zeros,
2 stars, rejected stars, non-finite input).
"""
import math
import warnings

import numpy as np
import pytest

import startrack._kernels.attitude as kernels
import startrack.attitude as att_mod
from startrack.attitude import AttitudeResult, estimate_attitude, round_decimals
from startrack.records import Attitude, ReasonCode, Status
from startrack.rotations import (
    _angles_deg_one,
    _r2_r1,
    dcm_to_euler123,
    dcm_to_quaternion,
    dcm_to_radec_roll,
    euler123_to_dcm,
    quaternion_to_dcm,
    radec_roll_to_dcm,
    random_quaternions,
)

# ------------------------------------------------------------------------------------------------------------------
# The oracles: the code before the fast paths, verbatim but for the function names
# ------------------------------------------------------------------------------------------------------------------


def _section_reference(self) -> dict:
    out = {"status": self.status, "method": self.method}
    if self.reason:
        out["reason"] = self.reason
    if self.reason_code:
        out["reason_code"] = str(self.reason_code)
    if self.dcm is None:
        if self.rejected:
            out["rejected"] = self.rejected
        return out
    ra, dec, roll = dcm_to_radec_roll(self.dcm)
    yaw, pitch, roll123 = dcm_to_euler123(self.dcm)
    arcsec = math.degrees(1.0) * 3600.0
    out.update(
        quaternion=[float(v) for v in dcm_to_quaternion(self.dcm)],
        dcm=[[float(v) for v in row] for row in self.dcm],
        ra=float(ra), dec=float(dec), roll=float(roll),
        euler123_deg={"yaw": float(yaw), "pitch": float(pitch), "roll": float(roll123)},
        n_stars=len(self.used), loss=self.loss,
        residuals=[{"star": s, "id": i, "residual_arcsec": r}
                   for (s, i), r in zip(self.used, _round_decimals_reference(self.residuals_arcsec, 4))],
        rms_residual_arcsec=float(np.sqrt(np.mean(np.square(self.residuals_arcsec)))) if self.residuals_arcsec
        else None,
        time_ms=round(self.time_ms, 4),
        variance_factor=round(float(self.variance_factor), 4),
    )
    if self.cov_rad2 is not None:
        p = self.cov_rad2
        out["covariance_arcsec2"] = [[float(v) * arcsec**2 for v in row] for row in p]
        out["sigma_cross_boresight_arcsec"] = float(math.sqrt((p[0, 0] + p[1, 1]) / 2.0) * arcsec)
        out["sigma_pitch_yaw_arcsec"] = [float(math.sqrt(p[0, 0]) * arcsec), float(math.sqrt(p[1, 1]) * arcsec)]
        out["sigma_roll_arcsec"] = float(math.sqrt(p[2, 2]) * arcsec)
    if self.bound:
        out.update(self.bound)
    if self.rejected:
        out["rejected"] = self.rejected
    return out


def _record_reference(self):
    if self.bound:
        from startrack.formats.sections import from_section

        return from_section(Attitude, _section_reference(self), "attitude", validate=False)
    att = Attitude(Status(self.status), self.method)
    if self.reason:
        att.reason = self.reason
    if self.reason_code:
        code = str(self.reason_code)
        try:
            att.reason_code = ReasonCode(code)
        except ValueError:
            att.reason_code = code
    if self.dcm is None:
        if self.rejected:
            att.rejected = self.rejected
        return att
    ra, dec, roll = dcm_to_radec_roll(self.dcm)
    yaw, pitch, roll123 = dcm_to_euler123(self.dcm)
    arcsec = math.degrees(1.0) * 3600.0
    att.quaternion = np.array([float(v) for v in dcm_to_quaternion(self.dcm)], dtype=np.float64)
    att.ra, att.dec, att.roll = float(ra), float(dec), float(roll)
    att.euler123_deg = {"yaw": float(yaw), "pitch": float(pitch), "roll": float(roll123)}
    att.n_stars = len(self.used)
    if self.loss is not None:
        att.loss = float(self.loss)
    att.residuals = [{"star": s, "id": i, "residual_arcsec": r}
                     for (s, i), r in zip(self.used, _round_decimals_reference(self.residuals_arcsec, 4))]
    if self.residuals_arcsec:
        att.rms_residual_arcsec = float(np.sqrt(np.mean(np.square(self.residuals_arcsec))))
    att.time_ms = float(round(self.time_ms, 4))
    att.variance_factor = float(round(float(self.variance_factor), 4))
    if self.cov_rad2 is not None:
        p = self.cov_rad2
        att.covariance_arcsec2 = np.array([[float(v) * arcsec**2 for v in row] for row in p], dtype=np.float64)
        att.sigma_cross_boresight_arcsec = float(math.sqrt((p[0, 0] + p[1, 1]) / 2.0) * arcsec)
        att.sigma_pitch_yaw_arcsec = np.array([float(math.sqrt(p[0, 0]) * arcsec),
                                               float(math.sqrt(p[1, 1]) * arcsec)], dtype=np.float64)
        att.sigma_roll_arcsec = float(math.sqrt(p[2, 2]) * arcsec)
    if self.rejected:
        att.rejected = self.rejected
    att.details = {"dcm": [[float(v) for v in row] for row in self.dcm]}
    return att


def _round_decimals_reference(values, ndigits):
    v = np.asarray(values, dtype=np.float64).reshape(-1)
    scale = 10.0 ** ndigits
    y = v * scale
    n = np.rint(y)
    with np.errstate(invalid="ignore"):
        safe = (np.abs(np.abs(y - n) - 0.5) > 1e-6) & (np.abs(y) < 2.0**52)
    out = (n / scale).tolist()
    if not safe.all():
        vals = v.tolist()
        for k in np.flatnonzero(~safe).tolist():
            out[k] = round(vals[k], ndigits)
    return out


def _bad_input_reference(b, r, sig):
    """estimate_attitude's old finiteness test (True: fails with bad_input)."""
    return not (np.all(np.isfinite(b)) and np.all(np.isfinite(r)) and np.all(np.isfinite(sig)) and np.all(sig > 0))


# ------------------------------------------------------------------------------------------------------------------


def _same(x, y, where="") -> None:
    """The same types and bits, recursively (floats by their bits: NaN and the sign of zero count; arrays by dtype,
    shape, bytes and C order)."""
    assert type(x) is type(y), (where, type(x), type(y))
    if isinstance(x, np.ndarray):
        assert x.dtype == y.dtype and x.shape == y.shape and x.tobytes() == y.tobytes(), where
        assert x.flags.c_contiguous == y.flags.c_contiguous and x.flags.writeable == y.flags.writeable, where
    elif isinstance(x, (float, np.floating)):
        assert np.float64(x).tobytes() == np.float64(y).tobytes(), (where, x, y)
    elif isinstance(x, dict):
        assert list(x) == list(y), where
        for k in x:
            _same(x[k], y[k], f"{where}.{k}")
    elif isinstance(x, (list, tuple)):
        assert len(x) == len(y), where
        for k, (u, v) in enumerate(zip(x, y)):
            _same(u, v, f"{where}[{k}]")
    elif hasattr(x, "__dataclass_fields__"):
        for k in x.__dataclass_fields__:
            _same(getattr(x, k), getattr(y, k), f"{where}.{k}")
    else:
        assert x == y, (where, x, y)


def _check_result(res):
    _same(res.record(), _record_reference(res), "record")
    _same(res.section(), _section_reference(res), "section")


def _edge_dcms(rng):
    """Attitudes at the edges of the angle conversions, and a few matrices that are not rotations."""
    out = [np.eye(3), -np.eye(3), np.diag([1.0, -1.0, -1.0]), np.diag([-1.0, 1.0, -1.0]), np.diag([-1.0, -1.0, 1.0]),
           np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]]),
           np.array([[0.0, 0.0, -1.0], [0.0, -1.0, 0.0], [-1.0, 0.0, 0.0]]), np.zeros((3, 3)),
           np.full((3, 3), -0.0), np.diag([-0.0, -1.0, -0.0])]
    for roll in (180.0, -180.0, 179.999999999, -179.999999999, np.nextafter(180.0, 0.0), 0.0, -0.0, 90.0):
        for dec in (90.0, -90.0, 89.99999999, -89.99999999, 0.0, 45.0):
            for ra in (0.0, 359.9999999999, 180.0, 1e-12):
                out.append(radec_roll_to_dcm(ra, dec, roll))
    for pitch in (90.0, -90.0, 89.9999999, -89.9999999, 0.0, -0.0):
        for yaw, roll in ((0.0, 0.0), (10.0, 20.0), (-30.0, 180.0), (180.0, -180.0), (-0.0, 179.9999999)):
            out.append(euler123_to_dcm(yaw, pitch, roll))
    for axis in range(3):
        for ang in (0.0, 90.0, 180.0, 270.0, -90.0, 1e-9, 179.99999):
            from startrack.rotations import elementary_rotation

            out.append(elementary_rotation(axis + 1, ang))
    for _ in range(300):
        out.append(rng.normal(size=(3, 3)) * 10.0 ** rng.uniform(-200, 100))    # not rotations: same arithmetic
        m = quaternion_to_dcm(random_quaternions(1, rng)[0])
        m[rng.random((3, 3)) < 0.3] = 0.0                                       # exact zeros and their signs
        m[rng.random((3, 3)) < 0.2] *= -0.0
        out.append(m)
    return [np.ascontiguousarray(m, dtype=np.float64) for m in out]


def test_one_matrix_angles_are_the_public_functions_to_the_bit():
    """_angles_deg_one: dcm_to_radec_roll's and dcm_to_euler123's numbers to the bit (random rotations, the edges,
    exact zeros of either sign, non-rotations); None (the public functions decide) for NaN, inf and huge entries."""
    rng = np.random.default_rng(38)
    cases = [quaternion_to_dcm(q) for q in random_quaternions(3000, rng)] + _edge_dcms(rng)
    for a in cases:
        got = _angles_deg_one(a, a.tolist())
        want = [float(v) for v in (*dcm_to_radec_roll(a), *dcm_to_euler123(a))]
        assert got is not None
        _same(list(got), want, repr(a.tolist()))
    for bad in (np.nan, np.inf, -np.inf, 1e200):
        a = np.eye(3)
        a[1, 2] = bad
        assert _angles_deg_one(a, a.tolist()) is None


def test_euler_rotations_product_is_numpys_matmul():
    """_r2_r1: the product R2(pitch) R1(yaw) written out entry by entry is numpy's matmul of the two to the bit,
    signs of zero included (random angles, 0, -0, +-pi/2, pi, tiny angles: products that underflow, whose sign of
    zero a fused multiply-add decides, are numpy's own)."""
    rng = np.random.default_rng(7)
    special = [0.0, -0.0, math.pi / 2, -math.pi / 2, math.pi, -math.pi, 1e-300, -1e-300, 1e-170, -1e-170, 1e-160,
               5e-324, 3.0]
    angles = [(p, y) for p in special for y in special] + [tuple(rng.uniform(-math.pi, math.pi, 2)) for _ in range(3000)]
    for pitch, yaw in angles:
        pitch = max(-math.pi / 2, min(math.pi / 2, pitch))
        sp, sy = np.sin((pitch, yaw)).tolist()
        cp, cy = np.cos((pitch, yaw)).tolist()
        r2 = np.array([[cp, 0.0, -sp], [0.0, 1.0, 0.0], [sp, 0.0, cp]])
        r1 = np.array([[1.0, 0.0, 0.0], [0.0, cy, sy], [0.0, -sy, cy]])
        assert _r2_r1(cp, sp, cy, sy).tobytes() == (r2 @ r1).tobytes(), (pitch, yaw)


def _star_set(rng, a, k, outlier=False, spread_deg=6.0):
    """k catalog directions within spread_deg of the boresight of a and their camera vectors with 1e-5 rad noise."""
    bore = a[2]
    t = np.cross(bore, [1.0, 0.0, 0.0] if abs(bore[0]) < 0.9 else [0.0, 1.0, 0.0])
    t /= np.linalg.norm(t)
    u = np.cross(bore, t)
    off = np.radians(rng.uniform(-spread_deg, spread_deg, (k, 2)))
    r = bore + off[:, :1] * t + off[:, 1:] * u
    r /= np.linalg.norm(r, axis=1, keepdims=True)
    b = r @ a.T + rng.normal(scale=1e-5, size=(k, 3))
    if outlier and k > 3:
        b[int(rng.integers(k))] += 3e-3
    return b, r


def test_records_of_solved_frames_are_the_old_records_to_the_bit():
    """record() and section() of estimate_attitude's results (QUEST and SVD; 2 to 60 stars; rejected stars;
    attitudes at the edges) and of hand-made results are the old code's, every field's type and bits."""
    rng = np.random.default_rng(11)
    dcms = [quaternion_to_dcm(q) for q in random_quaternions(150, rng)]
    dcms += [m for m in _edge_dcms(rng) if abs(np.linalg.det(m) - 1.0) < 1e-9]
    results = []
    n_ok = n_rej = 0
    for j, a in enumerate(dcms):
        k = 2 if j % 7 == 0 else int(rng.integers(3, 61))
        b, r = _star_set(rng, a, k, outlier=j % 3 == 0)
        method = "svd" if j % 5 == 0 else "quest"
        res = estimate_attitude(b, r, np.full(k, 1e-5), method, [(i, 1000 + i) for i in range(k)])
        results.append(res)
        n_ok += res.status == "ok"
        n_rej += bool(res.rejected)
    assert n_ok > 0.8 * len(dcms) and n_rej > 20
    # Hand-made results: no residuals, a covariance not of float64 or not C-ordered, residuals as ints, float32,
    # None, a failed result, a bound, a dcm as a list or with a NaN.
    a = radec_roll_to_dcm(10.0, -89.9999, 179.99999)
    cov = np.diag([1e-10, 2e-10, 5e-9])
    used = [(0, 1), (1, 2), (2, 3)]
    results += [
        AttitudeResult("ok", "quest", a, None, [], [], [], None, None),
        AttitudeResult("ok", "quest", a, None, used, [], [0.1, 2.5, 1e-7], 0.5, np.asfortranarray(cov + 1e-12)),
        AttitudeResult("ok", "quest", a, None, used, [], [1, 2, 3], 0.5, cov.astype(np.float32)),
        AttitudeResult("ok", "quest", a, None, used, [], [np.float32(0.1), np.float32(0.2), np.float32(0.3)], 0.5,
                       cov),
        AttitudeResult("ok", "quest", a, None, used, [], [0.00005, 0.00015, 2.5e-5], 0.5, cov[::-1, ::-1]),
        AttitudeResult("ok", "quest", a.tolist(), None, used, [], [0.1, math.nan, math.inf], 0.5, cov),
        AttitudeResult("ok", "quest", a, None, used, [], [0.1, 0.2, 0.3], 0.5, cov, bound={"crb_roll_arcsec": 1.5}),
        AttitudeResult("failed", "quest", reason="x", reason_code="not_a_code"),
        AttitudeResult("failed", "quest", reason="", reason_code=ReasonCode.TOO_FEW_STARS, rejected=[{"star": 1}]),
    ]
    nan_dcm = a.copy()
    nan_dcm[0, 0] = math.nan
    results.append(AttitudeResult("ok", "quest", nan_dcm, None, used, [], [0.1, 0.2, 0.3], 0.5, cov))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)        # the NaN matrix's, in both
        for res in results:
            _check_result(res)
    # A residual of None (np.square) or a covariance as lists (p[0, 0]): both fail alike.
    for res in (AttitudeResult("ok", "quest", a, None, used, [], [0.1, None, 0.3], 0.5, cov),
                AttitudeResult("ok", "quest", a, None, used, [], [0.1, 0.2, 0.3], 0.5, cov.tolist())):
        for fn in (res.record, lambda: _record_reference(res)):    # noqa: B023 (called at once)
            with pytest.raises(TypeError):
                fn()


def test_rms_and_rounding_of_residual_lists_of_every_length():
    rng = np.random.default_rng(3)
    for n in range(1, 140):
        values = (rng.random(n) * 10.0 ** rng.uniform(-3, 3, n)).tolist()
        res = AttitudeResult("ok", "quest", np.eye(3), None, [(i, i) for i in range(n)], [], values, 0.1, None)
        _same(res.record(), _record_reference(res))


def test_round_decimals_fast_test_is_the_old_mask():
    """round_decimals' whole-array test (no value near a tie, none infinite or beyond 2^52) gives the old per-value
    answer, warns of nothing for infinite values, and takes no decimal conversion when every value is safe."""
    rng = np.random.default_rng(5)
    near = [k + 0.5 + d for k in range(50) for d in (0.0, 1e-7, -1e-7, 1.5e-6, -1.5e-6, 2.5e-6, -2.5e-6, 1e-3)]
    for values in ([], [0.0], [-0.0], near, (rng.random(5000) * 1e4).tolist(), [1.0, math.inf], [math.nan, 2.0],
                   [2.0**53, 1.0], (np.array(near) / 1e4).tolist()):
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            got = round_decimals(values, 4)
        _same(got, _round_decimals_reference(values, 4))


def _bodies(rng, k):
    a = quaternion_to_dcm(random_quaternions(1, rng)[0])
    b, r = _star_set(rng, a, k)
    return b * rng.uniform(0.5, 2.0, (k, 1)), r * rng.uniform(0.5, 2.0, (k, 1))      # not unit: normalised


def test_estimate_attitude_normalises_and_checks_as_before(monkeypatch):
    """The kernel and the solvers get the old normalisation's bits (b / np.linalg.norm(b, axis=1)), whatever the
    number of stars; the results are the old kernel call's."""
    seen = []
    kernel = kernels.gated_quest

    def spy(b, r, *args):
        seen.append((b.copy(), r.copy()))
        return kernel(b, r, *args)

    monkeypatch.setattr(kernels, "gated_quest", spy)
    solve = att_mod.solve_wahba

    def spy_solve(method, b, r, w):
        seen.append((b.copy(), r.copy()))
        return solve(method, b, r, w)

    monkeypatch.setattr(att_mod, "solve_wahba", spy_solve)
    rng = np.random.default_rng(21)
    for k in list(range(2, 40)) + [75, 200]:
        b, r = _bodies(rng, k)
        sig = rng.uniform(5e-6, 2e-5, k)
        for method in ("quest", "svd"):
            seen.clear()
            res = estimate_attitude(b, r, sig, method)
            bn = b / np.linalg.norm(b, axis=1, keepdims=True)
            rn = r / np.linalg.norm(r, axis=1, keepdims=True)
            assert seen[0][0].tobytes() == bn.tobytes() and seen[0][1].tobytes() == rn.tobytes(), (k, method)
            if method == "quest" and res.status == "ok" and not res.rejected:
                want = kernel(bn, rn, sig, True, 13.8, max(2, math.ceil(k / 2)))
                assert res.dcm.tobytes() == want[1].tobytes() and res.cov_rad2.tobytes() == want[11].tobytes()


@pytest.mark.parametrize("where", ["body", "reference", "sigma"])
@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf, 0.0, -1e-5])
def test_estimate_attitude_bad_input_as_before(where, bad):
    """Non-finite vectors and non-finite or non-positive sigmas fail with bad_input as before, warning of nothing
    (also when the gate is bad too: the input is checked first); zero vector entries and sigmas are fine."""
    rng = np.random.default_rng(2)
    b, r = _bodies(rng, 6)
    sig = np.full(6, 1e-5)
    arr = {"body": b, "reference": r, "sigma": sig}[where]
    if where == "sigma":
        arr[3] = bad
    else:
        arr[3, 1] = bad
    expect_bad = _bad_input_reference(b, r, sig)
    assert expect_bad == (where == "sigma" or not math.isfinite(bad))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        res = estimate_attitude(b, r, sig)
        if expect_bad:
            assert res.status == "failed" and res.reason_code == ReasonCode.BAD_INPUT
            assert res.reason == "non-finite star vectors or uncertainties"
            assert estimate_attitude(b, r, sig, gate=-1.0).reason_code == ReasonCode.BAD_INPUT
        else:
            assert res.reason_code != ReasonCode.BAD_INPUT


def test_wcs_boresight_east_north_are_the_public_functions_to_the_bit():
    """wcs_keywords' one-matrix path (_boresight_east_north_one): ra, dec of dcm_to_radec_roll and east, north of
    east_north at them, to the bit and of the same types and shapes, on random rotations and at the poles, ra 0 and
    360, and the axis flips."""
    from startrack.rotations import (
        _boresight_east_north_one,
        dcm_to_radec_roll,
        east_north,
        quaternion_to_dcm,
        radec_roll_to_dcm,
        random_quaternions,
    )

    mats = [quaternion_to_dcm(q) for q in random_quaternions(20000, np.random.default_rng(5))]
    mats += [radec_roll_to_dcm(ra, dec, roll) for ra in (0.0, 90.0, 180.0, 359.9999999, 1e-12)
             for dec in (-90.0, -89.9999999, 0.0, 45.0, 90.0) for roll in (0.0, 180.0, -90.0)]
    mats += [np.eye(3), -np.eye(3), np.diag([1.0, -1.0, -1.0])]
    for a in mats:
        a = np.ascontiguousarray(a, dtype=np.float64)
        ra, dec, _ = dcm_to_radec_roll(a)
        east, north = east_north(ra, dec)
        got = _boresight_east_north_one(a)
        for want, value in zip((ra, dec, east, north), got, strict=True):
            assert type(value) is type(want) and np.shape(value) == np.shape(want)
            assert np.asarray(value).tobytes() == np.asarray(want).tobytes(), a


def test_duplicate_labels_are_found_as_by_the_lists_without_none():
    """estimate_attitude's repeated-label test decides and words it as the lists of the star indices and ids that are
    not None say: random labels with None, repeats and both (and none given: no repeat)."""
    rng = np.random.default_rng(11)
    a = np.eye(3)
    for _ in range(400):
        n = int(rng.integers(2, 9))
        r = rng.normal(size=(n, 3))
        r /= np.linalg.norm(r, axis=1, keepdims=True)
        pool_s = [None, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9][: int(rng.integers(2, 12))]
        pool_i = [None, 100, 101, 102, 103, 104, 105, 106, 107, 108][: int(rng.integers(2, 11))]
        labels = [(pool_s[int(rng.integers(len(pool_s)))], pool_i[int(rng.integers(len(pool_i)))]) for _ in range(n)]
        stars = [s for s, _ in labels if s is not None]
        ids = [i for _, i in labels if i is not None]
        want = len(set(stars)) != len(stars) or len(set(ids)) != len(ids)
        res = estimate_attitude(r @ a.T, r, np.full(n, 1e-5), labels=labels)
        assert (res.reason_code == ReasonCode.DUPLICATE_MATCH) == want, labels
        if want:
            dup_s = sorted({s for s in stars if stars.count(s) > 1})[:5]
            dup_i = sorted({i for i in ids if ids.count(i) > 1})[:5]
            assert (f"star(s) {dup_s}" in res.reason) == bool(dup_s) and (f"id(s) {dup_i}" in res.reason) == bool(dup_i)
    # No labels: the ones estimate_attitude makes (each star its own index, no id) repeat nothing.
    r = rng.normal(size=(6, 3))
    r /= np.linalg.norm(r, axis=1, keepdims=True)
    assert estimate_attitude(r, r, np.full(6, 1e-5)).status == "ok"
