"""Paper 000's triangle database (``startrack.triangles/1``) and its modified pyramid identification.

Hashemi, Mousavi Mashhadi & Fiuzy (2019), Sec. 3.2: every triple of catalog
stars that can be in one field is stored with the three internal angles of its
triangle (Eq. 2, Table 4), sorted by the smallest angle.  A measured triangle
is looked up by its smallest angle; instead of Mortari's k-vector line, a
least-squares quadratic through the sorted smallest angles (Eqs. 7-9) is
inverted to give the index range (Eqs. 10-12), which the paper reports 3x
shorter (Table 5) and 14x faster (Table 6).  Four stars give four triangles;
a triangle's candidates are confirmed by a fourth star (the pyramid's
confirmation, Mortari et al. 2004), and the four-star pattern goes to the
shared verification of :mod:`startrack.identify.verify`.

Eq. 2 is applied to the stars' unit direction vectors (paper 000 Eq. 13 for
image stars, Eq. 14 for catalog stars): the chord triangle's angles are the
same wherever the triangle lies in the field, so database and image agree.
Which triples are stored: the paper says "each of three stars of catalog that
can be neighbour to each other" in its 8 x 8 deg field; we keep the triples
whose three pairs are all closer than ``max_separation_deg`` (default: the
field's shorter side), and measured triangles with a longer side are not
looked up.
"""
from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field

import numpy as np

from startrack.errors import BadInputError, DatabaseMismatchError

__all__ = ["TRIANGLES_FORMAT", "TriangleDatabase", "build_triangles", "save_triangles", "load_triangles",
           "check_triangles", "search_intervals"]

log = logging.getLogger(__name__)

TRIANGLES_FORMAT = "startrack.triangles/1"

# Refuse builds that would not fit in memory on an ordinary machine (24 bytes a triangle).
MAX_TRIANGLES = 60_000_000


@dataclass
class TriangleDatabase:
    """The triangle table in memory, sorted by the smallest internal angle (radians)."""

    star_id: np.ndarray
    star_vector: np.ndarray
    star_mag: np.ndarray
    tri_stars: np.ndarray       # (n, 3) star indices, vertex with the smallest angle first
    tri_angles: np.ndarray      # (n, 3) internal angles, ascending (radians, float32)
    tri_key: np.ndarray         # (n,) smallest angle, float64, ascending
    tri_hand: np.ndarray        # (n,) +1/-1: sign of (v0 x v1) . v2 in that vertex order
    kvector: np.ndarray
    line: tuple
    kquad: np.ndarray
    quad: tuple
    max_separation_deg: float
    catalog_sha256: str
    params: dict = field(default_factory=dict)
    path: str = ""

    @property
    def n_triangles(self) -> int:
        return len(self.tri_key)

    @property
    def n_stars(self) -> int:
        return len(self.star_id)


