"""What every identification algorithm shares: tolerances, verification, confidence, the result.

An algorithm proposes a few star correspondences (a pyramid, a voting
cluster, a label group).  Then, identically for all algorithms:

1. the attitude of the proposal is solved (SVD, determinant fixed);
2. every catalog star is projected with it and each image star is matched
   to the nearest catalog star within the match radius (uniquely);
3. the attitude is refined on all matches and the matching repeated;
4. the probability that the result is a coincidence is computed and the
   identification refused when it is above ``max_false_probability``.

The false-match probability combines Mortari's argument for the pyramid (the
expected number of catalog pyramids matching by chance, ``E = N^4 eps^5 ...``,
the LOST estimate of Mortari et al. 2004) with tetra3's test of the other stars:
the binomial probability that at least ``m`` of the ``n`` other image stars land
by chance within the match radius of one of the ``k`` catalog stars predicted in
the image.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

__all__ = ["IdentifyParams", "IdentifyResult", "Proposal", "tolerance_rad", "verify"]


@dataclass
class IdentifyParams:
    """Settings shared by all algorithms (angles in radians, pixels for the centroid noise)."""

    sigma_px: float | None = None
    tolerance_sigma: float = 4.0
    match_sigma: float = 5.0
    tolerance_arcsec: float | None = None
    margin_arcsec: float = 2.0
    match_radius_px: float | None = None
    max_stars: int = 12
    max_triads: int = 200
    min_matches: int = 4
    max_false_probability: float = 1e-6
    max_focal_error: float = 0.05
    extra: dict = field(default_factory=dict)


@dataclass
class Proposal:
    """An algorithm's hypothesis: image-star indices and catalog indices (into the database's star table)."""

    image: list
    catalog: list
    trials: int = 0
    extra: dict = field(default_factory=dict)


@dataclass
class IdentifyResult:
    """The ``identification`` section of a frame document."""

    status: str
    algorithm: str
    matches: list
    time_ms: float
    reason: str | None = None
    false_probability: float | None = None
    dcm: np.ndarray | None = None
    extra: dict = field(default_factory=dict)

    def section(self) -> dict:
        out = {"status": self.status, "algorithm": self.algorithm,
               "matches": [{"star": m["star"], "id": m["id"]} for m in self.matches],
               "time_ms": round(self.time_ms, 4)}
        if self.reason:
            out["reason"] = self.reason
        if self.false_probability is not None:
            out["false_match_probability"] = float(self.false_probability)
        if self.dcm is not None:
            from startrack.rotations import dcm_to_quaternion

            out["quaternion_estimate"] = dcm_to_quaternion(self.dcm).tolist()
        out.update(self.extra)
        return out


def centroid_sigma_px(stars: list, params: IdentifyParams) -> float:
    """1-sigma centroid noise: the option, else the median reported ``sigma_px``, else 0.5 px."""
    if params.sigma_px is not None:
        return float(params.sigma_px)
    reported = [s.get("sigma_px") for s in stars if isinstance(s.get("sigma_px"), (int, float))]
    reported = [v for v in reported if v is not None and math.isfinite(v) and v > 0]
    if reported:
        return float(max(0.05, min(2.0, np.median(reported) * 1.5)))
    return 0.5


def tolerance_rad(camera, sigma_px: float, params: IdentifyParams) -> float:
    """Half-width of the inter-star angle window.

    ``eps = k sqrt(2) sigma_px / f + margin``: an angle between two stars
    errs by the two centroid errors along their separation (``sqrt 2`` of one),
    ``k`` = ``tolerance_sigma`` (4 by default: a pyramid has six angles, and at
    3 sigma one in sixty true pyramids would be missed), plus a small margin
    for calibration.  ``tolerance_arcsec`` overrides it.
    """
    if params.tolerance_arcsec is not None:
        return math.radians(params.tolerance_arcsec / 3600.0)
    return params.tolerance_sigma * math.sqrt(2.0) * sigma_px / camera.focal_length_px + \
        math.radians(params.margin_arcsec / 3600.0)


def _binomial_sf(m: int, n: int, p: float) -> float:
    """P(X >= m) for X ~ Binomial(n, p)."""
    if m <= 0:
        return 1.0
    if m > n:
        return 0.0
    total = 0.0
    for k in range(m, n + 1):
        total += math.comb(n, k) * p**k * (1 - p) ** (n - k)
    return min(1.0, total)


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
    pred = star_vec[front] @ dcm.T
    if len(pred) == 0:
        return floor
    local = 10.0 * radius
    cos_local = math.cos(local)
    counts = np.sum((b_vectors[others] @ pred.T) >= cos_local, axis=1)
    p_each = np.minimum(1.0, counts * (radius / local) ** 2)
    return float(max(floor, np.mean(p_each)))


def _focal_scale(b_all, proposal, star_vec):
    """Least-squares ``s`` with ``theta_cat = s theta_mea`` over the proposal's pairs (None if < 3 stars)."""
    img, cat = list(proposal.image), list(proposal.catalog)
    if len(img) < 3:
        return None
    iu = np.triu_indices(len(img), 1)
    b = b_all[img]
    r = star_vec[cat]
    mea = np.arccos(np.clip((b @ b.T)[iu], -1.0, 1.0))
    ref = np.arccos(np.clip((r @ r.T)[iu], -1.0, 1.0))
    denom = float(mea @ mea)
    return float(ref @ mea / denom) if denom > 0 else None


