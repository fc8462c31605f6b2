"""The star catalog: load, filter, propagate, merge, thin, and count stars in a field.

A :class:`Catalog` is a table of stars in ICRS: ``id`` (HIP number for the
shipped catalog), ``ra``/``dec`` in degrees at ``epoch`` (decimal year),
``mag`` (Hipparcos Hp for the shipped catalog), proper motions ``pm_ra``
(``mu_alpha* = mu_alpha cos(dec)``) and ``pm_dec`` in mas/yr, and ``bv``.

The shipped catalog (``catalogs/hip2.h5``, see ``catalogs/README.md``) holds
every Hipparcos 2 star to Hp 8.0 at epoch J1991.25.
"""
from __future__ import annotations

import hashlib
import json
import logging
import math
import os
import time
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from types import MappingProxyType

import numpy as np

from startrack._version import __version__
from startrack.errors import BadInputError, ParameterError

__all__ = [
    "CATALOG_FORMAT",
    "CATALOG_NAMES",
    "Catalog",
    "default_catalog_path",
    "load_catalog",
    "write_catalog",
    "merged_arrays",
    "merge_radius_arcsec",
    "thin_for_field",
    "star_pairs",
    "FieldStatistics",
    "field_statistics",
]

log = logging.getLogger(__name__)

CATALOG_FORMAT = "startrack.catalog/1"
MAS_TO_RAD = math.pi / (180.0 * 3600.0 * 1000.0)
_COLUMNS = ("id", "ra", "dec", "mag", "pm_ra", "pm_dec", "bv", "plx")


def default_catalog_path() -> str:
    """The shipped catalog: ``$STARTRACK_CATALOG``, the packaged copy, or ``catalogs/hip2.h5``."""
    env = os.environ.get("STARTRACK_CATALOG")
    if env:
        return env
    here = os.path.dirname(os.path.abspath(__file__))
    for candidate in (os.path.join(here, "data", "hip2.h5"),
                      os.path.join(os.path.dirname(here), "catalogs", "hip2.h5")):
        if os.path.exists(candidate):
            return candidate
    raise BadInputError("catalog", None, "the shipped catalog hip2.h5 was not found; give a catalog file")


def id_table(ids) -> tuple:
    """A table of the rows of catalog ids ``ids`` for :func:`rows_in`: ``("dense", row by id)`` when they are distinct
    non-negative integers below ``max(1024, 4 n)`` (Hipparcos numbers: 0.5 MB, built in about a millisecond, where a
    dictionary of the shipped catalog takes 16 ms and a sort ~8), else ``("sorted", rows, their ids ascending)`` (Gaia's
    64-bit source ids; equal ids keep their row order)."""
    ids = np.asarray(ids, dtype=np.int64)
    n = len(ids)
    if n and ids.min() >= 0 and ids.max() < max(1024, 4 * n):
        dense = np.full(int(ids.max()) + 1, -1, dtype=np.int32 if n < 2**31 else np.int64)
        dense[ids] = np.arange(n)
        if np.count_nonzero(dense >= 0) == n:       # distinct ids (else the sorted table)
            return ("dense", dense)
    order = np.argsort(ids, kind="stable")
    return ("sorted", order, ids[order])


def rows_in(table: tuple, ids, first: bool = False) -> np.ndarray:
    """The row of each catalog id of ``ids`` in ``table`` (:func:`id_table`), int64, -1 for an id it does not hold; of an
    id the catalog repeats, its last row (``first``: its first)."""
    want = np.asarray(ids, dtype=np.int64).reshape(-1)
    if table[0] == "dense":
        dense = table[1]
        inside = (want >= 0) & (want < len(dense))
        out = np.full(len(want), -1, dtype=np.int64)
        out[inside] = dense[want[inside]]
        return out
    order, keys = table[1], table[2]
    if not len(keys):
        return np.full(len(want), -1, dtype=np.int64)
    at = np.searchsorted(keys, want, side="left") if first else np.searchsorted(keys, want, side="right") - 1
    at = np.clip(at, 0, len(keys) - 1)
    return np.where(keys[at] == want, order[at], -1).astype(np.int64)


