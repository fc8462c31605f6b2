"""The labelling database of paper 004 (Kim & Cho 2019), ``startrack.labels/1``.

For boresights swept over the whole sphere (``step_deg`` apart in declination
and, on each declination ring, in right ascension), the ``stars_per_field``
brightest catalog stars within the field (a circle of diameter ``fov_deg``:
independent of roll) are taken, and every combination of ``group_size`` of them
becomes an entry:

* the pairwise angular distances, sorted in descending order, give the
  sub-labels ``l_1i = d_i / d_1`` (Eq. 1), scaled by ``alpha = 10^r`` and rounded
  (Eq. 2), combined into one integer label ``L = sum alpha^(n-i) L_1i`` (Eq. 3;
  Table 1: 452, 385, 276 px with r = 2 give 8561);
* the member stars, ordered by descending sum of their distances within the
  group (Sec. 2.3), so that equal labels put stars in correspondence.

Duplicate combinations (the same stars seen from neighbouring boresights) are
removed; entries are sorted by label; a polynomial trend line maps a label to
its approximate index (Fig. 3), with its largest error stored so that the
search window around the estimate is guaranteed to contain every equal label.

Distances are angles between unit vectors.  In an image, angles computed with
the nominal focal length are all scaled by the same factor by a focal-length
error (to first order), which the ratios cancel: the method's tolerance to
focal-length error (paper 004 Fig. 7).
"""
from __future__ import annotations

import itertools
import logging
import math
import time
from dataclasses import dataclass, field

import numpy as np

from startrack.errors import BadInputError, DatabaseMismatchError, ParameterError

__all__ = ["LABELS_FORMAT", "LabelDatabase", "build_labels", "load_labels", "save_labels", "label_from_distances",
           "sweep_boresights"]

log = logging.getLogger(__name__)

LABELS_FORMAT = "startrack.labels/1"


def label_from_distances(distances, scale_digits: int = 2) -> int:
    """Paper 004 Eqs. 1-3 for one group: ``label_from_distances([452, 385, 276]) == 8561``."""
    from startrack._kernels.database import label_of_distances

    d = np.asarray(distances, dtype=np.float64)
    if d.ndim != 1 or len(d) < 2 or not np.all(d > 0):
        raise BadInputError("distances", None, "need at least two positive distances")
    return int(label_of_distances(d, float(10 ** scale_digits)))


MIN_STEP_DEG = 0.1
"""Finest boresight sweep: 0.1 deg is ~4.1 million boresights (about 2 GB of work arrays at build time)."""


def sweep_boresights(step_deg: float) -> np.ndarray:
    """Unit vectors on declination rings ``step_deg`` apart, ``~step_deg`` apart along each ring."""
    decs = np.arange(-90.0, 90.0 + 1e-9, step_deg)
    out = []
    for dec in decs:
        n_ra = max(1, int(round(360.0 * math.cos(math.radians(dec)) / step_deg)))
        ras = np.arange(n_ra) * 360.0 / n_ra
        d = math.radians(dec)
        r = np.radians(ras)
        out.append(np.stack([np.cos(r) * math.cos(d), np.sin(r) * math.cos(d), np.full(n_ra, math.sin(d))], axis=1))
    return np.ascontiguousarray(np.concatenate(out))


@dataclass
class LabelDatabase:
    """Sorted labels, their star groups, the trend line and the star table."""

    label: np.ndarray
    members: np.ndarray
    star_id: np.ndarray
    star_vector: np.ndarray
    star_mag: np.ndarray
    trend: np.ndarray
    trend_scale: float
    trend_radius: int
    fov_deg: float
    scale_digits: int
    group_size: int
    stars_per_field: int
    catalog_sha256: str
    params: dict = field(default_factory=dict)
    path: str = ""

    def estimate_index(self, label: int) -> int:
        """The trend line's index for ``label`` (paper 004 Fig. 3)."""
        return int(round(float(np.polyval(self.trend, label / self.trend_scale))))

    def lookup(self, label: int):
        """Indices ``[start, end)`` of the entries whose label equals ``label``."""
        from startrack._kernels.database import label_search

        return label_search(self.label, np.int64(label), self.estimate_index(label), self.trend_radius)