def build_triangles(catalog, max_separation_deg: float, progress=None, params: dict | None = None
                    ) -> TriangleDatabase:
    """Every catalog triangle whose three sides are shorter than ``max_separation_deg``.

    Parameters
    ----------
    catalog : startrack.catalog.Catalog
        Stars, sorted here brightest first.
    max_separation_deg : float
        Longest side kept (degrees).
    progress : callable, optional
        ``progress(done, total)``.
    """
    from startrack._kernels.triangles import fill_triangles
    from startrack.catalog import star_pairs
    from startrack.kvector import _kvector_line, _quadratic_fit

    if len(catalog) < 3:
        raise BadInputError("catalog", None, f"needs at least 3 stars after filtering, has {len(catalog)}")
    if not 0 < max_separation_deg <= 90:
        raise BadInputError("max_separation_deg", None, f"must be in (0, 90] deg, got {max_separation_deg:g}")
    t0 = time.perf_counter()
    cat = catalog.sorted_by_magnitude()
    vec = np.ascontiguousarray(cat.vectors())
    first, second, _ = star_pairs(vec, math.radians(max_separation_deg))
    a = np.concatenate([first, second]).astype(np.int64)
    b = np.concatenate([second, first]).astype(np.int64)
    order = np.lexsort((b, a))
    idx = np.ascontiguousarray(b[order])
    ptr = np.zeros(len(vec) + 1, dtype=np.int64)
    np.add.at(ptr, a + 1, 1)
    ptr = np.cumsum(ptr)
    cos_max = math.cos(math.radians(max_separation_deg))
    none = np.empty((0, 3), dtype=np.int32)
    n = int(fill_triangles(ptr, idx, vec, cos_max, none, np.empty((0, 3)), np.empty(0, dtype=np.int8), False))
    if n == 0:
        raise BadInputError("max_separation_deg", None, "no three stars are that close: the database would be empty")
    if n > MAX_TRIANGLES:
        raise BadInputError("max_separation_deg", None,
                            f"{n:,} triangles (more than {MAX_TRIANGLES:,}): use a brighter magnitude limit or a "
                            "smaller separation")
    if progress:
        progress(1, 3)
    stars = np.empty((n, 3), dtype=np.int32)
    angles = np.empty((n, 3), dtype=np.float64)
    hand = np.empty(n, dtype=np.int8)
    fill_triangles(ptr, idx, vec, cos_max, stars, angles, hand)
    order = np.argsort(angles[:, 0], kind="stable")
    stars, angles, hand = stars[order], angles[order], hand[order]
    key = np.ascontiguousarray(angles[:, 0])
    if progress:
        progress(2, 3)
    kvec, line = _kvector_line(key)
    quad = _quadratic_fit(key)
    kquad, coeffs = quad if quad is not None else (kvec.copy(), (0.0, line[0], line[1]))
    if progress:
        progress(3, 3)
    all_params = dict(params or {})
    all_params.update(max_separation_deg=float(max_separation_deg), n_stars=int(len(cat)), n_triangles=n,
                      mag_min=float(cat.mag.min()), mag_max=float(cat.mag.max()), epoch=float(cat.epoch),
                      quadratic_monotonic=quad is not None, build_seconds=round(time.perf_counter() - t0, 3))
    return TriangleDatabase(cat.id.astype(np.int64), vec, cat.mag.astype(np.float64), stars,
                            angles.astype(np.float32), key, hand, kvec, line, kquad, coeffs,
                            float(max_separation_deg), cat.checksum(), all_params)


def save_triangles(db: TriangleDatabase, path: str) -> None:
    """Write ``startrack.triangles/1`` atomically."""
    from startrack.formats.hdf5 import write_hdf5

    write_hdf5(path, TRIANGLES_FORMAT, db.params, {
        "star_id": db.star_id, "star_vector": db.star_vector, "star_mag": (db.star_mag, {"unit": "mag"}),
        "tri_stars": (db.tri_stars, {"note": "star indices, vertex of the smallest internal angle first"}),
        "tri_angles": (db.tri_angles, {"unit": "rad", "note": "internal angles, ascending (paper 000 Eq. 2)"}),
        "tri_key": (db.tri_key, {"unit": "rad", "note": "smallest internal angle, ascending"}),
        "tri_hand": (db.tri_hand, {"note": "sign of (v0 x v1) . v2"}),
        "kvector": db.kvector, "kquad": db.kquad,
    }, attrs={"catalog_sha256": db.catalog_sha256, "max_separation_deg": db.max_separation_deg,
              "kvector_line": np.array(db.line), "quadratic": np.array(db.quad)})