@dataclass
class Catalog:
    """A star table; arrays of equal length, sorted brightest first when built here."""

    id: np.ndarray
    ra: np.ndarray
    dec: np.ndarray
    mag: np.ndarray
    pm_ra: np.ndarray
    pm_dec: np.ndarray
    bv: np.ndarray
    epoch: float
    params: dict = field(default_factory=dict)
    source: str = ""
    merged: dict = field(default_factory=dict)
    """``{id of an entry: [ids of the fainter stars merged into it]}`` (see :meth:`merge_close`)."""
    plx: np.ndarray | None = None
    """Parallax, mas (0 where unknown; None: 0 for every star); the apparent place's parallax for an observer
    off the barycentre (:func:`startrack.apparent.aberrate`)."""

    def __post_init__(self):
        self.id = np.asarray(self.id, dtype=np.int64)
        if self.plx is None:
            self.plx = np.zeros(len(self.id))
        for name in ("ra", "dec", "mag", "pm_ra", "pm_dec", "bv", "plx"):
            setattr(self, name, np.asarray(getattr(self, name), dtype=np.float64))
        n = len(self.id)
        for name in _COLUMNS:
            if len(getattr(self, name)) != n:
                raise BadInputError(self.source or "catalog", name, f"has {len(getattr(self, name))} rows, expected {n}")

    def __len__(self) -> int:
        return len(self.id)

    def subset(self, index) -> "Catalog":
        """The stars selected by a boolean mask or an index array, in that order."""
        out = replace(self, **{name: getattr(self, name)[index] for name in _COLUMNS},
                      params=dict(self.params))
        if self.merged:
            kept = set(out.id.tolist())
            out.merged = {k: list(v) for k, v in self.merged.items() if k in kept}
        return out

    def sorted_by_magnitude(self) -> "Catalog":
        return self.subset(np.lexsort((self.id, self.mag)))

    def _derived(self, name, make):
        """``make()``, computed once per catalog and kept on it.

        A catalog is a value: its operations return new catalogs and nothing in startrack
        changes its arrays in place.  The cache is keyed on the arrays themselves, so a
        column replaced by assignment is noticed; a caller that writes into a column in
        place must make a new catalog (:meth:`subset`) instead.
        """
        key = (self.id, self.ra, self.dec)
        got = self.__dict__.get("_cache_" + name)
        if got is None or any(a is not b for a, b in zip(got[0], key, strict=True)):
            got = (key, make())
            self.__dict__["_cache_" + name] = got
        return got[1]

    def __getstate__(self):
        # The derived tables are rebuilt where they are needed (a worker process), not pickled.
        return {k: v for k, v in self.__dict__.items() if not k.startswith("_cache_")}

    def rows_by_id(self) -> Mapping[int, int]:
        """``{catalog id: row}`` (read-only, built once per catalog), to look up the rows of identified stars."""
        return self._derived("rows", lambda: MappingProxyType(dict(zip(self.id.tolist(), range(len(self.id))))))

    def rows_of(self, ids) -> np.ndarray:
        """The row of each catalog id of ``ids`` (int64; -1 for an id the catalog does not hold).

        What :meth:`rows_by_id` tells id by id, for a frame's few dozen matches at once: through a table indexed
        by the id itself when the ids are small non-negative integers (Hipparcos numbers: 0.5 MB, built in
        about a millisecond, where the dictionary takes 16 ms for the shipped catalog and each of its look-ups
        is a cache miss or three), else a binary search of the sorted ids (Gaia's 64-bit source ids).  A
        catalog that repeats an id answers with the last of its rows, as :meth:`rows_by_id` does.
        """
        return rows_in(self._derived("id_table", self._id_table), ids)

    def _id_table(self):
        """:meth:`rows_of`'s table (:func:`id_table` of the ids)."""
        return id_table(self.id)

    def positions_of(self, ids, epoch: float | None = None):
        """The ICRS unit vectors of the stars ``ids`` at ``epoch`` (decimal year; None: the catalog's own): ``(rows,
        vectors, catalog_rows)``, ``rows`` an ``{id: row of vectors}`` and ``catalog_rows`` each such row's row of
        the catalog (int64); an id the catalog does not hold is left out.

        The same numbers, row by row, as ``propagate(epoch)`` (any ``epoch`` given, as
        :meth:`startrack.solve.BandDatabases.catalog_at`) then :meth:`rows_by_id` and :meth:`vectors` of the
        whole catalog: every step works star by star.  A frame's attitude reads its matches alone, and moving the
        whole catalog to the frame's time took a solve 90 ms (the shipped catalog's 118,000 stars) for each time.
        """
        want = [int(i) for i in ids]
        found = self.rows_of(want).tolist()
        rows: dict = {}
        take: list = []
        for i, r in zip(want, found, strict=True):
            if r >= 0 and i not in rows:
                rows[i] = len(take)
                take.append(r)
        take = np.asarray(take, dtype=np.int64)
        if epoch is None:
            return rows, self.vectors()[take], take     # (the catalog's own positions: its vectors, made once)
        return rows, self.subset(take).propagate(epoch).vectors(), take

    def vectors(self) -> np.ndarray:
        """ICRS unit vectors, shape ``(n, 3)``, C-contiguous (paper 000 Eq. 14).

        Computed once per catalog and shared by every caller: read it, never write into it.
        (It is not flagged read-only: numba compiles kernels again for read-only arrays.)
        """
        def make():
            from startrack.rotations import radec_to_vector

            return np.ascontiguousarray(radec_to_vector(self.ra, self.dec))

        return self._derived("vectors", make)

    def sky_index(self):
        """The :class:`startrack.skyindex.SkyIndex` of :meth:`vectors` (cone queries), built once per catalog."""
        def make():
            from startrack.skyindex import SkyIndex

            return SkyIndex(self.vectors())

        return self._derived("sky_index", make)

    def checksum(self) -> str:
        """SHA-256 of the star table (ids, positions, magnitudes and epoch).

        Databases record it so that one built from another catalog is refused.
        """
        h = hashlib.sha256()
        for name in ("id", "ra", "dec", "mag"):
            h.update(np.ascontiguousarray(getattr(self, name)).tobytes())
        h.update(repr(float(self.epoch)).encode())
        return h.hexdigest()

    # ------------------------------------------------------------ operations
    def filter_magnitude(self, mag_min: float | None = None, mag_max: float | None = None) -> "Catalog":
        """Stars with ``mag_min <= mag <= mag_max`` (paper 000 keeps 2.5 to 6.59)."""
        if mag_min is not None and mag_max is not None and mag_min > mag_max:
            raise ParameterError("mag_min", f"{mag_min:g} is larger than the faintest magnitude kept ({mag_max:g})")
        keep = np.ones(len(self), dtype=bool)
        if mag_min is not None:
            keep &= self.mag >= mag_min
        if mag_max is not None:
            keep &= self.mag <= mag_max
        out = self.subset(keep)
        out.params.update(mag_min=mag_min, mag_max=mag_max)
        return out

    def propagate(self, epoch: float) -> "Catalog":
        """Positions and proper motions moved to ``epoch`` (decimal Julian year).

        Each star moves along its great circle at constant angular rate
        ``mu = hypot(mu_a*, mu_d)``: ``u(t) = u0 cos(mu dt) + d sin(mu dt)`` with
        ``d`` the unit direction of motion, and the proper-motion components are
        re-expressed in the new local east/north frame, so propagating there and
        back returns the same catalog.  Parallax and radial velocity are neglected
        (well under 1 mas per century for all but a handful of nearby stars).
        """
        from startrack.rotations import _east_north_rad, _radec_to_vector_rad, _vector_to_radec_rad

        if not math.isfinite(epoch):
            raise ParameterError("epoch", f"must be a finite decimal year, got {epoch}")
        dt = float(epoch) - float(self.epoch)

        ra = np.radians(self.ra)
        dec = np.radians(self.dec)
        u = _radec_to_vector_rad(ra, dec)
        east, north = _east_north_rad(ra, dec)
        pm_ra = np.nan_to_num(self.pm_ra) * MAS_TO_RAD
        pm_dec = np.nan_to_num(self.pm_dec) * MAS_TO_RAD
        velocity = pm_ra[:, None] * east + pm_dec[:, None] * north
        mu = np.linalg.norm(velocity, axis=1)
        direction = velocity / np.where(mu > 0, mu, 1.0)[:, None]
        angle = (mu * dt)[:, None]
        u_new = u * np.cos(angle) + direction * np.sin(angle)
        v_new = (-u * np.sin(angle) + direction * np.cos(angle)) * mu[:, None]
        u_new /= np.linalg.norm(u_new, axis=1, keepdims=True)
        new_ra, new_dec = _vector_to_radec_rad(u_new)
        east2, north2 = _east_north_rad(new_ra, new_dec)
        out = replace(self, ra=np.degrees(new_ra), dec=np.degrees(new_dec), epoch=float(epoch),
                      pm_ra=np.where(np.isfinite(self.pm_ra), np.sum(v_new * east2, axis=1) / MAS_TO_RAD, np.nan),
                      pm_dec=np.where(np.isfinite(self.pm_dec), np.sum(v_new * north2, axis=1) / MAS_TO_RAD, np.nan),
                      params=dict(self.params))
        out.params["epoch"] = float(epoch)
        return out

    def photocentres(self, rows, radius_arcsec: float, vectors=None) -> dict:
        """``{id: unit vector}``: the photocentre of each of ``rows``' stars and its companions closer than
        ``radius_arcsec``, for those that have any (what :meth:`merge_close` gives those stars' entries,
        computed around them only: milliseconds for a frame's matches instead of a pass over the catalog).

        A companion's own companions are not followed (``merge_close`` joins chains); at a
        sensor's unresolved separation such chains are rare and their far ends move the
        photocentre least.
        """
        if not radius_arcsec > 0:
            raise ParameterError("radius_arcsec", f"must be positive, got {radius_arcsec:g}")
        vec = self.vectors() if vectors is None else vectors
        rows = np.asarray(list(rows), dtype=np.int64)
        if rows.size == 0:
            return {}
        cos_r = math.cos(math.radians(radius_arcsec / 3600.0))
        near = (vec[rows] @ vec.T) >= cos_r           # (k, N): each star and its companions
        flux = 10.0 ** (-0.4 * np.asarray(self.mag, dtype=np.float64))
        out = {}
        for r, mask in zip(rows.tolist(), near, strict=True):
            members = np.flatnonzero(mask)
            if members.size < 2:
                continue
            c = flux[members] @ vec[members]
            out[int(self.id[r])] = c / np.linalg.norm(c)
        return out

    def photocentres_at(self, ids, radius_arcsec: float, epoch: float | None = None) -> dict:
        """:meth:`photocentres` of the stars ``ids`` in this catalog moved to ``epoch`` (``propagate(epoch)``; None:
        as it is), reading only the stars that can be their companions then.

        A companion at ``epoch`` lies within ``radius_arcsec`` plus both stars' motion since the catalog's epoch
        (at most twice the catalog's fastest proper motion times the interval) of the star now: those stars
        alone are moved, with the arithmetic of the whole catalog's move, star by star.  The answer is the
        whole catalog's, moved then searched (a frame's time cost an `attitude` stream 100 ms a frame that way).
        Ids the catalog does not hold are left out.
        """
        if not radius_arcsec > 0:
            raise ParameterError("radius_arcsec", f"must be positive, got {radius_arcsec:g}")
        found = self.rows_of([int(i) for i in ids])
        rows = found[found >= 0]
        if rows.size == 0:
            return {}
        dt = 0.0 if epoch is None else abs(float(epoch) - float(self.epoch))
        reach = math.radians(radius_arcsec / 3600.0) + 2.0 * self._fastest_motion_rad_yr() * dt + math.radians(1 / 3600)
        vec0, sky = self.vectors(), self.sky_index()
        cos_reach = math.cos(min(reach, math.pi))
        near = np.unique(np.concatenate([sky.cone(vec0[r], cos_reach) for r in rows.tolist()] + [rows]))
        part = self.subset(near)
        if epoch is not None:
            part = part.propagate(epoch)
        return part.photocentres(np.searchsorted(near, rows), radius_arcsec)

    def _fastest_motion_rad_yr(self) -> float:
        """The catalog's largest total proper motion (rad/yr; 0 without any)."""
        def make():
            mu = np.hypot(np.nan_to_num(self.pm_ra), np.nan_to_num(self.pm_dec))
            return float(mu.max()) * MAS_TO_RAD if mu.size else 0.0

        return self._derived("fastest_motion", make)

    def merge_close(self, radius_arcsec: float) -> "Catalog":
        """Merge stars closer than ``radius_arcsec`` into one entry (paper 004 Sec. 3).

        Close stars image as one blob (an unresolved double), so the catalog
        should hold one entry where the sensor sees one star: the combined
        brightness ``m = -2.5 log10(sum 10^(-0.4 m_i))`` at the flux-weighted
        mean direction (the photocentre).  Groups are the connected components of
        the "closer than radius" relation; the entry keeps the id, proper motion
        and colour of the group's brightest star, and :attr:`merged` lists the
        others under that id, so an identification names the star the sensor
        sees brightest.

        Parameters
        ----------
        radius_arcsec : float
            Separation (arcsec) below which stars are unresolved, e.g. about
            2 pixels of the sensor (:func:`merge_radius_arcsec`).
        """
        from startrack.rotations import _vector_to_radec_rad

        if not radius_arcsec > 0:
            raise ParameterError("radius_arcsec", f"must be positive, got {radius_arcsec:g}")
        first, second, _ = star_pairs(self, math.radians(radius_arcsec / 3600.0))
        out = self.subset(np.arange(len(self)))
        out.params["merge_arcsec"] = float(radius_arcsec)
        out.params["merged_groups"] = 0
        if len(first) == 0:
            return out
        n = len(self)
        parent = np.arange(n)

        def root(i):
            while parent[i] != i:
                parent[i] = parent[parent[i]]
                i = parent[i]
            return i

        for a, b in zip(first.tolist(), second.tolist(), strict=True):
            ra_, rb = root(a), root(b)
            if ra_ != rb:
                parent[max(ra_, rb)] = min(ra_, rb)
        involved = np.unique(np.concatenate([first, second]))
        roots = np.array([root(int(i)) for i in involved])
        order = np.argsort(roots, kind="stable")
        involved, roots = involved[order], roots[order]
        starts = np.r_[0, np.flatnonzero(np.diff(roots)) + 1, len(roots)]
        vec = self.vectors()
        flux = 10.0 ** (-0.4 * self.mag)
        keep = np.ones(n, dtype=bool)
        ra, dec, mag = out.ra.copy(), out.dec.copy(), out.mag.copy()
        merged = {k: list(v) for k, v in self.merged.items()}
        for g in range(len(starts) - 1):
            members = involved[starts[g]:starts[g + 1]]
            members = members[np.lexsort((self.id[members], self.mag[members]))]
            brightest = members[0]
            w = flux[members]
            mean = (vec[members] * w[:, None]).sum(axis=0)
            a, d = _vector_to_radec_rad(mean / np.linalg.norm(mean))
            keep[members[1:]] = False
            ra[brightest], dec[brightest] = math.degrees(a), math.degrees(d)
            mag[brightest] = -2.5 * math.log10(w.sum())
            absorbed = []
            for m in members[1:]:
                absorbed.append(int(self.id[m]))
                absorbed += merged.pop(int(self.id[m]), [])
            merged[int(self.id[brightest])] = merged.get(int(self.id[brightest]), []) + absorbed
        result = replace(out, ra=ra, dec=dec, mag=mag, merged=merged).subset(keep).sorted_by_magnitude()
        result.params["merged_groups"] = len(starts) - 1
        return result

    def thin_uniform(self, per_cell: int, cell_deg: float = 4.0) -> "Catalog":
        """Keep the ``per_cell`` brightest stars in each sky cell of about ``cell_deg``.

        In the spirit of Samaan, Bruccoleri, Mortari & Junkins's nearly uniform
        catalog: dense regions (the Milky Way) are thinned so that every field holds
        about the same number of stars.  Cells form an equal-area "igloo" grid:
        declination bands of height ``cell_deg`` divided in right ascension into
        ``round(360 cos(dec) / cell_deg)`` cells.
        """
        if per_cell < 1:
            raise ParameterError("per_cell", f"must be at least 1, got {per_cell}")
        if not 0 < cell_deg <= 90:
            raise ParameterError("cell_deg", f"must be in (0, 90], got {cell_deg:g}")
        cell, _ = _cells(self.ra, self.dec, cell_deg, count=False)
        order = np.lexsort((self.id, self.mag, cell))
        sorted_cell = cell[order]
        start = np.r_[0, np.flatnonzero(np.diff(sorted_cell)) + 1]
        rank = np.arange(len(order)) - np.repeat(start, np.diff(np.r_[start, len(order)]))
        keep = np.zeros(len(self), dtype=bool)
        keep[order[rank < per_cell]] = True
        out = self.subset(keep).sorted_by_magnitude()
        out.params.update(uniform_per_cell=int(per_cell), uniform_cell_deg=float(cell_deg))
        return out


