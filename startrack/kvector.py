"""The star-pair database and Mortari's k-vector (``startrack.kvector/1``).

Every catalog star pair closer than the sensor's largest angular separation is
stored with the cosine of its angle, sorted ascending (paper 003 Eq. 10:
``P``, ``I`` = brighter star, ``J`` = dimmer star), together with

* Mortari's k-vector (Mortari & Neta 2000; paper 003 Eqs. 11-14) for O(1)
  range look-ups of all pairs whose cosine lies in an interval;
* paper 000's modified search: a least-squares quadratic through the sorted
  values (Eqs. 7-9) and its own index array, queried by Eqs. 10-12;
* per-star neighbour lists (CSR) for geometric voting and grid patterns;
* the star table (ids, unit vectors, magnitudes) so that ``identify`` needs
  nothing else.

The file records the catalog checksum and the parameters, and
:func:`check_database` refuses a database built for another catalog or field.
"""
from __future__ import annotations

import json
import logging
import math
import os
import time
from dataclasses import dataclass, field

import numpy as np

from startrack.errors import BadInputError, DatabaseMismatchError, ParameterError

__all__ = ["KVECTOR_FORMAT", "KVectorDatabase", "build_kvector", "load_kvector", "check_database",
           "max_separation_deg", "choose_database_stars", "DEFAULT_MAX_PAIRS", "DEFAULT_STARS_PER_FIELD"]

log = logging.getLogger(__name__)

KVECTOR_FORMAT = "startrack.kvector/1"


def max_separation_deg(fov_deg: float | None = None, camera=None, margin_deg: float = 0.5) -> float:
    """Largest angle between two stars of one image: the diagonal FOV plus a margin."""
    if camera is not None:
        diag = camera.diagonal_fov_deg
    else:
        if fov_deg is None or not fov_deg > 0:
            raise ParameterError("fov_deg", f"must be positive, got {fov_deg}")
        # A square field of side fov: diagonal 2 atan(sqrt(2) tan(fov/2)).
        diag = math.degrees(2 * math.atan(math.sqrt(2) * math.tan(math.radians(fov_deg) / 2)))
    return diag + margin_deg


