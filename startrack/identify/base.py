"""What every identification algorithm shares: the search driver, tolerances, verification, the result.

An algorithm is a *generator of proposals*: a few star correspondences (a
pyramid, a voting cluster, a label group, ...) in the order its paper searches
them.  The driver :func:`run` takes them one by one and, identically for every
algorithm,

1. solves the attitude of the proposal (QUEST) and measures the focal-length
   scale it implies;
2. projects every database star with it and matches every detection to the
   nearest predicted star within the detection's own match radius
   (``match_sigma`` of its centroid sigma; one-to-one, ambiguous neighbours
   refused), refines the attitude on all matches and matches again; then
   every match must be unambiguous within its radius (a close pair of catalog
   stars with two detections is named by position and magnitude only when the
   other assignment is clearly worse, else refused), magnitude-consistent
   (outside the proposal) and agree with the attitude the *other* matches give
   (leave one out: a proposal whose fit bent to take a wrong star is rejected);
3. computes the probability that the result is a coincidence
   (:func:`false_match_probability`) and accepts the first proposal whose
   probability, *multiplied by the number of patterns and proposals tried*
   (look-elsewhere), is below ``max_false_probability``.

The search stops at the first accepted proposal or when a budget
(``max_proposals``, ``max_time_ms``) runs out; the result reports the trials.
Because every proposal passes the same gate, an algorithm that proposes more
(continuing after a rejected candidate, as paper 003's Fig. 5 loop and paper
004's search do) gains success but never wrong answers.
"""
from __future__ import annotations

import contextvars
import itertools
import logging
import math
import operator
import time
from dataclasses import dataclass, field
from typing import Callable, Iterator

import numpy as np

from startrack.records import Identification, Match, ReasonCode, StarTable, Status

__all__ = ["Algorithm", "IdentifyParams", "NoConfig", "Proposal", "SearchContext", "false_match_probability",
           "CatalogStars", "match_catalog", "run", "tolerance_rad"]

log = logging.getLogger(__name__)
_LOGGED_PROPOSALS = 20      # rejected proposals logged one by one (debug) before going quiet
#: True while :func:`startrack.identify.warm_up` runs its made-up frame: nothing of it is logged.
WARMING_UP = contextvars.ContextVar("startrack_identify_warming_up", default=False)
log.addFilter(lambda _record: not WARMING_UP.get())


@dataclass
class IdentifyParams:
    """Settings shared by all algorithms.

    Attributes
    ----------
    sigma_px : float or None
        1-sigma centroid noise (px) of every star; ``None``: each star's own
        ``sigma_px`` (times ``reported_sigma_factor``), else 0.5 px.
    tolerance_sigma : float
        Half-width of an inter-star angle window in sigmas of that angle.
    match_sigma : float
        Match radius of a detection in sigmas of its centroid.
    tolerance_arcsec : float or None
        Fixed angle half-width (arcsec), overriding the sigma-based one.
    margin_arcsec : float
        Added to every tolerance (calibration, aberration), arcsec.
    match_radius_px : float or None
        Fixed match radius (px), overriding the sigma-based one.
    max_stars : int
        Brightest detections the pattern search uses (all are matched at the end).
    max_search_stars : int
        When the search of the ``max_stars`` brightest ends without a proposal that passes
        (every pattern compared or the proposal budget spent, within ``max_time_ms``), it searches
        again with twice as many detections and a proposal budget of its own, and so on up to this
        many (:func:`search_levels`): a field whose brightest detections are mostly not catalog
        stars (nebulae, halos, false stars, stars beyond the database) is found among the fainter
        ones, as astrometry.net deepens its field stars.  A search with a free-focal-length pass
        (the pyramid, ``max_focal_error`` > 0) searches every depth at the nominal focal length
        before the free focal length's (:func:`search_plan`).
        The trials of every search count in the false-match probability.
    min_matches : int
        Matched stars needed (three when the frame has only three).
    max_false_probability : float
        Refuse an identification more likely than this to be a coincidence.
    max_focal_error : float
        Largest relative focal-length error measured and corrected; the pyramid searches its
        triads once more with the focal length free within it when the nominal one finds nothing
        (in the same search, or, when deeper searches are to come, after them: :func:`search_plan`);
        brightness and voting are searched again at the scales within it that their tolerance tells
        apart (:attr:`Algorithm.focal_sweep`).
    max_proposals : int
        Proposals verified before giving up (the budget of each search, see ``max_search_stars``;
        the pyramid's nominal pass has half of it when its free-focal-length pass follows, and its
        first tier, the pattern stars' pairs, a quarter:
        :func:`startrack.identify.pyramid.pattern_database`).
    max_time_ms : float
        Search time before giving up, ms.
    reported_sigma_factor : float
        Scale applied to the stars' own ``sigma_px`` (centroid estimates run low).
    max_triads : int
        Triads for 0.x-style proposers (paper 000's modified pyramid); the
        pyramid's own setting is :class:`startrack.identify.pyramid.PyramidConfig`.
    max_chance_match : float
        With a catalog to match everything against (:func:`run`'s ``catalog``), a
        detection is matched only when the chance that a catalog star lies within
        its radius by accident is below this.
    """

    sigma_px: float | None = None
    tolerance_sigma: float = 4.0
    match_sigma: float = 5.0
    tolerance_arcsec: float | None = None
    margin_arcsec: float = 2.0
    match_radius_px: float | None = None
    max_stars: int = 20
    max_search_stars: int = 80
    min_matches: int = 4
    max_false_probability: float = 1e-6
    max_focal_error: float = 0.05
    max_proposals: int = 200
    max_time_ms: float = 2000.0
    reported_sigma_factor: float = 1.5
    max_triads: int = 200
    max_chance_match: float = 0.001