DEFAULT_MERGE_PX = 2.0
"""Default unresolved separation (pixels): two PSF sigmas at ``render``'s default sigma of 1 px.

Two equal Gaussian images show no dip between them closer than 2 sigma, and
``render`` blends stars closer than that into one blob."""


def merge_radius_arcsec(camera, merge_px: float = DEFAULT_MERGE_PX) -> float:
    """The separation (arcsec) of ``merge_px`` pixels at the camera's centre pixel scale."""
    if not merge_px > 0:
        raise ParameterError("merge_px", f"must be positive, got {merge_px:g}")
    return float(merge_px) * float(camera.pixel_scale_arcsec)


def _cells(ra_deg, dec_deg, cell_deg: float, count: bool = True):
    """Cell number of each direction on the equal-area igloo grid of :meth:`Catalog.thin_uniform`, and the
    number of cells on the sky (``None`` unless ``count``).

    Memory is that of the stars, whatever ``cell_deg`` (issue 41: 1e-6 deg took 2.8 GB, 1e-7 ran out of
    memory): the occupied cells are numbered densely, and the bands are counted in blocks.
    """
    n_bands = max(1, round(180.0 / cell_deg))
    band = np.minimum(((np.asarray(dec_deg) + 90.0) / 180.0 * n_bands).astype(np.int64), n_bands - 1)
    centre = -90.0 + (band + 0.5) * 180.0 / n_bands
    n_ra = np.maximum(1, np.round(360.0 * np.cos(np.radians(centre)) / cell_deg)).astype(np.int64)
    ra_cell = np.minimum((np.mod(ra_deg, 360.0) / 360.0 * n_ra).astype(np.int64), n_ra - 1)
    # dense numbers of the occupied cells, in (band, cell in band) order: no overflow at any size
    cell = np.unique(np.stack([band, ra_cell]), axis=1, return_inverse=True)[1].ravel() if len(band) else band
    if not count:
        return cell, None
    total = 0
    block = 1 << 20
    for b0 in range(0, n_bands, block):
        centres = -90.0 + (np.arange(b0, min(n_bands, b0 + block)) + 0.5) * 180.0 / n_bands
        total += int(np.maximum(1, np.round(360.0 * np.cos(np.radians(centres)) / cell_deg)).astype(np.int64).sum())
    return cell, total


