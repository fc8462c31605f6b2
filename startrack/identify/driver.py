"""The search driver: an algorithm's proposals, each verified, until one passes; the plan of its searches.

An algorithm (:class:`~startrack.identify.algorithm.Algorithm`) is a *generator of proposals*: a few
star correspondences (a pyramid, a voting cluster, a label group, ...) in the order its paper searches
them.  The driver :func:`run` takes them one by one and verifies each identically for every algorithm
(:mod:`startrack.identify.verify`: attitude, every other detection matched, the false-match
probability), accepting the first proposal whose false-match probability, *multiplied by the number of
patterns and proposals tried* (look-elsewhere), is below ``max_false_probability``.  When a search of the
brightest stars finds nothing it searches again (:func:`search_plan`: more stars, the other focal-length
pass, other focal lengths: :func:`focal_scales`), and with a catalog it matches the detections the
database does not hold (:mod:`startrack.identify.catalog_match`).

The search stops at the first accepted proposal or when a budget
(``max_proposals``, ``max_time_ms``) runs out; the result reports the trials.
Because every proposal passes the same gate, an algorithm that proposes more
(continuing after a rejected candidate, as paper 003's Fig. 5 loop and paper
004's search do) gains success but never wrong answers.
"""
from __future__ import annotations

import contextvars
import logging
import math
import time

import numpy as np

from startrack.identify.algorithm import (
    BOTH_PASSES,
    FREE_PASS,
    NOMINAL_PASS,
    Algorithm,
    FusedFrame,
    NoConfig,
    SearchContext,
    SearchOutcome,
)
from startrack.identify.catalog_match import apparent_quaternion, match_identified
from startrack.identify.params import IdentifyParams, _frame_arrays, _table_arrays, _tolerances, star_sigmas_px
from startrack.identify.verify import _geometry, _pixels_to_vectors, _scaled_camera, _verify_fused, _verify_with_focal
from startrack.records import Identification, ReasonCode, StarTable, Status

__all__ = ["FUSED_SEARCH", "FUSED_VERIFY", "WARMING_UP", "focal_scales", "run", "search_levels", "search_plan"]

log = logging.getLogger(__name__)
_LOGGED_PROPOSALS = 20      # rejected proposals logged one by one (debug) before going quiet
#: True while :func:`startrack.identify.warm_up` runs its made-up frame: nothing of it is logged.
WARMING_UP = contextvars.ContextVar("startrack_identify_warming_up", default=False)
log.addFilter(lambda _record: not WARMING_UP.get())

#: Verify pinhole-camera proposals with one kernel call (:func:`~startrack.identify.verify._verify_fused`); False: the
#: step-by-step Python path (:func:`~startrack.identify.verify._verify_with_focal`), which the tests compare it with.
FUSED_VERIFY = True
#: Run an algorithm's search and verification loop in one kernel (:attr:`~startrack.identify.algorithm.Algorithm.fused`) where it has
#: one and :data:`FUSED_VERIFY` applies; False: the Python loop over its proposals (the tests compare them).
FUSED_SEARCH = True