def run(algorithm_name: str, propose, frame_stars: list, camera, db, params: IdentifyParams) -> IdentifyResult:
    """Common driver: vectors, tolerance, the algorithm's proposal, verification and timing."""
    t0 = time.perf_counter()
    n_all = len(frame_stars)
    if n_all < 3:
        return IdentifyResult("failed", algorithm_name, [], (time.perf_counter() - t0) * 1000,
                              f"{n_all} star(s): at least 3 are needed")
    xs = np.array([s["x"] for s in frame_stars], dtype=np.float64)
    ys = np.array([s["y"] for s in frame_stars], dtype=np.float64)
    b_all = camera.pixels_to_vectors(xs, ys)
    sigma_px = centroid_sigma_px(frame_stars, params)
    eps = tolerance_rad(camera, sigma_px, params)
    use = min(n_all, params.max_stars)
    proposal = propose(np.ascontiguousarray(b_all[:use]), db, eps, params, frame_stars[:use], camera)
    if proposal is None or len(proposal.image) == 0:
        reason = (proposal.extra.get("reason") if proposal is not None else None) or "no consistent star pattern found"
        return IdentifyResult("failed", algorithm_name, [], (time.perf_counter() - t0) * 1000, reason,
                              extra={"tolerance_arcsec": math.degrees(eps) * 3600})
    # The focal-length scale the proposal implies (angles scale as 1 / f): a
    # focal-length error is measured here, and the rest of the frame is matched
    # with the corrected focal length; the scale is then re-estimated from every
    # matched star and the matching repeated until it settles.
    scale = _focal_scale(b_all, proposal, db.star_vector)
    total_scale = 1.0
    if scale is not None and (abs(scale - 1.0) > params.max_focal_error or abs(scale - 1.0) < 5e-4):
        scale = None    # within noise (or beyond belief): keep the nominal focal length
    if scale is not None:
        total_scale = scale
        camera = camera.with_focal_length(camera.focal_length_px / scale)
        b_all = camera.pixels_to_vectors(xs, ys)
    matches, dcm, p_false, reason = verify(proposal, b_all, frame_stars, camera, db.star_vector, db.star_id, eps,
                                           sigma_px, params)
    for _ in range(3):
        if matches is None or scale is None or len(matches) < 3:
            break
        everything = Proposal([m["star"] for m in matches], [m["index"] for m in matches])
        step = _focal_scale(b_all, everything, db.star_vector)
        if step is None or abs(step - 1.0) < 1e-5 or abs(total_scale * step - 1.0) > params.max_focal_error:
            break
        total_scale *= step
        camera = camera.with_focal_length(camera.focal_length_px / step)
        b_all = camera.pixels_to_vectors(xs, ys)
        matches, dcm, p_false, reason = verify(proposal, b_all, frame_stars, camera, db.star_vector, db.star_id,
                                               eps, sigma_px, params)
    scale = total_scale if scale is not None else None
    elapsed = (time.perf_counter() - t0) * 1000
    extra = {"tolerance_arcsec": round(math.degrees(eps) * 3600, 3), "trials": int(proposal.trials)}
    if scale is not None:
        extra["focal_scale"] = round(float(scale), 7)
    extra.update(proposal.extra)
    if matches is None:
        return IdentifyResult("failed", algorithm_name, [], elapsed, reason, p_false, extra=extra)
    return IdentifyResult("ok", algorithm_name, matches, elapsed, None, p_false, dcm, extra)