def thin_for_field(catalog: Catalog, field_w_deg: float, field_h_deg: float, stars_per_field: float = 20.0,
                   sky_fraction: float = 0.95, cell_deg: float | None = None) -> Catalog:
    """The database stars for a field: a magnitude limit and a uniform thinning.

    The sky is cut into equal-area cells about half the field's short side
    (:meth:`Catalog.thin_uniform`), each with a quota of
    ``ceil(stars_per_field * cell area / field area)`` stars.  The magnitude
    limit is the depth at which ``sky_fraction`` of the cells fill their quota
    (the quota's faintest star, at that quantile over all cells; cells with
    fewer catalog stars count as needing infinite depth); then each cell keeps
    its quota of brightest stars at or brighter than that limit.  Dense
    regions (the Milky Way) are thinned to the quota, sparse ones go as deep as
    the limit allows: a field holds about ``stars_per_field`` stars almost
    everywhere, and they are the brightest of their cell, the ones a sensor
    detects first.  In the spirit of tetra3's and cedar-solve's per-field star
    budget, with the igloo grid of Samaan et al.'s uniform catalog.

    Parameters
    ----------
    catalog : Catalog
    field_w_deg, field_h_deg : float
        The sensor's field (degrees).
    stars_per_field : float
        Stars wanted in one field.
    sky_fraction : float
        Fraction of the cells whose quota sets the magnitude limit (0, 1].
    cell_deg : float, optional
        Cell side (degrees); default half the short side of the field.

    Returns
    -------
    Catalog
        Brightest first, with ``params``: ``depth_mag_max``, ``uniform_per_cell``,
        ``uniform_cell_deg``, ``stars_per_field``, ``sky_fraction``.
    """
    if not stars_per_field >= 1:
        raise ParameterError("stars_per_field", f"must be at least 1, got {stars_per_field:g}")
    if not 0 < sky_fraction <= 1:
        raise ParameterError("sky_fraction", f"must be in (0, 1], got {sky_fraction:g}")
    if not (field_w_deg > 0 and field_h_deg > 0):
        raise ParameterError("field_w_deg", "the field must have a positive size")
    cell = float(cell_deg) if cell_deg is not None else min(field_w_deg, field_h_deg) / 2.0
    cell = min(max(cell, 0.05), 90.0)
    per_cell = max(1, math.ceil(stars_per_field * cell * cell / (field_w_deg * field_h_deg)))
    cells, n_cells = _cells(catalog.ra, catalog.dec, cell)
    order = np.lexsort((catalog.id, catalog.mag, cells))
    sorted_cells = cells[order]
    start = np.r_[0, np.flatnonzero(np.diff(sorted_cells)) + 1]
    counts = np.diff(np.r_[start, len(order)])
    # The quota's faintest star in each cell that has one; other cells need infinite depth.
    full = counts >= per_cell
    quota_mag = np.full(n_cells, np.inf)
    quota_mag[:int(full.sum())] = catalog.mag[order[start[full] + per_cell - 1]]
    limit = float(np.quantile(quota_mag, sky_fraction, method="higher"))
    if not math.isfinite(limit):
        limit = float(catalog.mag.max()) if len(catalog) else math.inf
    out = catalog.filter_magnitude(None, limit).thin_uniform(per_cell, cell)
    out.params.update(depth_mag_max=limit, stars_per_field=float(stars_per_field), sky_fraction=float(sky_fraction))
    return out


