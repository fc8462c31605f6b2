"""Attitude from vector pairs: Wahba's problem and its solvers (paper 000 Secs. 3.3.2-3.3.3).

Find the rotation ``A`` minimising ``L(A) = 1/2 sum a_i |b_i - A r_i|^2``
(paper 000 Eq. 15) for body (camera) unit vectors ``b_i`` (Eq. 13) and
reference (ICRS) unit vectors ``r_i`` (Eq. 14).  ``B = sum a_i b_i r_i^T``
(Eq. 19) is the attitude profile matrix and ``L(A) = lambda_0 - tr(A B^T)``
(Eq. 18).  Every solver returns a proper rotation (never a reflection).

Solvers (``METHODS``): ``q-method`` (Davenport; Eqs. 23-26), ``quest`` (Shuster
& Oh 1981), ``svd`` (Markley 1988, determinant sign fixed), ``foam`` (Markley
1993), ``esoq2`` (Mortari 1997), ``triad`` (Black 1964; two stars).

Uncertainty: the QUEST measurement model (Shuster & Oh 1981): each ``b_i``
errs perpendicular to itself with variance ``sigma_i^2`` per axis, and the
covariance of the small body-frame error rotation is
``P = [sum_i (I - b_i b_i^T) / sigma_i^2]^-1`` (rad^2); its x and y diagonal
entries are the cross-boresight (pitch/yaw) variances, z the roll variance.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from startrack.errors import BadInputError, ParameterError
from startrack.records import Attitude, ReasonCode, Status
from startrack.rotations import (
    _angles_deg_one,
    _boresight_east_north_one,
    _dcm_to_quaternion_one,
    dcm_to_euler123,
    dcm_to_quaternion,
    dcm_to_radec_roll,
)

__all__ = [
    "METHODS",
    "AttitudeResult",
    "covariance",
    "esoq2",
    "estimate_attitude",
    "foam",
    "profile_matrix",
    "q_method",
    "quest",
    "solve_wahba",
    "svd_solve",
    "triad",
    "wahba_loss",
    "wcs_header",
    "wcs_keywords",
]

METHODS = ("quest", "q-method", "svd", "foam", "esoq2", "triad")


def profile_matrix(body, reference, weights=None):
    """``B = sum a_i b_i r_i^T`` (paper 000 Eq. 19)."""
    b = np.asarray(body, dtype=np.float64)
    r = np.asarray(reference, dtype=np.float64)
    a = np.ones(len(b)) if weights is None else np.asarray(weights, dtype=np.float64)
    return np.einsum("i,ij,ik->jk", a, b, r)


def wahba_loss(dcm, body, reference, weights=None):
    """``L(A) = 1/2 sum a_i |b_i - A r_i|^2`` (paper 000 Eq. 15)."""
    b = np.asarray(body, dtype=np.float64)
    r = np.asarray(reference, dtype=np.float64)
    a = np.ones(len(b)) if weights is None else np.asarray(weights, dtype=np.float64)
    diff = b - r @ np.asarray(dcm).T
    return 0.5 * float(np.sum(a * np.sum(diff * diff, axis=1)))


def _k_matrix(bmat):
    """Davenport's ``K = [[S - sigma I, Z], [Z^T, sigma]]`` (paper 000 Eqs. 24-25)."""
    s = bmat + bmat.T
    sigma = np.trace(bmat)
    z = np.array([bmat[1, 2] - bmat[2, 1], bmat[2, 0] - bmat[0, 2], bmat[0, 1] - bmat[1, 0]])
    k = np.empty((4, 4))
    k[:3, :3] = s - sigma * np.eye(3)
    k[:3, 3] = z
    k[3, :3] = z
    k[3, 3] = sigma
    return k


def q_method(body, reference, weights=None):
    """Davenport's q-method: the eigenvector of ``K`` with the largest eigenvalue (Eqs. 23-26)."""
    from startrack.rotations import quaternion_to_dcm

    vals, vecs = np.linalg.eigh(_k_matrix(profile_matrix(body, reference, weights)))
    return quaternion_to_dcm(vecs[:, np.argmax(vals)])


def quest(body, reference, weights=None):
    """QUEST (Shuster & Oh 1981): Newton on the characteristic equation, sequential rotations near 180 deg."""
    from startrack._kernels.attitude import quat_to_dcm
    from startrack._kernels.attitude import quest as quest_kernel

    b = np.ascontiguousarray(body, dtype=np.float64)
    r = np.ascontiguousarray(reference, dtype=np.float64)
    w = np.ones(len(b)) if weights is None else np.ascontiguousarray(weights, dtype=np.float64)
    q, _ = quest_kernel(b, r, w)
    return quat_to_dcm(q)


def svd_solve(body, reference, weights=None):
    """Markley's SVD solution (1988): ``A = U diag(1, 1, det U det V) V^T`` -- never a reflection."""
    bmat = profile_matrix(body, reference, weights)
    u, _, vt = np.linalg.svd(bmat)
    d = np.linalg.det(u) * np.linalg.det(vt)
    return u @ np.diag([1.0, 1.0, d]) @ vt