@dataclass(frozen=True)
class NoConfig:
    """An algorithm without settings of its own."""


@dataclass
class Proposal:
    """An algorithm's hypothesis.

    Attributes
    ----------
    image : list of int
        Indices of the search stars (into :attr:`SearchContext.b`).
    catalog : list of int
        Database star indices (into the database's star table), same order.
    patterns : int
        Image patterns the algorithm has compared with the database so far
        (cumulative; the look-elsewhere factor of the confidence).
    details : dict
        Algorithm-specific facts reported with the result (``mode``, ``votes``, ...).
    """

    image: list
    catalog: list
    patterns: int = 1
    details: dict = field(default_factory=dict)


#: :attr:`SearchContext.focal_pass`: a search with focal-length passes (:attr:`Algorithm.focal_passes`)
#: searches the nominal focal length, then the free one (both, one search); the nominal alone; the free alone.
BOTH_PASSES, NOMINAL_PASS, FREE_PASS = 0, 1, 2


@dataclass
class SearchContext:
    """What a proposal generator gets for one frame.

    Attributes
    ----------
    b : ndarray, shape (n, 3)
        Unit vectors (camera frame) of the search stars, brightest first.
    stars : list of dict
        The search stars as given (``x``, ``y``, ``flux``, ``sigma_px``, ...).
    camera : Camera
    db : database of the algorithm's kind
    eps : float
        Angle tolerance (rad) valid for every pair of search stars (the largest pair tolerance).
    tol : ndarray, shape (n,)
        Per-star angle tolerance (rad): the pair (i, j) tolerance is
        ``sqrt(tol_i^2 + tol_j^2) + margin``.
    margin : float
        Additive part of every pair tolerance (rad).
    params : IdentifyParams
    flux : ndarray or None
        Fluxes of the search stars (``None`` when the frame has none).
    deadline : float
        ``time.perf_counter()`` value at which the driver's time budget ends: a search
        with long steps between proposals stops there too (:meth:`expired`).
    focal_pass : int
        For a search with focal-length passes (:attr:`Algorithm.focal_passes`): :data:`BOTH_PASSES`,
        :data:`NOMINAL_PASS` or :data:`FREE_PASS` (:func:`search_plan`); others ignore it.
    """

    b: np.ndarray
    stars: list
    camera: object
    db: object
    eps: float
    tol: np.ndarray
    margin: float
    params: IdentifyParams
    flux: np.ndarray | None = None
    deadline: float = math.inf
    focal_pass: int = 0

    def expired(self) -> bool:
        """True once the driver's time budget (``params.max_time_ms``) is spent."""
        return time.perf_counter() > self.deadline

    def pair_eps(self, i: int, j: int) -> float:
        """Tolerance (rad) of the angle between search stars ``i`` and ``j``."""
        return math.hypot(self.tol[i], self.tol[j]) + self.margin