def load_catalog(path: str | None = None, mag_max: float | None = None) -> Catalog:
    """Read a ``startrack.catalog/1`` HDF5 file (default: the shipped catalog).

    Parameters
    ----------
    path : str, optional
        The file; default :func:`default_catalog_path`.  A name of :data:`CATALOG_NAMES` instead:
        ``"hipparcos"`` (the shipped file) or ``"gaia"`` (Gaia DR3 to G 10 merged with Hipparcos,
        :mod:`startrack.gaia`; needs the extra ``startrack[gaia]``).
    mag_max : float, optional
        Read only the stars at most this faint.  The shipped file is sorted
        brightest first, so only its first rows are read and decompressed:
        commands that need bright stars do not pay for the deep catalog.

    Raises
    ------
    BadInputError
        If the file is missing, not HDF5, not a catalog, or holds NaN positions.
    """
    if path in CATALOG_NAMES:
        return _load_named(path, mag_max)
    t0 = time.perf_counter()
    if path is None:
        # The shipped catalog, from the cache's decompressed and verified copy of it when there is one.
        path = default_catalog_path()
        cached = _cached_catalog(path)
        if cached is not None:
            cat = _rows_to(cached, mag_max)
            log.info("catalog %s: %d stars%s, epoch %g, read in %.0f ms from the cache", path, len(cat),
                     f" to Hp {mag_max:g}" if mag_max is not None else "", cat.epoch,
                     (time.perf_counter() - t0) * 1000)
            return cat
        if mag_max is not None and not _cache_writable():
            return _read_catalog(path, mag_max, t0)     # no cache to write: the rows asked for alone, as ever
        full = _read_catalog(path, None, t0)
        _cache_catalog(path, full)
        return full if mag_max is None else _rows_to(full, mag_max)
    return _read_catalog(path, mag_max, t0)


def _cache_writable() -> bool:
    """Whether the cache directory can take the catalog's cached copy (a read-only home: no)."""
    from startrack.cachedir import cache_dir

    try:
        return os.access(cache_dir(), os.W_OK)
    except OSError:
        return False


def _rows_to(cat: Catalog, mag_max: float | None) -> Catalog:
    """:func:`load_catalog`'s ``mag_max`` of a catalog read whole: the rows :func:`_read_catalog` reads (the
    first ones of a catalog sorted by magnitude, else those at most ``mag_max``), the same arrays."""
    if mag_max is None:
        return cat
    rows = _mag_rows(cat.mag, mag_max)
    params = dict(cat.params)
    params["read_mag_max"] = float(mag_max)
    out = replace(cat, **{name: getattr(cat, name)[rows] for name in _COLUMNS}, params=params, merged={})
    if cat.merged:
        kept = set(out.id.tolist())
        out.merged = {k: v for k, v in cat.merged.items() if k in kept}
    held = cat.__dict__.get("_cache_vectors")
    if held is not None and all(a is b for a, b in zip(held[0], (cat.id, cat.ra, cat.dec), strict=True)):
        # (a star's vector is its own ra and dec's: the rows' vectors are the vectors of the rows)
        _keep_vectors(out, np.ascontiguousarray(held[1][rows]))
    return out


def _mag_rows(mag, mag_max: float):
    """The rows of the stars at most ``mag_max``: the first ones of magnitudes sorted brightest first (a slice: only
    those rows are read and decompressed from a file), else a selection."""
    if len(mag) > 1 and np.all(mag[1:] >= mag[:-1]):
        return slice(0, int(np.searchsorted(mag, mag_max, side="right")))
    return np.flatnonzero(mag <= mag_max)


def _catalog_cache_path(path: str) -> str:
    """The cache file of the catalog file ``path``, named by its path, size and modification time."""
    import hashlib

    from startrack.formats.flatcopy import MAGIC

    st = os.stat(path)
    stamp = f"{os.path.abspath(path)}|{st.st_size}|{st.st_mtime_ns}|{CATALOG_FORMAT}|{MAGIC.decode()}|{_CACHE_LAYOUT}"
    from startrack.cachedir import cache_dir

    return os.path.join(cache_dir(), f"catalog-{hashlib.sha256(stamp.encode()).hexdigest()[:12]}.bin")


#: The cache file is a flat copy (:mod:`startrack.formats.flatcopy`: checked against its sha256 whenever it changed)
#: of the columns and of what a process would otherwise compute from them: the stars' ICRS unit vectors
#: (:meth:`Catalog.vectors`) and their sky index (:meth:`Catalog.sky_index`'s ``cells`` and ``ra``), ~22 and ~12 ms of
#: the shipped catalog's; its header holds the epoch, parameters, rows and merged pairs.
_CACHE_LAYOUT = 3


