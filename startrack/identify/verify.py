"""Verification of one proposal and the probability that it is a coincidence (the same for every algorithm).

For a proposal, identically for every algorithm (:func:`verify`, :func:`_verify_with_focal`; one kernel
call for a distortion-free camera, :func:`_verify_fused`):

1. solve the attitude of the proposal (QUEST) and measure the focal-length scale it implies;
2. project every database star with it and match every detection to the nearest predicted star
   within the detection's own match radius (``match_sigma`` of its centroid sigma; one-to-one,
   ambiguous neighbours refused), refine the attitude on all matches and match again; then every
   match must be unambiguous within its radius (a close pair of catalog stars with two detections is
   named by position and magnitude only when the other assignment is clearly worse, else refused),
   magnitude-consistent (outside the proposal) and agree with the attitude the *other* matches give
   (leave one out: a proposal whose fit bent to take a wrong star is rejected);
3. compute the probability that the result is a coincidence (:func:`false_match_probability`); the
   driver (:mod:`startrack.identify.driver`) accepts the first proposal whose probability,
   *multiplied by the number of patterns and proposals tried* (look-elsewhere), is below
   ``max_false_probability``.

The kernels are :mod:`startrack._kernels.verify`'s (and :mod:`startrack._kernels.focal`'s,
:mod:`startrack._kernels.sky_index`'s).
"""
from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from startrack.identify.params import IdentifyParams
from startrack.records import Match, ReasonCode

if TYPE_CHECKING:
    from startrack.identify.algorithm import Proposal

__all__ = ["AMBIGUITY_CHI2", "MAG_GATE", "MAG_SIGMA_FLOOR", "false_match_probability", "pattern_chance", "verify"]


def _binomial_sf(m: int, n: int, p: float) -> float:
    """P(X >= m) for X ~ Binomial(n, p)."""
    if m <= 0:
        return 1.0
    if m > n:
        return 0.0
    total = 0.0
    if n <= 1000:
        for k in range(m, n + 1):
            total += math.comb(n, k) * p**k * (1 - p) ** (n - k)
        return min(1.0, total)
    # Beyond ~1000 stars (an all-sky frame) the coefficient overflows a float: its logarithm instead.
    if p <= 0.0:
        return 0.0
    if p >= 1.0:
        return 1.0
    lp, lq, lgn = math.log(p), math.log1p(-p), math.lgamma(n + 1)
    for k in range(m, n + 1):
        total += math.exp(lgn - math.lgamma(k + 1) - math.lgamma(n - k + 1) + k * lp + (n - k) * lq)
    return min(1.0, total)


def pattern_chance(n_cat: int, eps: float, vecs) -> float:
    """Expected number of catalog patterns matching the measured directions by chance.

    Mortari et al. (2004) / LOST: for a pair ``E = N (N-1)/2 eps sin(theta)``;
    a triangle ``E = N^3 eps^3 sin(theta_ij) / (pi sin(phi_k))``; a pyramid
    (four stars) ``E = N^4 eps^5 sin(theta_ij) / (2 pi^2 sin(phi_k) max sin(phi))``,
    ``phi`` the triangle's inner angles.  ``eps`` is the angle window (rad),
    ``N`` the stars of the database, ``vecs`` the first two to four unit vectors.
    """
    from startrack._kernels.verify import pattern_chance as kernel

    return float(kernel(int(n_cat), float(eps), np.ascontiguousarray(vecs, dtype=np.float64)))


def _missing_probability(missing: int, n_bright: int, area_frac: float) -> float:
    """Chance that a random field holds no more undetected bright catalog stars than this one.

    With the attitude, the catalog stars predicted in the image that are
    clearly brighter than the faintest detection (by the frame's own
    flux-magnitude zero point, less three times its scatter and at least
    0.5 mag; :func:`startrack._kernels.verify.check_matches`) should all be
    detected.  A coincidental match puts the pattern at a random place of the
    sky, where such stars appear at the catalog's average density: Poisson with
    mean ``lambda`` = ``n_bright`` (database stars brighter than the cut) x
    ``area_frac`` (image solid angle / 4 pi), halved for the sparsest skies.
    Returns ``P(K <= missing)``; 1 without magnitudes (``n_bright`` = 0).  The fused verification
    calls the same kernel.
    """
    from startrack._kernels.verify import missing_probability

    return float(missing_probability(int(missing), int(n_bright), float(area_frac)))


