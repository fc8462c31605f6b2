"""Identification settings and what they make of a frame's stars: centroid sigmas and angle tolerances.

:class:`IdentifyParams` is shared by every algorithm; :func:`star_sigmas_px` and :func:`tolerance_rad` turn
it and a frame's detections into the 1-sigma centroid noise of each star (px) and the half-width of an
inter-star angle window (rad) that the searches and the verification use.
"""
from __future__ import annotations

import math
import operator
from dataclasses import dataclass

import numpy as np

__all__ = ["IdentifyParams", "star_sigmas_px", "tolerance_rad"]


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
        many (:func:`~startrack.identify.driver.search_levels`): a field whose brightest detections are mostly not catalog
        stars (nebulae, halos, false stars, stars beyond the database) is found among the fainter
        ones, as astrometry.net deepens its field stars.  A search with a free-focal-length pass
        (the pyramid, ``max_focal_error`` > 0) searches every depth at the nominal focal length
        before the free focal length's (:func:`~startrack.identify.driver.search_plan`).
        The trials of every search count in the false-match probability.
    min_matches : int
        Matched stars needed (three when the frame has only three).
    max_false_probability : float
        Refuse an identification more likely than this to be a coincidence.
    max_focal_error : float
        Largest relative focal-length error measured and corrected; the pyramid searches its
        triads once more with the focal length free within it when the nominal one finds nothing
        (in the same search, or, when deeper searches are to come, after them: :func:`~startrack.identify.driver.search_plan`);
        brightness and voting are searched again at the scales within it that their tolerance tells
        apart (:attr:`~startrack.identify.algorithm.Algorithm.focal_sweep`).
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
        With a catalog to match everything against (:func:`~startrack.identify.driver.run`'s ``catalog``), a
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

_NUMBER = frozenset((float, int, bool, np.float64, type(None)))    # types read as themselves (None: NaN)
_GET_X, _GET_Y = operator.itemgetter("x"), operator.itemgetter("y")
_GET_FLUX = operator.methodcaller("get", "flux")
_F64 = np.dtype(np.float64)      # the dtype itself: numpy converts np.float64 (the type) to it on every call


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
    xs = np.fromiter(map(_GET_X, frame_stars), _F64, n)
    ys = np.fromiter(map(_GET_Y, frame_stars), _F64, n)
    return xs, ys, _floats(list(map(_GET_FLUX, frame_stars)))


def _floats(values: list) -> np.ndarray:
    """``values`` as float64, NaN for None and for anything not an int or float (e.g. a string)."""
    if _NUMBER.issuperset(map(type, values)):         # None is NaN too
        try:
            return np.fromiter(values, _F64, len(values))       # np.array's values, without its shape discovery
        except TypeError:                                       # a None: np.array makes it NaN
            return np.array(values, _F64)
    return np.array([v if isinstance(v, (int, float)) else np.nan for v in values], dtype=np.float64)


def _tolerances(params, sig_px, use, f):
    """``(margin, eps)``: the angle margin and the search's largest inter-star angle tolerance (rad) of a
    search of the first ``use`` stars (:class:`~startrack.identify.algorithm.SearchContext`)."""
    if params.tolerance_arcsec is not None:
        eps = math.radians(params.tolerance_arcsec / 3600.0)
        return eps, eps
    margin = math.radians(params.margin_arcsec / 3600.0)
    # The largest per-star tolerance (its product and quotient are monotonic in sigma).
    smax = float(params.sigma_px) if params.sigma_px is not None else float(np.maximum.reduce(sig_px[:use]))
    return margin, float(math.sqrt(2.0) * (params.tolerance_sigma * smax / f) + margin)