@dataclass(frozen=True)
class Algorithm:
    """A registered identification algorithm.

    Attributes
    ----------
    name : str
        The name on the command line (``-a NAME``).
    search : callable
        ``search(ctx: SearchContext, config) -> Iterator[Proposal]`` in the paper's order.
    config : type
        Dataclass of the algorithm's settings (every field has a default and
        ``metadata["help"]``); the command line offers each field as an option.
    database : str
        The database kind it needs (``"kvector"``, ``"labels"``).
    summary : str
        One line for ``--help``.
    uses_brightness : bool
        True when the search's own pattern statistics already include the
        magnitudes (the confidence then does not count magnitude agreement
        again).  A search that only *filters* geometric candidates by
        brightness (paper 003's brightness order) leaves it False: the
        pattern chance ``E_core`` counts every geometric chance match, and a
        chance match must then also agree in magnitude, so multiplying by the
        magnitude agreement's probability counts nothing twice.
    fused : callable or None
        The search *and* the driver's verification loop in compiled code, for a
        distortion-free camera: ``fused(config, frame, camera, db, params) -> SearchOutcome``
        (``frame``: a :class:`FusedFrame`), deciding exactly as :func:`run` does
        with ``search`` and :func:`_verify_fused` (one kernel call per frame
        instead of a Python round trip per proposal).  :func:`run` uses it when
        set, the camera has no distortion and debug logging (which reports each
        rejected proposal) is off.
    prepare : callable or None
        ``prepare(config, camera, db, eps) -> bool``: what the search needs of the
        database for this sensor and tolerance, built once (e.g. the grid's catalog
        patterns); :func:`run` calls it before the frame's clock starts and reports
        a build's time as ``details["prepare_ms"]`` (True: it built now).
    focal_passes : bool
        True when the search has a second pass with the focal length free within
        ``params.max_focal_error`` (after the nominal focal length's) and searches one of the
        two alone when :attr:`SearchContext.focal_pass` (:attr:`FusedFrame.focal_pass`) says so:
        :func:`search_plan` then searches every depth at the nominal focal length first.
    focal_sweep : bool
        True when the search compares angles at the focal length it is given and has no pass of
        its own with the focal length free: when every search of the plan found nothing and
        ``params.max_focal_error`` > 0, :func:`run` searches the first depth again at each
        focal-length scale the tolerance tells apart (:func:`focal_scales`, :func:`_steps`), a camera
        of that focal length each time.
    """

    name: str
    search: Callable[..., Iterator[Proposal]]
    config: type = NoConfig
    database: str = "kvector"
    summary: str = ""
    uses_brightness: bool = False
    fused: Callable | None = None
    prepare: Callable | None = None
    focal_passes: bool = False
    focal_sweep: bool = False


@dataclass(slots=True)
class FusedFrame:
    """What :attr:`Algorithm.fused` gets: the frame as :func:`run` read it.

    ``xs``, ``ys``, ``flux`` (NaN where unknown; the fluxes count when at least three are
    finite), ``sig_px``: float64 arrays of every star; ``use``: the search stars (the first);
    ``eps``, ``margin``: the angle tolerances (rad) of :class:`SearchContext`; ``deadline``: the
    end of the time budget (``time.perf_counter()``); ``trials0``: the trials of this frame's earlier
    searches (:func:`search_plan`), added to this search's in the false-match probability;
    ``focal_pass``: :attr:`SearchContext.focal_pass`."""

    xs: np.ndarray
    ys: np.ndarray
    flux: np.ndarray
    sig_px: np.ndarray
    use: int
    eps: float
    margin: float
    deadline: float
    trials0: int = 0
    focal_pass: int = 0


@dataclass(slots=True)
class SearchOutcome:
    """The driver loop's result (:attr:`Algorithm.fused`): the accepted verdict and its focal scale and
    proposal details, or the best rejected one; proposals tried, patterns compared, why it stopped."""

    accepted: _Verdict | None
    scale: float | None
    details: dict
    best: _Verdict | None
    best_details: dict
    tried: int
    patterns: int
    reason: str
    code: ReasonCode


def star_sigmas_px(stars: list, params: IdentifyParams) -> np.ndarray:
    """1-sigma centroid noise per star (px): the parameter, else the star's ``sigma_px`` (scaled), else 0.5."""
    return _sigmas(len(stars), params, lambda: _floats([s.get("sigma_px") for s in stars]))


def _sigmas(n: int, params: IdentifyParams, reported) -> np.ndarray:
    """:func:`star_sigmas_px` of ``n`` stars: ``params.sigma_px`` for all, else ``reported()`` (their reported
    sigmas, NaN: none; ``None``: no column) scaled by ``params.reported_sigma_factor`` within 0.05-2 px, a
    star without one getting the frame's median and a frame without any 0.5 px each."""
    if params.sigma_px is not None:
        out = np.empty(n)
        out.fill(float(params.sigma_px))        # np.full's values, in a third of its time
        return out
    reported = reported()
    if reported is None:
        return np.full(n, 0.5)
    ok = np.isfinite(reported) & (reported > 0)
    have = np.count_nonzero(ok)
    if have == 0:
        return np.full(len(reported), 0.5)
    # np.clip's values (NaN stays NaN), without its Python wrapper
    scaled = np.minimum(np.maximum(reported * params.reported_sigma_factor, 0.05), 2.0)
    if have < len(scaled):
        scaled[~ok] = float(np.median(scaled[ok]))
    return scaled