def build_labels(catalog, fov_deg: float, stars_per_field: int = 8, group_size: int = 4, scale_digits: int = 2,
                 step_deg: float = 1.0, trend_degree: int = 7, progress=None, params: dict | None = None):
    """Build paper 004's label database.

    Parameters
    ----------
    catalog : Catalog
        Already filtered to the sensor's magnitude limit (paper 004: 5.2) and,
        ideally, with close pairs merged.
    fov_deg : float
        The field of view; the field is the circle of this diameter.
    stars_per_field, group_size, scale_digits, step_deg :
        Paper 004's 8, 4, r = 2 and 1 degree.
    """
    from startrack._kernels.database import label_sweep

    if not 0 < fov_deg <= 90:
        raise ParameterError("fov_deg", f"must be in (0, 90], got {fov_deg:g}")
    if not 2 <= group_size <= stars_per_field:
        raise ParameterError("group_size", f"need 2 <= group size <= stars per field, got {group_size}")
    if group_size * (group_size - 1) // 2 - 1 > 9 or scale_digits < 1 or \
            (group_size * (group_size - 1) // 2 - 1) * scale_digits > 18:
        raise ParameterError("scale_digits", "the label would not fit in 64 bits: use fewer digits or a smaller group")
    if not MIN_STEP_DEG <= step_deg <= 30:
        n = 41253.0 / step_deg ** 2 if step_deg > 0 else float("inf")
        raise ParameterError("step_deg", f"must be in [{MIN_STEP_DEG:g}, 30], got {step_deg:g}"
                            + (f" (it would sweep {n:.3g} boresights)" if step_deg < MIN_STEP_DEG else ""))
    if len(catalog) < stars_per_field:
        raise ParameterError("catalog", f"has {len(catalog)} stars, fewer than the {stars_per_field} stars per field")
    t0 = time.perf_counter()
    cat = catalog.sorted_by_magnitude()
    vec = np.ascontiguousarray(cat.vectors())
    bores = sweep_boresights(step_deg)
    combos = np.array(list(itertools.combinations(range(stars_per_field), group_size)), dtype=np.int64)
    radius_cos = math.cos(math.radians(fov_deg / 2.0))
    labels = []
    members = []
    chunk = 2000
    for start in range(0, len(bores), chunk):
        lab, mem = label_sweep(vec, bores[start:start + chunk], radius_cos, stars_per_field, group_size,
                               float(10 ** scale_digits), combos)
        keep = lab >= 0
        labels.append(lab[keep])
        members.append(mem[keep])
        if progress:
            progress(min(start + chunk, len(bores)), len(bores))
    labels = np.concatenate(labels)
    members = np.concatenate(members)
    if len(labels) == 0:
        raise ParameterError("catalog", f"no field holds {stars_per_field} stars: use a fainter catalog or wider FOV")
    raw = len(labels)
    # Remove duplicate groups: the same stars, whatever order they were found in.
    key_sorted = np.sort(members, axis=1).astype(np.int64)
    packed = np.zeros(len(key_sorted), dtype=np.int64)
    bits = max(1, int(math.ceil(math.log2(len(cat) + 1))))
    if bits * group_size > 62:
        packed = None
    else:
        for a in range(group_size):
            packed = (packed << bits) | key_sorted[:, a]
    if packed is not None:
        _, first = np.unique(packed, return_index=True)
    else:
        _, first = np.unique(key_sorted, axis=0, return_index=True)
    labels = labels[first]
    members = members[first]
    order = np.lexsort((first, labels))
    labels = np.ascontiguousarray(labels[order])
    members = np.ascontiguousarray(members[order].astype(np.int32))
    # Trend line: index ~ poly(label / scale), with its worst error as the search radius.
    scale = float(max(labels.max(), 1))
    idx = np.arange(len(labels), dtype=np.float64)
    degree = min(trend_degree, max(1, len(np.unique(labels)) - 1))
    trend = np.polyfit(labels / scale, idx, degree)
    err = np.abs(np.polyval(trend, labels / scale) - idx)
    radius = int(math.ceil(err.max())) + 2
    all_params = dict(params or {})
    all_params.update(fov_deg=float(fov_deg), stars_per_field=int(stars_per_field), group_size=int(group_size),
                      scale_digits=int(scale_digits), step_deg=float(step_deg), boresights=int(len(bores)),
                      raw_combinations=int(raw), combinations=int(len(labels)),
                      distinct_labels=int(len(np.unique(labels))), n_stars=int(len(cat)),
                      mag_max=float(cat.mag.max()), epoch=float(cat.epoch), trend_degree=int(degree),
                      trend_radius=radius, field="circle of diameter fov_deg",
                      build_seconds=round(time.perf_counter() - t0, 3))
    return LabelDatabase(labels, members, cat.id.astype(np.int64), vec, cat.mag.astype(np.float64), trend, scale,
                         radius, float(fov_deg), int(scale_digits), int(group_size), int(stars_per_field),
                         cat.checksum(), all_params)


def save_labels(db: LabelDatabase, path: str) -> None:
    from startrack.formats.hdf5 import write_hdf5

    write_hdf5(path, LABELS_FORMAT, db.params, {
        "label": (db.label, {"note": "paper 004 Eq. 3, ascending"}),
        "members": (db.members, {"note": "star indices, descending distance sums (Sec. 2.3)"}),
        "star_id": db.star_id, "star_vector": db.star_vector, "star_mag": db.star_mag,
    }, attrs={"catalog_sha256": db.catalog_sha256, "trend": db.trend, "trend_scale": db.trend_scale,
              "trend_radius": db.trend_radius, "fov_deg": db.fov_deg, "scale_digits": db.scale_digits,
              "group_size": db.group_size, "stars_per_field": db.stars_per_field})


def load_labels(path: str) -> LabelDatabase:
    from startrack.formats.hdf5 import read_hdf5

    t0 = time.perf_counter()
    f = read_hdf5(path, LABELS_FORMAT)
    for attr in ("catalog_sha256", "trend", "trend_scale", "trend_radius", "fov_deg", "scale_digits", "group_size",
                 "stars_per_field"):
        if attr not in f.attrs:
            raise BadInputError(path, attr, "attribute is missing")
    # Every array checked against the others before the labelling kernel indexes with it (as load_kvector does):
    # a damaged or forged file is named here, never a crash or a wrong star in a kernel.
    a = f.attrs
    # build_labels' limits: groups of 2 or more whose g(g-1)/2 - 1 distance ratios are at most 9 (g <= 5), each of
    # scale_digits >= 1 digits, at most 18 digits in all (an int64 label).
    group_size = _whole(path, a, "group_size", 2, 5)
    scale_digits = _whole(path, a, "scale_digits", 1, 18)
    if (group_size * (group_size - 1) // 2 - 1) * scale_digits > 18:
        raise BadInputError(path, "scale_digits", f"{scale_digits} digits for groups of {group_size}: the label "
                                                  "would not fit in 64 bits")
    stars_per_field = _whole(path, a, "stars_per_field", group_size, 10**6)
    star_id = f.array("star_id", np.int64)
    n = len(star_id)
    if n < group_size:
        raise BadInputError(path, "star_id", f"holds {n} star(s): a group needs {group_size}")
    label = f.array("label", np.int64, ascending=True)
    m = len(label)
    if m < 1:
        raise BadInputError(path, "label", "holds no label")
    members = f.array("members", np.int32, (m, group_size), index_of=n)
    try:
        trend = np.asarray(a["trend"], dtype=np.float64).ravel()
    except (TypeError, ValueError):
        raise BadInputError(path, "trend", "attribute is not numeric") from None
    if not 1 <= len(trend) <= 64 or not np.isfinite(trend).all():
        raise BadInputError(path, "trend", f"attribute must be 1 to 64 finite polynomial coefficients, got "
                                           f"{trend.tolist()[:6]}")
    fov_deg = f.numbers("fov_deg", positive=True)
    if not fov_deg < 180:
        raise BadInputError(path, "fov_deg", f"attribute must be below 180 deg, got {fov_deg:g}")
    db = LabelDatabase(label, members, star_id, f.array("star_vector", np.float64, (n, 3), within=(-1.0, 1.0)),
                       f.array("star_mag", np.float64, (n,), finite=True), trend,
                       f.numbers("trend_scale", positive=True), _whole(path, a, "trend_radius", 0, m), fov_deg,
                       scale_digits, group_size, stars_per_field, str(a["catalog_sha256"]), f.params, path)
    log.info("label database %s: %d labels of %d stars, %g deg fields, read in %.0f ms", path, len(db.label),
             len(db.star_id), db.fov_deg, (time.perf_counter() - t0) * 1000)
    return db


def _whole(path: str, attrs: dict, name: str, lo: int, hi: int) -> int:
    """Root attribute ``name`` as a whole number in ``[lo, hi]``, else a BadInputError naming the file and it."""
    value = attrs[name]
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise BadInputError(path, name, f"attribute must be a whole number, got {value!r}") from None
    if not (math.isfinite(number) and number == int(number) and lo <= number <= hi):
        raise BadInputError(path, name, f"attribute must be a whole number in {lo}..{hi}, got {value!r}")
    return int(number)


def check_labels(db: LabelDatabase, camera=None, catalog=None, tolerance: float = 0.1) -> None:
    """Refuse a label database built for another field of view (labels depend on which stars share a field)."""
    name = db.path or "database"
    if camera is not None:
        fov = max(camera.fov_deg)
        if abs(fov - db.fov_deg) > tolerance * db.fov_deg:
            raise DatabaseMismatchError(name, "fov_deg", f"built for a {db.fov_deg:g} deg field, the camera's is "
                                        f"{fov:.2f} deg: rebuild it for a {fov:.1f} deg field")
    if catalog is not None and catalog.checksum() != db.catalog_sha256:
        raise DatabaseMismatchError(name, "catalog_sha256", "was built from another catalog: rebuild the database")