# A close pair is named only when the other assignment is this much worse in chi-square
# (position and magnitude): a likelihood ratio of e^8, about 3000 to 1.
AMBIGUITY_CHI2 = 16.0
# Magnitude scatter assumed at least (mag): catalog band against the sensor's, colour.
MAG_SIGMA_FLOOR = 0.2
# A match outside the proposal whose magnitude disagrees by more than this (or four
# times the frame's scatter) is dropped: a false star on an undetected catalog star.
MAG_GATE = 1.0


@dataclass(slots=True)
class _Verdict:
    matches: list | None
    star_index: np.ndarray | None
    cat_index: np.ndarray | None
    dcm: np.ndarray | None
    p_false: float | None
    reason: str | None
    code: ReasonCode | None
    residual_arcsec: np.ndarray | None = None
    quaternion: np.ndarray | None = None
    residual_rms: float | None = None       # arcsec; else from residual_arcsec


def false_match_probability(e_core: float, trials: int, n_others_matched: int, n_others: int, p_hit: float,
                            p_mags: float = 1.0) -> float:
    """The chance that an accepted identification is a coincidence.

    ``min(1, E_core * trials) * P(X >= n_others_matched) * p_mags`` with
    ``E_core`` the expected chance matches of the proposal's pattern
    (:func:`pattern_chance`), ``trials`` the patterns and proposals tried
    (look-elsewhere: each is another chance to be fooled), ``X ~ Binomial(
    n_others, p_hit)`` the other detections landing on predicted stars by
    accident (tetra3's test), and ``p_mags`` what the magnitudes add: the chance
    that a random field lacks the bright stars this one lacks
    (:func:`_missing_probability`) times the chance that random catalog stars
    agree with the core's fluxes as well as these do
    (:func:`startrack._kernels.verify.check_matches`); 1 without fluxes and
    for algorithms whose search already chose by brightness.
    """
    return min(1.0, e_core * max(trials, 1)) * _binomial_sf(n_others_matched, n_others, p_hit) * p_mags


_GEOMETRY: dict = {}


def _geometry(camera):
    """``cos`` of the largest off-axis angle (plus 0.5 deg) and the projection numbers of ``camera``
    (cached per camera model: the off-axis angle costs a projection of the corners)."""
    key = (float(camera.focal_length_px), float(camera.cx), float(camera.cy), int(camera.width), int(camera.height),
           camera.lens_terms)
    got = _GEOMETRY.get(key)
    if got is None:
        if len(_GEOMETRY) > 256:
            _GEOMETRY.clear()
        if not camera.is_pinhole:
            cos_fov = camera.cone_cos(0.5)
        elif camera.has_distortion:
            cos_fov = math.cos(math.radians(camera.max_off_axis_deg + 0.5))
        else:       # a pinhole: the farthest corner's angle, without projecting the corners
            dx = max(abs(-0.5 - camera.cx), abs(camera.width - 0.5 - camera.cx))
            dy = max(abs(-0.5 - camera.cy), abs(camera.height - 0.5 - camera.cy))
            off_axis = math.degrees(math.atan(math.hypot(dx, dy) / camera.focal_length_px))
            cos_fov = math.cos(math.radians(off_axis + 0.5))
        got = _GEOMETRY[key] = (cos_fov, (float(camera.focal_length_px), float(camera.cx), float(camera.cy),
                                          float(camera.width), float(camera.height)) + camera.lens_terms)
    return got


def _sorted_mags(db):
    """Every database magnitude, sorted (cached on the database): the verification's counts."""
    got = db.__dict__.get("_mags_sorted")
    if got is None or len(got) != len(db.star_mag):
        got = db.__dict__["_mags_sorted"] = np.sort(np.asarray(db.star_mag, dtype=np.float64))
    return got


_NO_INDEX = (np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.float64))


def _sky_index(db):
    """The database's sky index (:func:`startrack._kernels.sky_index.sky_index`: bands of z, right
    ascension within a band), cached on the database: the verification looks at the stars that can be
    in the field only (:func:`startrack._kernels.sky_index.cone_stars`).  About sqrt(N) bands."""
    got = db.__dict__.get("_sky_index")
    if got is None or got[0] is not db.star_vector:
        from startrack._kernels.sky_index import sky_index

        sv = np.ascontiguousarray(db.star_vector, dtype=np.float64)
        got = db.__dict__["_sky_index"] = (db.star_vector, sky_index(sv, max(8, min(1024, int(math.sqrt(len(sv)))))))
    return got[1]