def _adj(m):
    """Adjugate (transpose of the cofactor matrix) of a 3 x 3 matrix."""
    c = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            minor = np.delete(np.delete(m, i, axis=0), j, axis=1)
            c[i, j] = (-1) ** (i + j) * (minor[0, 0] * minor[1, 1] - minor[0, 1] * minor[1, 0])
    return c.T


def _upper_bound(body, reference, weights):
    """``sum a_i |b_i| |r_i|``: no eigenvalue of ``K`` exceeds it, so Newton started there finds the largest."""
    b = np.asarray(body, dtype=np.float64)
    r = np.asarray(reference, dtype=np.float64)
    return float(np.sum(weights * np.linalg.norm(b, axis=1) * np.linalg.norm(r, axis=1))) * (1 + 1e-12)


def foam(body, reference, weights=None):
    """FOAM (Markley 1993): ``lambda`` by Newton on
    ``(l^2 - |B|^2)^2 - 8 l det B - 4 |adj B|^2 = 0`` from ``sum a_i``, then
    ``A = [(kappa + |B|^2) B + l adj(B^T) - B B^T B] / zeta`` (Newton started
    at the upper bound ``sum a |b| |r|`` rather than ``sum a``) with
    ``kappa = (l^2 - |B|^2) / 2`` and ``zeta = kappa l - det B``."""
    bmat = profile_matrix(body, reference, weights)
    a = np.ones(len(body)) if weights is None else np.asarray(weights, dtype=np.float64)
    nb2 = float(np.sum(bmat * bmat))
    detb = float(np.linalg.det(bmat))
    adjb = _adj(bmat)
    nadj2 = float(np.sum(adjb * adjb))
    lam = _upper_bound(body, reference, a)
    for _ in range(50):
        psi = (lam * lam - nb2) ** 2 - 8 * lam * detb - 4 * nadj2
        dpsi = 4 * lam * (lam * lam - nb2) - 8 * detb
        if dpsi == 0:
            break
        step = psi / dpsi
        lam -= step
        if abs(step) < 1e-15 * max(1.0, abs(lam)):
            break
    kappa = 0.5 * (lam * lam - nb2)
    zeta = kappa * lam - detb
    # (Newton started above from the upper bound of lambda_max, see _upper_bound.)
    return ((kappa + nb2) * bmat + lam * adjb.T - bmat @ bmat.T @ bmat) / zeta


def esoq2(body, reference, weights=None):
    """ESOQ2 (Mortari 1997): the rotation axis from a cross product of two rows of
    ``M = t (S - (tr B + l) I) - Z Z^T`` (``t = tr B - l``), ``q ~ (t e, -Z.e)``.

    ``l`` is QUEST's largest eigenvalue.  ESOQ2 is singular for a rotation of
    zero angle, so the reference frame is first turned by 180 degrees about the
    axis that moves the attitude farthest from the identity (two columns of
    ``B`` negated; Markley's ESOQ2.1 device) and turned back at the end.
    """
    from startrack._kernels.attitude import _quest_core
    from startrack.rotations import quaternion_to_dcm

    bmat0 = profile_matrix(body, reference, weights)
    a = np.ones(len(body)) if weights is None else np.asarray(weights, dtype=np.float64)
    traces = [np.trace(bmat0), 2 * bmat0[0, 0] - np.trace(bmat0), 2 * bmat0[1, 1] - np.trace(bmat0),
              2 * bmat0[2, 2] - np.trace(bmat0)]
    axis = int(np.argmin(traces)) - 1        # -1: no rotation
    bmat = bmat0.copy()
    if axis >= 0:
        for col in range(3):
            if col != axis:
                bmat[:, col] = -bmat[:, col]
    lam = _quest_core(bmat, _upper_bound(body, reference, a))[4]
    s = bmat + bmat.T
    z = np.array([bmat[1, 2] - bmat[2, 1], bmat[2, 0] - bmat[0, 2], bmat[0, 1] - bmat[1, 0]])
    tr = np.trace(bmat)
    t = tr - lam
    m = t * (s - (tr + lam) * np.eye(3)) - np.outer(z, z)
    cands = [np.cross(m[1], m[2]), np.cross(m[2], m[0]), np.cross(m[0], m[1])]
    e = max(cands, key=lambda v: float(v @ v))
    e = e / np.linalg.norm(e)
    q = np.array([t * e[0], t * e[1], t * e[2], -float(z @ e)])
    q /= np.linalg.norm(q)
    if axis == 0:
        q = np.array([q[3], -q[2], q[1], -q[0]])
    elif axis == 1:
        q = np.array([q[2], q[3], -q[0], -q[1]])
    elif axis == 2:
        q = np.array([-q[1], q[0], q[3], -q[2]])
    return quaternion_to_dcm(q)