def run(algorithm: Algorithm, config, frame_stars: list, camera, db, params: IdentifyParams,
        catalog=None, apparent=None) -> Identification:
    """The search driver: proposals from ``algorithm.search``, each verified, until one passes or the budget ends.

    Parameters
    ----------
    algorithm : Algorithm
    config : dataclass instance of ``algorithm.config``
    frame_stars : list of dict or StarTable
        ``x``, ``y`` (px), optionally ``flux`` and ``sigma_px``, brightest first; a
        :class:`~startrack.records.StarTable`'s columns are read as they are (no per-star dict).
    camera : Camera
    db : database of ``algorithm.database`` kind
    params : IdentifyParams
    catalog : CatalogStars or Catalog, optional
        A catalog to match the detections the database does not hold against
        (:func:`~startrack.identify.catalog_match.match_catalog`), e.g. the full catalog behind a shallow database.
    apparent : callable, optional
        ``apparent(vectors, parallax_mas)``: ICRS unit vectors to the frame's apparent places (parallax,
        stellar aberration; :meth:`startrack.apparent.FrameApparent.apparent`): the final match and
        the reported attitude use them, so that ``quaternion_estimate`` is the
        camera's true orientation.  The search and the verification compare
        angles within the field, which aberration changes by at most 1e-4 of
        themselves (v/c), far inside their tolerances.

    Returns
    -------
    Identification
        ``ok`` with every matched detection, or ``failed`` with a reason and code;
        ``trials`` is the number of proposals verified.
    """
    t0 = time.perf_counter()
    if isinstance(algorithm, str):
        # The 0.x call run(name, propose, stars, camera, db, params): one proposal from propose().
        name_, propose = algorithm, config

        def search(ctx, _config):
            yield propose(ctx.b, ctx.db, ctx.eps, ctx.params, ctx.stars, ctx.camera)

        algorithm, config = Algorithm(name_, search), NoConfig()
    name = algorithm.name
    table = isinstance(frame_stars, StarTable)
    if table:
        xs, ys, flux, sig_px = _table_arrays(frame_stars, params)
        n_all = len(xs)
    else:
        n_all = len(frame_stars)
    if n_all < 3:
        return Identification.failed(name, f"{n_all} star(s): at least 3 are needed", ReasonCode.TOO_FEW_STARS,
                                     time_ms=(time.perf_counter() - t0) * 1000, trials=0)
    if not table:
        xs, ys, flux = _frame_arrays(frame_stars)
        sig_px = star_sigmas_px(frame_stars, params)
    use = min(n_all, params.max_stars)
    margin, eps = _tolerances(params, sig_px, use, camera.focal_length_px)
    prepare_ms = None
    if algorithm.prepare is not None:
        tp = time.perf_counter()
        if algorithm.prepare(config, camera, db, eps):     # (:func:`_prepare`, without a call)
            pause = time.perf_counter() - tp
            prepare_ms = pause * 1000
            t0 += pause       # loading for this sensor, not identification: not in time_ms
    deadline = t0 + params.max_time_ms / 1000.0
    info = log.isEnabledFor(logging.INFO)
    debug = info and log.isEnabledFor(logging.DEBUG)
    if debug:
        log.debug("%s: %d stars (%d searched), tolerance %.1f arcsec, budget %d proposals / %g ms, database %s",
                  name, n_all, use, math.degrees(eps) * 3600, params.max_proposals, params.max_time_ms,
                  getattr(db, "path", None) or type(db).__name__)
    fused = FUSED_VERIFY and not camera.has_distortion and camera.is_pinhole and (params.match_radius_px is None or
                                                               params.match_radius_px > 0)
    in_kernel = fused and FUSED_SEARCH and algorithm.fused is not None and not debug
    b_all = None if in_kernel else _pixels_to_vectors(camera, xs, ys)
    frame = (algorithm, config, frame_stars, xs, ys, b_all, flux, sig_px, fused, in_kernel, camera, db, params)
    plan = search_plan(n_all, params, algorithm.focal_passes) if use < n_all else None
    out = _search(frame, use, eps, margin, deadline, 0, plan[0][1] if plan else BOTH_PASSES)
    searched, searches, swept = use, 1, None
    if out.accepted is None:
        out, searched, searches, eps, pause, swept = _deepen(frame, out, plan or [(use, BOTH_PASSES)], eps,
                                                             deadline)
        if pause:
            prepare_ms = (prepare_ms or 0.0) + pause * 1000
            t0 += pause
            deadline += pause
    accepted, reason, code = out.accepted, out.reason, out.code
    if accepted is None and code == ReasonCode.NO_PATTERN and time.perf_counter() > deadline:
        # The search itself stopped at the deadline (ctx.expired) between proposals.
        reason, code = f"search time of {params.max_time_ms:g} ms spent", ReasonCode.TIMEOUT
    elapsed = (time.perf_counter() - t0) * 1000
    tol_arcsec = _TOL_ARCSEC.get(eps)
    if tol_arcsec is None:
        if len(_TOL_ARCSEC) > 256:
            _TOL_ARCSEC.clear()
        tol_arcsec = _TOL_ARCSEC[eps] = round(math.degrees(eps) * 3600, 3)
    tried, patterns = out.tried, out.patterns
    if accepted is None:
        best = out.best
        if best is not None and reason.startswith("no consistent"):
            reason, code = best.reason, best.code
        elif best is not None:
            reason = f"{reason}; best: {best.reason}"
        if info:
            log.info("%s: not identified after %d proposal(s), %d pattern(s), %.0f ms: %s", name, tried, patterns,
                     elapsed, reason)
        return Identification.failed(name, reason, code, time_ms=elapsed, trials=tried, tolerance_arcsec=tol_arcsec,
                                     false_match_probability=best.p_false if best is not None else None,
                                     details={**out.best_details, "patterns": int(patterns),
                                              **({"search_stars": searched} if searched > use else {}),
                                              **({"searches": searches} if searches > 1 else {}),
                                              **({"prepare_ms": round(prepare_ms, 1)} if prepare_ms else {})})
    matches, quaternion, scale = accepted.matches, accepted.quaternion, out.scale
    if swept is not None:
        # The verification's scale is of the swept camera's focal length: the frame's is their product.
        scale = swept * (1.0 if scale is None else scale)
    depth = q = None
    # (every detection identified: nothing for the catalog, as match_identified says)
    matched_all = catalog is not None and len(matches) >= n_all
    if catalog is not None and not matched_all:
        n_db = len(matches)
        matches, q, depth = match_identified(catalog, accepted, scale, camera, xs, ys, b_all, flux, sig_px, db,
                                             params, apparent)
        if q is not None:
            quaternion = q
    if apparent is not None and (catalog is None or q is None):
        quaternion = apparent_quaternion(accepted, scale, camera, xs, ys, sig_px, db, apparent, catalog)
    if (catalog is not None and not matched_all) or apparent is not None:
        # The final match and the apparent refit are identification; the record's bookkeeping below is not,
        # with or without them (as the time taken before them).
        elapsed = (time.perf_counter() - t0) * 1000
    details = out.details
    details["patterns"] = int(patterns)
    if searched > use:
        details["search_stars"] = searched
    if searches > 1:
        details["searches"] = searches
    if prepare_ms:
        details["prepare_ms"] = round(prepare_ms, 1)
    rms = accepted.residual_rms
    if rms is None:
        res = np.asarray(accepted.residual_arcsec, dtype=np.float64)
        rms = math.sqrt(float(res @ res) / len(res))
    details["residual_arcsec_rms"] = round(rms, 3)
    if depth is not None:
        details["match_mag_limit"] = round(depth, 2)
    if q is not None:
        details["matched_beyond_database"] = len(matches) - n_db
    if info:
        log.info("%s: %d of %d stars identified at proposal %d (%d pattern(s)), false-match probability %.2g, "
                 "%.0f ms", name, len(matches), n_all, tried, patterns, float(accepted.p_false), elapsed)
    return Identification(Status.OK, name, matches, time_ms=elapsed, false_match_probability=float(accepted.p_false),
                          trials=tried, tolerance_arcsec=tol_arcsec,
                          focal_scale=None if scale is None else round(float(scale), 7),
                          quaternion_estimate=quaternion, details=details)