def _pixels_to_vectors(camera, xs, ys):
    """``camera.pixels_to_vectors`` (one kernel call for a distortion-free pinhole)."""
    if camera.has_distortion or not camera.is_pinhole:
        return camera.pixels_to_vectors(xs, ys)
    from startrack._kernels.common import pixels_to_unit

    return pixels_to_unit(xs, ys, float(camera.focal_length_px), float(camera.cx), float(camera.cy))


def verify(proposal: Proposal, b_all: np.ndarray, flux: np.ndarray, sig_px: np.ndarray, camera, db, eps: float,
           params: IdentifyParams, trials: int, use_magnitudes: bool, geom=None, scale_offset: float = 0.0) -> _Verdict:
    """Attitude, every other detection and the confidence of one proposal (see the module docstring).

    ``geom`` is :func:`_geometry` of ``camera`` (computed when not given).  ``scale_offset``
    is ``|s - 1|`` of a focal-length scale fitted to the data before this call (0: none): a
    random catalog pattern then needs to match the core's shape only up to one of the scales
    the fit could have chosen (within ``params.max_focal_error``), which multiplies the chance
    of a coincidence by their number (:func:`startrack._kernels.focal.scale_cells`; see
    :func:`_verify_with_focal`).
    """
    from startrack._kernels.verify import verify_core

    star_vec = db.star_vector
    img = np.asarray(proposal.image, dtype=np.int64)
    cat = np.asarray(proposal.catalog, dtype=np.int64)
    if len(img) < 2:
        return _Verdict(None, None, None, None, None, "fewer than two stars proposed", ReasonCode.NO_PATTERN)
    f = camera.focal_length_px
    margin_px = math.radians(params.margin_arcsec / 3600.0) * f
    if params.match_radius_px is not None:
        radius_px = np.full(len(b_all), float(params.match_radius_px))
    else:
        radius_px = np.maximum(1.0, params.match_sigma * sig_px + margin_px)
    radius = radius_px / f
    cos_fov, geometry = geom if geom is not None else _geometry(camera)
    n_all = len(b_all)
    # Fluxes serve the consistency checks (bright stars missing, close pairs, magnitudes of the
    # matches) for every algorithm; only the confidence leaves out the core's magnitude
    # agreement when the search itself chose by brightness (``use_magnitudes`` False).
    # One kernel: attitude and match-all, unambiguous and magnitude-consistent matches,
    # leave-one-out, the proposal's agreement, bright stars missing, the count of matches
    # (reasons below), and the numbers of the false-match probability.
    fl = flux if flux is not None else np.full(n_all, np.nan)
    code, match, q, dcm, n_pred, _, missing, n_bright, p_mag, bright_pred, e_core, p_hit, *_near = verify_core(
        b_all, star_vec, db.star_mag, _sorted_mags(db), img, cat, radius, sig_px / f, fl, bool(use_magnitudes), cos_fov, *geometry,
        int(params.min_matches), float(eps), float(scale_offset), float(params.max_focal_error), AMBIGUITY_CHI2,
        MAG_SIGMA_FLOOR, MAG_GATE, *_sky_index(db))
    if code == 1:
        return _Verdict(None, None, None, dcm, None, "a star of the proposal disagrees with the attitude of the others",
                        ReasonCode.VERIFICATION_FAILED)
    if code == 2:
        return _Verdict(None, None, None, dcm, None, "the proposal's stars do not agree with the refined attitude",
                        ReasonCode.VERIFICATION_FAILED)
    if code == 3:
        return _Verdict(None, None, None, dcm, None,
                        f"{missing} of {bright_pred} bright catalog stars predicted in the image are not detected",
                        ReasonCode.VERIFICATION_FAILED)
    matched = np.flatnonzero(match >= 0)
    n_matched = len(matched)
    if code == 4:
        return _Verdict(None, None, None, dcm, None, f"only {n_matched} stars matched (need {params.min_matches})",
                        ReasonCode.TOO_FEW_STARS)
    core = img[:4]
    n_others = n_all - len(set(core.tolist()))
    core_agree = int(np.count_nonzero(match[core] >= 0))
    # Bright catalog stars predicted in the image but not detected (magnitudes).
    p_missing = _missing_probability(missing, n_bright, camera.sky_fraction)
    p_missing *= p_mag
    p_false = false_match_probability(e_core, trials, n_matched - core_agree, n_others, p_hit, p_missing)
    if p_false > params.max_false_probability:
        return _Verdict(None, None, None, dcm, p_false, (f"false-match probability {p_false:.2g} above the limit "
                                                         f"{params.max_false_probability:g}"),
                        ReasonCode.FALSE_MATCH_PROBABILITY)
    resid = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", b_all[matched], star_vec[match[matched]] @ dcm.T),
                                         -1, 1))) * 3600
    ids = db.star_id[match[matched]].tolist()
    out = [Match(s, i) for s, i in zip(matched.tolist(), ids)]
    q = q / math.sqrt(float(q @ q))
    return _Verdict(out, matched, match[matched], dcm, p_false, None, None, resid, -q if q[3] < 0 else q)