@dataclass
class KVectorDatabase:
    """The pair database in memory; arrays are contiguous and ready for numba."""

    star_id: np.ndarray
    star_vector: np.ndarray
    star_mag: np.ndarray
    pair_i: np.ndarray
    pair_j: np.ndarray
    pair_cos: np.ndarray
    kvector: np.ndarray
    line: tuple
    kquad: np.ndarray
    quad: tuple
    neighbor_ptr: np.ndarray
    neighbor_idx: np.ndarray
    max_angle_deg: float
    catalog_sha256: str
    params: dict = field(default_factory=dict)
    path: str = ""
    merged_into: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    merged_id: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    """Unresolved doubles: star ``merged_id[k]`` is held by the entry of id ``merged_into[k]``."""

    def __setattr__(self, name, value):
        # What identification derives from the arrays is cached on the database under names starting
        # with "_" (sorted magnitudes, the sky index, the pyramid's plan, ...): setting a public field drops
        # them all, so that no cache outlives the arrays it was made from.
        if not name.startswith("_"):
            d = self.__dict__
            for key in [k for k in d if k.startswith("_")]:
                del d[key]
        object.__setattr__(self, name, value)

    def __getstate__(self):
        # Pickled (a process pool, a cluster's workers) without what identification derived from the arrays
        # ("_" names: the kernels' plans, which hold compiled functions, the sky index, the pyramid's tiers):
        # the receiver makes them again when it needs them.
        return {k: v for k, v in self.__dict__.items() if not k.startswith("_")}

    @property
    def n_stars(self) -> int:
        return len(self.star_id)

    @property
    def n_pairs(self) -> int:
        return len(self.pair_cos)

    def range_linear(self, cos_lo: float, cos_hi: float):
        """Candidate index range ``[start, end)`` by the k-vector."""
        from startrack._kernels.database import kvector_range

        return kvector_range(self.kvector, self.line[0], self.line[1], cos_lo, cos_hi)

    def range_quadratic_pure(self, cos_lo: float, cos_hi: float):
        """Candidate index range ``[start, end)`` by paper 000's quadratic search alone (Eqs. 10-12)."""
        from startrack._kernels.database import quadratic_range

        return quadratic_range(self.kquad, *self.quad, cos_lo, cos_hi)

    def range_quadratic(self, cos_lo: float, cos_hi: float):
        """Paper 000's quadratic range clipped to the k-vector's.

        Both ranges contain every pair in the interval, so their intersection
        does too, and it is never longer than either.  On cosine-sorted pairs
        the k-vector line is already close to the data (cosines of random pairs
        are nearly uniform), so the quadratic alone is as often a little longer
        as shorter; clipped, it is never longer.
        """
        from startrack._kernels.database import kvector_range, quadratic_range

        s1, e1 = kvector_range(self.kvector, self.line[0], self.line[1], cos_lo, cos_hi)
        s2, e2 = quadratic_range(self.kquad, *self.quad, cos_lo, cos_hi)
        start, end = max(s1, s2), min(e1, e2)
        return (start, end) if end > start else (start, start)

    def pairs_subset(self, keep: np.ndarray) -> "KVectorDatabase":
        """The database with the pairs where ``keep`` (a boolean per pair) is true, the same stars (the
        star arrays are shared; star indices mean the same), its own k-vector, quadratic fit and
        neighbour lists."""
        keep = np.asarray(keep, dtype=bool)
        pair_i = np.ascontiguousarray(self.pair_i[keep])
        pair_j = np.ascontiguousarray(self.pair_j[keep])
        pair_cos = np.ascontiguousarray(self.pair_cos[keep])
        if len(pair_cos) == 0:
            raise ParameterError("keep", "keeps no pair: the database would be empty")
        kvec, line = _kvector_line(pair_cos)
        quad = _quadratic_fit(pair_cos)
        kquad, coeffs = (quad if quad is not None else (kvec.copy(), (0.0, line[0], line[1])))
        neighbor_ptr, neighbor_idx = _neighbours(pair_i, pair_j, len(self.star_id))
        params = dict(self.params, n_pairs=int(len(pair_cos)), quadratic_monotonic=quad is not None)
        return KVectorDatabase(self.star_id, self.star_vector, self.star_mag, pair_i, pair_j, pair_cos, kvec, line,
                               kquad, coeffs, neighbor_ptr, neighbor_idx, self.max_angle_deg, self.catalog_sha256,
                               params, self.path, self.merged_into, self.merged_id)

    def pairs_between(self, angle_lo: float, angle_hi: float, method: str = "linear"):
        """Indices of the pairs whose angle (radians) lies in ``[angle_lo, angle_hi]``."""
        cos_lo, cos_hi = math.cos(min(angle_hi, math.pi)), math.cos(max(angle_lo, 0.0))
        start, end = (self.range_linear if method == "linear" else self.range_quadratic)(cos_lo, cos_hi)
        idx = np.arange(start, end)
        c = self.pair_cos[start:end]
        return idx[(c >= cos_lo) & (c <= cos_hi)]


def _kvector_line(y: np.ndarray):
    """Mortari's line through (0, y_min - xi) and (n, y_max + xi), and K(k) = #{y <= m k + q}."""
    from startrack._kernels.database import count_at_or_below

    n = len(y)
    xi = np.finfo(np.float64).eps * max(abs(y[0]), abs(y[-1]), 1.0) * 4
    m = (y[-1] - y[0] + 2 * xi) / max(n, 1)
    q = y[0] - xi
    k = np.arange(n + 1, dtype=np.float64)
    return count_at_or_below(y, m * k + q), (float(m), float(q))


