"""The identification API before issue 14's search driver, kept for :mod:`startrack.patterns` (blind solving).

:mod:`startrack.patterns` verifies its own candidates with the single-proposal
verification of startrack 0.x (``verify`` with a ``Proposal(trials=...)``) and
returns an ``IdentifyResult``.  This module keeps that contract unchanged
while the blind solver is rewritten; the identification algorithms use
:mod:`startrack.identify.base`.  ``IdentifyResult(...)`` now returns an
:class:`startrack.records.Identification` whose matches also answer
``m["star"]``, ``m["id"]`` and ``m["index"]``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from startrack.identify.params import IdentifyParams, tolerance_rad
from startrack.identify.verify import _binomial_sf
from startrack.records import Identification, ReasonCode, Status

__all__ = ["IdentifyParams", "IdentifyResult", "Proposal", "centroid_sigma_px", "tolerance_rad", "verify"]


class LegacyMatch(tuple):
    """``(star, id, index)`` that also answers ``m["star"]``, ``m["id"]``, ``m["index"]`` and ``m.star``, ``m.id``."""

    def __new__(cls, star: int, id: int, index: int = -1):  # noqa: A002 (the field's name)
        return super().__new__(cls, (int(star), int(id), int(index)))

    star = property(lambda self: tuple.__getitem__(self, 0))
    id = property(lambda self: tuple.__getitem__(self, 1))
    index = property(lambda self: tuple.__getitem__(self, 2))

    def __getitem__(self, key):
        if isinstance(key, str):
            return getattr(self, key)
        return tuple.__getitem__(self, key)

    def get(self, key, default=None):
        return getattr(self, key, default)


@dataclass
class LegacyIdentification(Identification):
    """The typed record plus the 0.x attributes ``dcm`` and ``extra`` (= ``details``)."""

    dcm: np.ndarray | None = None

    @property
    def extra(self) -> dict:
        return self.details

    @property
    def false_probability(self):
        return self.false_match_probability


def IdentifyResult(status, algorithm, matches, time_ms, reason=None, false_probability=None, dcm=None,  # noqa: N802
                   extra=None) -> Identification:
    """The 0.x result constructor, returning the typed record (``extra`` becomes ``details``)."""
    from startrack.rotations import dcm_to_quaternion

    extra = dict(extra or {})
    ok = str(status) == "ok"
    return LegacyIdentification(
        Status.OK if ok else Status.FAILED, algorithm,
        [LegacyMatch(m["star"], m["id"], m.get("index", -1)) for m in matches], time_ms=time_ms, reason=reason,
        reason_code=None if ok else ReasonCode.NO_PATTERN, false_match_probability=false_probability,
        focal_scale=extra.pop("focal_scale", None),
        quaternion_estimate=None if dcm is None else dcm_to_quaternion(dcm), details=extra, dcm=dcm)


@dataclass
class Proposal:
    """An algorithm's hypothesis: image-star indices and catalog indices (into the database's star table)."""

    image: list
    catalog: list
    trials: int = 0
    extra: dict = field(default_factory=dict)


def centroid_sigma_px(stars: list, params: IdentifyParams) -> float:
    """1-sigma centroid noise: the option, else the median reported ``sigma_px``, else 0.5 px."""
    if params.sigma_px is not None:
        return float(params.sigma_px)
    reported = [s.get("sigma_px") for s in stars if isinstance(s.get("sigma_px"), (int, float))]
    reported = [v for v in reported if v is not None and math.isfinite(v) and v > 0]
    if reported:
        return float(max(0.05, min(2.0, np.median(reported) * 1.5)))
    return 0.5


def _pyramid_chance(n_cat: int, eps: float, vecs) -> float:
    """Expected number of catalog pyramids matching four measured directions by chance (Mortari 2004; LOST)."""
    if len(vecs) < 3:
        # A lone pair: E = N (N - 1) / 2 * eps * sin(theta) chance pairs at that angle.
        th = math.acos(max(-1.0, min(1.0, float(vecs[0] @ vecs[1])))) if len(vecs) == 2 else math.pi / 2
        return float(n_cat * (n_cat - 1) / 2 * eps * math.sin(th))
    a, b, c = vecs[0], vecs[1], vecs[2]
    th_ij = math.acos(max(-1.0, min(1.0, float(a @ b))))

    def cross(p, q):
        return (p[1] * q[2] - p[2] * q[1], p[2] * q[0] - p[0] * q[2], p[0] * q[1] - p[1] * q[0])

    def inner(p, q, r):
        """Spherical angle at vertex p between the arcs to q and r."""
        u = cross(p, q)
        v = cross(p, r)
        nu = math.sqrt(u[0] ** 2 + u[1] ** 2 + u[2] ** 2)
        nv = math.sqrt(v[0] ** 2 + v[1] ** 2 + v[2] ** 2)
        if nu == 0 or nv == 0:
            return 0.0
        return math.acos(max(-1.0, min(1.0, (u[0] * v[0] + u[1] * v[1] + u[2] * v[2]) / (nu * nv))))

    phis = [inner(a, b, c), inner(b, a, c), inner(c, a, b)]
    if len(vecs) < 4:
        # A lone triangle: E = N^3 eps^3 sin(theta_ij) / (pi sin(phi_k)).
        return float(n_cat**3 * eps**3 * math.sin(th_ij) / (math.pi * max(math.sin(phis[2]), 1e-6)))
    denom = 2 * math.pi**2 * max(math.sin(phis[2]), 1e-6) * max(max(math.sin(p) for p in phis), 1e-6)
    return float(n_cat**4 * eps**5 * math.sin(th_ij) / denom)


def verify(proposal: Proposal, b_vectors: np.ndarray, stars: list, camera, star_vec, star_id, eps: float,
           sigma_px: float, params: IdentifyParams):
    """Attitude, remaining stars and confidence for a proposal; returns ``(matches, dcm, p_false, reason)``."""
    from startrack._kernels.attitude import quat_to_dcm, refine

    img = np.array(proposal.image, dtype=np.int64)
    cat = np.array(proposal.catalog, dtype=np.int64)
    if len(img) < 2:
        return None, None, None, "fewer than two stars identified"
    radius_px = params.match_radius_px if params.match_radius_px is not None else \
        max(1.0, params.match_sigma * sigma_px + math.radians(params.margin_arcsec / 3600.0) * camera.focal_length_px)
    radius = radius_px / camera.focal_length_px
    cos_fov = math.cos(math.radians(camera.max_off_axis_deg + 0.5))
    match, q, n_pred = refine(np.ascontiguousarray(b_vectors), star_vec, img, cat, cos_fov,
                              float(camera.focal_length_px), float(camera.cx), float(camera.cy),
                              float(camera.width), float(camera.height), float(camera.k1), float(camera.k2),
                              radius, 2)
    dcm = quat_to_dcm(q)
    n_matched = int(np.sum(match >= 0))
    # A proposal star agrees when the refined attitude puts its catalog star
    # within the match radius of it (whether or not the star-by-star matching,
    # which refuses ambiguous neighbours, kept it).
    predicted = star_vec[cat] @ dcm.T
    agree = int(np.sum(np.einsum("ij,ij->i", b_vectors[img], predicted) >= math.cos(radius)))
    if agree < min(len(img), params.min_matches):
        return None, dcm, None, "the proposal's stars do not agree with the refined attitude"
    if n_matched < params.min_matches and not (len(b_vectors) == 3 and n_matched == 3):
        return None, dcm, None, f"only {n_matched} stars matched (need {params.min_matches})"
    # Confidence: the chance that a pattern of the proposal's first four stars
    # (three when that is all) matches by coincidence, times the chance that the
    # other stars fall on predicted catalog stars by accident.
    core = img[:4]
    p_hit = _local_hit_probability(b_vectors, np.delete(np.arange(len(b_vectors)), core), star_vec, dcm, camera,
                                   radius, cos_fov, n_pred, radius_px)
    others = len(b_vectors) - len(core)
    core_pred = star_vec[cat[:4]] @ dcm.T
    core_agree = int(np.sum(np.einsum("ij,ij->i", b_vectors[core], core_pred) >= math.cos(radius)))
    e_pyr = _pyramid_chance(len(star_vec), eps, b_vectors[core])
    p_false = min(1.0, e_pyr * max(proposal.trials, 1)) * _binomial_sf(n_matched - core_agree, others, p_hit)
    if p_false > params.max_false_probability:
        return None, dcm, p_false, (f"false-match probability {p_false:.2g} above the limit "
                                    f"{params.max_false_probability:g}")
    out = [{"star": int(s), "id": int(star_id[c]), "index": int(c)} for s, c in enumerate(match) if c >= 0]
    return out, dcm, p_false, None


def _local_hit_probability(b_vectors, others, star_vec, dcm, camera, radius, cos_fov, n_pred, radius_px):
    """Mean chance that one of ``others`` lands within ``radius`` of a predicted catalog star by accident.

    The density of catalog stars is taken around each image star (within ten
    match radii), not over the whole image: in a cluster (the Hyades, the
    Pleiades) chance coincidences are far more likely than the field average
    suggests.  The global average is the floor.
    """
    floor = min(1.0, n_pred * math.pi * radius_px**2 / (camera.width * camera.height))
    if len(others) == 0:
        return floor
    front = star_vec @ dcm[2] > cos_fov
    # The rows by their indices: the same rows, ~10x faster than a boolean mask on ~5e4 rows.
    pred = star_vec[np.flatnonzero(front)] @ dcm.T
    if len(pred) == 0:
        return floor
    local = 10.0 * radius
    cos_local = math.cos(local)
    counts = np.sum((b_vectors[others] @ pred.T) >= cos_local, axis=1)
    p_each = np.minimum(1.0, counts * (radius / local) ** 2)
    return float(max(floor, np.mean(p_each)))
