"""The final catalog match: the detections the database does not hold, matched to a (deeper) catalog once the
identification's attitude is known (:func:`match_catalog`), and the attitude refined with them."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from startrack._kernels.catalog_match import match_detections
from startrack.records import Match

__all__ = ["CatalogStars", "CatalogStarsAt", "match_catalog", "match_identified", "warm_final_match"]


@dataclass
class CatalogStars:
    """A catalog's stars ready for :func:`match_catalog`: ICRS unit vectors, ids, magnitudes, and their
    sky index (:class:`startrack.skyindex.SkyIndex`, made at the first cone that needs it when not given: a frame whose
    depth the index of the brightest stars serves never does, ~25 ms of the shipped catalog's)."""

    vectors: np.ndarray
    id: np.ndarray
    mag: np.ndarray
    sky: object = None
    #: ``vectors`` minus the same stars' at the epoch they were propagated from (:meth:`moved`), or None.
    motion: np.ndarray | None = None
    #: Parallaxes (mas; 0: none), or None: the apparent places' parallax (:func:`match_catalog`'s ``apparent``).
    plx: np.ndarray | None = None
    _id_order: tuple | None = None        # startrack.catalog.id_table(id)
    _mag64: np.ndarray | None = None
    _mag_order: tuple | None = None
    _bright: dict | None = None
    _id64: np.ndarray | None = None
    #: Where :attr:`sky` comes from when a cone first needs it (the catalog's own, shared), or None (made here).
    _sky_source: object = None

    @classmethod
    def from_catalog(cls, catalog, since=None) -> CatalogStars:
        """From a :class:`startrack.catalog.Catalog` (its vectors and sky index, made once per catalog);
        ``since``: the same catalog at the epoch it was propagated from (the stars' ``motion``)."""
        motion = None if since is None else catalog.vectors() - since.vectors()
        plx = getattr(catalog, "plx", None)
        return cls(catalog.vectors(), np.asarray(catalog.id), np.asarray(catalog.mag), None, motion,
                   None if plx is None or not np.any(plx > 0) else np.asarray(plx, dtype=np.float64),
                   _sky_source=catalog.sky_index)

    @property
    def mag64(self) -> np.ndarray:
        """``mag`` as contiguous float64 (made once; the final match's kernel reads it)."""
        if self._mag64 is None or len(self._mag64) != len(self.mag):
            self._mag64 = np.ascontiguousarray(self.mag, dtype=np.float64)
        return self._mag64

    @property
    def id64(self) -> np.ndarray:
        """``id`` as contiguous int64 (made once; the final match's kernel reads it)."""
        if self._id64 is None or len(self._id64) != len(self.id):
            self._id64 = np.ascontiguousarray(self.id, dtype=np.int64)
        return self._id64

    def _rows(self, ids):
        """``(rows, found)``: the row of each of ``ids`` (its first, for an id the catalog repeats; a row in range
        but meaningless where not found) and whether the catalog has it."""
        from startrack.catalog import id_table, rows_in

        if self._id_order is None:
            self._id_order = id_table(self.id)
        rows = rows_in(self._id_order, ids, first=True)
        return np.maximum(rows, 0), rows >= 0

    def parallax_of(self, ids) -> np.ndarray | None:
        """The parallaxes (mas) of catalog ids ``ids``, 0 for an id the catalog lacks; None without parallaxes."""
        if self.plx is None:
            return None
        rows, found = self._rows(ids)
        return np.where(found, self.plx[rows], 0.0)

    def moved(self, ids, vectors: np.ndarray) -> np.ndarray:
        """``vectors`` (a database's stars ``ids``, at the epoch this catalog was propagated from) moved by their
        catalog stars' proper motion to this catalog's epoch (``motion``); unchanged without it or for an id
        the catalog lacks.  A database's merged photocentre moves with the star it is named after."""
        if self.motion is None:
            return vectors
        rows, found = self._rows(ids)
        out = np.array(vectors, dtype=np.float64, copy=True)
        out[found] += self.motion[rows[found]]
        return out / np.linalg.norm(out, axis=1, keepdims=True)

    def vectors_of(self, rows) -> np.ndarray:
        """The unit vectors of ``rows`` (an index array; :meth:`in_cone`'s answer)."""
        return self.vectors[rows]

    def in_cone(self, axis: np.ndarray, cos_radius: float, mag_limit: float | None = None) -> np.ndarray:
        """The rows with ``vectors @ axis > cos_radius`` (and, with ``mag_limit``, ``mag <= mag_limit``), ascending:
        the stars near the sky index's cone, tested as a pass over every star would test them.

        With ``mag_limit`` the cone is looked up in the index of the catalog's brightest stars that holds every
        star at or brighter than the limit (:meth:`_bright_index`): a frame's depth keeps a few per cent of a
        deep catalog, which the whole catalog's cone would visit all of."""
        bright = None if mag_limit is None else self._bright_index(mag_limit)
        if bright is not None:
            rows, sky = bright
            near = rows[sky.near(axis, cos_radius)]
        else:
            if self.sky is None:
                if self._sky_source is not None:
                    self.sky = self._sky_source()
                else:
                    from startrack.skyindex import SkyIndex

                    self.sky = SkyIndex(self.vectors)
            near = self.sky.near(axis, cos_radius)
        near = near[self.vectors[near] @ axis > cos_radius]
        return near if mag_limit is None else near[self.mag[near] <= mag_limit]

    def _bright_index(self, mag_limit: float):
        """``(rows, SkyIndex of vectors[rows])``: the brightest ``2^k`` stars (rows ascending), the fewest such
        that hold every star at or brighter than ``mag_limit``; None when that is half the catalog or more (its
        cones would hold at least half the whole catalog's: not worth an index of its own, whose build a
        process's first frame at that depth pays, ~5 ms for 65,536 stars).  Made at the first use of each size
        (at most ``log2(n)`` of them, each at most twice the stars it must hold)."""
        if self._mag_order is None or len(self._mag_order[0]) != len(self.mag):
            order = np.argsort(self.mag64, kind="stable")
            self._mag_order = (order, self.mag64[order])
            self._bright = {}
        order, sorted_mag = self._mag_order
        n = int(np.searchsorted(sorted_mag, mag_limit, side="right"))
        size = 1 << max(0, n - 1).bit_length()
        if 2 * size > len(order):
            return None
        got = self._bright.get(size)
        if got is None:
            from startrack.skyindex import SkyIndex

            rows = np.sort(order[:size])
            got = self._bright[size] = (rows, SkyIndex(self.vectors[rows]))
        return got


class CatalogStarsAt(CatalogStars):
    """A catalog's :class:`CatalogStars` moved to ``epoch`` (:meth:`startrack.catalog.Catalog.propagate`), its stars
    moved only where a frame reads them: a final match's cone (:meth:`in_cone`, :meth:`vectors_of`) and the verified
    stars' motion (:meth:`moved`).

    The answers are ``CatalogStars.from_catalog(catalog.propagate(epoch), since)``'s, ``since`` the catalog at
    ``since_epoch`` (the database's epoch; None: the catalog's own): the same arithmetic, star by star, without moving
    the whole catalog and building its sky index again for each frame time (118,000 stars: ~100 ms a frame of an
    ``identify`` stream whose frames are hours apart).  A star lies in a cone at ``epoch`` only if it lay within the
    cone's radius plus the catalog's fastest proper motion times the interval at the catalog's epoch: that wider cone of
    ``stars`` (the catalog at its own epoch) is moved, then tested as the moved catalog's cone would test it."""

    def __init__(self, stars: CatalogStars, catalog, epoch: float, since_epoch: float | None = None):
        super().__init__(None, stars.id, stars.mag, None, None, stars.plx)
        self._at = stars
        self._catalog = catalog
        self.epoch = float(epoch)
        self._since = None if since_epoch is None else float(since_epoch)
        self._reach = catalog._fastest_motion_rad_yr() * abs(self.epoch - float(catalog.epoch))
        self._cone = None       # the last cone's (rows, vectors): what the final match reads next

    @property
    def mag64(self) -> np.ndarray:
        return self._at.mag64

    @property
    def id64(self) -> np.ndarray:
        return self._at.id64

    def _rows(self, ids):
        return self._at._rows(ids)

    def _vectors_at(self, rows, epoch) -> np.ndarray:
        """The unit vectors of the catalog's ``rows`` moved to ``epoch`` (None: as they are), star by star."""
        part = self._catalog.subset(np.asarray(rows, dtype=np.int64))
        return (part if epoch is None else part.propagate(epoch)).vectors()

    def vectors_of(self, rows) -> np.ndarray:
        """The unit vectors of ``rows`` at the epoch (the last :meth:`in_cone`'s own, kept)."""
        if self._cone is not None and rows is self._cone[0]:
            return self._cone[1]
        return self._vectors_at(rows, self.epoch)

    def in_cone(self, axis: np.ndarray, cos_radius: float, mag_limit: float | None = None) -> np.ndarray:
        radius = math.acos(max(-1.0, min(1.0, float(cos_radius))))
        if radius + self._reach + 1e-9 >= math.pi:
            wide = np.arange(len(self.id))
            if mag_limit is not None:
                wide = wide[self.mag[wide] <= mag_limit]
        else:
            wide = self._at.in_cone(axis, math.cos(radius + self._reach + 1e-9), mag_limit)
        vec = self._vectors_at(wide, self.epoch)
        keep = vec @ axis > cos_radius
        front = wide[keep]
        self._cone = (front, vec[keep])
        return front

    def moved(self, ids, vectors: np.ndarray) -> np.ndarray:
        rows, found = self._rows(ids)
        out = np.array(vectors, dtype=np.float64, copy=True)
        take = rows[found]
        out[found] += self._vectors_at(take, self.epoch) - self._vectors_at(take, self._since)
        return out / np.linalg.norm(out, axis=1, keepdims=True)


def match_catalog(matches: list, ref: np.ndarray, dcm: np.ndarray, b_all: np.ndarray, radius: np.ndarray, camera,
                  stars: CatalogStars, max_chance: float, cos_fov: float, mag_limit: float | None = None,
                  sigma: np.ndarray | None = None, passes: int = 3, apparent=None):
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

    The match is then made again from ``matches`` with the refined attitude,
    until the matched set holds still (at most ``passes`` times in all).
    Which detections a pass takes depends on their offsets from the attitude
    it starts from: a detection whose noise points along that attitude's error
    lands nearer its catalog star and is taken more often, so that one pass's
    refined attitude keeps about a quarter of the error it started from (a few
    verified stars' attitude).  Each pass starts from an attitude many times
    better; what it leaves out it leaves out evenly about the truth.

    ``apparent(vectors, parallax_mas)``, when given, maps ICRS (catalog) unit
    vectors to the frame's apparent places (:meth:`startrack.apparent.FrameApparent.apparent`:
    parallax with the catalog's ``plx``, stellar aberration): the catalog stars are matched at the places the
    camera sees them, and the attitude is the camera's true orientation.

    Parameters
    ----------
    matches : list of Match
        The identification's matches; ``ref`` their ICRS unit vectors.

    Returns
    -------
    (matches, quaternion or None)
        ``None`` when nothing was added.
    """
    from startrack.rotations import quaternion_to_dcm

    if apparent is not None:
        ref = apparent(ref, stars.parallax_of([m.id for m in matches]))
    out, q = _match_once(matches, ref, dcm, b_all, radius, camera, stars, max_chance, cos_fov, mag_limit, sigma,
                         apparent)
    for _ in range(passes - 1):
        if q is None:
            break
        again, q2 = _match_once(matches, ref, quaternion_to_dcm(q), b_all, radius, camera, stars, max_chance, cos_fov,
                                mag_limit, sigma, apparent)
        if q2 is None:
            break
        held = again == out
        out, q = again, q2
        if held:
            break
    return out, q


def _match_once(matches, ref, dcm, b_all, radius, camera, stars, max_chance, cos_fov, mag_limit, sigma, apparent):
    """One pass of :func:`match_catalog`: the detections matched with the attitude ``dcm`` and the attitude
    refined with them."""

    done = np.zeros(len(b_all), dtype=bool)
    done[[m.star for m in matches]] = True
    todo = np.flatnonzero(~done)
    if len(todo) == 0:
        return matches, None
    # The catalog stars in the field's cone only (the sky index), not a pass over the catalog.
    front = stars.in_cone(dcm[2], cos_fov, mag_limit)
    cone = stars.vectors_of(front)
    if apparent is not None:
        cone = apparent(cone, None if stars.plx is None else stars.plx[front])
    pc = cone @ dcm.T
    x, y = camera.vectors_to_pixels(pc)
    keep = camera.in_image(x, y)
    idx, pc, cone = front[keep], pc[keep], cone[keep]
    if len(idx) < 1:
        return matches, None
    dots = b_all[todo] @ pc.T                                   # (detections, predicted)
    r = radius[todo]
    # The per-detection decisions in one kernel (see there): nearest star, ambiguity, unresolved pairs, chance,
    # the ids taken, one detection per catalog star.
    det, cand = match_detections(dots, pc, r, r if sigma is None else sigma[todo], idx, stars.mag64, stars.id64,
                                 np.array([int(m.id) for m in matches], dtype=np.int64), float(max_chance),
                                 float(camera.focal_length_px), float(camera.width * camera.height))
    if len(det) == 0:
        return matches, None
    new_star = todo[det].tolist()
    ids = stars.id[idx[cand]].tolist()
    out = list(matches) + [Match(i, cid) for i, cid in zip(new_star, ids)]
    body = np.vstack([b_all[[m.star for m in matches]], b_all[new_star]])
    ref_all = np.vstack([ref, cone[cand]])
    q = _quest(body, ref_all, 1.0 / radius[[m.star for m in out]] ** 2)
    out.sort(key=lambda m: m.star)
    return out, q


def warm_final_match() -> None:
    """Run the final match's kernels once on two made-up detections and two predicted stars, with the argument
    types :func:`_match_once` gives them (:func:`startrack._kernels.catalog_match.match_detections`, and QUEST
    through :func:`_quest`; two detections, as an array of one row is F-contiguous too), so that a process that
    warms the identification, and the ahead-of-time build made from one, has them compiled: without QUEST's entry
    a process's first final match imported numba and loaded the kernel from its cache (~0.3 s, inside that
    frame's time_ms)."""
    pc = np.array([[0.0, 0.0, 1.0], [1e-4, 0.0, math.sqrt(1.0 - 1e-8)]])
    b = np.array([[0.0, 0.0, 1.0], [0.0, 1e-4, math.sqrt(1.0 - 1e-8)]])
    dots = b @ pc.T
    r = np.full(2, 1e-3)
    match_detections(dots, pc, r, r, np.arange(2, dtype=np.int64), np.zeros(2), np.arange(2, dtype=np.int64),
                     np.zeros(0, dtype=np.int64), 1e-3, 1000.0, 1e6)
    _quest(np.vstack([b[:1], b[1:]]), np.vstack([pc[:1], pc[1:]]), 1.0 / r ** 2)


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
    zp = _median(mags[ok] + 2.5 * np.log10(f[ok]))
    return float(-2.5 * np.log10(fl.min()) + zp + margin)


def _median(values: np.ndarray) -> float:
    """``np.median`` of a short array, the same number without its machinery (a frame's few stars)."""
    v = np.sort(values)
    n = len(v)
    if n == 0 or np.isnan(v[-1]):
        return float(np.median(values))
    return float(v[n // 2]) if n % 2 else float((v[n // 2 - 1] + v[n // 2]) / 2)


def match_identified(catalog, accepted, scale, camera, xs, ys, b_all, flux, sig_px, db, params, apparent=None):
    """:func:`match_catalog` of an accepted identification (:func:`startrack.identify.driver.run`'s ``catalog``).

    ``accepted`` is the verification's verdict (its matches, database indices and attitude), ``scale`` the
    focal-length scale it measured (None: the nominal one), ``b_all`` the detections' unit vectors at the
    nominal focal length (None: computed here), ``flux`` NaN where unknown.  Each detection's radius is the
    verification's (``match_sigma`` of its centroid sigma plus the margin, or ``match_radius_px``); only
    catalog stars down to the frame's depth (:func:`_frame_depth`) take part.

    Returns
    -------
    (matches, quaternion or None, depth or None)
        ``quaternion`` None when nothing was added; ``depth`` the magnitude limit used (None: no
        detection was left to match, or no fluxes).
    """
    if len(accepted.matches) >= len(xs):
        return accepted.matches, None, None        # every detection identified: nothing for the catalog
    from startrack.identify.verify import _geometry, _pixels_to_vectors

    has_flux = int(np.count_nonzero(np.isfinite(flux))) >= 3
    depth = _frame_depth(flux if has_flux else None, accepted.star_index, db.star_mag[accepted.cat_index])
    if not isinstance(catalog, CatalogStars):
        catalog = CatalogStars.from_catalog(catalog)
    if b_all is None:
        b_all = _pixels_to_vectors(camera, xs, ys)
    cam = camera if scale is None else camera.with_focal_length(camera.focal_length_px / scale)
    b = b_all if scale is None else _pixels_to_vectors(cam, xs, ys)
    margin_px = math.radians(params.margin_arcsec / 3600.0) * cam.focal_length_px
    radius_px = np.full(len(xs), float(params.match_radius_px)) if params.match_radius_px is not None else \
        np.maximum(1.0, params.match_sigma * sig_px + margin_px)
    # The verified stars at the catalog's epoch (the frame's: proper motion applied), not the database's.
    ref = catalog.moved(db.star_id[accepted.cat_index], db.star_vector[accepted.cat_index])
    matches, q = match_catalog(accepted.matches, ref, accepted.dcm, b,
                               radius_px / cam.focal_length_px, cam, catalog, params.max_chance_match,
                               _geometry(camera if scale is None else cam)[0], depth, sig_px / cam.focal_length_px,
                               apparent=apparent)
    return matches, q, depth


def apparent_quaternion(accepted, scale, camera, xs, ys, sig_px, db, apparent, catalog=None):
    """The attitude of the verified matches alone refitted to their apparent places (QUEST, weights
    ``1 / sigma^2``): the camera's true orientation when no catalog match refined it
    (:func:`match_catalog`'s ``apparent``).  With ``catalog`` (a :class:`CatalogStars`) the database's
    stars are first moved to its epoch (:meth:`CatalogStars.moved`); else they are at the database's."""
    from startrack.identify.verify import _pixels_to_vectors

    cam = camera if scale is None else camera.with_focal_length(camera.focal_length_px / scale)
    stars = np.asarray(accepted.star_index, dtype=np.int64)
    body = _pixels_to_vectors(cam, np.asarray(xs)[stars], np.asarray(ys)[stars])
    ref = db.star_vector[accepted.cat_index]
    plx = None
    if isinstance(catalog, CatalogStars):
        ref = catalog.moved(db.star_id[accepted.cat_index], ref)
        plx = catalog.parallax_of(db.star_id[accepted.cat_index])
    ref = apparent(ref, plx)
    return _quest(body, ref, 1.0 / np.asarray(sig_px, dtype=np.float64)[stars] ** 2)


def _quest(body, ref, w):
    """QUEST's unit quaternion (scalar last, non-negative) of ``body`` against ``ref`` with weights ``w``."""
    from startrack._kernels.attitude import quest

    q, _ = quest(np.ascontiguousarray(body), np.ascontiguousarray(ref), w / w.sum())
    q = q / math.sqrt(float(q @ q))
    return -q if q[3] < 0 else q