def triad(body, reference, weights=None):
    """TRIAD (Black 1964): the first pair exactly, the second's plane.

    ``M(v1, v2) = [v1, w, v1 x w]`` with ``w = v1 x v2 / |v1 x v2|`` and
    ``A = M(b1, b2) M(r1, r2)^T``.  Only the first two pairs are used; the more
    accurate star (largest weight) goes first.
    """
    b = np.asarray(body, dtype=np.float64)
    r = np.asarray(reference, dtype=np.float64)
    if len(b) < 2:
        raise BadInputError("triad", None, "needs two stars")
    order = [0, 1]
    if weights is not None and len(weights) >= 2 and weights[1] > weights[0]:
        order = [1, 0]

    def frame(v1, v2):
        w = np.cross(v1, v2)
        nw = np.linalg.norm(w)
        if nw < 1e-12:
            raise BadInputError("triad", None, "the two stars are parallel")
        w /= nw
        return np.column_stack([v1, w, np.cross(v1, w)])

    return frame(b[order[0]], b[order[1]]) @ frame(r[order[0]], r[order[1]]).T


_SOLVERS = {"quest": quest, "q-method": q_method, "svd": svd_solve, "foam": foam, "esoq2": esoq2, "triad": triad}


def solve_wahba(method: str, body, reference, weights=None):
    """Attitude matrix by ``method`` (one of :data:`METHODS`)."""
    if method not in _SOLVERS:
        raise ParameterError("method", f"unknown method {method!r}; choose from {', '.join(METHODS)}")
    return _SOLVERS[method](body, reference, weights)


def covariance(body, sigmas_rad):
    """QUEST measurement-model covariance ``P = [sum (I - b b^T) / sigma^2]^-1`` (rad^2, body frame)."""
    b = np.asarray(body, dtype=np.float64)
    s2 = np.asarray(sigmas_rad, dtype=np.float64) ** 2
    info = np.einsum("i,ijk->jk", 1.0 / s2, np.eye(3)[None, :, :] - b[:, :, None] * b[:, None, :])
    return np.linalg.inv(info)


def round_decimals(values, ndigits: int) -> list:
    """``[round(float(v), ndigits) for v in values]`` (Python's correctly rounded decimal rounding, ties to even), to
    the bit, without a decimal conversion per value.

    ``rint(v 10^n) / 10^n`` is that value: below 2^52 the half-integers are doubles, so rounding the product
    ``y = v 10^n`` (monotonic) never carries it across one, only onto one (a tie, or near enough: within a
    millionth, taken through ``round``); the nearest integer is then the exact product's, and dividing an integer
    below 2^53 by ``10^n`` (both exact doubles) gives the double nearest to the decimal number, as ``round`` does.
    The other values (near a tie, beyond 2^52, not finite) go through ``round``."""
    return _round_decimals_1d(np.asarray(values, dtype=np.float64).reshape(-1), ndigits)


def _round_decimals_1d(v, ndigits: int) -> list:
    """:func:`round_decimals` of a 1-D float64 array.

    When every ``|y|`` is below 2^52 (so no value is infinite: ``y - n`` warns of nothing) and every ``|y - n|``
    (exact: ``n`` is ``y``'s nearest integer) is more than two millionths from 0.5, every value is safe and
    ``n / 10^n`` is the answer (the old per-value mask would mark them all safe); otherwise each value is decided as
    :func:`round_decimals` says."""
    if not len(v):
        return []
    scale = 10.0 ** ndigits
    y = v * scale
    n = np.rint(y)
    if np.abs(y).max() < 2.0**52 and np.abs(y - n).max() < 0.5 - 2e-6:       # NaN fails both
        return (n / scale).tolist()
    with np.errstate(invalid="ignore"):
        safe = (np.abs(np.abs(y - n) - 0.5) > 1e-6) & (np.abs(y) < 2.0**52)
    out = (n / scale).tolist()
    if not safe.all():
        vals = v.tolist()
        for k in np.flatnonzero(~safe).tolist():
            out[k] = round(vals[k], ndigits)
    return out