def _field_scale(b_all, xs, ys, sig_px, camera, dcm, star_vec, core, radius_px, max_err, zindex=None):
    """The focal-length scale the whole field implies (None with fewer than four tentative matches, or
    when they cannot tell it from 1).

    With the attitude of a proposal solved at a wrong focal length, the other stars sit
    off their predictions by up to ``max_err`` times their distance from the core (the
    error grows away from where the attitude was fitted), so the normal match radius
    misses the outer ones and a scale fitted to the few matched near the core stays
    wrong.  Each detection here takes the one predicted star within its radius widened by
    that displacement (none when two are), and the scale is the median of catalog over
    measured chord (angle, :func:`startrack._kernels.focal.focal_scale`) over the long pairs of
    these tentative matches (robust to the odd wrong one); significant as
    :func:`startrack._kernels.focal.scale_significant` says.
    """
    from startrack._kernels.focal import field_scale, scale_significant

    if not camera.has_distortion and camera.is_pinhole:
        cos_front = math.cos(math.acos(_geometry(camera)[0]) + math.radians(0.5))
        got = field_scale(b_all, xs, ys, sig_px, star_vec, dcm, cos_front, float(camera.focal_length_px),
                          float(camera.cx), float(camera.cy), 0.0, 0.0, np.asarray(core, dtype=np.int64),
                          np.asarray(radius_px, dtype=np.float64), float(max_err), *(zindex or _NO_INDEX))
        return None if math.isnan(got) else float(got)
    front = np.flatnonzero(star_vec @ dcm[2] > camera.cone_cos(1.0))
    if len(front) < 4:
        return None
    x, y = camera.vectors_to_pixels(star_vec[front] @ dcm.T)
    ok = np.isfinite(x) & np.isfinite(y)
    front, x, y = front[ok], x[ok], y[ok]
    if len(front) < 4:
        return None
    d_core = np.hypot(xs - float(np.mean(xs[core])), ys - float(np.mean(ys[core])))
    allowed = radius_px + max_err * d_core
    dist = np.hypot(xs[:, None] - x[None, :], ys[:, None] - y[None, :])
    order = np.argsort(dist, axis=1)[:, :2]
    rows = np.arange(len(xs))
    near = dist[rows, order[:, 0]]
    second = dist[rows, order[:, 1]] if order.shape[1] > 1 else np.full(len(xs), np.inf)
    take = (near <= allowed) & (second > allowed)
    img = np.flatnonzero(take)
    if len(img) < 4:
        return None
    cat = front[order[img, 0]]
    if len(np.unique(cat)) < len(cat):
        keep = np.unique(cat, return_index=True)[1]
        img, cat = img[keep], cat[keep]
        if len(img) < 4:
            return None
    iu = np.triu_indices(len(img), 1)
    # Chords, as the kernel's focal_scale: the angle ratio without an arccos.
    mea = np.linalg.norm(b_all[img][:, None, :] - b_all[img][None, :, :], axis=2)[iu]
    ref = np.linalg.norm(star_vec[cat][:, None, :] - star_vec[cat][None, :, :], axis=2)[iu]
    long = mea >= 0.3 * mea.max()
    if np.count_nonzero(long) < 3:
        return None
    if not scale_significant(xs, ys, sig_px, float(camera.focal_length_px), img.astype(np.int64),
                             np.ascontiguousarray(ref), np.ascontiguousarray(mea)):
        return None
    return float(np.median(ref[long] / mea[long]))


_REASONS = {1: ("a star of the proposal disagrees with the attitude of the others", ReasonCode.VERIFICATION_FAILED),
            2: ("the proposal's stars do not agree with the refined attitude", ReasonCode.VERIFICATION_FAILED)}