def tolerance_rad(camera, sigma_px: float, params: IdentifyParams) -> float:
    """Half-width of the angle window between two stars of centroid noise ``sigma_px`` each.

    ``eps = k sqrt(2) sigma_px / f + margin``: an angle between two stars errs
    by the two centroid errors along their separation (``sqrt 2`` of one),
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


def pattern_chance(n_cat: int, eps: float, vecs) -> float:
    """Expected number of catalog patterns matching the measured directions by chance.

    Mortari et al. (2004) / LOST: for a pair ``E = N (N-1)/2 eps sin(theta)``;
    a triangle ``E = N^3 eps^3 sin(theta_ij) / (pi sin(phi_k))``; a pyramid
    (four stars) ``E = N^4 eps^5 sin(theta_ij) / (2 pi^2 sin(phi_k) max sin(phi))``,
    ``phi`` the triangle's inner angles.  ``eps`` is the angle window (rad),
    ``N`` the stars of the database, ``vecs`` the first two to four unit vectors.
    """
    from startrack._kernels.identify import pattern_chance as kernel

    return float(kernel(int(n_cat), float(eps), np.ascontiguousarray(vecs, dtype=np.float64)))


def _missing_probability(missing: int, n_bright: int, area_frac: float) -> float:
    """Chance that a random field holds no more undetected bright catalog stars than this one.

    With the attitude, the catalog stars predicted in the image that are
    clearly brighter than the faintest detection (by the frame's own
    flux-magnitude zero point, less three times its scatter and at least
    0.5 mag; :func:`startrack._kernels.identify.check_matches`) should all be
    detected.  A coincidental match puts the pattern at a random place of the
    sky, where such stars appear at the catalog's average density: Poisson with
    mean ``lambda`` = ``n_bright`` (database stars brighter than the cut) x
    ``area_frac`` (image solid angle / 4 pi), halved for the sparsest skies.
    Returns ``P(K <= missing)``; 1 without magnitudes (``n_bright`` = 0).  The fused verification
    calls the same kernel.
    """
    from startrack._kernels.identify import missing_probability

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
    (:func:`startrack._kernels.identify.check_matches`); 1 without fluxes and
    for algorithms whose search already chose by brightness.
    """
    return min(1.0, e_core * max(trials, 1)) * _binomial_sf(n_others_matched, n_others, p_hit) * p_mags


_GEOMETRY: dict = {}


def _geometry(camera):
    """``cos`` of the largest off-axis angle (plus 0.5 deg) and the projection numbers of ``camera``
    (cached per camera model: the off-axis angle costs a projection of the corners)."""
    key = (float(camera.focal_length_px), float(camera.cx), float(camera.cy), int(camera.width), int(camera.height),
           float(camera.k1), float(camera.k2))
    got = _GEOMETRY.get(key)
    if got is None:
        if len(_GEOMETRY) > 256:
            _GEOMETRY.clear()
        if camera.k1 or camera.k2:
            off_axis = camera.max_off_axis_deg
        else:       # a pinhole: the farthest corner's angle, without projecting the corners
            dx = max(abs(-0.5 - camera.cx), abs(camera.width - 0.5 - camera.cx))
            dy = max(abs(-0.5 - camera.cy), abs(camera.height - 0.5 - camera.cy))
            off_axis = math.degrees(math.atan(math.hypot(dx, dy) / camera.focal_length_px))
        got = _GEOMETRY[key] = (math.cos(math.radians(off_axis + 0.5)),
                                (float(camera.focal_length_px), float(camera.cx), float(camera.cy),
                                 float(camera.width), float(camera.height), float(camera.k1), float(camera.k2)))
    return got


def _sorted_mags(db):
    """Every database magnitude, sorted (cached on the database): the verification's counts."""
    got = db.__dict__.get("_mags_sorted")
    if got is None or len(got) != len(db.star_mag):
        got = db.__dict__["_mags_sorted"] = np.sort(np.asarray(db.star_mag, dtype=np.float64))
    return got


_NO_INDEX = (np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.float64))


def _sky_index(db):
    """The database's sky index (:func:`startrack._kernels.identify.sky_index`: bands of z, right
    ascension within a band), cached on the database: the verification looks at the stars that can be
    in the field only (:func:`startrack._kernels.identify.cone_stars`).  About sqrt(N) bands."""
    got = db.__dict__.get("_sky_index")
    if got is None or got[0] is not db.star_vector:
        from startrack._kernels.identify import sky_index

        sv = np.ascontiguousarray(db.star_vector, dtype=np.float64)
        got = db.__dict__["_sky_index"] = (db.star_vector, sky_index(sv, max(8, min(1024, int(math.sqrt(len(sv)))))))
    return got[1]