def _cached_catalog(path: str) -> Catalog | None:
    """The shipped catalog from its cache file (written by :func:`_cache_catalog` from a read that decompressed and
    verified the HDF5 file), its columns mapped copy-on-write, or None: no cache file yet, or one that does not read.

    Reading the HDF5 file costs a process ~60 ms (h5py's import, the decompression, the sha256 of every column);
    mapping the cache file ~1 ms, and the pages of the rows used are read as they are used."""
    from startrack.formats.flatcopy import read_copy

    try:
        got = read_copy(_catalog_cache_path(path))
        if got is None:
            return None
        meta, arrays = got
        n = int(meta["rows"])
        cols = {name: arrays[name] for name in _COLUMNS}
        vec = arrays["vectors"]
        if any(c.shape != (n,) for c in cols.values()) or vec.shape != (n, 3):
            return None
        from startrack.skyindex import SkyIndex

        sky = SkyIndex.from_arrays(vec, arrays["sky_cells"], arrays["sky_ra"])     # (checked: a kernel reads it)
        merged: dict = {}
        for into, mid in meta["merged"]:
            merged.setdefault(int(into), []).append(int(mid))
        cat = Catalog(epoch=float(meta["epoch"]), params=meta["params"], source=path, **cols)
    except (OSError, ValueError, KeyError, TypeError, ParameterError):
        return None
    cat.merged = merged
    _keep_vectors(cat, vec)
    cat.__dict__["_cache_sky_index"] = ((cat.id, cat.ra, cat.dec), sky)
    return cat


def _keep_vectors(cat: Catalog, vec: np.ndarray) -> None:
    """Hold ``vec`` as ``cat``'s :meth:`Catalog.vectors` (what it would compute from its ``ra`` and ``dec``: the cache
    file's copy of them, or a catalog's rows of its source's)."""
    cat.__dict__["_cache_vectors"] = ((cat.id, cat.ra, cat.dec), vec)


def _cache_catalog(path: str, cat: Catalog) -> None:
    """Write the cache file of the shipped catalog ``cat`` (read whole from ``path``), atomically; nothing when its
    parameters do not survive JSON as they are, or the cache cannot be written."""
    from startrack.formats.flatcopy import write_copy

    try:
        if json.loads(json.dumps(cat.params)) != cat.params:
            return
        cache = _catalog_cache_path(path)
    except (OSError, TypeError, ValueError):     # no cache dir; parameters JSON cannot hold
        return
    sky = cat.sky_index()
    arrays = {name: getattr(cat, name) for name in _COLUMNS}
    arrays.update(vectors=cat.vectors(), sky_cells=sky.cells, sky_ra=sky.ra)
    write_copy(cache, {"epoch": cat.epoch, "params": cat.params, "rows": len(cat.id),
                       "merged": [[into, mid] for into, mids in cat.merged.items() for mid in mids]}, arrays)


def _read_catalog(path: str, mag_max: float | None, t0: float) -> Catalog:
    """:func:`load_catalog` of a file: read, checked and verified."""
    import h5py

    from startrack.formats.hdf5 import corrupt_hdf5, read_hdf5

    f = read_hdf5(path, CATALOG_FORMAT, names=["mag"])
    mag = np.asarray(f["mag"])
    if mag.dtype.kind not in "iuf" or mag.ndim != 1:
        raise BadInputError(path, "mag", f"holds {mag.dtype} values of shape {mag.shape}, expected one number per star")
    rows = slice(None) if mag_max is None else _mag_rows(mag, mag_max)
    cols = {"mag": mag[rows]}
    with corrupt_hdf5(path) as where, h5py.File(path, "r") as h5:
        for name in ("id", "ra", "dec"):
            where.field = name
            if name not in h5:
                raise BadInputError(path, name, "dataset is missing")
            cols[name] = np.asarray(h5[name][rows])
        n = len(cols["id"])
        for name in ("pm_ra", "pm_dec", "bv", "plx"):
            where.field = name
            cols[name] = np.asarray(h5[name][rows]) if name in h5 else np.full(n, np.nan if name == "bv" else 0.0)
        # A parallax not measured, or measured negative (noise about a small one), is none.
        cols["plx"] = np.where(np.isfinite(cols["plx"]) & (cols["plx"] > 0), cols["plx"], 0.0)
        merged = {}
        where.field = "merged_id"
        if "merged_id" in h5 and "merged_into" in h5:
            into_ids = np.asarray(h5["merged_into"]).tolist()
            for into, mid in zip(into_ids, np.asarray(h5["merged_id"]).tolist(), strict=True):
                merged.setdefault(int(into), []).append(int(mid))
    n = len(cols["mag"])
    for name, value in cols.items():
        numeric = "iu" if name == "id" else "iubf"
        if value.dtype.kind not in numeric or value.ndim != 1:
            raise BadInputError(path, name, f"holds {value.dtype} values of shape {value.shape}, expected one "
                                            f"{'integer' if name == 'id' else 'number'} per star")
        if len(value) != n:
            raise BadInputError(path, name, f"has {len(value)} rows, expected {n} (as mag)")
    if isinstance(rows, slice) and rows == slice(None):
        from startrack.formats.hdf5 import _checksums, verify_dataset

        sums = _checksums(path, f.attrs)
        for name in ("id", "ra", "dec", "pm_ra", "pm_dec", "bv"):
            if sums is not None and name in sums:
                verify_dataset(path, sums, name, cols[name])
    for name in ("ra", "dec", "mag"):
        bad = ~np.isfinite(cols[name])
        if bad.any():
            raise BadInputError(path, name, f"has {int(bad.sum())} non-finite values (first at row {int(np.argmax(bad))})")
    if n and (cols["dec"].min() < -90 or cols["dec"].max() > 90):
        raise BadInputError(path, "dec", "holds declinations outside [-90, 90] deg")
    try:
        epoch = float(f.attrs.get("epoch", f.params.get("epoch", 2000.0)))
    except (TypeError, ValueError):
        raise BadInputError(path, "epoch", "is not a number") from None
    params = dict(f.params)
    if mag_max is not None:
        params["read_mag_max"] = float(mag_max)
    cat = Catalog(epoch=epoch, params=params, source=path, **cols)
    if merged:
        kept = set(cat.id.tolist())
        cat.merged = {k: v for k, v in merged.items() if k in kept}
    log.info("catalog %s: %d stars%s, epoch %g, read in %.0f ms", path, len(cat),
             f" to Hp {mag_max:g}" if mag_max is not None else "", epoch, (time.perf_counter() - t0) * 1000)
    return cat