def _verify_fused(proposal, xs, ys, b_all, flux, sig_px, camera, db, eps, params, trials, use_mags):
    """:func:`_verify_with_focal` for a distortion-free camera in one kernel call
    (:func:`startrack._kernels.verify.verify_focal`): the same steps and checks on the same
    kernels, the same verdict.  Returns ``(verdict, focal scale or None)``."""
    from startrack._kernels import verify as kernels

    # Every argument's type is fixed here (fresh int64 and float64 arrays, Python scalars) or by the
    # database: the kernel's entry is resolved once per database (LazyKernel.resolve).
    img = np.array(proposal.image, dtype=np.int64)
    cat = np.array(proposal.catalog, dtype=np.int64)
    n_all = len(xs)
    fl = flux if flux is not None else np.full(n_all, np.nan)
    args = (xs, ys, b_all, db.star_vector, db.star_mag, _sorted_mags(db), img, cat, sig_px, fl, bool(use_mags),
            float(camera.focal_length_px), float(camera.cx), float(camera.cy), float(camera.width),
            float(camera.height), -1.0 if params.match_radius_px is None else float(params.match_radius_px),
            float(params.match_sigma), math.radians(params.margin_arcsec / 3600.0), int(params.min_matches),
            float(eps), AMBIGUITY_CHI2, MAG_SIGMA_FLOOR, MAG_GATE, int(trials), float(params.max_false_probability),
            float(params.max_focal_error)) + _sky_index(db)
    kernel = kernels.verify_focal
    got = db.__dict__.get("_verify_focal_entry")
    if got is None or got[0] is not kernel or got[1] is not db.star_vector or got[2] is not db.star_mag:
        got = db.__dict__["_verify_focal_entry"] = (kernel, db.star_vector, db.star_mag,
                                                    kernel.resolve(args) if hasattr(kernel, "resolve") else kernel)
    code, match, q, dcm, p_false, missing, bright_pred, n_matched, total, matched, rms = got[3](*args)
    return _fused_verdict(code, match, q, dcm, p_false, missing, bright_pred, n_matched, matched, rms, db, params), \
        (None if total == 1.0 else float(total))


def _fused_verdict(code, match, q, dcm, p_false, missing, bright_pred, n_matched, matched, rms, db, params):
    """The :class:`_Verdict` of :func:`startrack._kernels.verify.verify_focal`'s result."""
    if code != 0:
        if code in _REASONS:
            reason, rc = _REASONS[code]
        elif code == 3:
            reason, rc = (f"{missing} of {bright_pred} bright catalog stars predicted in the image are not detected",
                          ReasonCode.VERIFICATION_FAILED)
        elif code == 4:
            reason, rc = f"only {n_matched} stars matched (need {params.min_matches})", ReasonCode.TOO_FEW_STARS
        else:
            return _Verdict(None, None, None, dcm, float(p_false),
                            (f"false-match probability {p_false:.2g} above the limit "
                             f"{params.max_false_probability:g}"), ReasonCode.FALSE_MATCH_PROBABILITY)
        return _Verdict(None, None, None, dcm, None, reason, rc)
    return _accepted_verdict(match, matched, q, dcm, p_false, rms, db)


def _accepted_verdict(match, matched, q, dcm, p_false, rms, db):
    """The :class:`_Verdict` of an accepted verification (:func:`_fused_verdict` with code 0): ``match``
    the database index of every detection (-1: none), ``matched`` the matched detections."""
    cat_index = match[matched]
    out = list(map(_new_tuple, itertools.repeat(Match), zip(matched.tolist(), db.star_id[cat_index].tolist())))
    return _Verdict(out, matched, cat_index, dcm, float(p_false), None, None, None, q, rms)


_new_tuple = tuple.__new__      # a Match from a (star, id) pair without NamedTuple's Python-level __new__