_TOL_ARCSEC: dict = {}      # the reported tolerance (arcsec, 3 decimals) per eps: round() costs a string conversion


def search_levels(n_stars: int, params: IdentifyParams) -> list:
    """The search stars of each search of a frame of ``n_stars`` detections: ``max_stars``, then twice as many
    each time the one before ended without a proposal that passes, up to ``max_search_stars`` (and the
    frame's count); e.g. 20, 40, 80.  (:func:`run` searches the next only while the budget lasts.)"""
    use = min(n_stars, params.max_stars)
    deep = min(n_stars, params.max_search_stars)
    levels = [use]
    while 0 < use < deep:
        use = min(deep, 2 * use)
        levels.append(use)
    return levels


def search_plan(n_stars: int, params: IdentifyParams, focal_passes: bool = False) -> list:
    """The searches of a frame of ``n_stars`` detections, in order, while none finds a proposal that passes:
    ``(search stars, focal_pass)`` each (:attr:`~startrack.identify.algorithm.SearchContext.focal_pass`).

    The depths are :func:`search_levels`'.  For a search with a free-focal-length pass
    (:attr:`~startrack.identify.algorithm.Algorithm.focal_passes`, ``params.max_focal_error`` > 0) and more than one depth, every depth
    is searched at the nominal focal length first (:data:`~startrack.identify.algorithm.NOMINAL_PASS`), then at the free focal length
    (:data:`~startrack.identify.algorithm.FREE_PASS`), e.g. (20, nominal), (40, nominal), (80, nominal), (20, free), (40, free),
    (80, free): the free pass compares each triad at every scale it tells apart, many times the nominal
    pass's work, and a frame whose brightest detections are not stars is found by a deeper nominal search
    at a fraction of its cost; a camera whose focal length is off pays the nominal searches (and their
    trials) before its free pass.  Otherwise each depth searches both passes (:data:`~startrack.identify.algorithm.BOTH_PASSES`), as a
    frame of one depth always does."""
    levels = search_levels(n_stars, params)
    if focal_passes and params.max_focal_error > 0 and len(levels) > 1:
        return [(u, NOMINAL_PASS) for u in levels] + [(u, FREE_PASS) for u in levels]
    return [(u, BOTH_PASSES) for u in levels]