_NUMBER = frozenset((float, int, bool, np.float64, type(None)))    # types read as themselves (None: NaN)
_GET_X, _GET_Y = operator.itemgetter("x"), operator.itemgetter("y")


def _table_arrays(table, params: IdentifyParams):
    """``x``, ``y``, ``flux`` and the 1-sigma noise (:func:`star_sigmas_px`) of a
    :class:`~startrack.records.StarTable`'s columns, float64 and contiguous, without a per-star
    object."""
    xs = np.ascontiguousarray(table.x, dtype=np.float64)
    ys = np.ascontiguousarray(table.y, dtype=np.float64)
    flux = np.ascontiguousarray(table.flux, dtype=np.float64)
    sig = _sigmas(len(xs), params,
                  lambda: None if table.sigma_px is None else np.asarray(table.sigma_px, dtype=np.float64))
    return xs, ys, flux, sig


def _frame_arrays(frame_stars):
    """``x``, ``y`` and ``flux`` (NaN where missing or not an int or float, e.g. a string) of the stars as
    float64 arrays."""
    n = len(frame_stars)
    xs = np.fromiter(map(_GET_X, frame_stars), np.float64, n)
    ys = np.fromiter(map(_GET_Y, frame_stars), np.float64, n)
    return xs, ys, _floats([s.get("flux") for s in frame_stars])


def _floats(values: list) -> np.ndarray:
    """``values`` as float64, NaN for None and for anything not an int or float (e.g. a string)."""
    if _NUMBER.issuperset(map(type, values)):         # None is NaN too
        return np.array(values, dtype=np.float64)
    return np.array([v if isinstance(v, (int, float)) else np.nan for v in values], dtype=np.float64)


def _pixels_to_vectors(camera, xs, ys):
    """``camera.pixels_to_vectors`` (one kernel call without distortion)."""
    if camera.k1 or camera.k2:
        return camera.pixels_to_vectors(xs, ys)
    from startrack._kernels.identify import pixels_to_unit

    return pixels_to_unit(xs, ys, float(camera.focal_length_px), float(camera.cx), float(camera.cy))


