"""What an identification algorithm is and what it gets: the interface between the algorithms and the driver.

An algorithm (:class:`Algorithm`) is a *generator of proposals* (:class:`Proposal`): a few star
correspondences in the order its paper searches them, made from a frame's :class:`SearchContext`
(or, for an algorithm with a fused kernel, from a :class:`FusedFrame`, returning a
:class:`SearchOutcome`).  The driver (:mod:`startrack.identify.driver`) verifies each proposal
(:mod:`startrack.identify.verify`).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Callable, Iterator

import numpy as np

from startrack.identify.params import IdentifyParams
from startrack.records import ReasonCode

if TYPE_CHECKING:
    from startrack.identify.verify import _Verdict

__all__ = ["Algorithm", "BOTH_PASSES", "FREE_PASS", "FusedFrame", "NOMINAL_PASS", "NoConfig", "Proposal",
           "SearchContext", "SearchOutcome"]


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
        :data:`NOMINAL_PASS` or :data:`FREE_PASS` (:func:`~startrack.identify.driver.search_plan`); others ignore it.
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
        (``frame``: a :class:`FusedFrame`), deciding exactly as :func:`~startrack.identify.driver.run` does
        with ``search`` and :func:`~startrack.identify.verify._verify_fused` (one kernel call per frame
        instead of a Python round trip per proposal).  :func:`~startrack.identify.driver.run` uses it when
        set, the camera has no distortion and debug logging (which reports each
        rejected proposal) is off.
    prepare : callable or None
        ``prepare(config, camera, db, eps) -> bool``: what the search needs of the
        database for this sensor and tolerance, built once (e.g. the grid's catalog
        patterns); :func:`~startrack.identify.driver.run` calls it before the frame's clock starts and reports
        a build's time as ``details["prepare_ms"]`` (True: it built now).
    focal_passes : bool
        True when the search has a second pass with the focal length free within
        ``params.max_focal_error`` (after the nominal focal length's) and searches one of the
        two alone when :attr:`SearchContext.focal_pass` (:attr:`FusedFrame.focal_pass`) says so:
        :func:`~startrack.identify.driver.search_plan` then searches every depth at the nominal focal length first.
    focal_sweep : bool
        True when the search compares angles at the focal length it is given and has no pass of
        its own with the focal length free: when every search of the plan found nothing and
        ``params.max_focal_error`` > 0, :func:`~startrack.identify.driver.run` searches the first depth again at each
        focal-length scale the tolerance tells apart (:func:`~startrack.identify.driver.focal_scales`, :func:`~startrack.identify.driver._steps`), a camera
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
    """What :attr:`Algorithm.fused` gets: the frame as :func:`~startrack.identify.driver.run` read it.

    ``xs``, ``ys``, ``flux`` (NaN where unknown; the fluxes count when at least three are
    finite), ``sig_px``: float64 arrays of every star; ``use``: the search stars (the first);
    ``eps``, ``margin``: the angle tolerances (rad) of :class:`SearchContext`; ``deadline``: the
    end of the time budget (``time.perf_counter()``); ``trials0``: the trials of this frame's earlier
    searches (:func:`~startrack.identify.driver.search_plan`), added to this search's in the false-match probability;
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
