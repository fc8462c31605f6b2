"""Pyramid identification (Mortari, Samaan, Bruccoleri & Junkins 2004).

Triads of image stars are taken in Mortari's smart index sequence (every
triad once, bright stars early, spikes spread out); for each, the kernel
(:func:`startrack._kernels.pyramid.pyramid_candidates`) finds the catalog
triangles through k-vector range look-ups on the inter-star angles, the
third angle and the specular (handedness) test, and confirms each triangle
with a fourth image star matching exactly one catalog star (the pyramid).
Every confirmed pyramid is a proposal, the triad's in the order found: where
Mortari's pyramid stops at the first triad with a *unique* triangle, this
search also proposes the pyramids of ambiguous triads and goes on after a
rejected one (the shared verification decides), which is what a sparse field
of four or five stars needs.  When the triads give no accepted proposal and the
focal length may be off (``max_focal_error``), they are searched once more with
the focal length free within that (one scale for a triangle's three sides): in the
same search, or, for a frame that the driver searches again with more stars, after
the nominal searches of every depth (:func:`startrack.identify.driver.search_plan`;
the driver says which pass in ``SearchContext.focal_pass``).

The search has two tiers when they differ enough (:func:`pattern_database`) and the
frame has more than :data:`PATTERN_STARS` search stars: first
the pairs of the database's *pattern stars* -- those with fewer than
:data:`PATTERN_STARS` brighter database stars within half the sensor's short side,
the stars a field shows among its brightest (tetra3 makes its patterns of the ten
brightest stars of each field-sized patch) -- with a quarter of the proposal budget,
then, when that found nothing, every pair.  A wide field's pair windows hold several
times fewer chance triangles in the first tier; the second keeps every field the full
database identifies.  Verification is the same in both (every database star).  The
second tier compares the same image patterns again, against every pair, so the
false-match gate counts the more of the two tiers' patterns (and every proposal of both).

Paper 000's quadratic search on its triangle database is
:mod:`startrack.identify.modified_pyramid`.
"""
from __future__ import annotations

import math
import operator
import threading
import time
from dataclasses import dataclass, field
from itertools import repeat

import numpy as np

from startrack._kernels import pyramid as _kernels
from startrack.identify.algorithm import FREE_PASS, NOMINAL_PASS, Algorithm, Proposal, SearchOutcome
from startrack.identify.verify import (
    AMBIGUITY_CHI2,
    MAG_GATE,
    MAG_SIGMA_FLOOR,
    _fused_verdict,
    _new_tuple,
    _sky_index,
    _sorted_mags,
    _Verdict,
)
from startrack.kvector import KVectorDatabase, cached_subset
from startrack.records import Match, ReasonCode


@dataclass(frozen=True)
class PyramidConfig:
    """Settings of the pyramid search."""

    max_triads: int = field(default=300, metadata={"help": "Triads of image stars tried (smart index order)."})
    max_triangles: int = field(default=64, metadata={
        "help": "Catalog triangles of one triad beyond which the triad is skipped as uninformative (in the "
                "free-focal-length pass, times the scales the triad tells apart)."})


_TRIADS: dict = {}      # smart index sequence per number of search stars

#: A pattern star has fewer than this many brighter database stars within half the sensor's short side of
#: it (:func:`pattern_database`).  A frame of at most this many search stars is searched in one tier: it has
#: few patterns to compare, so the proposals a first tier verified in vain (a star of its pattern not a
#: pattern star) would weigh on its false-match gate, where a dense frame's patterns outnumber them.
PATTERN_STARS = 10
#: The first tier is searched when it holds at most this fraction of the database's pairs (else it would
#: save little and double the search of a frame it cannot identify).
PATTERN_PAIRS_MAX = 0.5