def verify(proposal: Proposal, b_all: np.ndarray, flux: np.ndarray, sig_px: np.ndarray, camera, db, eps: float,
           params: IdentifyParams, trials: int, use_magnitudes: bool, geom=None, scale_offset: float = 0.0) -> _Verdict:
    """Attitude, every other detection and the confidence of one proposal (see the module docstring).

    ``geom`` is :func:`_geometry` of ``camera`` (computed when not given).  ``scale_offset``
    is ``|s - 1|`` of a focal-length scale fitted to the data before this call (0: none): a
    random catalog pattern then needs to match the core's shape only up to one of the scales
    the fit could have chosen (within ``params.max_focal_error``), which multiplies the chance
    of a coincidence by their number (:func:`startrack._kernels.identify.scale_cells`; see
    :func:`_verify_with_focal`).
    """
    from startrack._kernels.identify import verify_core

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
    p_missing = _missing_probability(missing, n_bright, camera.width * camera.height / f**2 / (4 * math.pi))
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
    measured chord (angle, :func:`startrack._kernels.identify.focal_scale`) over the long pairs of
    these tentative matches (robust to the odd wrong one); significant as
    :func:`startrack._kernels.identify.scale_significant` says.
    """
    from startrack._kernels.identify import field_scale, scale_significant

    if not (camera.k1 or camera.k2):
        cos_front = math.cos(math.acos(_geometry(camera)[0]) + math.radians(0.5))
        got = field_scale(b_all, xs, ys, sig_px, star_vec, dcm, cos_front, float(camera.focal_length_px),
                          float(camera.cx), float(camera.cy), 0.0, 0.0, np.asarray(core, dtype=np.int64),
                          np.asarray(radius_px, dtype=np.float64), float(max_err), *(zindex or _NO_INDEX))
        return None if math.isnan(got) else float(got)
    front = np.flatnonzero(star_vec @ dcm[2] > math.cos(math.radians(camera.max_off_axis_deg + 1.0)))
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


#: Verify pinhole-camera proposals with one kernel call (:func:`_verify_fused`); False: the
#: step-by-step Python path (:func:`_verify_with_focal`), which the tests compare it with.
FUSED_VERIFY = True
#: Run an algorithm's search and verification loop in one kernel (:attr:`Algorithm.fused`) where it has
#: one and :data:`FUSED_VERIFY` applies; False: the Python loop over its proposals (the tests compare them).
FUSED_SEARCH = True

_REASONS = {1: ("a star of the proposal disagrees with the attitude of the others", ReasonCode.VERIFICATION_FAILED),
            2: ("the proposal's stars do not agree with the refined attitude", ReasonCode.VERIFICATION_FAILED)}


def _verify_fused(proposal, xs, ys, b_all, flux, sig_px, camera, db, eps, params, trials, use_mags):
    """:func:`_verify_with_focal` for a distortion-free camera in one kernel call
    (:func:`startrack._kernels.identify.verify_focal`): the same steps and checks on the same
    kernels, the same verdict.  Returns ``(verdict, focal scale or None)``."""
    from startrack._kernels import identify as kernels

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
    """The :class:`_Verdict` of :func:`startrack._kernels.identify.verify_focal`'s result."""
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
    taken only when the stars tell it from 1 (:func:`startrack._kernels.identify.scale_significant`:
    a step within noise changes no match, only the time); each verification at a fitted scale
    pays for every scale the fit could have chosen (``scale_offset`` of :func:`verify`), and the
    identification is refused when the field's scale refuses it.  Without this, a focal-length
    error left a few outer stars matched to the wrong neighbour (paper 004 Fig. 7 conditions).
    Scales beyond ``params.max_focal_error`` (the stated uncertainty) are never used.
    Returns ``(verdict, focal scale or None)``.
    """
    from startrack._kernels.identify import focal_scale, matched_scale

    star_vec = db.star_vector
    scale = focal_scale(b_all, np.asarray(proposal.image, dtype=np.int64), star_vec,
                        np.asarray(proposal.catalog, dtype=np.int64))     # NaN with fewer than 3 stars
    scale = None if math.isnan(scale) else float(scale)
    if scale is not None and (abs(scale - 1.0) > params.max_focal_error or abs(scale - 1.0) < 5e-4):
        scale = None    # within noise (or beyond belief): keep the nominal focal length
    cam = camera
    if scale is not None:
        cam = camera.with_focal_length(camera.focal_length_px / scale)
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
        cam = camera.with_focal_length(camera.focal_length_px / total)
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
        cam = camera.with_focal_length(camera.focal_length_px / total)
        b_all = _pixels_to_vectors(cam, xs, ys)
        v = verify(proposal, b_all, flux, sig_px, cam, db, eps, params, trials, use_mags, None, abs(total - 1.0))
    return v, (None if total == 1.0 else total)


@dataclass
class CatalogStars:
    """A catalog's stars ready for :func:`match_catalog`: ICRS unit vectors, ids, magnitudes."""

    vectors: np.ndarray
    id: np.ndarray
    mag: np.ndarray

    @classmethod
    def from_catalog(cls, catalog) -> CatalogStars:
        """From a :class:`startrack.catalog.Catalog` (vectors computed once)."""
        return cls(np.ascontiguousarray(catalog.vectors()), np.asarray(catalog.id), np.asarray(catalog.mag))