@dataclass
class AttitudeResult:
    """The ``attitude`` section of a frame document."""

    status: str
    method: str
    dcm: np.ndarray | None = None
    reason: str | None = None
    used: list = field(default_factory=list)
    rejected: list = field(default_factory=list)
    residuals_arcsec: list = field(default_factory=list)
    loss: float | None = None
    cov_rad2: np.ndarray | None = None
    time_ms: float = 0.0
    variance_factor: float = 1.0
    reason_code: str | None = None
    bound: dict | None = None

    def section(self) -> dict:
        out = {"status": self.status, "method": self.method}
        if self.reason:
            out["reason"] = self.reason
        if self.reason_code:
            out["reason_code"] = str(self.reason_code)
        if self.dcm is None:
            if self.rejected:
                out["rejected"] = self.rejected
            return out
        # The numbers of one matrix in Python floats, the residuals converted once: the same bits
        # (tests/test_attitude_fast_paths.py).
        (ra, dec, roll, yaw, pitch, roll123), rows = self._angles()
        q = _dcm_to_quaternion_one(rows) if rows is not None else None
        arcsec = math.degrees(1.0) * 3600.0
        rounded, rms = self._residual_numbers()
        out.update(
            quaternion=q.tolist() if q is not None else [float(v) for v in dcm_to_quaternion(self.dcm)],
            dcm=rows if rows is not None else [[float(v) for v in row] for row in self.dcm],
            ra=ra, dec=dec, roll=roll,
            euler123_deg={"yaw": yaw, "pitch": pitch, "roll": roll123},
            n_stars=len(self.used), loss=self.loss,
            residuals=[{"star": s, "id": i, "residual_arcsec": r} for (s, i), r in zip(self.used, rounded)],
            rms_residual_arcsec=rms,
            time_ms=round(self.time_ms, 4),
            variance_factor=round(float(self.variance_factor), 4),
        )
        if self.cov_rad2 is not None:
            p = self.cov_rad2
            out["covariance_arcsec2"] = self._covariance_arcsec2().tolist()
            out["sigma_cross_boresight_arcsec"] = float(math.sqrt((p[0, 0] + p[1, 1]) / 2.0) * arcsec)
            out["sigma_pitch_yaw_arcsec"] = [float(math.sqrt(p[0, 0]) * arcsec), float(math.sqrt(p[1, 1]) * arcsec)]
            out["sigma_roll_arcsec"] = float(math.sqrt(p[2, 2]) * arcsec)
        if self.bound:
            out.update(self.bound)
        if self.rejected:
            out["rejected"] = self.rejected
        return out


    def record(self):
        """The :class:`~startrack.records.Attitude` of :meth:`section`: what ``from_section(Attitude,
        self.section(), validate=False)`` reads back, made without the section (a result with ``bound`` through
        it)."""
        if self.bound:
            from startrack.formats.sections import from_section

            return from_section(Attitude, self.section(), "attitude", validate=False)
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
        # The section's numbers in the section's arithmetic (test_attitude_record: every field's bits and type).
        (ra, dec, roll, yaw, pitch, roll123), rows = self._angles()
        arcsec = math.degrees(1.0) * 3600.0
        q = _dcm_to_quaternion_one(rows) if rows is not None else None
        att.quaternion = q if q is not None else np.array([float(v) for v in dcm_to_quaternion(self.dcm)],
                                                          dtype=np.float64)
        att.ra, att.dec, att.roll = ra, dec, roll
        att.euler123_deg = {"yaw": yaw, "pitch": pitch, "roll": roll123}
        att.n_stars = len(self.used)
        if self.loss is not None:
            att.loss = float(self.loss)
        rounded, rms = self._residual_numbers()
        att.residuals = [{"star": s, "id": i, "residual_arcsec": r} for (s, i), r in zip(self.used, rounded)]
        if rms is not None:
            att.rms_residual_arcsec = rms
        att.time_ms = float(round(self.time_ms, 4))
        att.variance_factor = float(round(float(self.variance_factor), 4))
        if self.cov_rad2 is not None:
            p = self.cov_rad2
            att.covariance_arcsec2 = self._covariance_arcsec2()
            att.sigma_cross_boresight_arcsec = float(math.sqrt((p[0, 0] + p[1, 1]) / 2.0) * arcsec)
            att.sigma_pitch_yaw_arcsec = np.array([float(math.sqrt(p[0, 0]) * arcsec),
                                                   float(math.sqrt(p[1, 1]) * arcsec)], dtype=np.float64)
            att.sigma_roll_arcsec = float(math.sqrt(p[2, 2]) * arcsec)
        if self.rejected:
            att.rejected = self.rejected
        att.details = {"dcm": rows if rows is not None else [[float(v) for v in row] for row in self.dcm]}
        return att

    def _residual_numbers(self):
        """``round_decimals(residuals_arcsec, 4)`` and ``float(np.sqrt(np.mean(np.square(residuals_arcsec))))`` (None
        without residuals), the list converted once when it converts to float64 by itself (np.square's own array)."""
        res = np.asarray(self.residuals_arcsec)
        if res.dtype == np.float64 and res.ndim == 1:
            rounded = _round_decimals_1d(res, 4)
            # np.mean(x) is np.add.reduce(x, axis=None) / len(x); np.sqrt and math.sqrt are correctly rounded.
            return rounded, (math.sqrt(float(np.add.reduce(np.square(res), axis=None)) / len(res))
                             if self.residuals_arcsec else None)
        rounded = round_decimals(self.residuals_arcsec, 4)
        return rounded, (float(np.sqrt(np.mean(np.square(self.residuals_arcsec)))) if self.residuals_arcsec else None)

    def _covariance_arcsec2(self):
        """``np.array([[float(v) * arcsec**2 for v in row] for row in cov_rad2])``: one product for a float64 3 x 3."""
        p = self.cov_rad2
        arcsec = math.degrees(1.0) * 3600.0
        if type(p) is np.ndarray and p.shape == (3, 3) and p.dtype == np.float64:
            return np.multiply(p, arcsec**2, order="C")
        return np.array([[float(v) * arcsec**2 for v in row] for row in p], dtype=np.float64)

    def _angles(self):
        """``(ra, dec, roll, yaw, pitch, roll123)`` of :func:`~startrack.rotations.dcm_to_radec_roll` and
        :func:`~startrack.rotations.dcm_to_euler123` as Python floats, and ``dcm.tolist()`` when the one-matrix path
        took it (a finite 3 x 3 float64 array; else None)."""
        d = self.dcm
        if type(d) is np.ndarray and d.shape == (3, 3) and d.dtype == np.float64:
            rows = d.tolist()
            angles = _angles_deg_one(d, rows)
            if angles is not None:
                return angles, rows
        ra, dec, roll = dcm_to_radec_roll(d)
        yaw, pitch, roll123 = dcm_to_euler123(d)
        return (float(ra), float(dec), float(roll), float(yaw), float(pitch), float(roll123)), None