def _load_named(name: str, mag_max):
    """The catalog registered as ``name`` in :data:`CATALOG_NAMES`: ``"module:function"``, called with ``mag_max``."""
    import importlib

    module, _, function = CATALOG_NAMES[name].partition(":")
    return getattr(importlib.import_module(module), function)(mag_max=mag_max)


def _load_hipparcos(mag_max=None) -> Catalog:
    return load_catalog(None, mag_max)


CATALOG_NAMES = {"hipparcos": "startrack.catalog:_load_hipparcos", "gaia": "startrack.gaia:load_gaia_catalog"}
"""Catalogs that :func:`load_catalog` (and every command's ``--catalog``) takes by name instead of a path
(``./gaia`` names a file called ``gaia``), as ``"module:function(mag_max=...)"``, the way ``startrack.identify``
registers its algorithms (the deep catalog's module sits above this one: it builds on :class:`Catalog`)."""


def write_catalog(catalog: Catalog, path: str, params: dict | None = None) -> None:
    """Write a catalog as HDF5 (``.h5``/``.hdf5``) or CSV (``.csv``, or ``-`` for stdout).

    In HDF5, merged stars (:meth:`Catalog.merge_close`) are listed in two more
    datasets: ``merged_id`` (the fainter star) and ``merged_into`` (the id of
    the entry that holds it).
    """
    all_params = dict(catalog.params)
    all_params.update(params or {})
    all_params["epoch"] = catalog.epoch
    all_params["source_catalog"] = os.path.basename(catalog.source) if catalog.source else None
    ext = os.path.splitext(path)[1].lower()
    if path == "-" or ext == ".csv":
        _write_csv(catalog, path, all_params)
        return
    if ext not in (".h5", ".hdf5"):
        raise BadInputError(path, None, "unknown output extension: use .h5, .hdf5 or .csv")
    from startrack.formats.hdf5 import write_hdf5

    datasets = {
        "id": (catalog.id.astype(np.int64), {"note": "Hipparcos number (HIP) for Hipparcos stars, Gaia DR3 "
                                                     "source_id for Gaia stars (catalog gaia)"}),
        "ra": (catalog.ra, {"unit": "deg", "note": "ICRS at epoch"}),
        "dec": (catalog.dec, {"unit": "deg", "note": "ICRS at epoch"}),
        "mag": (catalog.mag.astype(np.float32), {"unit": "mag"}),
        "pm_ra": (catalog.pm_ra.astype(np.float32), {"unit": "mas/yr", "note": "pmRA*cos(dec)"}),
        "pm_dec": (catalog.pm_dec.astype(np.float32), {"unit": "mas/yr"}),
        "bv": (catalog.bv.astype(np.float32), {"unit": "mag"}),
        "plx": (catalog.plx.astype(np.float32), {"unit": "mas", "note": "parallax; 0 where unknown"}),
    }
    if catalog.merged:
        into, mid = merged_arrays(catalog.merged)
        datasets["merged_id"] = (mid, {"note": "a star merged into another entry (unresolved double)"})
        datasets["merged_into"] = (into, {"note": "id of the entry holding merged_id"})
    write_hdf5(path, CATALOG_FORMAT, all_params, datasets, attrs={"epoch": float(catalog.epoch)})


def merged_arrays(merged: dict):
    """``(into, merged_id)`` int64 arrays of a ``{entry id: [merged ids]}`` mapping, sorted by entry."""
    pairs = sorted((int(k), int(m)) for k, v in merged.items() for m in v)
    into = np.array([p[0] for p in pairs], dtype=np.int64)
    mid = np.array([p[1] for p in pairs], dtype=np.int64)
    return into, mid


def _write_csv(catalog: Catalog, path: str, params: dict) -> None:
    import csv
    import sys

    from startrack.formats.atomic import atomic_open

    def emit(handle):
        handle.write(f"# startrack {__version__} catalog; params: {json.dumps(params, sort_keys=True)}\n")
        writer = csv.writer(handle, lineterminator="\n")
        writer.writerow(["id", "ra_deg", "dec_deg", "mag", "pm_ra_mas_yr", "pm_dec_mas_yr", "bv"])
        for row in zip(catalog.id.tolist(), catalog.ra.tolist(), catalog.dec.tolist(), catalog.mag.tolist(),
                       catalog.pm_ra.tolist(), catalog.pm_dec.tolist(), catalog.bv.tolist()):
            writer.writerow([row[0], f"{row[1]:.9f}", f"{row[2]:.9f}", f"{row[3]:.4f}",
                             f"{row[4]:.3f}", f"{row[5]:.3f}", "" if math.isnan(row[6]) else f"{row[6]:.3f}"])

    if path == "-":
        emit(sys.stdout)
        sys.stdout.flush()
    else:
        with atomic_open(path, "w", encoding="utf-8") as handle:
            emit(handle)


def star_pairs(catalog_or_vectors, max_angle: float):
    """All star pairs separated by at most ``max_angle`` radians.

    Parameters
    ----------
    catalog_or_vectors : Catalog or ndarray, shape (n, 3)
    max_angle : float
        Radians.

    Returns
    -------
    first, second : ndarray of int64
        Star indices with ``first < second``.
    cosine : ndarray of float64
        Cosine of each pair's angle.
    """
    from startrack._kernels.sphere import pairs_within

    vec = catalog_or_vectors.vectors() if isinstance(catalog_or_vectors, Catalog) else catalog_or_vectors
    vec = np.ascontiguousarray(vec, dtype=np.float64)
    dec = np.arcsin(np.clip(vec[:, 2], -1.0, 1.0))
    order = np.argsort(dec, kind="stable").astype(np.int64)
    first, second, cosine = pairs_within(vec, dec, order, float(max_angle), math.cos(max_angle))
    lo = np.minimum(first, second)
    hi = np.maximum(first, second)
    return lo, hi, cosine