def match_catalog(matches: list, ref: np.ndarray, dcm: np.ndarray, b_all: np.ndarray, radius: np.ndarray, camera,
                  stars: CatalogStars, max_chance: float, cos_fov: float, mag_limit: float | None = None,
                  sigma: np.ndarray | None = None):
    """Match every detection left over to a (deeper) catalog with the identification's attitude.

    Each unmatched detection takes the nearest catalog star projected into the
    image within its own radius (``radius``, rad), when no other catalog star
    is within twice the radius (an unresolved neighbour -- closer to it than
    the radius -- is taken only when it is the brighter), the catalog star is
    not matched already (one-to-one, the nearer detection wins), and the
    chance of a catalog star as close by accident, ``1 - exp(-lambda)``, is
    below ``max_chance``: ``lambda`` is the density of catalog stars around the
    detection (the others within ten radii, at least the image average) times
    the disc of radius ``max(offset, sigma)`` (the observed offset, at least
    the detection's 1-sigma ``sigma``, rad; a p-value of the distance).
    Only catalog stars at or brighter than ``mag_limit`` take part (the
    sensor's depth: a deeper catalog only adds chance neighbours).  The
    attitude is then refined with every match (QUEST, weights ``1 / radius^2``).

    Parameters
    ----------
    matches : list of Match
        The identification's matches; ``ref`` their ICRS unit vectors.

    Returns
    -------
    (matches, quaternion or None)
        ``None`` when nothing was added.
    """
    from startrack._kernels.attitude import quest

    vec = stars.vectors
    front = np.flatnonzero((vec @ dcm[2] > cos_fov) & (stars.mag <= (np.inf if mag_limit is None else mag_limit)))
    pc = vec[front] @ dcm.T
    x, y = camera.vectors_to_pixels(pc)
    keep = camera.in_image(x, y)
    idx, pc = front[keep], pc[keep]
    done = np.zeros(len(b_all), dtype=bool)
    done[[m.star for m in matches]] = True
    todo = np.flatnonzero(~done)
    if len(idx) < 1 or len(todo) == 0:
        return matches, None
    taken = {int(m.id) for m in matches}
    dots = b_all[todo] @ pc.T                                   # (detections, predicted)
    order = np.argsort(-dots, axis=1)[:, :2]
    r = radius[todo]
    lam_floor = len(idx) * math.pi * (r * camera.focal_length_px) ** 2 / float(camera.width * camera.height)
    n_local = np.count_nonzero(dots >= np.cos(10 * r)[:, None], axis=1) - 1
    cand = {}
    for row, i in enumerate(todo.tolist()):
        best = int(order[row, 0])
        if dots[row, best] < math.cos(r[row]):
            continue
        if order.shape[1] > 1 and dots[row, order[row, 1]] >= math.cos(2 * r[row]):
            other = int(order[row, 1])
            if float(pc[best] @ pc[other]) < math.cos(r[row]):
                continue                                        # two distinct stars near it: ambiguous
            if stars.mag[idx[other]] < stars.mag[idx[best]]:
                best = other                                    # an unresolved pair: the brighter
        offset = math.acos(min(1.0, float(dots[row, best])))
        closest = max(offset, float(sigma[i]) if sigma is not None else r[row]) / r[row]
        if 1.0 - math.exp(-max(n_local[row] / 100.0, lam_floor[row]) * min(1.0, closest) ** 2) > max_chance:
            continue
        cid = int(stars.id[idx[best]])
        if cid in taken:
            continue
        if cid not in cand or dots[row, best] > cand[cid][1]:
            cand[cid] = (i, float(dots[row, best]), int(idx[best]))
    if not cand:
        return matches, None
    new = sorted(cand.items(), key=lambda kv: kv[1][0])
    out = list(matches) + [Match(i, cid) for cid, (i, _, _) in new]
    body = np.vstack([b_all[[m.star for m in matches]], b_all[[i for _, (i, _, _) in new]]])
    ref_all = np.vstack([ref, vec[[k for _, (_, _, k) in new]]])
    w = 1.0 / radius[[m.star for m in out]] ** 2
    q, _ = quest(np.ascontiguousarray(body), np.ascontiguousarray(ref_all), w / w.sum())
    q = q / math.sqrt(float(q @ q))
    out.sort(key=lambda m: m.star)
    return out, (-q if q[3] < 0 else q)


def _frame_depth(flux, star_index, mags, margin: float = 1.0):
    """The faintest catalog magnitude the frame can hold: its faintest detection by the zero point
    (median of catalog magnitude + 2.5 log10 flux over the identified stars) plus ``margin``; None
    without fluxes."""
    if flux is None:
        return None
    f = flux[star_index]
    ok = np.isfinite(f) & (f > 0)
    fl = flux[np.isfinite(flux) & (flux > 0)]
    if ok.sum() < 3 or len(fl) == 0:
        return None
    zp = float(np.median(mags[ok] + 2.5 * np.log10(f[ok])))
    return float(-2.5 * np.log10(fl.min()) + zp + margin)