def _fail(method, code, reason, t0, used=(), rejected=()):
    return AttitudeResult("failed", method, reason=reason, reason_code=code, used=list(used), rejected=list(rejected),
                          time_ms=(time.perf_counter() - t0) * 1000)


def estimate_attitude(body, reference, sigmas_rad=None, method: str = "quest", labels=None, gate: float = 13.8,
                      weighted: bool = True, max_variance_factor: float = 10.0) -> AttitudeResult:
    """Solve the attitude with outlier rejection and uncertainty, checking the identification it is given.

    Parameters
    ----------
    body, reference : array (n, 3)
        Camera-frame and ICRS unit vectors of the identified stars.
    sigmas_rad : array (n,), optional
        1-sigma line-of-sight error per star and axis (radians); default 1e-5.
    labels : list of (star index, catalog id), optional
        Carried into the result's residual list; a star index or a catalog id
        that appears twice makes the result failed (``duplicate_match``): a
        repeated measurement is not new information, and counting it would
        shrink the covariance.
    gate : float
        Chi-square gate on ``residual^2 / (k sigma)^2`` (2 degrees of freedom;
        13.8 is the 0.1% point).  The worst star beyond it is dropped and the
        attitude solved again, until all pass.  ``k >= 1``
        is a robust variance factor, ``k^2 = median(chi^2) / 1.386`` (the median
        of chi-square with 2 dof) when at least 5 stars remain and that ratio
        exceeds 2.5: when the given sigmas are clearly too small for the data
        (uncalibrated optics), all stars are scaled alike instead of being
        rejected one by one; the covariance is scaled by the same factor and
        ``k`` is reported.
    weighted : bool
        Weights ``a_i = 1 / sigma_i^2`` (the optimal QUEST weights); equal when false.
    max_variance_factor : float
        Largest ``k`` accepted: residuals more than this many times the
        centroid sigmas mean a wrong identification or camera, not noise.

    Returns
    -------
    AttitudeResult
        Status ``failed`` with a ``reason_code`` when the identification does
        not hold up: ``too_few_stars`` (fewer than 2), ``bad_input``
        (non-finite vectors or sigmas), ``duplicate_match``,
        ``degenerate_geometry`` (no two directions far enough apart, in units
        of the sigmas, to fix the roll), ``residuals_too_large`` (a star still
        fails the gate when no star can be dropped, fewer than half the stars
        agree, or ``k`` exceeds ``max_variance_factor``).
    """
    t0 = time.perf_counter()
    b = np.asarray(body, dtype=np.float64).reshape(-1, 3)
    r = np.asarray(reference, dtype=np.float64).reshape(-1, 3)
    n = len(b)
    given = labels is not None
    labels = list(labels) if given else [(i, None) for i in range(n)]
    sig = np.full(n, 1e-5) if sigmas_rad is None else np.asarray(sigmas_rad, dtype=np.float64).reshape(-1)
    if n < 2:
        return _fail(method, ReasonCode.TOO_FEW_STARS, f"{n} identified star(s): at least 2 are needed", t0)
    if len(r) != n or len(sig) != n or len(labels) != n:
        return _fail(method, ReasonCode.BAD_INPUT, "star vectors, references, sigmas and labels differ in length", t0)
    # b and r stacked: one finiteness check and one normalisation (row by row the same arithmetic).
    br = np.concatenate((b, r))
    if not (np.isfinite(br).all() and sig.min() > 0 and sig.max() < math.inf):      # a NaN fails both
        return _fail(method, ReasonCode.BAD_INPUT, "non-finite star vectors or uncertainties", t0)
    if not (math.isfinite(gate) and gate > 0 and math.isfinite(max_variance_factor) and max_variance_factor >= 1):
        raise ParameterError("gate", f"must be a positive number, got {gate!r}")
    # np.linalg.norm(x, axis=1, keepdims=True) of a real array is this expression.
    br = br / np.sqrt(np.add.reduce(br * br, axis=(1,), keepdims=True))
    b, r = br[:n], br[n:]
    # A star index or catalog id (None: unknown, not compared) given twice.  Labels made here (none given) are distinct
    # star indices without ids.
    repeated = False
    if given:
        stars = [s for s, _ in labels if s is not None]
        ids = [i for _, i in labels if i is not None]
        repeated = len(set(stars)) != len(stars) or len(set(ids)) != len(ids)
    if repeated:
        dup_s = sorted({s for s in stars if stars.count(s) > 1})[:5]
        dup_i = sorted({i for i in ids if ids.count(i) > 1})[:5]
        what = "; ".join(x for x in (f"star(s) {dup_s} matched more than once" if dup_s else "",
                                     f"catalog id(s) {dup_i} used more than once" if dup_i else "") if x)
        return _fail(method, ReasonCode.DUPLICATE_MATCH, f"the identification repeats itself: {what}", t0)
    if method == "quest":
        # The loop below in one numba kernel; a failure is replayed by the loop for its message.
        from startrack._kernels.attitude import gated_quest

        code, dcm, keep, nk, resid, factor2, w, rej, rej_resid, rej_chi2, n_rej, cov, loss = gated_quest(
            b, r, sig, bool(weighted), float(gate), max(2, math.ceil(n / 2)))
        if code == 0 and factor2 <= max_variance_factor**2:
            keep = keep[:nk]
            resid = resid[:nk]
            rejected = [{"star": labels[k][0], "id": labels[k][1],
                         "residual_arcsec": round(float(np.degrees(rr) * 3600), 3),
                         "reason": f"chi-square {c2:.1f} above the gate {gate:g}"}
                        for k, rr, c2 in zip(rej[:n_rej].tolist(), rej_resid[:n_rej].tolist(),
                                             rej_chi2[:n_rej].tolist(), strict=True)] if n_rej else []
            return _ok(method, dcm, labels, keep, rejected, resid, factor2, cov, float(loss), t0)
    keep = np.arange(n)
    rejected = []
    factor2 = 1.0
    while True:
        # Geometry: two directions at least 20 sigma apart (else the roll about them is unknown).
        kb, kr = b[keep], r[keep]
        sep_b = np.arccos(np.clip(kb @ kb.T, -1.0, 1.0))
        sep_r = np.arccos(np.clip(kr @ kr.T, -1.0, 1.0))
        scale = 20.0 * float(np.median(sig[keep]))
        if sep_b.max() < scale or sep_r.max() < scale:
            return _fail(method, ReasonCode.DEGENERATE_GEOMETRY,
                         f"the {len(keep)} stars are within {math.degrees(sep_b.max()) * 3600:.3g} arcsec of one "
                         "another: their directions do not fix the roll", t0, [labels[k] for k in keep], rejected)
        w = 1.0 / sig[keep] ** 2 if weighted else np.ones(len(keep))
        w = w / w.sum()
        dcm = solve_wahba(method, kb, kr, w)
        pred = kr @ dcm.T
        resid = np.arccos(np.clip(np.einsum("ij,ij->i", kb, pred), -1.0, 1.0))
        chi2 = (resid / sig[keep]) ** 2
        factor2 = float(np.median(chi2)) / 1.386 if len(keep) >= 5 else 1.0
        factor2 = factor2 if factor2 > 2.5 else 1.0   # only when the sigmas are clearly too small
        chi2 = chi2 / factor2
        worst = int(np.argmax(chi2))
        if chi2[worst] <= gate:
            break
        s, i = labels[keep[worst]]
        rej = {"star": s, "id": i, "residual_arcsec": round(float(np.degrees(resid[worst]) * 3600), 3),
               "reason": f"chi-square {chi2[worst]:.1f} above the gate {gate:g}"}
        # Dropping is allowed while at least 2 stars and at least half of those given remain.
        if len(keep) - 1 < max(2, math.ceil(n / 2)):
            return _fail(method, ReasonCode.RESIDUALS_TOO_LARGE,
                         f"star {s} (id {i}) is {rej['residual_arcsec']:.4g} arcsec from its catalog position "
                         f"(chi-square {chi2[worst]:.3g} above the gate {gate:g}) and {len(rejected)} of {n} stars "
                         "are already dropped: the identification does not hold up", t0,
                         [labels[k] for k in keep], rejected + [rej])
        rejected.append(rej)
        keep = np.delete(keep, worst)
    if factor2 > max_variance_factor**2:
        return _fail(method, ReasonCode.RESIDUALS_TOO_LARGE,
                     f"the residuals are {math.sqrt(factor2):.3g} times the centroid sigmas (limit "
                     f"{max_variance_factor:g}; rms {math.degrees(float(np.sqrt(np.mean(resid**2)))) * 3600:.4g} "
                     "arcsec): a wrong identification, catalog or camera", t0, [labels[k] for k in keep], rejected)
    return _ok(method, dcm, labels, keep, rejected, resid, factor2, covariance(b[keep], sig[keep]) * factor2,
               wahba_loss(dcm, b[keep], r[keep], w), t0)