def _prepare(algorithm, config, camera, db, eps):
    """Seconds ``algorithm.prepare`` spent building for this database, sensor and tolerance (0: built before):
    loading, which :func:`run` keeps out of ``time_ms`` and the time budget."""
    tp = time.perf_counter()
    return time.perf_counter() - tp if algorithm.prepare(config, camera, db, eps) else 0.0


def _search(frame, use, eps, margin, deadline, trials0=0, focal_pass=0):
    """One search of the first ``use`` stars (``focal_pass``: :attr:`~startrack.identify.algorithm.SearchContext.focal_pass`): the
    algorithm's fused kernel or :func:`_search_loop`.  ``frame``: :func:`run`'s ``(algorithm, config,
    frame_stars, xs, ys, b_all, flux, sig_px, fused, in_kernel, camera, db, params)``."""
    algorithm, config, frame_stars, xs, ys, b_all, flux, sig_px, fused, in_kernel, camera, db, params = frame
    if in_kernel:
        return algorithm.fused(config, FusedFrame(xs, ys, flux, sig_px, use, eps, margin, deadline, trials0,
                                                  focal_pass), camera, db, params)
    return _search_loop(algorithm, config, frame_stars, xs, ys, b_all, flux, sig_px, use, eps, margin, deadline,
                        fused, camera, db, params, trials0, focal_pass)