def load_triangles(path: str) -> TriangleDatabase:
    """Read a ``startrack.triangles/1`` file (one-line errors for anything else)."""
    from startrack.formats.hdf5 import read_hdf5

    t0 = time.perf_counter()
    f = read_hdf5(path, TRIANGLES_FORMAT)
    for attr in ("catalog_sha256", "max_separation_deg", "kvector_line", "quadratic"):
        if attr not in f.attrs:
            raise BadInputError(path, attr, "attribute is missing")

    # Every array checked against the others before the modified-pyramid kernel indexes with it (as load_kvector
    # does): a damaged or forged file is named here, never a crash or a wrong star in a kernel.
    star_id = f.array("star_id", np.int64)
    n = len(star_id)
    if n < 3:
        raise BadInputError(path, "star_id", f"holds {n} star(s): a triangle needs 3")
    # The smallest internal angle of a triangle is at most 60 deg (a rounding's margin above it).
    tri_key = f.array("tri_key", np.float64, within=(0.0, math.pi / 3 + 1e-6), ascending=True)
    m = len(tri_key)
    if m < 1:
        raise BadInputError(path, "tri_key", "holds no triangle")
    line = f.numbers("kvector_line", 2)
    if not line[0] > 0:
        raise BadInputError(path, "kvector_line", f"slope must be positive, got {line[0]}")
    max_separation_deg = f.numbers("max_separation_deg", positive=True)
    if not max_separation_deg <= 90:
        raise BadInputError(path, "max_separation_deg", f"attribute must be at most 90 deg, got {max_separation_deg:g}")
    db = TriangleDatabase(
        star_id, f.array("star_vector", np.float64, (n, 3), within=(-1.0, 1.0)),
        f.array("star_mag", np.float64, (n,), finite=True),
        f.array("tri_stars", np.int32, (m, 3), index_of=n),
        f.array("tri_angles", np.float32, (m, 3), within=(0.0, math.pi)), tri_key,
        f.array("tri_hand", np.int8, (m,), within=(-1, 1)),
        f.array("kvector", np.int64, (m + 1,), within=(0, m), ascending=True), line,
        f.array("kquad", np.int64, (m + 1,), within=(0, m), ascending=True), f.numbers("quadratic", 3),
        max_separation_deg, str(f.attrs["catalog_sha256"]), f.params, path)
    log.info("triangle database %s: %d stars, %d triangles, read in %.0f ms", path, db.n_stars, db.n_triangles,
             (time.perf_counter() - t0) * 1000)
    return db


def check_triangles(db: TriangleDatabase, camera=None, catalog=None) -> None:
    """Refuse a database built for another catalog or a much wider or narrower field."""
    name = getattr(db, "path", "") or "database"
    if camera is not None:
        side = min(camera.fov_deg)
        if db.max_separation_deg < 0.5 * side or db.max_separation_deg > 2.5 * camera.diagonal_fov_deg:
            raise DatabaseMismatchError(name, "max_separation_deg",
                                        f"built for sides up to {db.max_separation_deg:.2f} deg, but the camera's "
                                        f"field is {camera.fov_deg[0]:.2f} x {camera.fov_deg[1]:.2f} deg: "
                                        "build one for this sensor (startrack build-triangles)")
    if catalog is not None and catalog.checksum() != db.catalog_sha256:
        raise DatabaseMismatchError(name, "catalog_sha256", "was built from another catalog: rebuild the database")


def search_intervals(db: TriangleDatabase, smallest_angles_rad: np.ndarray, tolerance_rad: float) -> dict:
    """Mean interval searched per look-up, by Mortari's k-vector line and by the fitted quadratic (Table 5)."""
    from startrack._kernels.triangles import _quad_inverse, linear_interval

    lin, quad = [], []
    n = db.n_triangles
    for theta in np.asarray(smallest_angles_rad, dtype=float):
        lo, hi = theta - tolerance_rad, theta + tolerance_rad
        lin.append(int(linear_interval(db.kvector, db.line[0], db.line[1], lo, hi)))
        kb = min(max(int(math.floor(_quad_inverse(*db.quad, lo, n))), 0), n)
        kt = min(max(int(math.ceil(_quad_inverse(*db.quad, hi, n))), 0), n)
        quad.append(int(db.kquad[kt] - db.kquad[kb]))
        # The exact count, for reference: how many triangles really lie in the window.
    exact = np.searchsorted(db.tri_key, np.asarray(smallest_angles_rad) + tolerance_rad, "right") - \
        np.searchsorted(db.tri_key, np.asarray(smallest_angles_rad) - tolerance_rad, "left")
    return {"linear": float(np.mean(lin)), "quadratic": float(np.mean(quad)), "exact": float(np.mean(exact)),
            "n_triangles": n}