def _ok(method, dcm, labels, keep, rejected, resid, factor2, cov, loss, t0):
    used = [labels[k] for k in keep.tolist()]
    out = AttitudeResult("ok", method, dcm, None, used, rejected, (np.degrees(resid) * 3600).tolist(), loss, cov,
                         (time.perf_counter() - t0) * 1000)
    out.variance_factor = math.sqrt(factor2)
    return out


#: The FITS zenithal projection (WCS Paper II, Calabretta and Greisen 2002, Sect. 5.1) of each of our
#: projections without distortion: their ``R_theta`` is ours, ``(180 / pi) g(theta)``.
FITS_PROJECTIONS = {"pinhole": "TAN", "equidistant": "ARC", "equisolid": "ZEA", "stereographic": "STG",
                    "orthographic": "SIN"}
ZPN_DEGREE = 9          # the highest power of the ZPN polynomial fitted to a distorted fisheye (odd powers)


def zpn_coefficients(camera):
    """``PV2_m`` of a FITS ZPN projection, ``R = (180 / pi) sum_m PV2_m theta^m`` (theta off-axis, radians).

    The equidistant projection with ``k1..k4`` (OpenCV's fisheye model) *is* a ZPN polynomial:
    ``r / f = theta + k1 theta^3 + k2 theta^5 + k3 theta^7 + k4 theta^9``, exactly.  Another distorted
    fisheye's ``g(theta_d(theta))`` is fitted by least squares in odd powers up to :data:`ZPN_DEGREE` over
    the angles the image sees (0 to its farthest corner, or the model's end); returns ``(coefficients,
    largest error in pixels over those angles)``.
    """
    from startrack.camera import projection_radius

    if camera.projection == "equidistant":
        return {1: 1.0, 3: float(camera.k1), 5: float(camera.k2), 7: float(camera.k3), 9: float(camera.k4)}, 0.0
    top = min(math.radians(camera.max_off_axis_deg), camera.max_theta)
    theta = np.linspace(0.0, top, 2001)
    target = projection_radius(camera.projection, camera.theta_distorted(theta))
    powers = list(range(1, ZPN_DEGREE + 1, 2))
    design = np.stack([theta ** m for m in powers], axis=1)
    coef, *_ = np.linalg.lstsq(design, target, rcond=None)
    err = float(np.max(np.abs(design @ coef - target))) * camera.focal_length_px
    return {m: float(c) for m, c in zip(powers, coef)}, err