def _deepen(frame, out, plan, eps, deadline):
    """:func:`run`'s searches after the first of ``plan`` (:func:`search_plan`) found nothing (``out``;
    ``frame``: see :func:`_search`; ``eps``: the first search's tolerance): while a search ends without an
    accepted proposal and within the frame's time (every pattern compared, or its proposal budget spent on
    chance patterns of false detections), the next one searches (:func:`_steps`: more stars, the other
    focal-length pass, or the first depth at another focal length) with a proposal budget of its own, its
    trials on top of the earlier ones' (the false-match probability's look-elsewhere factor counts every
    search).

    Returns ``(outcome, search stars of the last search, searches run, its tolerance eps, seconds spent
    preparing, its focal-length scale or None)``: the outcome has the last search's verdict, reason and
    code, every search's proposals and patterns (summed) and the best rejected verdict of them all."""
    algorithm, config, frame_stars, xs, ys, _, flux, sig_px, fused, in_kernel, camera, db, params = frame
    pause = 0.0
    trials0 = 0
    last = out
    use = plan[0][0]
    searches = 1
    swept = None
    for deeper, focal_pass, scale in _steps(frame, plan, eps):
        if last.accepted is not None or last.code != ReasonCode.NO_PATTERN or time.perf_counter() > deadline:
            break
        cam, fr = camera, frame
        if scale is not None:
            cam = _scaled_camera(camera, scale)
            if cam is None:     # no camera at this focal length (its lens's terms): no search there
                continue
            fr = (algorithm, config, frame_stars, xs, ys, None if in_kernel else _pixels_to_vectors(cam, xs, ys),
                  flux, sig_px, fused, in_kernel, cam, db, params)
        trials0 += max(last.tried, last.patterns)
        margin, eps = _tolerances(params, sig_px, deeper, cam.focal_length_px)
        if algorithm.prepare is not None:
            dt = _prepare(algorithm, config, cam, db, eps)
            pause += dt
            deadline += dt
        log.debug("%s: nothing found searching the %d brightest stars: searching the %d brightest%s", algorithm.name,
                  use, deeper, " with the focal length free" if focal_pass == FREE_PASS else
                  "" if scale is None else f" at focal-length scale {scale:.4f}")
        last = _search(fr, deeper, eps, margin, deadline, trials0, focal_pass)
        out = _after(out, last)
        use, swept = deeper, scale
        searches += 1
    return out, use, searches, eps, pause, swept if out.accepted is not None else None


def _steps(frame, plan, eps):
    """The searches :func:`_deepen` may run after the first, ``(search stars, focal_pass, focal-length scale or
    None)`` each: the rest of ``plan``, then, for an algorithm with :attr:`~startrack.identify.algorithm.Algorithm.focal_sweep` and
    ``params.max_focal_error`` > 0, the first depth at each of :func:`focal_scales` (``eps``: the first
    search's tolerance), made only when the plan is through."""
    for use, focal_pass in plan[1:]:
        yield use, focal_pass, None
    algorithm, _, _, xs, ys, _, _, _, _, _, camera, _, params = frame
    if algorithm.focal_sweep and params.max_focal_error > 0:
        use = plan[0][0]
        for s in focal_scales(_pixels_to_vectors(camera, xs[:use], ys[:use]), eps, params.max_focal_error):
            yield use, BOTH_PASSES, s


def focal_scales(b, eps: float, max_error: float) -> list:
    """The focal-length scales (``theta_catalog / theta_measured``) a search at the nominal focal length
    does not reach, nearest first: ``1 + d, 1 - d, 1 + 2 d, ...`` within ``1 +- max_error``.

    A pattern of the search stars ``b`` (unit vectors) seen at scale ``s`` has its longest side, at most
    their widest angle ``theta``, off by ``theta |s - 1|``; the search's windows (half-width ``eps``) hold
    it while that is at most ``eps``, so searches at scales ``d = 2 eps / theta`` apart leave no scale
    between them uncovered."""
    b = np.asarray(b, dtype=np.float64)
    if len(b) < 2 or eps <= 0 or max_error <= 0:
        return []
    theta = math.acos(max(-1.0, min(1.0, float(np.min(b @ b.T)))))
    d = 2.0 * eps / max(theta, eps)
    out = []
    k = 1
    while k * d <= max_error:
        out += [1.0 + k * d, 1.0 - k * d]
        k += 1
    return out