def _verify_with_focal(proposal, xs, ys, b_all, flux, sig_px, camera, db, eps, params, trials, use_mags, geom):
    """:func:`verify`, measuring and correcting the focal-length scale the proposal implies.

    Angles scale as ``1 / f``: the proposal's pairs measure the scale and the frame is
    matched with the corrected focal length.  An accepted match is then checked against
    the scale the whole field implies (:func:`_field_scale`; not searched when every detection
    matched), and the scale re-estimated from every matched star until it settles, each step
    taken only when the stars tell it from 1 (:func:`startrack._kernels.focal.scale_significant`:
    a step within noise changes no match, only the time); each verification at a fitted scale
    pays for every scale the fit could have chosen (``scale_offset`` of :func:`verify`), and the
    identification is refused when the field's scale refuses it.  Without this, a focal-length
    error left a few outer stars matched to the wrong neighbour (paper 004 Fig. 7 conditions).
    Scales beyond ``params.max_focal_error`` (the stated uncertainty) are never used.
    Returns ``(verdict, focal scale or None)``.
    """
    from startrack._kernels.focal import focal_scale, matched_scale

    star_vec = db.star_vector
    scale = focal_scale(b_all, np.asarray(proposal.image, dtype=np.int64), star_vec,
                        np.asarray(proposal.catalog, dtype=np.int64))     # NaN with fewer than 3 stars
    scale = None if math.isnan(scale) else float(scale)
    if scale is not None and (abs(scale - 1.0) > params.max_focal_error or abs(scale - 1.0) < 5e-4):
        scale = None    # within noise (or beyond belief): keep the nominal focal length
    cam = camera
    if scale is not None:
        cam = _scaled_camera(camera, scale)
        if cam is None:
            return _not_a_camera(camera, scale), None
        b_all = _pixels_to_vectors(cam, xs, ys)
    v = verify(proposal, b_all, flux, sig_px, cam, db, eps, params, trials, use_mags,
               geom if scale is None else None, abs(scale - 1.0) if scale is not None else 0.0)
    if v.matches is None or v.dcm is None:
        return v, scale
    total = 1.0 if scale is None else scale
    margin_px = math.radians(params.margin_arcsec / 3600.0) * cam.focal_length_px
    radius_px = np.full(len(xs), float(params.match_radius_px)) if params.match_radius_px is not None else \
        np.maximum(1.0, params.match_sigma * sig_px + margin_px)
    # Every detection matched: the matches' least-squares scale below speaks for the whole field.
    step = None if len(v.matches) == len(xs) else _field_scale(
        b_all, xs, ys, sig_px, cam, v.dcm, star_vec, np.asarray(proposal.image[:4]), radius_px,
        params.max_focal_error, _sky_index(db))
    # (None also when the tentative matches cannot tell the field's scale from 1: noise.)
    if step is not None and abs(step - 1.0) >= 5e-4 and abs(total * step - 1.0) <= params.max_focal_error:
        total *= step
        cam = _scaled_camera(camera, total)
        if cam is None:
            return _not_a_camera(camera, total), None
        b_all = _pixels_to_vectors(cam, xs, ys)
        v = verify(proposal, b_all, flux, sig_px, cam, db, eps, params, trials, use_mags, None, abs(total - 1.0))
    for _ in range(4):
        if v.matches is None or len(v.matches) < 3:
            break
        step, significant = matched_scale(b_all, xs, ys, sig_px, float(cam.focal_length_px), star_vec,
                                          np.asarray(v.star_index, dtype=np.int64),
                                          np.asarray(v.cat_index, dtype=np.int64))
        if math.isnan(step) or abs(step - 1.0) < 1e-5 or abs(total * step - 1.0) > params.max_focal_error:
            break
        # A step that moves the farthest matched star by less than a tenth of the smallest
        # match radius cannot change a match, nor one the matches cannot tell from 1 (noise).
        far = float(np.max(np.hypot(xs[v.star_index] - cam.cx, ys[v.star_index] - cam.cy)))
        if abs(step - 1.0) * far < 0.1 * float(radius_px.min()) or not significant:
            break
        total *= step
        cam = _scaled_camera(camera, total)
        if cam is None:
            return _not_a_camera(camera, total), None
        b_all = _pixels_to_vectors(cam, xs, ys)
        v = verify(proposal, b_all, flux, sig_px, cam, db, eps, params, trials, use_mags, None, abs(total - 1.0))
    return v, (None if total == 1.0 else total)


def _scaled_camera(camera, scale):
    """``camera`` with its focal length divided by ``scale``, or None when that is no camera: a lens whose terms, fitted
    at the first focal length, move the image's farthest corner by more than its own distance from the centre at
    the shorter one (:class:`~startrack.camera.Camera` refuses it)."""
    from startrack.errors import ParameterError

    try:
        return camera.with_focal_length(camera.focal_length_px / scale)
    except ParameterError:
        return None


def _not_a_camera(camera, scale):
    """The verdict on a proposal whose focal-length scale makes ``camera`` no camera (:func:`_scaled_camera`): refused."""
    return _Verdict(None, None, None, None, None,
                    f"the focal length the stars imply ({camera.focal_length_px / scale:.6g} px) makes the lens no "
                    f"camera (its distortion moves the farthest corner by more than 100 %)", ReasonCode.NO_PATTERN)