@dataclass
class FieldStatistics:
    """Monte Carlo statistics of the stars a camera sees (paper 000 Fig. 2).

    Held as histograms, so memory does not grow with the number of samples:
    ``count_hist[c]`` attitudes saw ``c`` stars; ``mag_hist`` counts the
    brightest star's magnitude in 0.5-mag bins from ``mag_hist_start``.
    ``counts`` and ``brightest_mag`` (per attitude) are kept only for runs of at
    most one chunk (``None`` otherwise).
    """

    count_hist: np.ndarray
    mag_hist: np.ndarray
    mag_hist_start: float
    brightest_min: float
    brightest_max: float
    n_empty: int
    n_catalog: int
    mag_bins: list
    mag_bin_counts: list
    params: dict
    counts: np.ndarray | None = None
    brightest_mag: np.ndarray | None = None

    def _percentile(self, p: float) -> float:
        """numpy's default (linear) percentile of the per-attitude counts, from the histogram."""
        cum = np.cumsum(self.count_hist)
        n = int(cum[-1])
        rank = (n - 1) * p / 100.0
        lo, hi = math.floor(rank), math.ceil(rank)
        v_lo = int(np.searchsorted(cum, lo, side="right"))
        v_hi = int(np.searchsorted(cum, hi, side="right"))
        return v_lo + (v_hi - v_lo) * (rank - lo)

    def summary(self) -> dict:
        h = self.count_hist.astype(np.float64)
        values = np.arange(len(h), dtype=np.float64)
        n = h.sum()
        mean = float((h * values).sum() / n)
        std = float(math.sqrt(max(0.0, (h * (values - mean) ** 2).sum() / n)))
        nonzero = np.flatnonzero(self.count_hist)
        if math.isfinite(self.brightest_min):
            lo_edge = math.floor(self.brightest_min)
            hi_edge = math.ceil(self.brightest_max) + 1
            edges = np.arange(lo_edge, hi_edge, 0.5)
            i0 = int(round((lo_edge - self.mag_hist_start) / 0.5))
            hist = self.mag_hist[i0:i0 + len(edges) - 1]
        else:
            edges = np.arange(-2, 9, 0.5)
            hist = np.array([], dtype=np.int64)
        pcts = [1, 5, 25, 50, 75, 95, 99]
        return {
            "boresights": int(n),
            "catalog_stars": int(self.n_catalog),
            "min": int(nonzero[0]),
            "max": int(nonzero[-1]),
            "mean": mean,
            "std": std,
            "percentiles": {str(p): float(self._percentile(p)) for p in pcts},
            "fraction_at_least": {str(k): float(h[k:].sum() / n) for k in (1, 2, 3, 4, 5, 6, 8, 10)},
            "brightest_mag_histogram": {"edges": [float(e) for e in edges], "counts": [int(v) for v in hist]},
            "brightest_mag_empty_fields": int(self.n_empty),
            "mag_bins": {"edges": self.mag_bins, "counts": self.mag_bin_counts},
            "params": self.params,
        }


FIELD_STATISTICS_CHUNK = 250_000
"""Attitudes drawn and counted at a time by :func:`field_statistics` (about 100 MB of work arrays)."""


def field_statistics(catalog: Catalog, camera, n_boresights: int, rng: np.random.Generator,
                     mag_edges=None, chunk: int = FIELD_STATISTICS_CHUNK) -> FieldStatistics:
    """Count the catalog stars inside ``camera``'s image over random attitudes.

    Attitudes are uniform over SO(3) (random boresight and roll), the Monte Carlo
    of paper 000 Fig. 2 and paper 003 Fig. 3.  Radial distortion is included.
    The attitudes are drawn and counted ``chunk`` at a time into histograms, so
    memory stays bounded (a few hundred MB) for any ``n_boresights``; a run of at
    most one chunk draws the same attitudes as one of any larger chunk size.
    """
    from startrack._kernels.sphere import count_in_fov
    from startrack.rotations import quaternion_to_dcm, random_quaternions

    if n_boresights < 1:
        raise ParameterError("n_boresights", f"must be at least 1, got {n_boresights}")
    if chunk < 1:
        raise ParameterError("chunk", f"must be at least 1, got {chunk}")
    vec = catalog.vectors()
    dec = np.arcsin(np.clip(vec[:, 2], -1, 1))
    order = np.argsort(dec, kind="stable")
    svec = np.ascontiguousarray(vec[order])
    sdec = np.ascontiguousarray(dec[order])
    smag = np.ascontiguousarray(catalog.mag[order])
    mag_start = math.floor(float(np.min(catalog.mag))) if len(catalog) else -2.0
    mag_stop = math.ceil(float(np.max(catalog.mag))) + 1 if len(catalog) else 8.0
    mag_hist = np.zeros(int(round((mag_stop - mag_start) / 0.5)) + 1, dtype=np.int64)
    count_hist = np.zeros(1, dtype=np.int64)
    b_min, b_max, n_empty = math.inf, -math.inf, 0
    keep = n_boresights <= chunk
    counts = brightest = None
    done = 0
    while done < n_boresights:
        m = min(chunk, n_boresights - done)
        dcms = np.ascontiguousarray(quaternion_to_dcm(random_quaternions(m, rng)))
        c, b = count_in_fov(svec, sdec, smag, dcms, float(camera.focal_length_px),
                            float(camera.cx), float(camera.cy), float(camera.width), float(camera.height),
                            *camera.lens_terms, math.acos(camera.cone_cos()) + 1e-9)
        del dcms
        bc = np.bincount(np.asarray(c, dtype=np.int64))
        if len(bc) > len(count_hist):
            count_hist = np.concatenate([count_hist, np.zeros(len(bc) - len(count_hist), np.int64)])
        count_hist[:len(bc)] += bc
        finite = b[np.isfinite(b)]
        n_empty += int(len(b) - len(finite))
        if finite.size:
            b_min = min(b_min, float(finite.min()))
            b_max = max(b_max, float(finite.max()))
            idx = np.clip(np.floor((finite - mag_start) / 0.5).astype(np.int64), 0, len(mag_hist) - 1)
            mag_hist += np.bincount(idx, minlength=len(mag_hist))
        if keep:
            counts, brightest = c, b
        done += m
    if mag_edges is None:
        mag_edges = [-2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0]
    hist, _ = np.histogram(catalog.mag, bins=mag_edges)
    return FieldStatistics(count_hist, mag_hist, float(mag_start), b_min, b_max, n_empty, len(catalog),
                           [float(e) for e in mag_edges], [int(h) for h in hist],
                           {"samples": int(n_boresights), "chunk": int(chunk)}, counts, brightest)