def _after(out, last):
    """The outcome of the searches of ``out`` and then ``last``: the last one's verdict, reason and code, both
    searches' proposals and patterns, the better of their best rejected verdicts (:func:`_better`; on a tie
    the earlier)."""
    best, best_details = (last.best, last.best_details) if _better(last.best, out.best) else \
        (out.best, out.best_details)
    return SearchOutcome(last.accepted, last.scale, last.details, best, best_details, out.tried + last.tried,
                         out.patterns + last.patterns, last.reason, last.code)


def _better(v, best):
    """A rejected verdict ``v`` to keep as the search's best instead of ``best``: the first, or one with a
    lower false-match probability."""
    return v is not None and (best is None or (v.p_false is not None and (best.p_false is None or
                                                                          v.p_false < best.p_false)))


def _search_loop(algorithm, config, frame_stars, xs, ys, b_all, flux, sig_px, use, eps, margin, deadline, fused,
                 camera, db, params, trials0=0, focal_pass=0) -> SearchOutcome:
    """:func:`run`'s loop in Python: ``algorithm.search``'s proposals, each verified (:func:`~startrack.identify.verify._verify_fused`
    when ``fused``, else :func:`~startrack.identify.verify._verify_with_focal`), until one passes or the budget ends.  ``trials0``: the
    trials of the frame's earlier searches (:attr:`FusedFrame.trials0`); ``focal_pass``:
    :attr:`~startrack.identify.algorithm.SearchContext.focal_pass`."""
    name = algorithm.name
    has_flux = int(np.count_nonzero(np.isfinite(flux))) >= 3
    if params.tolerance_arcsec is not None:
        tol = np.zeros(use)
    else:
        tol = params.tolerance_sigma * sig_px[:use] / camera.focal_length_px
    if isinstance(frame_stars, StarTable):
        frame_stars = frame_stars.to_list()     # the searches read stars as dicts
    ctx = SearchContext(np.ascontiguousarray(b_all[:use]), frame_stars[:use], camera, db, eps, tol, margin, params,
                        flux[:use] if has_flux else None, deadline, focal_pass)
    use_mags = has_flux and not algorithm.uses_brightness
    geom = None if fused else _geometry(camera)
    tried = patterns = 0
    best = accepted = scale = None
    details, best_details = {}, {}
    reason, code = "no consistent star pattern found", ReasonCode.NO_PATTERN
    seen = set()
    for proposal in algorithm.search(ctx, config):
        if proposal is None or len(proposal.image) == 0:
            continue
        # The same correspondences proposed again (another triad of the same stars) are no new trial.
        key = frozenset(zip(proposal.image, proposal.catalog))
        if key in seen:
            continue
        seen.add(key)
        tried += 1
        patterns = max(patterns, proposal.patterns)
        if fused and len(proposal.image) >= 2:
            v, scale = _verify_fused(proposal, xs, ys, b_all, flux if has_flux else None, sig_px, camera, db, eps,
                                     params, trials0 + max(tried, proposal.patterns), use_mags)
        else:
            v, scale = _verify_with_focal(proposal, xs, ys, b_all, flux if has_flux else None, sig_px, camera, db,
                                          eps, params, trials0 + max(tried, proposal.patterns), use_mags, geom)
        if v.matches is not None:
            accepted = v
            details = dict(proposal.details)
            break
        if tried <= _LOGGED_PROPOSALS:
            log.debug("%s: proposal %d (stars %s = catalog %s) rejected: %s", name, tried, list(proposal.image),
                      list(proposal.catalog), v.reason)
        if _better(v, best):
            best = v
            best_details = dict(proposal.details)
        if tried >= params.max_proposals:
            reason, code = f"search budget of {params.max_proposals} proposals spent", ReasonCode.NO_PATTERN
            break
        if time.perf_counter() > deadline:
            reason, code = f"search time of {params.max_time_ms:g} ms spent", ReasonCode.TIMEOUT
            break
    return SearchOutcome(accepted, scale, details, best, best_details, tried, patterns, reason, code)