def wcs_header(dcm, camera, sip_order: int = 5, mirrored: bool = False):
    """A FITS WCS for an attitude: TAN (with SIP terms when the camera has distortion) for a pinhole,
    ARC / ZEA / STG / SIN for the fisheye projections, ZPN for a distorted fisheye
    (:func:`zpn_coefficients`).

    Pixel ``(x, y)`` (0-based, ours) is FITS ``(x + 1, y + 1)``.  ``CRPIX`` is
    the principal point, ``CRVAL`` the boresight, and the ``CD`` matrix maps
    pixel offsets to the tangent plane: ``CD = (180 / pi) / f [[X.E, Y.E],
    [X.N, Y.N]]`` with ``X``, ``Y`` the camera axes in ICRS (rows of ``A``)
    and ``E``, ``N`` east and north at the boresight.  With distortion, SIP
    ``A``/``B`` (distorted -> undistorted, fitted on a grid) and ``AP``/``BP``
    (undistorted -> distorted, exact for the radial model) are added.
    ``mirrored``: the image is the camera's flipped about the principal point's column
    (:mod:`startrack.parity`), pixel ``(x, y)`` being the camera's ``(2 cx - x, y)``: ``CD``'s first
    column changes sign (so does its determinant) and the SIP terms of odd powers of ``u`` follow.
    Returns an ``astropy.io.fits.Header`` of :func:`wcs_keywords`.
    """
    from astropy.io import fits

    hdr = fits.Header()
    for key, value in wcs_keywords(dcm, camera, sip_order, mirrored).items():
        hdr[key] = value
    return hdr