def run(algorithm: Algorithm, config, frame_stars: list, camera, db, params: IdentifyParams,
        catalog=None) -> Identification:
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
        (:func:`match_catalog`), e.g. the full catalog behind a shallow database.

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
        pause = _prepare(algorithm, config, camera, db, eps)
        if pause:
            prepare_ms = pause * 1000
            t0 += pause       # loading for this sensor, not identification: not in time_ms
    deadline = t0 + params.max_time_ms / 1000.0
    info = log.isEnabledFor(logging.INFO)
    debug = info and log.isEnabledFor(logging.DEBUG)
    if debug:
        log.debug("%s: %d stars (%d searched), tolerance %.1f arcsec, budget %d proposals / %g ms, database %s",
                  name, n_all, use, math.degrees(eps) * 3600, params.max_proposals, params.max_time_ms,
                  getattr(db, "path", None) or type(db).__name__)
    fused = FUSED_VERIFY and not (camera.k1 or camera.k2) and (params.match_radius_px is None or
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
    details = out.details
    details["patterns"] = int(patterns)
    if searched > use:
        details["search_stars"] = searched
    if searches > 1:
        details["searches"] = searches
    if prepare_ms:
        details["prepare_ms"] = round(prepare_ms, 1)
    rms = accepted.residual_rms if accepted.residual_rms is not None else \
        float(np.sqrt(np.mean(accepted.residual_arcsec**2)))
    details["residual_arcsec_rms"] = round(rms, 3)
    matches, quaternion, scale = accepted.matches, accepted.quaternion, out.scale
    if swept is not None:
        # The verification's scale is of the swept camera's focal length: the frame's is their product.
        scale = swept * (1.0 if scale is None else scale)
    if catalog is not None:
        if not isinstance(catalog, CatalogStars):
            catalog = CatalogStars.from_catalog(catalog)
        has_flux = int(np.count_nonzero(np.isfinite(flux))) >= 3
        if b_all is None:
            b_all = _pixels_to_vectors(camera, xs, ys)
        cam = camera if scale is None else camera.with_focal_length(camera.focal_length_px / scale)
        b = b_all if scale is None else _pixels_to_vectors(cam, xs, ys)
        margin_px = math.radians(params.margin_arcsec / 3600.0) * cam.focal_length_px
        radius_px = np.full(n_all, float(params.match_radius_px)) if params.match_radius_px is not None else \
            np.maximum(1.0, params.match_sigma * sig_px + margin_px)
        n_db = len(matches)
        depth = _frame_depth(flux if has_flux else None, accepted.star_index, db.star_mag[accepted.cat_index])
        matches, q = match_catalog(matches, db.star_vector[accepted.cat_index], accepted.dcm, b,
                                   radius_px / cam.focal_length_px, cam, catalog, params.max_chance_match,
                                   _geometry(camera if scale is None else cam)[0], depth,
                                   sig_px / cam.focal_length_px)
        if depth is not None:
            details["match_mag_limit"] = round(depth, 2)
        if q is not None:
            quaternion = q
            details["matched_beyond_database"] = len(matches) - n_db
        elapsed = (time.perf_counter() - t0) * 1000
    if info:
        log.info("%s: %d of %d stars identified at proposal %d (%d pattern(s)), false-match probability %.2g, "
                 "%.0f ms", name, len(matches), n_all, tried, patterns, float(accepted.p_false), elapsed)
    return Identification(Status.OK, name, matches, time_ms=elapsed, false_match_probability=float(accepted.p_false),
                          trials=tried, tolerance_arcsec=tol_arcsec,
                          focal_scale=None if scale is None else round(float(scale), 7),
                          quaternion_estimate=quaternion, details=details)


_TOL_ARCSEC: dict = {}      # the reported tolerance (arcsec, 3 decimals) per eps: round() costs a string conversion


def _tolerances(params, sig_px, use, f):
    """``(margin, eps)``: the angle margin and the search's largest inter-star angle tolerance (rad) of a
    search of the first ``use`` stars (:class:`SearchContext`)."""
    if params.tolerance_arcsec is not None:
        eps = math.radians(params.tolerance_arcsec / 3600.0)
        return eps, eps
    margin = math.radians(params.margin_arcsec / 3600.0)
    # The largest per-star tolerance (its product and quotient are monotonic in sigma).
    smax = float(params.sigma_px) if params.sigma_px is not None else float(np.maximum.reduce(sig_px[:use]))
    return margin, float(math.sqrt(2.0) * (params.tolerance_sigma * smax / f) + margin)


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
    ``(search stars, focal_pass)`` each (:attr:`SearchContext.focal_pass`).

    The depths are :func:`search_levels`'.  For a search with a free-focal-length pass
    (:attr:`Algorithm.focal_passes`, ``params.max_focal_error`` > 0) and more than one depth, every depth
    is searched at the nominal focal length first (:data:`NOMINAL_PASS`), then at the free focal length
    (:data:`FREE_PASS`), e.g. (20, nominal), (40, nominal), (80, nominal), (20, free), (40, free),
    (80, free): the free pass compares each triad at every scale it tells apart, many times the nominal
    pass's work, and a frame whose brightest detections are not stars is found by a deeper nominal search
    at a fraction of its cost; a camera whose focal length is off pays the nominal searches (and their
    trials) before its free pass.  Otherwise each depth searches both passes (:data:`BOTH_PASSES`), as a
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
    """One search of the first ``use`` stars (``focal_pass``: :attr:`SearchContext.focal_pass`): the
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
        trials0 += max(last.tried, last.patterns)
        cam, fr = camera, frame
        if scale is not None:
            cam = camera.with_focal_length(camera.focal_length_px / scale)
            fr = (algorithm, config, frame_stars, xs, ys, None if in_kernel else _pixels_to_vectors(cam, xs, ys),
                  flux, sig_px, fused, in_kernel, cam, db, params)
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
    None)`` each: the rest of ``plan``, then, for an algorithm with :attr:`Algorithm.focal_sweep` and
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
    """:func:`run`'s loop in Python: ``algorithm.search``'s proposals, each verified (:func:`_verify_fused`
    when ``fused``, else :func:`_verify_with_focal`), until one passes or the budget ends.  ``trials0``: the
    trials of the frame's earlier searches (:attr:`FusedFrame.trials0`); ``focal_pass``:
    :attr:`SearchContext.focal_pass`."""
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