def _neighbours(pair_i: np.ndarray, pair_j: np.ndarray, n: int):
    """Neighbour lists (CSR) of ``n`` stars, each star's neighbours sorted by index: ``(ptr, idx)``."""
    # One sort of the combined key a * n + b (faster than a two-key lexsort on millions of pairs).
    key = np.concatenate([pair_i.astype(np.int64) * n + pair_j, pair_j.astype(np.int64) * n + pair_i])
    key.sort()
    neighbor_idx = (key % n).astype(np.int32)
    neighbor_ptr = np.r_[0, np.cumsum(np.bincount(key // n, minlength=n))].astype(np.int64)
    return neighbor_ptr, neighbor_idx


def _quadratic_fit(y: np.ndarray):
    """Paper 000 Eqs. 7-9: least-squares ``y(k) = p1 k^2 + p2 k + p3`` over k = 1..n, and its K array.

    Eq. 8 as printed uses raw sums; it is the ordinary least-squares solution
    only with centred sums, so we solve the least-squares problem directly.
    The curve is shifted down / up at its ends so that it brackets the data
    (``f(0) < y_min``, ``f(n) > y_max``); returns ``None`` when it is not
    monotonic over the index range (then only the linear search applies).
    """
    from startrack._kernels.database import count_at_or_below

    n = len(y)
    k = np.arange(1, n + 1, dtype=np.float64)
    p1, p2, p3 = np.polyfit(k, y, 2)
    f = lambda kk: p1 * kk * kk + p2 * kk + p3  # noqa: E731
    slope0, slope_n = 2 * p1 * 0 + p2, 2 * p1 * n + p2
    if slope0 <= 0 or slope_n <= 0:
        return None
    # Bracket the data: lower the start, raise the end, by the largest residual.
    resid = y - f(k)
    p3_lo = p3 + min(resid.min(), 0.0) - 1e-12
    grid = np.arange(n + 1, dtype=np.float64)
    curve = p1 * grid * grid + p2 * grid + p3_lo
    top_gap = y[-1] - curve[-1]
    if top_gap > 0:
        # Tilt the curve up linearly so that it reaches y_max at k = n.
        curve = curve + top_gap * grid / n + 1e-12
        p2 = p2 + top_gap / n + 1e-12 / n
    return count_at_or_below(y, curve), (float(p1), float(p2), float(p3_lo))


def build_kvector(catalog, max_angle_deg: float, progress=None, params: dict | None = None) -> KVectorDatabase:
    """Build the pair database of a catalog for pairs up to ``max_angle_deg`` apart.

    Parameters
    ----------
    catalog : startrack.catalog.Catalog
        Stars; sorted here brightest first so that in every pair ``i < j``
        means ``i`` is the brighter star (paper 003 Sec. 4.2.1).
    max_angle_deg : float
        Largest separation kept (degrees): the diagonal FOV plus a margin.
    progress : callable, optional
        ``progress(done, total)``.
    """
    from startrack.catalog import star_pairs

    if len(catalog) < 2:
        raise ParameterError("catalog", f"needs at least 2 stars after filtering, has {len(catalog)}")
    if not 0 < max_angle_deg <= 180:
        raise ParameterError("max_angle_deg", f"largest separation must be in (0, 180] deg, got {max_angle_deg:g}")
    t0 = time.perf_counter()
    cat = catalog.sorted_by_magnitude()
    vec = np.ascontiguousarray(cat.vectors())
    if progress:
        progress(0, 3)
    first, second, cosine = star_pairs(vec, math.radians(max_angle_deg))
    order = np.argsort(cosine, kind="stable")
    pair_i = first[order].astype(np.int32)      # first < second: brighter star first
    pair_j = second[order].astype(np.int32)
    pair_cos = np.ascontiguousarray(cosine[order])
    if progress:
        progress(1, 3)
    if len(pair_cos) == 0:
        raise ParameterError("max_angle_deg", "no star pair is that close: the database would be empty")
    kvec, line = _kvector_line(pair_cos)
    quad = _quadratic_fit(pair_cos)
    kquad, coeffs = (quad if quad is not None else (kvec.copy(), (0.0, line[0], line[1])))
    n = len(cat)
    neighbor_ptr, neighbor_idx = _neighbours(pair_i, pair_j, n)
    if progress:
        progress(3, 3)
    all_params = dict(params or {})
    all_params.update(max_angle_deg=float(max_angle_deg), n_stars=int(n), n_pairs=int(len(pair_cos)),
                      mag_min=float(cat.mag.min()), mag_max=float(cat.mag.max()), epoch=float(cat.epoch),
                      quadratic_monotonic=quad is not None, build_seconds=round(time.perf_counter() - t0, 3))
    from startrack.catalog import merged_arrays

    merged_into, merged_id = merged_arrays(getattr(cat, "merged", {}) or {})
    all_params["merged_stars"] = len(merged_id)
    return KVectorDatabase(cat.id.astype(np.int64), vec, cat.mag.astype(np.float64), pair_i, pair_j, pair_cos,
                           kvec, line, kquad, coeffs, neighbor_ptr, neighbor_idx, float(max_angle_deg),
                           cat.checksum(), all_params, "", merged_into, merged_id)


DEFAULT_STARS_PER_FIELD = 20.0
"""Database stars wanted in one field when ``build-kvector`` chooses the depth."""
DEFAULT_MAX_PAIRS = 4_000_000
"""Pair budget of a chosen depth: about 50 MB on disk (12-13 bytes a pair with gzip)."""


def choose_database_stars(catalog, field_w_deg: float, field_h_deg: float, max_angle_deg: float,
                          stars_per_field: float = DEFAULT_STARS_PER_FIELD, sky_fraction: float = 0.95,
                          max_pairs: int = DEFAULT_MAX_PAIRS):
    """The stars of a database whose depth the builder chooses for a sensor.

    :func:`startrack.catalog.thin_for_field` sets a magnitude limit and thins
    the sky to a near-uniform ``stars_per_field``; when the pairs that would
    give exceed ``max_pairs``, the stars per field are lowered until they fit
    (pairs of ``n`` nearly uniform stars up to ``r`` apart:
    ``n^2 (1 - cos r) / 4``).

    Parameters
    ----------
    catalog : startrack.catalog.Catalog
        Stars (already merged for the sensor's resolution, propagated).
    field_w_deg, field_h_deg : float
        The sensor's field (degrees).
    max_angle_deg : float
        The database's largest pair separation (degrees).
    stars_per_field : float
        Wanted stars per field.
    sky_fraction : float
        Fraction of the sky whose cells must reach their quota at the limit.
    max_pairs : int
        Pair budget (sets size and build time).

    Returns
    -------
    Catalog
        With ``params`` ``depth_mag_max``, ``uniform_per_cell``,
        ``uniform_cell_deg``, ``stars_per_field`` (the one used),
        ``stars_per_field_wanted`` and ``estimated_pairs``.
    """
    from startrack.catalog import thin_for_field

    if not max_pairs >= 1:
        raise ParameterError("max_pairs", f"must be at least 1, got {max_pairs}")
    cap = (1.0 - math.cos(math.radians(max_angle_deg))) / 4.0
    want = float(stars_per_field)
    spf = want
    for _ in range(60):
        out = thin_for_field(catalog, field_w_deg, field_h_deg, spf, sky_fraction)
        estimate = len(out) ** 2 * cap
        if estimate <= max_pairs or spf <= 4.0:
            break
        spf = max(4.0, spf * min(0.95, math.sqrt(max_pairs / estimate)))
    out.params.update(stars_per_field=round(spf, 3), stars_per_field_wanted=want,
                      estimated_pairs=int(estimate), max_pairs=int(max_pairs))
    return out


def save_kvector(db: KVectorDatabase, path: str, compress: bool = True) -> None:
    """Write ``startrack.kvector/1`` atomically (``compress``: gzip its larger arrays, as a file handed to others
    wants; a cache read by every process does not, :func:`startrack.solve.band_database`)."""
    from startrack.formats.hdf5 import write_hdf5

    datasets = {
        "star_id": db.star_id, "star_vector": db.star_vector, "star_mag": (db.star_mag, {"unit": "mag"}),
        "pair_i": (db.pair_i, {"note": "brighter star (index into star_*)"}),
        "pair_j": (db.pair_j, {"note": "dimmer star"}),
        "pair_cos": (db.pair_cos, {"note": "cosine of the pair's angle, ascending"}),
        "kvector": db.kvector, "kquad": db.kquad,
        "neighbor_ptr": db.neighbor_ptr, "neighbor_idx": db.neighbor_idx,
    }
    if len(db.merged_id):
        datasets["merged_id"] = (db.merged_id, {"note": "a star merged into another entry (unresolved double)"})
        datasets["merged_into"] = (db.merged_into, {"note": "star_id of the entry holding merged_id"})
    write_hdf5(path, KVECTOR_FORMAT, db.params, datasets, attrs={
        "catalog_sha256": db.catalog_sha256, "max_angle_deg": db.max_angle_deg,
        "kvector_line": np.array(db.line), "quadratic": np.array(db.quad)}, compress=compress)


def load_kvector(path: str) -> KVectorDatabase:
    """Read a ``startrack.kvector/1`` file (one-line errors for anything else).

    The first read of a file (h5py, its decompression and checksums: ~60 ms a process for a 15 degree database)
    leaves a flat copy of its datasets and attributes in the cache (:mod:`startrack.formats.flatcopy`, checked
    against its own sha256 whenever it changed); the next process maps the copy instead, and checks every array
    as it would the file's."""
    t0 = time.perf_counter()
    f = _read_copy(path)
    if f is None:
        from startrack.formats.hdf5 import read_hdf5

        f = read_hdf5(path, KVECTOR_FORMAT)
        _write_copy(path, f)
    for attr in ("catalog_sha256", "max_angle_deg", "kvector_line", "quadratic"):
        if attr not in f.attrs:
            raise BadInputError(path, attr, "attribute is missing")
    # Every array checked against the others before any kernel indexes with it (a damaged file is named here,
    # never a crash in a kernel).
    star_id = f.array("star_id", np.int64)
    n = len(star_id)
    if n < 2:
        raise BadInputError(path, "star_id", f"holds {n} star(s): a database needs at least 2")
    merged_into = f.array("merged_into", np.int64) if "merged_into" in f else np.zeros(0, dtype=np.int64)
    merged_id = (f.array("merged_id", np.int64, (len(merged_into),)) if "merged_id" in f
                 else np.zeros(0, dtype=np.int64))
    pair_i, pair_j, pair_cos, kvector, line, kquad, quad, neighbor_ptr, neighbor_idx = _pair_arrays(f, n)
    db = KVectorDatabase(
        star_id, f.array("star_vector", np.float64, (n, 3), within=(-1.0, 1.0)),
        f.array("star_mag", np.float64, (n,), finite=True), pair_i, pair_j, pair_cos, kvector, line, kquad, quad,
        neighbor_ptr, neighbor_idx, f.numbers("max_angle_deg", positive=True), str(f.attrs["catalog_sha256"]),
        f.params, path, merged_into, merged_id)
    log.info("k-vector database %s: %d stars, %d pairs up to %g deg, read in %.0f ms", path, db.n_stars, db.n_pairs,
             db.max_angle_deg, (time.perf_counter() - t0) * 1000)
    return db


def _pair_arrays(f, n: int) -> tuple:
    """A database's pair arrays from ``f`` (:class:`~startrack.formats.hdf5.HDF5File`) of ``n`` stars, each checked
    against the others (indices of the stars and pairs, cosines, sorted look-up tables): ``(pair_i, pair_j,
    pair_cos, kvector, line, kquad, quad, neighbor_ptr, neighbor_idx)``."""
    pair_cos = f.array("pair_cos", np.float64, within=(-1.0, 1.0), ascending=True)
    m = len(pair_cos)
    if m < 1:
        raise BadInputError(f.path, "pair_cos", "holds no pair")
    neighbor_idx = f.array("neighbor_idx", np.int32, (2 * m,), index_of=n)
    line = f.numbers("kvector_line", 2)
    if not line[0] > 0:
        raise BadInputError(f.path, "kvector_line", f"slope must be positive, got {line[0]}")
    out = (f.array("pair_i", np.int32, (m,), index_of=n), f.array("pair_j", np.int32, (m,), index_of=n), pair_cos,
           f.array("kvector", np.int64, within=(0, m), ascending=True), line,
           f.array("kquad", np.int64, within=(0, m), ascending=True), f.numbers("quadratic", 3),
           f.array("neighbor_ptr", np.int64, (n + 1,), within=(0, 2 * m), ascending=True), neighbor_idx)
    for name, a in (("kvector", out[3]), ("kquad", out[5])):
        if len(a) < 1:
            raise BadInputError(f.path, name, "is empty: the file is damaged")
    return out


#: The arrays of a cached pairs subset (:func:`cached_subset`): a database's own pair arrays; its stars are the
#: parent's.
_SUBSET_ARRAYS = ("pair_i", "pair_j", "pair_cos", "kvector", "kquad", "neighbor_ptr", "neighbor_idx")


def cached_subset(db: KVectorDatabase, kind: str, make):
    """``make(db)``: a :meth:`KVectorDatabase.pairs_subset` of ``db`` (or None), kept in the cache when ``db`` was read
    from a file.

    The subset's pair arrays are a flat copy (:mod:`startrack.formats.flatcopy`) named by the file (its path, inode,
    size and modification time) and ``kind`` (what ``make`` depends on besides the file), checked against its
    sha256 whenever it changed and, read again, as :func:`load_kvector` checks a file's arrays (a damaged copy is
    made again); its stars are ``db``'s.  A pyramid's first tier for a camera (:func:`startrack.identify.pyramid.
    pattern_database`) took an ``identify`` process ~15-25 ms to make from a 15 degree database, every process again.
    """
    from startrack.formats.flatcopy import copy_path, read_copy, write_copy
    from startrack.formats.hdf5 import HDF5File

    where = copy_path(db.path, f"{KVECTOR_FORMAT}|subset|{kind}") if db.path else None
    if where is None:
        return make(db)
    got = read_copy(where)
    if got is not None:
        header, arrays = got
        try:
            if header["none"]:
                return None
            f = HDF5File(where, {"params": json.dumps(header["params"]), "kvector_line": header["line"],
                                 "quadratic": header["quad"]}, arrays)
            pair_i, pair_j, pair_cos, kvector, line, kquad, quad, neighbor_ptr, neighbor_idx = \
                _pair_arrays(f, db.n_stars)
            return KVectorDatabase(db.star_id, db.star_vector, db.star_mag, pair_i, pair_j, pair_cos, kvector, line,
                                   kquad, quad, neighbor_ptr, neighbor_idx, db.max_angle_deg, db.catalog_sha256,
                                   f.params, db.path, db.merged_into, db.merged_id)
        except (BadInputError, KeyError, TypeError, ValueError):
            pass            # (made again below)
    out = make(db)
    header = {"none": out is None}
    if out is not None:
        header.update(params=out.params, line=[float(v) for v in out.line], quad=[float(v) for v in out.quad])
    try:
        if json.loads(json.dumps(header)) != header:
            return out
    except (TypeError, ValueError):
        return out
    write_copy(where, header, {} if out is None else {name: getattr(out, name) for name in _SUBSET_ARRAYS})
    return out


def _read_copy(path: str):
    """The :class:`~startrack.formats.hdf5.HDF5File` of ``path`` from its flat copy in the cache, or None."""
    from startrack.formats.flatcopy import copy_path, read_copy

    try:
        where = copy_path(path, KVECTOR_FORMAT)
        got = read_copy(where) if where is not None else None
        if got is None:
            return None
        from startrack.formats.hdf5 import HDF5File

        header, arrays = got
        return HDF5File(path, header["attrs"], arrays)
    except (OSError, KeyError, TypeError, ValueError, BadInputError):
        return None


def _write_copy(path: str, f) -> None:
    """Leave the flat copy of ``f`` (``path`` read whole and verified) in the cache; nothing when its attributes do
    not survive JSON as they are, or the cache cannot take it."""
    from startrack.formats.flatcopy import copy_path, write_copy

    attrs = {}
    for key, value in f.attrs.items():
        if isinstance(value, np.ndarray):
            if value.dtype.kind not in "biuf":
                return
            value = value.tolist()
        attrs[key] = value
    try:
        if json.loads(json.dumps(attrs)) != attrs:
            return
    except (TypeError, ValueError):
        return
    where = copy_path(path, KVECTOR_FORMAT)
    if where is not None:
        write_copy(where, {"source": os.path.abspath(path), "attrs": attrs}, dict(f.datasets))


def check_database(db, camera=None, catalog=None, tolerance: float = 0.5) -> None:
    """Refuse a database that does not fit the camera or the catalog in use.

    Raises :class:`~startrack.errors.DatabaseMismatchError` (exit status 2) when

    * the camera's diagonal field is wider than the database's largest pair
      separation (pairs in the image would be missing from the database), or
      narrower than ``tolerance`` times it (built for another, wider sensor);
    * ``catalog`` is given and its checksum differs from the one recorded.
    """
    name = getattr(db, "path", "") or "database"
    if camera is not None:
        need = camera.diagonal_fov_deg
        have = db.max_angle_deg
        if need > have + 1e-9:
            raise DatabaseMismatchError(name, "max_angle_deg",
                                        f"built for separations up to {have:.2f} deg, but the camera's diagonal "
                                        f"field is {need:.2f} deg: rebuild it for the camera's field of view")
        if need < tolerance * have:
            raise DatabaseMismatchError(name, "max_angle_deg",
                                        f"built for a field of {have:.2f} deg but the camera's diagonal is "
                                        f"{need:.2f} deg: use a database built for this sensor")
    if catalog is not None and catalog.checksum() != db.catalog_sha256:
        raise DatabaseMismatchError(name, "catalog_sha256",
                                    "was built from another catalog (checksum differs): rebuild the database")