def wcs_keywords(dcm, camera, sip_order: int = 5, mirrored: bool = False) -> dict:
    """The keywords of :func:`wcs_header` and their values, in order, as a dict (without astropy)."""
    a = np.asarray(dcm, dtype=np.float64)
    if a.shape == (3, 3):
        ra, dec, east, north = _boresight_east_north_one(a)
    else:
        from startrack.rotations import dcm_to_radec_roll, east_north

        ra, dec, _ = dcm_to_radec_roll(a)
        east, north = east_north(ra, dec)
    k = math.degrees(1.0) / camera.focal_length_px
    cd = k * np.array([[a[0] @ east, a[1] @ east], [a[0] @ north, a[1] @ north]])
    flip = -1.0 if mirrored else 1.0
    cd[:, 0] *= flip
    hdr = {}
    hdr["WCSAXES"] = 2
    # Every zenithal projection maps the off-axis angle theta to R(theta) along the same azimuth: the CD
    # matrix (pixels to degrees at the centre, 1 / f rad per pixel: g'(0) = 1) is the same for all.
    fisheye = camera.projection != "pinhole"
    if fisheye:
        code = "ZPN" if camera.has_distortion else FITS_PROJECTIONS[camera.projection]
        hdr["CTYPE1"] = f"RA---{code}"
        hdr["CTYPE2"] = f"DEC--{code}"
    else:
        hdr["CTYPE1"] = "RA---TAN-SIP" if camera.has_distortion else "RA---TAN"
        hdr["CTYPE2"] = "DEC--TAN-SIP" if camera.has_distortion else "DEC--TAN"
    hdr["CRPIX1"] = camera.cx + 1.0
    hdr["CRPIX2"] = camera.cy + 1.0
    hdr["CRVAL1"] = float(ra)
    hdr["CRVAL2"] = float(dec)
    hdr["CUNIT1"] = "deg"
    hdr["CUNIT2"] = "deg"
    hdr["CD1_1"], hdr["CD1_2"] = float(cd[0, 0]), float(cd[0, 1])
    hdr["CD2_1"], hdr["CD2_2"] = float(cd[1, 0]), float(cd[1, 1])
    hdr["RADESYS"] = "ICRS"
    hdr["IMAGEW"] = camera.width
    hdr["IMAGEH"] = camera.height
    if fisheye and camera.has_distortion:
        coef, _ = zpn_coefficients(camera)
        for m in range(max(coef) + 1):
            hdr[f"PV2_{m}"] = float(coef.get(m, 0.0))
    elif camera.has_distortion:
        f = camera.focal_length_px
        k1, k2 = camera.k1, camera.k2
        # Inverse (AP/BP): undistorted offsets (U, V) -> distorted: U (k1 r^2 + k2 r^4), r^2 = (U^2 + V^2) / f^2.
        ap = {(3, 0): k1 / f**2, (1, 2): k1 / f**2, (5, 0): k2 / f**4, (3, 2): 2 * k2 / f**4, (1, 4): k2 / f**4}
        bp = {(0, 3): k1 / f**2, (2, 1): k1 / f**2, (0, 5): k2 / f**4, (2, 3): 2 * k2 / f**4, (4, 1): k2 / f**4}
        # Forward (A/B): distorted (u, v) -> undistorted - distorted, least squares on a grid over the image.
        xs = np.linspace(-0.5, camera.width - 0.5, 41) - camera.cx
        ys = np.linspace(-0.5, camera.height - 0.5, 41) - camera.cy
        gu, gv = (g.ravel() for g in np.meshgrid(xs, ys))
        uu, vv = camera.undistort(gu / f, gv / f)
        terms = [(p, q) for p in range(sip_order + 1) for q in range(sip_order + 1 - p) if p + q >= 2]
        # The powers of u and v once each (not a power per term), and one least-squares solve for A and B together
        # (2 ms of a 27 degree frame's 6 ms solve was this fit, made again for each frame's fitted camera).
        upow, vpow = np.ones((sip_order + 1, gu.size)), np.ones((sip_order + 1, gv.size))
        for n in range(1, sip_order + 1):
            upow[n] = upow[n - 1] * gu
            vpow[n] = vpow[n - 1] * gv
        design = np.stack([upow[p] * vpow[q] for p, q in terms], axis=1)
        scale = np.max(np.abs(design), axis=0)
        coef, *_ = np.linalg.lstsq(design / scale, np.stack([uu * f - gu, vv * f - gv], axis=1), rcond=None)
        ca, cb = coef[:, 0] / scale, coef[:, 1] / scale
        hdr["A_ORDER"] = sip_order
        hdr["B_ORDER"] = sip_order
        # Mirrored: u -> -u, so A(u, v) -> -A(-u, v) and B(u, v) -> B(-u, v) (AP/BP alike).
        for (p, q), va, vb in zip(terms, ca, cb):
            hdr[f"A_{p}_{q}"] = float(va) * (flip ** (p + 1))
            hdr[f"B_{p}_{q}"] = float(vb) * (flip ** p)
        hdr["AP_ORDER"] = 5
        hdr["BP_ORDER"] = 5
        for (p, q), v in ap.items():
            hdr[f"AP_{p}_{q}"] = float(v) * (flip ** (p + 1))
        for (p, q), v in bp.items():
            hdr[f"BP_{p}_{q}"] = float(v) * (flip ** p)
    return hdr