def pattern_budget(max_proposals: int) -> int:
    """The proposals the first tier may verify: a quarter of the budget (at least one)."""
    return max(1, max(int(max_proposals), 1) // 4)


def pattern_database(db, camera):
    """The first tier of the pyramid's search for ``camera``: ``db``'s pairs whose two stars are pattern
    stars (:meth:`~startrack.kvector.KVectorDatabase.pairs_subset`, the same stars), or None when that
    would keep more than :data:`PATTERN_PAIRS_MAX` of the pairs (or none).

    A star's brighter neighbours within ``r`` = half the field's short side are counted from the
    database's own pairs (every pair up to its largest angle; a database made for a narrower field
    counts fewer, keeping more stars); a pattern star has fewer than :data:`PATTERN_STARS`.  Made once
    per database and camera model (cached on the database, which drops it when its arrays are set)."""
    return _pattern_tier(db, camera)[0]


def _first_tier(db, camera, use):
    """The first tier a frame of ``use`` search stars is searched with (:func:`pattern_database`), or None: a
    frame of at most :data:`PATTERN_STARS` search stars has one tier."""
    return _pattern_tier(db, camera)[0] if use > PATTERN_STARS else None


def _pattern_tier(db, camera):
    """``(pattern_database(db, camera), made now)``."""
    if type(db) is not KVectorDatabase:
        return None, False
    d = db.__dict__
    last = d.get("_pattern_last")
    if last is not None and last[0] is camera:
        return last[1], False
    key = _PATTERN_KEY(camera)
    cache = d.get("_pattern_dbs")
    if cache is None:
        cache = d["_pattern_dbs"] = {}
    made = key not in cache
    if made:
        r = math.radians(min(camera.fov_deg)) / 2.0
        # (kept in the cache for the next process: the same tier of the same file and radius; "/1": this way of
        # making it, _pattern_database's)
        cache[key] = cached_subset(db, f"pattern-tier/1|{r!r}|{PATTERN_STARS}|{PATTERN_PAIRS_MAX!r}",
                                   lambda d: _pattern_database(d, r))
    first = cache[key]
    d["_pattern_last"] = (camera, first)
    return first, made


_PATTERN_KEY = operator.attrgetter("focal_length_px", "cx", "cy", "width", "height", "lens_terms")


def _pattern_database(db, r):
    """:func:`pattern_database` of the stars' brighter neighbours within ``r`` (rad)."""
    pair_cos = np.asarray(db.pair_cos)
    pair_i, pair_j = np.asarray(db.pair_i), np.asarray(db.pair_j)
    near = int(np.searchsorted(pair_cos, math.cos(r)))
    mag = np.asarray(db.star_mag, dtype=np.float64)
    pi, pj = pair_i[near:], pair_j[near:]
    mi, mj = mag[pi], mag[pj]
    n = len(mag)
    brighter = np.bincount(pj[mi < mj], minlength=n) + np.bincount(pi[mj < mi], minlength=n)
    pattern = brighter < PATTERN_STARS
    keep = pattern[pair_i] & pattern[pair_j]
    kept = int(np.count_nonzero(keep))
    if kept == 0 or kept > PATTERN_PAIRS_MAX * len(pair_cos):
        return None
    first = db.pairs_subset(keep)
    first.params["pattern_stars"] = int(np.count_nonzero(pattern))
    return first


def prepare_pyramid(config, camera, db, eps):
    """:attr:`Algorithm.prepare`: the first tier's database for this camera (:func:`pattern_database`)
    and its kernel arrays, made before the frame's clock starts.  True when they were made now."""
    first, made = _pattern_tier(db, camera)
    if made and first is not None:
        _plan(first)
    return made


def _search(ctx, config, quadratic):
    from startrack._kernels.pyramid import free_focal_patterns, pyramid_candidates, smart_triads

    n = len(ctx.b)
    tol = np.ascontiguousarray(ctx.tol, dtype=np.float64)
    triads = _TRIADS.get(n)
    if triads is None:
        if len(_TRIADS) > 64:
            _TRIADS.clear()
        triads = _TRIADS[n] = [tuple(r) for r in smart_triads(n).tolist()]
    seen = set()
    used = triads[:config.max_triads]
    budget = max(int(ctx.params.max_proposals), 1)
    first = _first_tier(ctx.db, ctx.camera, n)
    # The pattern stars' pairs first (a quarter of the budget), then every pair (module docstring).
    tiers = [(first, pattern_budget(budget)), (ctx.db, budget)] if first is not None else [(ctx.db, budget)]
    # The triads at the nominal focal length, then, when the focal length may be off
    # (params.max_focal_error), again with it free within that (pyramid_candidates' focal_error):
    # a field seen through a focal length 1 % off has its long pairs a few tolerances away from
    # the database's.  The pattern count goes on through the second pass and the second tier, a triad in a
    # free-focal-length pass counting the scales it tells apart (free_focal_patterns): the look-elsewhere
    # factor of the gate.
    # (ctx.focal_pass: the driver's choice of one pass alone, see FusedFrame.focal_pass.)
    passes = [0.0] + ([float(ctx.params.max_focal_error)] if ctx.params.max_focal_error > 0 else [])
    if ctx.focal_pass == NOMINAL_PASS:
        passes = passes[:1]
    elif ctx.focal_pass == FREE_PASS:
        passes = passes[1:]
    looked = 0
    # A triad's pyramid is completed by whichever other search star matches: n - 3 four-star patterns a triad.
    fourth = max(1, n - 3)
    proposed = 0
    floor = 0
    for tier, (db, tier_budget) in enumerate(tiers):
        if tier > 0:
            # The second tier compares the same image patterns again, against every pair: the patterns compared
            # are the more of the two tiers' counts, not their sum (fused_pyramid's floor).
            floor, looked = looked * fourth, 0
        arrays = db.__dict__.get("_pyramid_arrays")
        if arrays is None:
            arrays = db.__dict__["_pyramid_arrays"] = (np.asarray(db.line, dtype=np.float64),
                                                       np.asarray(db.quad, dtype=np.float64))
        line, quad = arrays
        adjacency = pair_adjacency(db)
        last = tier == len(tiers) - 1
        # With a second pass to come, the nominal focal length has half the tier's budget: a dense field seen
        # through a focal length a few per cent off can spend all of it on chance pyramids there.
        half = (tier_budget + 1) // 2 if len(passes) > 1 else None
        spent = False
        for focal_error in passes:
            if spent:
                break
            nominal = focal_error == 0.0 and half is not None
            for i, j, k in used:
                if spent or (nominal and proposed >= half):
                    break
                # The patterns compared so far: one a triad, a scale-free triad as many as it tells scales apart.
                scales = 1 if focal_error == 0.0 else free_focal_patterns(ctx.b, tol, ctx.margin, i, j, k,
                                                                           focal_error)
                looked += scales
                # A scale-free triad's windows hold its triangles at each scale it tells apart: it is uninformative
                # beyond that many times the nominal limit (max_triangles).
                out, n_tri = pyramid_candidates(ctx.b, tol, ctx.margin, i, j, k, db.star_vector, db.pair_i,
                                                db.pair_j, db.pair_cos, db.kvector, line, db.kquad, quad, quadratic,
                                                config.max_triangles * scales, 256, *adjacency, focal_error)
                for r, I, J, K, R in out.tolist():
                    if nominal and proposed >= half:
                        break
                    image, catalog = ([i, j, k], [I, J, K]) if r < 0 else ([i, j, k, r], [I, J, K, R])
                    # The driver's test: the same correspondences (another triad of the same stars, or the same
                    # pyramid found again in the second pass or tier) are no new trial, and do not count to
                    # ``half`` or the budgets.
                    key = frozenset(zip(image, catalog))
                    if key in seen:
                        continue
                    seen.add(key)
                    proposed += 1
                    yield Proposal(image, catalog, max(floor, looked * fourth), {"triangles": int(n_tri)})
                    if not last and proposed >= tier_budget:
                        # The first tier's budget is spent (the driver stops at the whole budget).
                        spent = True
                        break


def search_pyramid(ctx, config: PyramidConfig):
    """Pyramid proposals with k-vector range look-ups."""
    return _search(ctx, config, False)


#: Rejected proposals verified in one kernel call before the driver looks at its clock (the time budget).
PAUSE = 8


def fused_pyramid(config: PyramidConfig, frame, camera, db, params):
    """:func:`search_pyramid` with the driver's verification of each proposal, in one kernel call
    (:func:`startrack._kernels.pyramid.pyramid_identify`; :attr:`startrack.identify.algorithm.Algorithm.fused`).

    The kernel returns after :data:`PAUSE` rejected proposals so that the time budget is looked at
    between them (every proposal in the Python loop).  With two tiers (:func:`pattern_database`) the
    kernel searches the first with :func:`pattern_budget` proposals, then, when it found nothing, the
    whole database on the same state: the proposals tried (and their pairs) and the best rejected verdict go
    on, and the patterns compared are the more of the two tiers' counts (the second compares the same image
    patterns against every pair: the kernel's count never falls below the first tier's)."""
    xs = frame.xs
    n = len(xs)
    first = _first_tier(db, camera, frame.use)
    if first is not None:
        plan = _plan(first)
        buffers, rest, dcm = _inputs(plan, config, frame, camera, params, n, True)
        got = _drive(plan, (xs, frame.ys, frame.sig_px, frame.flux, *rest), frame)
        if got is None:
            return _failed(buffers, db, params, f"search time of {params.max_time_ms:g} ms spent", ReasonCode.TIMEOUT)
        if got[0] == 0:
            return _accepted(buffers, dcm, n, got)
        state, best = buffers[0], buffers[2]
        if state[2] >= max(int(params.max_proposals), 1):
            return _failed(buffers, db, params, f"search budget of {params.max_proposals} proposals spent",
                           ReasonCode.NO_PATTERN)
        # The patterns the first tier compared (pyramid_identify's count is (t + 1 + extra) x fourth): all its
        # triads when it searched them all, else those to the triad of its last proposal.  The second tier
        # compares the same image patterns again, against every pair: its count starts at its own first triad
        # and never falls below the first tier's (the kernel's floor state[3]), the patterns compared being
        # the more of the two, not their sum.
        fourth = max(1, frame.use - 3)
        first_patterns = int(state[0] + state[4]) * fourth if got[0] == 1 else int(state[3])
        keep_state, keep_best = state.copy(), best.copy()
        plan = _plan(db)
        buffers, rest, dcm = _inputs(plan, config, frame, camera, params, n)
        state, best = buffers[0], buffers[2]
        state[:] = keep_state
        best[:] = keep_best
        state[0] = state[1] = state[4] = 0
        state[3] = max(int(state[3]), first_patterns)
    else:
        plan = _plan(db)
        buffers, rest, dcm = _inputs(plan, config, frame, camera, params, n)
    got = _drive(plan, (xs, frame.ys, frame.sig_px, frame.flux, *rest), frame)
    if got is None:
        return _failed(buffers, db, params, f"search time of {params.max_time_ms:g} ms spent", ReasonCode.TIMEOUT)
    status = got[0]
    if status == 2:
        return _failed(buffers, db, params, f"search budget of {params.max_proposals} proposals spent",
                       ReasonCode.NO_PATTERN)
    if status == 1:
        return _failed(buffers, db, params, "no consistent star pattern found", ReasonCode.NO_PATTERN)
    return _accepted(buffers, dcm, n, got)


def _drive(plan, args, frame):
    """The kernel's calls on ``args`` until it accepts a proposal (status 0), searched every triad (1) or
    spent its budget (2): its last return, or None when the frame's time budget ran out at a pause."""
    fn = plan[3]
    if fn is None:
        kernel = plan[0]
        fn = plan[3] = kernel.resolve(args) if hasattr(kernel, "resolve") else kernel
    while True:
        got = fn(*args)
        if got[0] <= 2:
            return got
        if time.perf_counter() > frame.deadline:
            return None


def _accepted(buffers, dcm, n, got):
    """:func:`fused_pyramid`'s outcome of an accepted proposal (the kernel's return ``got``)."""
    _, _, p_false, nm, total, rms, n_tri = got
    # Views of this thread's buffers serve the rest of this frame's run(); the quaternion and the matches
    # outlive it.  res_i: every detection's match, the matched detections, their ids, their database indices.
    state, _, _, res_i, res_f = buffers
    _, _, tried, patterns, _, _ = state.tolist()
    end = n + nm
    pairs = res_i[n:end + nm].tolist()      # the matched detections, then their ids
    matches = list(map(_new_tuple, repeat(Match), zip(pairs[:nm], pairs[nm:])))
    return SearchOutcome(_Verdict(matches, res_i[n:end], res_i[end + nm:end + 2 * nm], dcm, float(p_false), None, None,
                                  None, res_f[:4].copy(), rms),
                         None if total == 1.0 else float(total), {"triangles": int(n_tri)}, None, {}, tried, patterns,
                         _NO_PATTERN_FOUND, _NO_PATTERN)


_NO_PATTERN_FOUND, _NO_PATTERN = "no consistent star pattern found", ReasonCode.NO_PATTERN   # (global look-ups)


def _failed(buffers, db, params, reason, code):
    """:func:`fused_pyramid`'s outcome without an accepted proposal: the best rejected one's verdict
    (the kernel's ``best``), the counts of its ``state``, why the search stopped."""
    state, _, best, _, _ = buffers
    _, _, tried, patterns, _, _ = state.tolist()
    if not best[0]:
        return SearchOutcome(None, None, {}, None, {}, tried, patterns, reason, code)
    bv = _fused_verdict(int(best[1]), None, None, None, best[2], int(best[3]), int(best[4]), int(best[5]), None, None,
                        db, params)
    return SearchOutcome(None, None, {}, bv, {"triangles": int(best[6])}, tried, patterns, reason, code)


def pair_adjacency(db):
    """Every database star's pairs sorted by cosine (:func:`startrack._kernels.pyramid.pair_adjacency`),
    built once per database (the fourth star's look-up of :func:`pyramid_candidates`)."""
    got = db.__dict__.get("_pair_adjacency")
    if got is None or got[0] is not db.pair_cos:
        got = db.__dict__["_pair_adjacency"] = (db.pair_cos, _kernels.pair_adjacency(
            len(db.star_vector), np.ascontiguousarray(db.pair_i), np.ascontiguousarray(db.pair_j),
            np.ascontiguousarray(db.pair_cos, dtype=np.float64)))
    return got[1]


_BUFFERS = threading.local()


def _buffers(budget, n):
    """``(buffers, dcm)``: the kernel's in/out arrays ``state``, ``seen``, ``best``, ``res_i`` and ``res_f``
    (:func:`fused_pyramid`) for a frame of ``n`` stars and the attitude matrix's view of ``res_f``, made
    once per thread and proposal budget (and grown for more stars) and reused by the thread's next
    frames: ``state`` and ``best`` zeroed, ``seen``'s rows read by the kernel only after it wrote them in
    the same search, ``res_i``/``res_f`` written with an accepted verdict."""
    got = getattr(_BUFFERS, "arrays", None)
    if got is None or len(got[0][1]) != budget or len(got[0][3]) < 4 * n:
        arrays = (np.zeros(6, np.int64), np.empty((budget, 9), np.int64), np.zeros(7),
                  np.empty(max(512, 4 * n), np.int64), np.empty(13))
        got = _BUFFERS.arrays = (arrays, arrays[4][4:13].reshape(3, 3))
    else:
        got[0][0].fill(0)
        got[0][2].fill(0)
    return got


def _inputs(plan, config, frame, camera, params, n, first=False):
    """``(buffers, rest, dcm)``: the thread's buffers (:func:`_buffers`; ``state`` and ``best`` zeroed but
    ``state[5]``, the frame's ``trials0``), the
    kernel's arguments after the frame's four arrays (the triads, ``fpar`` and ``ipar`` of :func:`_settings`,
    the buffers, the database's arrays of ``plan``) and the attitude matrix's view of the buffers.
    ``first``: ``plan`` is the first tier's (:func:`pattern_database`), whose ``ipar`` holds
    :func:`pattern_budget` proposals.

    Kept with the database's plan per value of the settings (the last 64) and used again while the
    thread's buffers are the same and large enough: one look-up instead of those of :func:`_settings`
    and :func:`_buffers` and a new tuple.  The thread's last frame's plan, camera and configuration
    (frozen; by identity), settings (which may change between frames; by value) and tolerances are
    compared first; when they are the same, the arguments are looked up by the frame's number of search
    stars and focal-length passes (:attr:`~startrack.identify.algorithm.FusedFrame.focal_pass`) alone, without
    hashing the settings (so the thread holds its last database's arrays until its next frame)."""
    pkey = _PARAMS_KEY(params)
    margin, eps = frame.margin, frame.eps
    use = 4 * frame.use + frame.focal_pass       # the search stars and the focal-length passes, one int
    buffers, dcm = getattr(_BUFFERS, "arrays", (None, None))
    last = getattr(_BUFFERS, "last", None)
    if (last is not None and last[0] is plan and last[1] is camera and last[2] is config and last[3] == pkey
            and last[4] == margin and last[5] == eps):
        by_use = last[6]
        rest = by_use.get(use)
    else:
        by_use = {}
        rest = None
    if rest is None:
        rest = plan[4].get((_CAMERA_KEY(camera), pkey, config.max_triads, config.max_triangles, margin, eps, use))
    # rest[3] is the state array of the buffers it was made with
    if rest is None or buffers is None or rest[3] is not buffers[0] or len(buffers[3]) < 4 * n:
        fpar, ipar, budget, triads = _settings(config, frame, camera, params)
        if first:
            ipar = ipar.copy()
            ipar[5] = pattern_budget(budget)
        buffers, dcm = _buffers(budget, n)
        memo = plan[4]
        if len(memo) > 64:
            memo.clear()
        rest = memo[(_CAMERA_KEY(camera), pkey, config.max_triads, config.max_triangles, margin, eps, use)] = (
            triads, fpar, ipar, *buffers, *plan[2])
    else:
        buffers[0].fill(0)
        buffers[2].fill(0)
    if frame.trials0:
        buffers[0][5] = frame.trials0       # the kernel's trials of the frame's earlier searches
    if by_use.get(use) is not rest:
        if len(by_use) > 64:
            by_use.clear()
        by_use[use] = rest
        _BUFFERS.last = (plan, camera, config, pkey, margin, eps, by_use)
    return buffers, rest, dcm


_SETTINGS: dict = {}         # fused_pyramid's kernel settings per camera, IdentifyParams and config values
_CAMERA_KEY = operator.attrgetter("focal_length_px", "cx", "cy", "width", "height")
_PARAMS_KEY = operator.attrgetter("match_radius_px", "match_sigma", "margin_arcsec", "max_false_probability",
                                  "max_focal_error", "tolerance_arcsec", "tolerance_sigma", "min_matches",
                                  "max_proposals")


def _settings(config, frame, camera, params):
    """:func:`fused_pyramid`'s ``fpar`` and ``ipar`` (the kernel only reads them), the proposal budget and
    the triads of the frame's search stars (smart index sequence).

    Made once per value of what they hold and looked up after: first by the camera's, the settings'
    and the configuration's values (IdentifyParams can change between frames: the key is its values,
    not the object), then by the frame's tolerance and number of search stars (the same for every
    frame with a fixed ``sigma_px``; with the stars' own sigmas a new frame copies the first level)."""
    key = (_CAMERA_KEY(camera), _PARAMS_KEY(params), config.max_triads, config.max_triangles)
    level = _SETTINGS.get(key)
    if level is None:
        fpar = np.array([0.0, camera.focal_length_px, camera.cx, camera.cy, camera.width, camera.height,
                         -1.0 if params.match_radius_px is None else params.match_radius_px, params.match_sigma,
                         math.radians(params.margin_arcsec / 3600.0), 0.0, AMBIGUITY_CHI2, MAG_SIGMA_FLOOR,
                         MAG_GATE, params.max_false_probability, params.max_focal_error,
                         -1.0 if params.tolerance_arcsec is not None else params.tolerance_sigma], dtype=np.float64)
        budget = max(int(params.max_proposals), 1)
        ipar = np.array([config.max_triads, config.max_triangles, params.min_matches, 0, 0, budget, PAUSE, 0, 0],
                        dtype=np.int64)
        if len(_SETTINGS) > 64:
            _SETTINGS.clear()
        level = _SETTINGS[key] = (fpar, ipar, budget, {})
    frames = level[3]
    use = frame.use
    fkey = (frame.margin, frame.eps, use, frame.focal_pass)
    got = frames.get(fkey)
    if got is None:
        fpar, ipar = level[0].copy(), level[1].copy()
        fpar[0], fpar[9], ipar[7], ipar[8] = frame.margin, frame.eps, use, frame.focal_pass
        triads = _TRIAD_ARRAYS.get(use)
        if triads is None:
            if len(_TRIAD_ARRAYS) > 64:
                _TRIAD_ARRAYS.clear()
            triads = _TRIAD_ARRAYS[use] = _kernels.smart_triads(use)
        if len(frames) > 64:
            frames.clear()
        got = frames[fkey] = (fpar, ipar, level[2], triads)
    return got


_PLAN_SOURCES = operator.attrgetter("star_vector", "pair_i", "pair_j", "pair_cos", "kvector", "line", "kquad", "quad",
                                    "star_mag", "star_id")


def _plan(db):
    """The database's arrays as :func:`fused_pyramid`'s kernel takes them, and the kernel's entry for
    them (resolved at the first call), cached on the database while its arrays (and the kernel) are
    the same objects: ``[kernel, source arrays, arrays, entry, the last frame's inputs]`` (:func:`_inputs`).
    A :class:`~startrack.kvector.KVectorDatabase` drops the cache itself when an array is set; another
    database's arrays are compared each time."""
    kernel = _kernels.pyramid_identify
    plan = db.__dict__.get("_pyramid_plan")
    if plan is not None and plan[0] is kernel and type(db) is KVectorDatabase:
        return plan
    src = _PLAN_SOURCES(db)
    if plan is not None and plan[0] is kernel and all(map(operator.is_, plan[1], src)):
        return plan
    z_order, z_sorted = _sky_index(db)
    arrays = (np.ascontiguousarray(db.star_vector, dtype=np.float64), np.ascontiguousarray(db.pair_i),
              np.ascontiguousarray(db.pair_j), np.ascontiguousarray(db.pair_cos, dtype=np.float64),
              np.ascontiguousarray(db.kvector), np.asarray(db.line, dtype=np.float64), np.ascontiguousarray(db.kquad),
              np.asarray(db.quad, dtype=np.float64), np.ascontiguousarray(db.star_mag, dtype=np.float64),
              _sorted_mags(db), z_order, z_sorted) + pair_adjacency(db) + (
                  np.ascontiguousarray(db.star_id, dtype=np.int64),)
    plan = db.__dict__["_pyramid_plan"] = [kernel, src, arrays, None, {}]
    return plan


_TRIAD_ARRAYS: dict = {}    # smart index sequence per number of search stars, as the kernel takes it


PYRAMID = Algorithm("pyramid", search_pyramid, PyramidConfig, "kvector",
                    "Mortari's pyramid on the k-vector pair database.", fused=fused_pyramid,
                    prepare=prepare_pyramid, focal_passes=True)
