"""A scale-invariant 4-star pattern index for blind solving, from about 2 to 70 degree fields.

The idea is tetra3's (Pettersson, ESA) and astrometry.net's (Lang et al. 2010):
a *pattern* of four stars is described by numbers that do not depend on the
focal length, and those numbers are hashed so that the image's patterns are
looked up in constant time.  Here:

* **Key**: the six edge angles of the pattern, sorted; the five smaller divided by
  the largest, each quantised in ``NBINS`` = 32 bins (25 bits).  A look-up probes
  every bin within the measured ratio's tolerance (centroid noise on both edges,
  plus a geometry allowance that grows with the pattern's size), so a ratio near
  a bin edge is never missed.  The 24 star correspondences are then tested on the
  six edges, which also fixes the focal length.
* **Scales**: one *level* per pattern size, a factor sqrt(2) apart (0.9 to 58
  degrees).  At each level the catalog is thinned to a uniform density, brightest
  first: a star is kept unless ``keep`` brighter kept stars lie within half the
  level's pattern size (no cell boundaries, unlike a fixed grid).  A level holds
  every pattern of its stars whose largest edge falls in that level's size range,
  each made once from its brightest star, at most ``max_per_anchor`` per anchor,
  the most compact first (``neighbours`` = ``"nearest"``, the default), or those of
  its brightest neighbours first (``"brightest"``: the three brightest, then the
  fourth with two of them, ...; tetra3's breadth-first order within a field).  The
  brightest-first order holds a pattern of a sparse field's 5-8 detections more
  often (170 against 162 of 200 test fields; 346 against 335 of 600 sparse lists
  solved), but a 33 degree photograph of another camera (``real-extra``'s apod4)
  took 398 candidates instead of 58 and 162 ms instead of 34: the default stays
  the nearest until a study of real wide photographs says otherwise.  The image's
  bright stars form patterns of all sizes; whichever size their level holds is found.
* **Focal length**: a level's size range bounds the focal length an image pattern
  implies; the image's angles are computed with a focal length in that range
  (several for wide levels, where the projection matters) and refined on the match.
* **File**: one flat binary file (a JSON header and aligned arrays) opened by
  ``numpy.memmap`` in milliseconds and shared by processes through the page cache.

Differences from tetra3/cedar-solve: the catalog patterns are uniform at every
scale instead of one field of view; the key is probed over all bins within the
measured tolerance; the correspondence is the best of 24 over all six edges; the
focal length range is a property of the level.  From astrometry.net: several
scales, uniform thinning.  Verification (attitude, every star matched, false-match
probability) is the blind search's own (:func:`_verify_blind`: one match radius for
every star, no magnitudes), combined as :func:`startrack.identify.verify.false_match_probability`
does; the result is the same :class:`~startrack.records.Identification` as every
identification algorithm's.
"""
from __future__ import annotations

import functools
import itertools
import json
import logging
import math
import os
import time
from dataclasses import dataclass, field, replace

import numpy as np

from startrack.cachedir import cache_dir
from startrack.errors import BadInputError, ParameterError
from startrack.timeutil import search_clock

__all__ = ["INDEX_FORMAT", "LEVELS_DEG", "DEEP_LEVELS_DEG", "INDEX_KINDS", "DEEP_FOV_DEG", "PatternIndex", "build_index", "save_index", "open_index", "check_index",
           "default_index_path", "default_index", "BlindOptions", "solve_blind", "cache_dir"]

log = logging.getLogger(__name__)

INDEX_FORMAT = "startrack.patterns/1"
_MAGIC = b"STPATIDX"
#: 2: the header carries ``header_sha256`` and ``data_sha256`` (issue 41).  3: the array ``shapes``.
_FILE_LAYOUT = 3
LEVEL_RATIO = math.sqrt(2.0)
LEVELS_DEG = tuple(0.9 * LEVEL_RATIO**k for k in range(13))     # 0.9 ... 57.6 degrees
BUILD_PARAMS = {"levels_deg": [round(v, 6) for v in LEVELS_DEG], "level_ratio": LEVEL_RATIO, "keep": 3,
                "thin_radius_fraction": 0.5, "max_per_anchor": 40, "min_edge_ratio": 0.05, "mag_max": 10.0,
                "neighbours": "nearest", "version": 1}
"""The default index's build parameters (:func:`build_index`; their hash names the cache file).  ``neighbours``: the
order an anchor's fainter neighbours make its patterns in, ``"brightest"`` or ``"nearest"`` (a parameter set without
the key: ``"nearest"``, as every index built before it was).

``max_per_anchor`` 40: an anchor's patterns stop at about its seventh nearest kept neighbour, and an image pattern with a
later one is not held (the 11 deg ESA image Alt40_Azi45's four brightest stars are their anchor's neighbours 1, 9 and
12 of 15: its search tries 42 patterns).  100 (nearly every pattern of every anchor; 2,648,885 patterns, 95 MB, against
2,212,925 and 81 MB) was measured and not kept (session 10, ``benchmarks/index_ab.py``): on 80 rendered 6-25 deg frames
it halved the patterns tried (mean 20.1 -> 11.8, median 6 -> 3) and cut the mean solve 4.22 -> 3.95 ms, but every
frame that searches many patterns (false stars, photographs whose brightest detections form no pattern) met more
chance candidates: the hint bench's 12 deg frames with 25 false stars took 6-13 % longer blind, the real-extra photos
6-8 %."""

DEEP_LEVELS_DEG = tuple(0.9 / LEVEL_RATIO * LEVEL_RATIO**k for k in range(14))     # 0.64 ... 57.6 degrees
DEEP_BUILD_PARAMS = {**BUILD_PARAMS, "levels_deg": [round(v, 6) for v in DEEP_LEVELS_DEG], "catalog": "gaia"}
"""The deep index: the same patterns over Gaia DR3 to G 10 with Hipparcos for the brightest
(:mod:`startrack.gaia`), one level finer (patterns of 0.45 to 0.64 degrees), for fields from about 0.8 degrees."""
INDEX_KINDS = {"default": BUILD_PARAMS, "deep": DEEP_BUILD_PARAMS}
"""The indexes :func:`default_index` builds: ``default`` from the shipped Hipparcos catalog (fields of 1.5 to 100
degrees), ``deep`` from the catalog ``gaia`` (the extra ``startrack[gaia]``; searched for fields under
:data:`DEEP_FOV_DEG`'s upper end, or for every field with ``catalog="gaia"``)."""
DEEP_FOV_DEG = (0.8, 3.0)
"""Fields (horizontal, degrees) the blind search looks for with the deep index when the default one found nothing.
Below 3 degrees (4:3) a field holds on average fewer than 7 Hipparcos stars to Hp 8.  The lower end is where the
finest level's patterns (0.45-0.64 degrees) still fit a field's brightest stars; measured at 1 and 1.5 degrees
(``benchmarks/narrow_solve.py``), not below."""


@dataclass
class PatternIndex:
    """The arrays of a pattern index (memory-mapped when opened from a file)."""

    star_id: np.ndarray          # (N,) int64 catalog ids, brightest first
    star_vec: np.ndarray         # (N, 3) float64 ICRS unit vectors
    star_mag: np.ndarray         # (N,) float32
    level_rho: np.ndarray        # (L,) float64 largest pattern edge of each level (rad)
    level_start: np.ndarray      # (L,) int64 first pattern of each level
    level_count: np.ndarray      # (L,) int64
    level_prefix: np.ndarray     # (L, 65537) int64 key-prefix offsets within each level
    patterns: np.ndarray         # (P, 4) uint32 star rows
    keys: np.ndarray             # (P,) uint32 25-bit keys, sorted within each level
    shapes: np.ndarray           # (P, 6) uint16 sorted edges over their sum (_kernels.patterns.pattern_shapes)
    params: dict = field(default_factory=dict)
    path: str | None = None

    @property
    def size_bytes(self) -> int:
        return int(sum(getattr(self, n).nbytes for n in _ARRAYS))


_ARRAYS = ("star_id", "star_vec", "star_mag", "level_rho", "level_start", "level_count", "level_prefix",
           "patterns", "keys", "shapes")


def build_index(catalog=None, progress=None, params: dict | None = None) -> PatternIndex:
    """Build the pattern index from ``catalog`` (default: the shipped catalog).

    Parameters
    ----------
    catalog : Catalog, optional
    progress : callable(done, total), optional
    params : dict, optional
        Overrides of :data:`BUILD_PARAMS`.

    Returns
    -------
    PatternIndex
    """
    from startrack._kernels.patterns import level_patterns, prefix_table, thin_uniform_radius
    from startrack.catalog import load_catalog

    p = dict(BUILD_PARAMS)
    p.update(params or {})
    if p.get("neighbours", "nearest") not in ("nearest", "brightest"):
        raise ParameterError("neighbours", f"must be 'nearest' or 'brightest', got {p['neighbours']!r}", "build_index")
    cat = (catalog or load_catalog(mag_max=p.get("mag_max"))).sorted_by_magnitude()
    if p.get("mag_max") is not None:
        # Fainter stars add build time and size for fields under ~2 degrees only.
        cat = cat.filter_magnitude(None, p["mag_max"])
    vec = np.ascontiguousarray(cat.vectors())
    rhos = [math.radians(v) for v in p["levels_deg"]]
    all_p, all_k, all_s, starts, counts, prefixes = [], [], [], [], [], []
    start = 0
    pool = np.arange(len(vec))
    for i, rho in enumerate(rhos):
        # Each level is thinned from the finer level's stars: the levels nest, and the
        # coarse levels cost little.
        kept = pool[thin_uniform_radius(np.ascontiguousarray(vec[pool]), rho * p["thin_radius_fraction"],
                                        int(p["keep"]))]
        pool = kept
        lp, lk, ls = level_patterns(np.ascontiguousarray(vec[kept]), rho, rho / p["level_ratio"], p["min_edge_ratio"],
                                    int(p["max_per_anchor"]), p.get("neighbours", "nearest") == "brightest")
        order = np.argsort(lk, kind="stable")
        lk = lk[order]
        rows = kept[lp[order]].astype(np.uint32)
        all_p.append(rows)
        all_k.append(lk.astype(np.uint32))
        all_s.append(ls[order])
        prefixes.append(prefix_table(lk))
        starts.append(start)
        counts.append(len(lk))
        start += len(lk)
        if progress:
            progress(i + 1, len(rhos))
    p.update(catalog_sha256=cat.checksum(), catalog_source=os.path.basename(cat.source or ""),
             catalog=cat.params.get("catalog", p.get("catalog", "hipparcos")),
             catalog_epoch=float(cat.epoch),
             n_stars=int(len(cat)), patterns_per_level=[int(c) for c in counts])
    return PatternIndex(cat.id.astype(np.int64), vec, cat.mag.astype(np.float32), np.array(rhos),
                        np.array(starts, dtype=np.int64), np.array(counts, dtype=np.int64),
                        np.stack(prefixes).astype(np.int64), np.concatenate(all_p), np.concatenate(all_k),
                        np.concatenate(all_s) if all_s else np.zeros((0, 6), dtype=np.uint16), p)


def _data_sha256(mapped, head_len: int) -> str:
    """The SHA-256 of everything after the header (the arrays and their padding)."""
    import hashlib

    return hashlib.sha256(memoryview(mapped)[head_len:]).hexdigest()


def _header_sha256(header: dict) -> str:
    import hashlib

    rest = {k: v for k, v in header.items() if k not in ("data_sha256", "header_sha256")}
    return hashlib.sha256(json.dumps(rest, sort_keys=True).encode()).hexdigest()


def save_index(index: PatternIndex, path: str) -> None:
    """Write ``index`` as one flat file: magic, header length, JSON header, 64-byte aligned arrays.

    The header carries the SHA-256 of itself and of the data after it (:func:`open_index` checks both).
    """
    import hashlib

    from startrack._version import __version__
    from startrack.formats.atomic import atomic_path

    check_index(index, path)  # never write an index the kernels could not trust
    arrays = {}
    offset = 0
    data = hashlib.sha256()
    for name in _ARRAYS:
        a = np.ascontiguousarray(getattr(index, name))
        arrays[name] = {"dtype": a.dtype.str, "shape": list(a.shape), "offset": offset}
        offset += (a.nbytes + 63) // 64 * 64
        data.update(a.tobytes())
        data.update(b"\0" * ((a.nbytes + 63) // 64 * 64 - a.nbytes))
    header = {"format": INDEX_FORMAT, "version": __version__, "params": index.params, "arrays": arrays}
    header["header_sha256"] = _header_sha256(header)
    header["data_sha256"] = data.hexdigest()
    blob = json.dumps(header).encode()
    head_len = (16 + len(blob) + 63) // 64 * 64
    with atomic_path(path, suffix=".idx") as tmp, open(tmp, "wb") as fh:
        fh.write(_MAGIC + np.uint64(head_len).tobytes())
        fh.write(blob + b" " * (head_len - 16 - len(blob)))
        for name in _ARRAYS:
            a = np.ascontiguousarray(getattr(index, name))
            fh.write(a.tobytes())
            fh.write(b"\0" * ((a.nbytes + 63) // 64 * 64 - a.nbytes))


def check_index(index: PatternIndex, source: str | None = None) -> None:
    """Refuse (``BadInputError`` naming the array) an index whose rows, offsets or vectors a kernel could not trust.

    The kernels index ``star_vec`` by ``patterns``, ``keys``/``patterns`` by ``level_start`` plus
    ``level_prefix``: every one of them is checked to lie in range, so that no file, however
    damaged, makes a kernel read outside an array.
    """
    from startrack._kernels.patterns import PREFIX_SIZE

    src = source or index.path or "pattern index"
    n_stars = len(index.star_id)
    n_pat = len(index.keys)
    n_lev = len(index.level_rho)

    def bad(name, problem):
        raise BadInputError(src, name, problem)

    if index.star_vec.shape != (n_stars, 3) or index.star_mag.shape != (n_stars,):
        bad("star_vec", f"shape {index.star_vec.shape} does not match {n_stars} stars")
    if n_stars and not np.all(np.abs(np.einsum("ij,ij->i", index.star_vec, index.star_vec) - 1.0) < 1e-6):
        bad("star_vec", "holds vectors that are not finite unit vectors")
    if index.patterns.shape != (n_pat, 4):
        bad("patterns", f"shape {index.patterns.shape} does not match {n_pat} keys")
    if n_pat and int(index.patterns.max()) >= n_stars:
        bad("patterns", f"names a star row beyond the {n_stars} stars")
    if n_pat and int(index.keys.max()) >= 1 << 25:
        bad("keys", "holds a key beyond 25 bits")
    if index.shapes.shape != (n_pat, 6) or index.shapes.dtype != np.uint16:
        bad("shapes", f"shape {index.shapes.shape} ({index.shapes.dtype}) is not {n_pat} x 6 uint16")
    if index.level_start.shape != (n_lev,) or index.level_count.shape != (n_lev,) or \
            index.level_prefix.shape != (n_lev, PREFIX_SIZE + 1):
        bad("level_start", f"the level tables do not match {n_lev} levels")
    if not np.all(np.isfinite(index.level_rho) & (index.level_rho > 0)):
        bad("level_rho", "holds a level size that is not a positive number")
    start, count = index.level_start, index.level_count
    if n_lev and (np.any(count < 0) or start[0] != 0 or np.any(start[1:] != start[:-1] + count[:-1])
                  or start[-1] + count[-1] != n_pat):
        bad("level_start", f"the levels do not tile the {n_pat} patterns")
    prefix = index.level_prefix
    if n_lev and (np.any(prefix[:, 0] != 0) or np.any(np.diff(prefix, axis=1) < 0) or np.any(prefix[:, -1] != count)):
        bad("level_prefix", "holds offsets out of order or beyond their level")


def open_index(path: str, verify: bool = True) -> PatternIndex:
    """Open a pattern index file by memory map (milliseconds; pages are read when used).

    With ``verify`` (the default) the file's checksums and every index a kernel follows are checked
    (:func:`check_index`) whenever the file changed since it was last checked (its inode, size and
    change time, kept in ``PATH.checked``; a write of any kind changes the change time): a damaged
    file is refused with ``BadInputError`` naming it and the array, never handed to a kernel.
    """
    try:
        with open(path, "rb") as fh:
            magic = fh.read(8)
            if magic != _MAGIC:
                raise BadInputError(path, None, "is not a startrack pattern index")
            head_len = int(np.frombuffer(fh.read(8), dtype=np.uint64)[0])
            if not 16 < head_len <= 1 << 24:
                raise BadInputError(path, "header", "has an impossible length: the file is damaged")
            header = json.loads(fh.read(head_len - 16).decode())
            if not isinstance(header, dict):
                raise ValueError("the header is not a JSON object")
    except (OSError, ValueError, IndexError) as exc:
        raise BadInputError(path, None, f"cannot read the pattern index: {exc}") from None
    if header.get("format") != INDEX_FORMAT:
        raise BadInputError(path, "format", f"expected {INDEX_FORMAT}, got {header.get('format')!r}")
    if "data_sha256" not in header or "header_sha256" not in header:
        raise BadInputError(path, "data_sha256", "is missing (an index from before checksums)")
    if header["header_sha256"] != _header_sha256(header):
        raise BadInputError(path, "header", "does not match its checksum: the file is damaged")
    size = os.path.getsize(path)
    out = {}
    if isinstance(header.get("arrays"), dict) and "keys" in header["arrays"] and "shapes" not in header["arrays"]:
        raise BadInputError(path, "shapes", "is missing (an index written before the pattern shapes, file layout 3): "
                            "build it again ('startrack cache build' for the cache)")
    try:
        for name in _ARRAYS:
            spec = header["arrays"][name]
            dt = np.dtype(spec["dtype"])
            shape = tuple(int(v) for v in spec["shape"])
            n = int(np.prod(shape)) if shape else 1
            if head_len + spec["offset"] + n * dt.itemsize > size:
                raise BadInputError(path, name, "is truncated")
            if n == 0:
                out[name] = np.zeros(shape, dtype=dt)
            else:
                out[name] = np.asarray(np.memmap(path, dtype=dt, mode="r", offset=head_len + spec["offset"],
                                                 shape=shape))
    except (KeyError, TypeError, ValueError) as exc:
        raise BadInputError(path, "arrays", f"the header's array table is damaged ({exc})") from None
    index = PatternIndex(**out, params=header["params"], path=path)
    if verify:
        from startrack.formats.flatcopy import is_checked, mark_checked, stamp

        taken = stamp(path, header["data_sha256"])
        if not is_checked(path, taken):
            whole = np.memmap(path, dtype=np.uint8, mode="r")
            if _data_sha256(whole, head_len) != header["data_sha256"]:
                raise BadInputError(path, "data_sha256", "does not match the arrays: the file is damaged")
            check_index(index, path)
            mark_checked(path, taken)
    log.info("pattern index %s: %.0f MB, memory-mapped", path, size / 1e6)
    return index


def _kind_params(kind: str) -> dict:
    if kind not in INDEX_KINDS:
        raise ParameterError("kind", f"must be one of {', '.join(INDEX_KINDS)}, got {kind!r}")
    return INDEX_KINDS[kind]


def default_index_path(catalog=None, kind: str = "default") -> str:
    """The cache file of the ``kind`` index (:data:`INDEX_KINDS`) for ``catalog`` (default: the kind's catalog).

    The name carries a hash of the build parameters and of the catalog: its
    content checksum when a catalog is given, else the source files' paths,
    sizes and modification times (so that a warm start does not read the catalog).
    """
    import hashlib

    params = _kind_params(kind)
    # the file layout is in the tag too: an index with checksums never shares a name with one without
    tag = hashlib.sha256(json.dumps({**params, "file_layout": _FILE_LAYOUT}, sort_keys=True).encode()
                         ).hexdigest()[:8]
    if catalog is not None:
        cat_tag = catalog.checksum()[:12]
    else:
        from startrack.catalog import default_catalog_path

        paths = [os.path.abspath(default_catalog_path())]
        stamp = []
        if kind == "deep":
            from startrack.gaia import gaia_path, merge_rules

            paths.append(gaia_path())
            stamp.append(merge_rules())
        for path in paths:
            st = os.stat(path)
            stamp.append(f"{path}|{st.st_size}|{st.st_mtime_ns}")
        cat_tag = hashlib.sha256("||".join(stamp).encode()).hexdigest()[:12]
    prefix = "patterns" if kind == "default" else f"patterns-{kind}"
    return os.path.join(cache_dir(), f"{prefix}-{cat_tag}-{tag}.idx")


def default_index(catalog=None, notice=None, progress=None, kind: str = "default") -> PatternIndex:
    """The ``kind`` pattern index (:data:`INDEX_KINDS`): opened from the cache (checked, :func:`open_index`),
    else built once.

    A missing or damaged file is built under :func:`startrack.formats.hdf5.build_lock`, one builder at a
    time: a second process waits and opens what the first built.  A damaged file gets one warning that
    names it and what is wrong, and is rebuilt.  ``notice(text)`` is called before a build.  The ``deep``
    kind needs the extra ``startrack[gaia]`` (``BadInputError`` naming it otherwise).
    """
    from startrack.formats.hdf5 import build_lock

    params = _kind_params(kind)
    path = default_index_path(catalog, kind)
    if os.path.exists(path):
        try:
            return open_index(path)
        except BadInputError:
            pass  # checked again, and rebuilt, under the lock
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with build_lock(path):
        if os.path.exists(path):
            try:
                return open_index(path)  # built by another process while this one waited
            except BadInputError as exc:
                log.warning("pattern index %s: %s%s: rebuilding it", path, f"{exc.field}: " if exc.field else "",
                            exc.problem)
        if catalog is None and params.get("catalog"):
            from startrack.catalog import load_catalog

            catalog = load_catalog(params["catalog"], mag_max=params.get("mag_max"))
        if notice is not None:
            what = "star index" if kind == "default" else f"{kind} star index ({params.get('catalog')} catalog)"
            notice(f"building the {what} once, ~{estimated_build_s(kind):.0f} s, into {os.path.dirname(path)}")
        index = build_index(catalog, progress=progress, params=params)
        save_index(index, path)
        return open_index(path)


def estimated_build_s(kind: str = "default") -> float:
    """A rough build time (s) of the ``kind`` index, kernels' first compilation included."""
    return 40.0 if kind == "default" else 50.0


# ---------------------------------------------------------------------------------------------- solving
@dataclass
class BlindOptions:
    """Settings of :func:`solve_blind` (degrees, pixels, seconds)."""

    fov_min_deg: float = 1.5
    fov_max_deg: float = 100.0
    pattern_stars: int = 16
    max_pattern_stars: int = 24
    verify_stars: int = 60
    sigma_px: float | None = None
    max_false_probability: float = 1e-6
    timeout_s: float = 5.0
    tol_geom: float = 0.05
    fit_distortion_deg: float = 25.0
    rank: str = "peak"
    # (ra, dec, radius) in degrees: the boresight lies within radius of (ra, dec); None: anywhere.
    sky_circle: tuple | None = None


@functools.lru_cache(maxsize=8)
def _combos(n: int):
    """4-star combinations of the ``n`` brightest stars, those of the brightest stars first (tetra3's order).

    The colexicographic order: by the faintest (largest) index, then the next, ...; so ``_combos(m)`` is the
    first ``C(m, 4)`` rows of ``_combos(n)`` for ``m < n``.  Built a block per largest index from the
    3-combinations in the same order (a process's first solve took 2-3 ms in a Python loop).
    Cached (the same few ``n`` serve every image): callers must not modify it.
    """
    rows = np.arange(max(n, 0), dtype=np.int64).reshape(-1, 1)       # 1-combinations
    for k in range(2, 5):
        blocks = [np.empty((0, k), dtype=np.int64)]
        for last in range(k - 1, n):
            head = rows[:math.comb(last, k - 1)]        # the (k-1)-combinations of 0..last-1
            blocks.append(np.column_stack([head, np.full(len(head), last, dtype=np.int64)]))
        rows = np.concatenate(blocks)
    return rows


def _pattern_blocks(n: int):
    """The blocks ``(s0, s1)`` of the ``n`` patterns looked up together (``combos[s0:s1]``): the first one, the next
    two, then six at a time, made as the search reaches them."""
    start = 0
    for end in itertools.chain((1, 3), itertools.count(6, 6)):
        if start >= n:
            return
        yield start, min(end, n)
        start = end


def _catalog_prefix(index: PatternIndex, solid_angle: float, want: int) -> int:
    """Rows (brightest first) such that the field holds about ``want`` catalog stars on average."""
    n = int(want * 4 * math.pi / max(solid_angle, 1e-9))
    return max(50, min(len(index.star_id), n))


def _fit_camera(cam, dcm, xy, ref, fit_k1):
    """Least-squares focal length (and k1) for fixed attitude: x - c = f u (1 + k1 r^2) per axis (linear in f, f k1).

    ``cam`` unchanged when the fit is degenerate; None when the fitted lens is no lens (a Camera refuses it)."""

    v = ref @ dcm.T
    u = v[:, 0] / v[:, 2]
    w = v[:, 1] / v[:, 2]
    obs = np.concatenate([xy[:, 0] - cam.cx, xy[:, 1] - cam.cy])
    a = np.concatenate([u, w])
    if fit_k1:
        r2 = u * u + w * w
        m = np.stack([a, a * np.concatenate([r2, r2])], axis=1)
        sol, *_ = np.linalg.lstsq(m, obs, rcond=None)
        f, fk1 = float(sol[0]), float(sol[1])
        k1 = fk1 / f if f > 0 else 0.0
    else:
        # k1 held (0 for a pinhole): too few matches to fit it.
        k1 = cam.k1
        if k1:
            r2 = u * u + w * w
            a = a * np.concatenate([1.0 + k1 * r2, 1.0 + k1 * r2])
        f = float(a @ obs / (a @ a))
    if not f > 0 or not math.isfinite(f) or abs(k1) > 1.0:
        return cam
    try:
        return cam.replace(focal_length_px=f, k1=k1, k2=0.0)
    except ParameterError:
        return None         # no lens (a corner moved by more than its radius): not this frame's camera


_WARMED: set = set()     # the array types of the indexes whose kernels this process has ready


def _index_types(index: PatternIndex) -> tuple:
    return tuple((a.dtype.str, a.ndim, a.flags.c_contiguous, a.flags.writeable)
                 for a in (index.level_rho, index.level_start, index.level_prefix, index.keys, index.patterns,
                           index.shapes, index.star_vec))


def warm_kernels(index: PatternIndex) -> None:
    """Compile (or load from numba's cache) the look-up and verification kernels: one-time set-up, not search.

    Once per process and kind of index arrays (a memory-mapped index is read-only, a built one is not).
    """
    from startrack._kernels.attitude import quat_to_dcm, refine
    from startrack._kernels.patterns import query_patterns
    from startrack._kernels.verify import blind_confidence, screen_in_cone, verify_in_cone

    types = _index_types(index)
    if types in _WARMED:
        return

    xy = np.array([[0.0, 0.0], [10.0, 0.0], [0.0, 10.0], [10.0, 12.0]])
    query_patterns(xy, 5.0, 5.0, np.zeros((0, 4), dtype=np.int64), index.level_rho, LEVEL_RATIO,
                   index.level_start, index.level_prefix, index.keys, index.patterns, index.shapes, index.star_vec,
                   _every_row(len(index.star_id)), 0.5, 0.1, 1.0, 2.0, 1)
    b = np.array([[0.0, 0.0, 1.0], [0.01, 0.0, 1.0]])
    b /= np.linalg.norm(b, axis=1)[:, None]
    # The catalog side is the index's own (read-only, memory-mapped) array, as in the
    # search, so that one compiled signature serves both (each one costs a load).
    rows = np.array([0, 1])
    _, q, _ = refine(b, index.star_vec, rows, rows, 0.5, 100.0, 5.0, 5.0, 10.0, 10.0, 0.0, 0.0, 0.0, 0.0, 0, 0.01, 1)
    # The verification on the whole catalog, when a refined field leaves its candidate's cone (_verify_blind).
    blind_confidence(b, rows, rows, index.star_vec[:2], quat_to_dcm(q), 0.5, 0.01, 2, 0.01)
    cone_rows = np.empty(2, dtype=np.int64)
    # (no sky index: the same argument types as a sky index's arrays, _screen_sky)
    _, k, axis = screen_in_cone(b, 2, index.star_vec, 2, rows, rows, 0.5, 0.01, 0.4, cone_rows, *_NO_SKY)
    verify_in_cone(b, np.ascontiguousarray(index.star_vec[:2]), rows, rows.copy(), 0.5, 100.0, 5.0, 5.0, 10.0, 10.0,
                   0.0, 0.0, 0.0, 0.0, 0, 0.01, 1, axis, 0.9, 2, 0.01)
    _WARMED.add(types)


@functools.lru_cache(maxsize=4)
def _every_row(n: int) -> np.ndarray:
    """``query_patterns``' ``allowed`` when the whole sky is searched (cached: callers must not modify it)."""
    return np.ones(n, dtype=np.uint8)


def solve_blind(stars: list, width: int, height: int, index: PatternIndex, options: BlindOptions | None = None,
                deadline: float | None = None):
    """Identify the stars of an image of unknown field of view with the pattern index.

    Parameters
    ----------
    stars : list of dict
        ``x``, ``y`` (pixels), brightest first (``sigma_px`` optional).
    width, height : int
        Image size (pixels); the principal point is taken at the image centre.
    index : PatternIndex
    options : BlindOptions
    deadline : float, optional
        :func:`startrack.timeutil.search_clock` (CPU seconds) value after which the search stops.

    Returns
    -------
    (camera, Identification, info dict)
        ``camera`` is None when nothing was identified; ``info`` counts the
        patterns and candidates tried and, when identified, holds ``rows``:
        the index row of each match, in the order of the matches.
    """
    from startrack._kernels.patterns import query_patterns
    from startrack.identify.params import IdentifyParams
    from startrack.records import Match

    opts = options or BlindOptions()
    warm_kernels(index)
    t0 = time.perf_counter()
    if deadline is None:
        deadline = search_clock() + opts.timeout_s
    info = {"patterns": 0, "candidates": 0, "verified": 0}
    n_all = len(stars)
    if n_all < 4:
        return None, _blind_result(None, 0.0, f"{n_all} star(s): at least 4 are needed"), info
    # Rank by peak (flux breaks ties): compact sources first.  In a photograph with nebulae, a
    # knot of nebula or a galaxy can hold more flux than a star but is never as peaked; for
    # stars of one PSF the order is the flux order.
    if opts.rank == "peak":
        keys = [(-s.get("peak", s.get("flux", 0.0)), -s.get("flux", 0.0)) for s in stars]
        ranked = sorted(range(n_all), key=keys.__getitem__)
    else:
        ranked = list(range(n_all))
    stars = [stars[i] for i in ranked]
    m = min(n_all, opts.verify_stars)
    xy_all = np.array([[s["x"], s["y"]] for s in stars[:m]], dtype=np.float64)
    n_pat = min(m, opts.pattern_stars)
    # Deeper searches when every pattern of the brightest stars is spent: a frame whose brightest detections
    # are mostly not catalog stars (a foreground's pieces, satellites, hot pixels) is found among later ones.
    depths = sorted({n_pat, min(m, max(n_pat, opts.max_pattern_stars))})
    cx, cy = (width - 1) / 2.0, (height - 1) / 2.0
    f_lo = (width / 2.0) / math.tan(math.radians(opts.fov_max_deg) / 2.0)
    f_hi = (width / 2.0) / math.tan(math.radians(opts.fov_min_deg) / 2.0)
    params = IdentifyParams(sigma_px=opts.sigma_px, max_false_probability=opts.max_false_probability)
    sigma = _centroid_sigma_px(stars[:m], params)
    combos = _combos(depths[-1])
    log.debug("pattern search: %d stars (%s in patterns, %d patterns), field %.1f to %.1f deg, %.1f CPU s left",
              n_all, " then ".join(map(str, depths)), len(combos), opts.fov_min_deg, opts.fov_max_deg,
              deadline - search_clock())
    xy_pat = np.ascontiguousarray(xy_all[:depths[-1]])
    # A position hint: a candidate's pattern stars are in the field, so each lies within the field's half
    # diagonal (at the candidate's focal length) of the boresight; those farther than that plus the radius from
    # the hinted centre are not verified, and a verified solution must have its boresight in the circle.
    hint_vec = None
    half_diag_px = math.hypot(width, height) / 2.0
    allowed = _every_row(len(index.star_id))
    if opts.sky_circle is not None:
        ra_h, dec_h, radius_h = (math.radians(v) for v in opts.sky_circle)
        hint_vec = np.array([math.cos(dec_h) * math.cos(ra_h), math.cos(dec_h) * math.sin(ra_h), math.sin(dec_h)])
        info["outside_hint"] = 0
        # The look-up compares no catalog pattern with a star beyond the widest field's half diagonal (at the
        # smallest focal length searched; 1.2 times it for a barrel-distorted corner) from the circle: they cannot
        # be in this image.
        reach = min(math.pi, radius_h + 1.2 * math.atan(half_diag_px / f_lo) + math.radians(0.5))
        allowed = _hint_rows(index, hint_vec, reach)
    seen = set()
    # Patterns are looked up a few at a time (one kernel call each), the first ones alone: most images
    # are identified by their first pattern, and the candidates are verified in the same order either way.
    # _combos(n) begins with _combos(n') for n' < n (tetra3's order: a pattern's faintest star last), so the
    # deeper searches are the same loop carried on past the first depth's patterns.
    reason = "no star pattern identified"
    for s0, s1 in _pattern_blocks(len(combos)):
        if search_clock() > deadline:
            reason = f"no solution within {opts.timeout_s:g} s of search"
            break
        block = combos[s0:s1]
        ci, cf = query_patterns(xy_pat, cx, cy, block, index.level_rho, LEVEL_RATIO, index.level_start,
                                index.level_prefix, index.keys, index.patterns, index.shapes, index.star_vec, allowed,
                                float(sigma), float(opts.tol_geom), f_lo, f_hi, 4096)
        info["patterns"] += len(block)
        info["candidates"] += len(ci)
        order = np.lexsort((cf[:, 1], ci[:, 0]))      # by image pattern (brightest first), best fit first
        if hint_vec is not None and len(order):
            reach = radius_h + 1.2 * np.arctan(half_diag_px / cf[order, 0]) + math.radians(0.5)
            # Every pattern star of the candidate within reach of the hinted centre (the farthest decides).
            cos_hint = np.min(index.star_vec[ci[order][:, 2:6].astype(np.int64)] @ hint_vec, axis=1)
            near = cos_hint >= np.cos(np.minimum(reach, math.pi))
            info["outside_hint"] += int(len(order) - np.count_nonzero(near))
            order = order[near]
        # (each candidate's row and focal length read as it is reached: most searches end at the first)
        for j in order.tolist():
            row, f = ci[j], cf[j, 0]
            if search_clock() > deadline:
                break
            img = [int(v) for v in block[row[0]]]
            cat_rows = [int(v) for v in row[2:6]]
            key = (tuple(sorted(zip(img, cat_rows, strict=True))), round(math.log(f), 2))
            if key in seen:
                continue
            seen.add(key)
            info["verified"] += 1
            res = _verify_candidate(stars[:m], xy_all, img, cat_rows, f, width, height, index, params, sigma,
                                    info["verified"], f_lo, f_hi, opts)
            if res is not None and hint_vec is not None and \
                    math.acos(max(-1.0, min(1.0, float(res[2][2] @ hint_vec)))) > radius_h:
                info["outside_hint"] += 1      # a field found elsewhere than the hint says: not this frame's answer
                res = None
            if res is not None:
                cam, (m_star, m_id, m_row), dcm, p_false = res
                matches = list(map(Match._make, zip([ranked[s_] for s_ in m_star.tolist()], m_id.tolist())))
                elapsed = (time.perf_counter() - t0) * 1000
                extra = {"level_deg": round(math.degrees(float(index.level_rho[row[1]])), 4),
                         "patterns_tried": info["patterns"], "candidates": info["candidates"],
                         "verified": info["verified"]}
                log.info("pattern search: field %.3f deg wide, %d stars matched after %d patterns and %d candidates "
                         "verified, %.0f ms", cam.fov_deg[0], len(matches), info["patterns"], info["verified"], elapsed)
                info["rows"] = m_row.tolist()
                return cam, _blind_result(matches, elapsed, None, p_false, dcm, extra), info
    elapsed = (time.perf_counter() - t0) * 1000
    reason = f"{reason} ({info['patterns']} patterns, {info['verified']} candidates verified)"
    log.info("pattern search: %s, %.0f ms", reason, elapsed)
    return None, _blind_result(None, elapsed, reason, extra=dict(info)), info


def _blind_result(matches, time_ms, reason, false_probability=None, dcm=None, extra=None):
    """The :class:`~startrack.records.Identification` of a blind search: ``ok`` with ``matches``
    (:class:`~startrack.records.Match` of ints, or ``{"star", "id"}`` each) and the attitude ``dcm``, else ``failed``
    with ``reason``; ``extra`` becomes ``details``."""
    from startrack.records import Identification, Match, ReasonCode, Status
    from startrack.rotations import dcm_to_quaternion

    extra = dict(extra or {})
    ok = matches is not None
    return Identification(Status.OK if ok else Status.FAILED, "patterns",
                          [m if type(m) is Match else Match(int(m["star"]), int(m["id"])) for m in matches or []],
                          time_ms=time_ms,
                          reason=reason, reason_code=None if ok else ReasonCode.NO_PATTERN,
                          false_match_probability=false_probability, focal_scale=extra.pop("focal_scale", None),
                          quaternion_estimate=None if dcm is None else dcm_to_quaternion(dcm), details=extra)


#: Relative focal-length step below which the fit-and-verify rounds of :func:`_verify_candidate` stop (when
#: the matches did not change): a tenth of the precision of f from a frame's stars (~0.1 px noise over
#: ~500 px radii and 13-60 stars: ~1e-5 to 1e-4), and the steps left would add up to ~5 % of it.
_F_CONVERGED = 1e-5

#: The chance of coincidence below which a wide field's verification at a radius wider than the strict one (the first,
#: a pinhole's with the radius padded for the unknown distortion, and those whose radius covers the fitted camera's
#: misfit) goes on to the next fit (the agreement and minimum matches apply too).  Every answer passes the false-match
#: limit at the strict radius on its fitted camera, so this is a speed setting, never a correctness one.  Without a
#: screen (1) every wrong wide candidate of any frame is fitted up to :data:`_WIDE_ROUNDS` times: the 4.5 deg photo
#: of ``real-extra`` took 182 ms instead of 92 and the 33 deg one 483 instead of 354 (in one process, load ~1).  With
#: 0.01 the 70 deg k1 -0.1 bench frame and 75 of 80 rendered 50-90 deg fields of k1 0 to -0.15 solve (80 without a
#: screen; 62 before the wide fit); a true 85 deg field of k1 -0.1 scored 0.01 to 0.5 there (1e-189 once fitted): the
#: extreme fields that fail it fail with a reason.
_WIDE_SCREEN_P = 1e-2

#: Fit-and-verify rounds of a wide field (the radius shrinks to the fitted camera's misfit, then to the strict one).
_WIDE_ROUNDS = 5

#: Relative change of a wide field's match radius below which a round that kept its matches is stuck
#: (:func:`_verify_candidate`): the next verification would be the last one again, at the same radius on the same
#: stars, and the candidate is refused (it never reached the strict radius).
_WIDE_STUCK = 0.01


def _misfit_rms_px(cam, dcm, xy, ref) -> float:
    """RMS distance (pixels) between the detections ``xy`` and their catalog stars ``ref`` projected by a pinhole
    ``cam`` of radial k1 (:func:`_fit_camera`'s model) at attitude ``dcm``."""
    v = ref @ dcm.T
    u = v[:, 0] / v[:, 2]
    w = v[:, 1] / v[:, 2]
    s = cam.focal_length_px * (1.0 + cam.k1 * (u * u + w * w))
    return float(np.sqrt(np.mean((cam.cx + s * u - xy[:, 0]) ** 2 + (cam.cy + s * w - xy[:, 1]) ** 2)))


def _verify_candidate(stars, xy, img, cat_rows, f, width, height, index, params, sigma, n_verified, f_lo, f_hi,
                      opts):
    """Verify one candidate strictly; fit the focal length (and k1 for wide fields) and verify again."""
    from startrack._kernels.verify import screen_in_cone
    from startrack.camera import Camera, unit_vectors
    from startrack.identify.params import tolerance_rad

    # Pinhole geometry from f alone (cheap: most candidates end at the screen below).
    cx, cy = (width - 1) / 2.0, (height - 1) / 2.0
    fov = (2 * math.degrees(math.atan(width / 2.0 / f)), 2 * math.degrees(math.atan(height / 2.0 / f)))
    wide = fov[0] > opts.fit_distortion_deg
    solid = math.radians(fov[0]) * math.radians(fov[1])
    n_rows = max(_catalog_prefix(index, solid, max(2 * len(stars), 30)), max(cat_rows) + 1)
    star_vec = index.star_vec[:n_rows]
    star_id = index.star_id[:n_rows]
    b = unit_vectors((xy[:, 0] - cx) / f, (xy[:, 1] - cy) / f)
    r_px = max(1.0, params.match_sigma * sigma)
    if wide:
        # Unknown distortion: first a wider match radius (the false-match probability accounts for it).
        r_px = max(r_px, 0.01 * math.hypot(width, height) * (fov[0] / 60.0) ** 2)
    half_diag = math.atan(math.hypot(width, height) / 2.0 / f)
    cos_fov = math.cos(half_diag + math.radians(0.5))
    # Screen: at least two more of the brightest stars on catalog stars, else not worth verifying.  The same pass
    # keeps the catalog rows near the pattern's boresight: the verification reads those (_CatalogCone).
    n_screen = min(len(b), 20)
    cone_rows = np.empty(n_rows, dtype=np.int64)
    cone_radius = math.acos(cos_fov) + _CONE_SLACK_RAD
    hits, k, axis = screen_in_cone(b, n_screen, index.star_vec, n_rows, np.asarray(img, dtype=np.int64),
                                   np.asarray(cat_rows, dtype=np.int64), cos_fov, r_px / f, math.cos(cone_radius),
                                   cone_rows, *_screen_sky(index, n_rows, cone_radius))
    if hits < min(2, n_screen - 4) or hits <= _chance_hits(k, cone_radius, r_px / f, n_screen, img):
        return None
    cone = _CatalogCone(cone_rows[:k], star_vec, star_id, axis, cone_radius)
    cam = Camera(width, height, float(f), cx, cy)
    # Look-elsewhere: every candidate verified so far, times the distinguishable focal lengths.
    pts = xy[img].tolist()      # (the pattern stars' rows at once: the same floats as a row each)
    pattern_px = max(math.hypot(p[0] - q[0], p[1] - q[1]) for p in pts for q in pts)
    n_scales = max(1.0, math.log(f_hi / f_lo) / max(3.0 * 1.4142 * sigma / pattern_px, 1e-4))
    eps = tolerance_rad(cam, sigma, params)
    trials = int(n_verified * n_scales)
    if not wide:
        # An undistorted pinhole whose focal length alone is fitted: the rounds below without a camera per round.
        return _verify_pinhole(xy, img, cat_rows, trials, b, cam, star_vec, star_id, eps, sigma, params, cone, f_lo,
                               f_hi)
    # A wide field's first verification is a pinhole's at the pattern's focal length with a padded radius: the start
    # of the focal length and k1 fit, not the decision.  Its chance of coincidence is the padded radius's (a true 73
    # deg field of k1 -0.1: 1e-7 to 1e-5, against 1e-160 once fitted), so the false-match limit holds at the strict
    # radius on a fitted camera below (the same look-elsewhere count); a verification at a wider radius is a screen
    # (_WIDE_SCREEN_P).
    screen = replace(params, max_false_probability=max(params.max_false_probability, _WIDE_SCREEN_P))
    matches, dcm, p_false, reason = _verify_blind(img, cat_rows, trials, b, cam, star_vec, star_id,
                                                  eps, sigma, replace(screen, match_radius_px=r_px), cone)
    if matches is None:
        return None
    decided = False         # whether the matches held passed the false-match limit
    verified_cam = cam
    # Fit the camera on the matches, re-solve and verify again with the fitted camera.
    previous = None
    radius_before = r_px        # the match radius of the verification that gave ``matches``
    for _ in range(_WIDE_ROUNDS):
        idx, _, rows = matches
        cam = _fit_camera(cam, dcm, xy[idx], star_vec[rows], len(idx) >= 8)
        if cam is None or not f_lo <= cam.focal_length_px <= f_hi * 1.1:
            return None
        pairs = (idx.tolist(), rows.tolist())
        if decided and pairs == previous:
            break
        round_params = params
        if not decided:
            # The radius covers the fitted camera's misfit on the matches (three rms), down to the strict radius.
            strict_px = _match_radius_px(params, sigma, cam.focal_length_px)
            misfit_px = 3.0 * _misfit_rms_px(cam, dcm, xy[idx], star_vec[rows])
            if misfit_px > strict_px:
                radius = min(r_px, misfit_px)
                if pairs == previous and abs(radius - radius_before) <= _WIDE_STUCK * radius_before:
                    # Stuck: the last round kept its matches, the camera fitted on them misfits them as much as before
                    # (the fit has converged: the alternation's steps shrink geometrically) and the radius is no
                    # nearer the strict one.  Another round is the same verification again: this field never passes
                    # the limit at the strict radius (a wrong wide candidate whose padded radius holds a few chance
                    # stars: ~0.16 ms a round, five rounds).
                    return None
                round_params = replace(screen, match_radius_px=radius)
                radius_before = radius
        previous = pairs
        b = cam.pixels_to_vectors(xy[:, 0], xy[:, 1])
        eps = tolerance_rad(cam, sigma, params)
        m2, dcm2, p2, _ = _verify_blind(idx, rows, trials, b, cam, star_vec, star_id, eps, sigma, round_params, cone)
        if m2 is None:
            break
        matches, dcm, p_false, verified_cam = m2, dcm2, p2, cam
        decided = decided or round_params is params
    if not decided:
        return None         # a wide field whose fitted camera never passed the limit at the strict radius
    return verified_cam, matches, dcm, p_false      # the camera its matches were verified with


def _chance_hits(n_cone: int, cone_radius: float, radius: float, n_screen: int, img) -> float:
    """How many of a screen's stars (:func:`startrack._kernels.verify.screen_in_cone`: the first ``n_screen`` image
    stars other than the pattern's ``img``) would land within ``radius`` (rad) of a catalog star by chance: each
    with probability ``1 - exp(-rho a)``, ``a`` the solid angle of the radius and ``rho`` the density of the
    ``n_cone`` catalog stars of the cone of ``cone_radius`` around the candidate's boresight (a Poisson field of the
    cone's own density).

    A candidate whose screen hits no more stars than that placed the image's brightest stars on catalog stars no
    more often than random positions would: no evidence for it, and :func:`_verify_candidate` refuses it before
    verifying.  This decides only where the radius is wide: a wide field's first radius is padded for its unknown
    distortion (up to ~2.7 deg at 90 deg), where a wrong candidate's chance hits number 2-7 of 16 and its
    verification and fits took 0.1-1.5 ms; a pinhole's radius holds well under one chance hit, where the two hits
    asked for already decide (measured on 55 frames of 6-92 deg: every right candidate had at least 2 hits more than
    this; 174 of 326 wrong ones, 30 of their 63 ms, had no more)."""
    omega = 2.0 * math.pi * (1.0 - math.cos(min(cone_radius, math.pi)))
    area = 2.0 * math.pi * (1.0 - math.cos(radius))
    p = -math.expm1(-n_cone * area / omega) if omega > 0 else 1.0
    return (n_screen - sum(1 for i in img if i < n_screen)) * p


def _verify_pinhole(xy, img, cat_rows, trials, b, cam, star_vec, star_id, eps, sigma, params, cone, f_lo, f_hi):
    """:func:`_verify_candidate`'s verification and fit-and-verify rounds for an undistorted pinhole ``cam`` (its
    focal length fitted, no lens terms): the numbers of :func:`_verify_blind` and :func:`_fit_camera` on the
    focal length alone, without a :class:`~startrack.camera.Camera` per round; the fitted camera made once.

    Returns ``(camera, (stars, ids, rows), dcm, p_false)`` or None."""
    from startrack.camera import MAX_FOCAL_LENGTH_PX, MIN_FOCAL_LENGTH_PER_SIDE, Camera, unit_vectors

    width, height, cx, cy = cam.width, cam.height, cam.cx, cam.cy
    f = cam.focal_length_px
    # What Camera() holds a focal length to (its other values are the candidate camera's): a fit outside is no
    # camera, and the candidate is refused (_fit_camera's None).
    f_min, f_max = MIN_FOCAL_LENGTH_PER_SIDE * max(width, height), MAX_FOCAL_LENGTH_PX
    # _cone_cos's pinhole corner and tolerance_rad's terms, per candidate.
    corner = math.hypot(max(abs(-0.5 - cx), abs(width - 0.5 - cx)), max(abs(-0.5 - cy), abs(height - 0.5 - cy)))
    half_deg = math.radians(0.5)
    tol_fixed = math.radians(params.tolerance_arcsec / 3600.0) if params.tolerance_arcsec is not None else None
    tol_num = params.tolerance_sigma * math.sqrt(2.0) * sigma
    margin = math.radians(params.margin_arcsec / 3600.0)
    dx, dy = xy[:, 0] - cx, xy[:, 1] - cy
    check = _VerifyCheck(trials, star_vec, star_id, sigma, params, cone, width, height, cx, cy)
    matches, dcm, p_false, pos = check(np.array(img, dtype=np.int64), np.array(cat_rows, dtype=np.int64), b, f,
                                       math.cos(math.atan(corner / f) + half_deg), eps, None)
    if matches is None:
        return None
    # Fit the focal length on the matches, re-solve and verify again with it (_fit_camera, _verify_blind).
    previous = None
    for _ in range(3):
        idx, _, rows = matches
        f_before = f
        # The matches' catalog vectors: their rows of the cone's copy when they were verified through it (the same
        # numbers as star_vec's rows, cone.vec = star_vec[cone.rows], already in the cache).
        v = (star_vec[rows] if pos is None else cone.vec[pos]) @ dcm.T
        a = np.concatenate([v[:, 0] / v[:, 2], v[:, 1] / v[:, 2]])
        fit = float(a @ np.concatenate([dx[idx], dy[idx]]) / (a @ a))
        if fit > 0 and math.isfinite(fit):
            if not f_min <= fit <= f_max:
                return None         # no camera (Camera refuses the focal length): not this frame's, as _fit_camera
            f = fit
        if not f_lo <= f <= f_hi * 1.1:
            return None
        pairs = (idx.tolist(), rows.tolist())
        if pairs == previous and abs(f / f_before - 1.0) < _F_CONVERGED:
            # Converged: the last verification kept the same matches and the fit moves f by less than
            # _F_CONVERGED; another round would move it by a few percent of that (the alternation
            # converges geometrically, ratio < 0.05 on the ESA frames).
            break
        previous = pairs
        b = unit_vectors(dx / f, dy / f)
        eps = tol_fixed if tol_fixed is not None else tol_num / f + margin
        m2, dcm2, p2, pos2 = check(idx, rows, b, f, math.cos(math.atan(corner / f) + half_deg), eps, pos)
        if m2 is None:
            break
        matches, dcm, p_false, pos = m2, dcm2, p2, pos2
    cam = cam if f == cam.focal_length_px else Camera(width, height, f, cx, cy)
    return cam, matches, dcm, p_false


def _centroid_sigma_px(stars: list, params) -> float:
    """1-sigma centroid noise: the option, else the median reported ``sigma_px``, else 0.5 px."""
    if params.sigma_px is not None:
        return float(params.sigma_px)
    reported = [v for v in (s.get("sigma_px") for s in stars)
                if isinstance(v, (int, float)) and math.isfinite(v) and v > 0]
    if reported:
        return float(max(0.05, min(2.0, _median(reported) * 1.5)))
    return 0.5


def _median(values: list) -> float:
    """The median of a list of floats, as ``numpy.median`` (the mean of the middle two for an even count) without
    a numpy call (nor :mod:`statistics`, whose import costs a solve process ~5 ms)."""
    v = sorted(values)
    n = len(v)
    return float(v[n // 2]) if n % 2 else float((v[n // 2 - 1] + v[n // 2]) / 2)


def _pattern_chance(n_cat: int, eps: float, vecs) -> float:
    """Expected number of catalog pyramids matching four measured directions by chance (Mortari 2004; LOST).

    The reference of :func:`startrack._kernels.verify.blind_confidence`'s ``e_core`` (the search calls the kernel;
    tests compare the two)."""
    if len(vecs) < 3:
        # A lone pair: E = N (N - 1) / 2 * eps * sin(theta) chance pairs at that angle.
        th = math.acos(max(-1.0, min(1.0, float(vecs[0] @ vecs[1])))) if len(vecs) == 2 else math.pi / 2
        return float(n_cat * (n_cat - 1) / 2 * eps * math.sin(th))
    a, b, c = vecs[0], vecs[1], vecs[2]
    th_ij = math.acos(max(-1.0, min(1.0, float(a @ b))))

    def cross(p, q):
        return (p[1] * q[2] - p[2] * q[1], p[2] * q[0] - p[0] * q[2], p[0] * q[1] - p[1] * q[0])

    def inner(p, q, r):
        """Spherical angle at vertex p between the arcs to q and r."""
        u = cross(p, q)
        v = cross(p, r)
        nu = math.sqrt(u[0] ** 2 + u[1] ** 2 + u[2] ** 2)
        nv = math.sqrt(v[0] ** 2 + v[1] ** 2 + v[2] ** 2)
        if nu == 0 or nv == 0:
            return 0.0
        return math.acos(max(-1.0, min(1.0, (u[0] * v[0] + u[1] * v[1] + u[2] * v[2]) / (nu * nv))))

    phis = [inner(a, b, c), inner(b, a, c), inner(c, a, b)]
    if len(vecs) < 4:
        # A lone triangle: E = N^3 eps^3 sin(theta_ij) / (pi sin(phi_k)).
        return float(n_cat**3 * eps**3 * math.sin(th_ij) / (math.pi * max(math.sin(phis[2]), 1e-6)))
    denom = 2 * math.pi**2 * max(math.sin(phis[2]), 1e-6) * max(max(math.sin(p) for p in phis), 1e-6)
    return float(n_cat**4 * eps**5 * math.sin(th_ij) / denom)


def _match_radius_px(params, sigma_px: float, f: float) -> float:
    """The blind verification's strict match radius (pixels) at focal length ``f``: ``params.match_radius_px``, else
    ``match_sigma`` centroid sigmas plus the angle margin, at least a pixel."""
    if params.match_radius_px is not None:
        return params.match_radius_px
    return max(1.0, params.match_sigma * sigma_px + math.radians(params.margin_arcsec / 3600.0) * f)


def _verify_blind(image: list, catalog: list, trials: int, b_vectors: np.ndarray, camera, star_vec, star_id,
                  eps: float, sigma_px: float, params, cone=None):
    """Attitude, remaining stars and confidence of a candidate: image stars ``image`` are the index's rows
    ``catalog``, after ``trials`` candidates (look-elsewhere).  Returns ``(matches, dcm, p_false, reason)``,
    ``matches`` three int arrays: the matched stars, their catalog ids and their rows of the index.

    The blind solver's verification with one match radius for every star (from the frame's centroid
    sigma, :func:`_centroid_sigma_px`): the attitude refined on every star within it, the candidate's stars
    agreeing with the refined attitude, and the chance of a coincidence (:func:`_pattern_chance`, times the
    chance of the other stars landing on predicted ones by accident, :func:`_local_hit_probability`,
    combined by :func:`startrack.identify.verify.false_match_probability` without magnitudes).  Not the
    identification algorithms' :func:`startrack.identify.verify.verify`: this index holds no magnitudes and
    its candidates come with a focal length still to fit.

    ``cone`` (:class:`_CatalogCone`, optional): the rows of ``star_vec`` near the candidate's boresight; the
    attitude and the confidence read only those when every attitude of the refinement keeps its field inside the
    cone (checked, else the whole of ``star_vec``): the same numbers either way.
    """
    img = np.array(image, dtype=np.int64)
    cat = np.array(catalog, dtype=np.int64)
    f = float(camera.focal_length_px)
    radius_px = _match_radius_px(params, sigma_px, f)
    check = _VerifyCheck(trials, star_vec, star_id, sigma_px, params, cone, camera.width, camera.height, camera.cx,
                         camera.cy, camera.lens_terms)
    matches, dcm, p_false, reason, _ = check.verify(img, cat, np.ascontiguousarray(b_vectors), f,
                                                    _cone_cos(camera, 0.5), eps, radius_px)
    return matches, dcm, p_false, reason


class _VerifyCheck:
    """:func:`_verify_blind` of one candidate's rounds: what stays the same from one round to the next (the
    catalog rows, their cone, the image size and principal point, the lens terms), and :meth:`verify` of one
    round's focal length."""

    def __init__(self, trials, star_vec, star_id, sigma_px, params, cone, width, height, cx, cy,
                 lens_terms=(0.0, 0.0, 0.0, 0.0, 0)):
        self.trials, self.star_vec, self.star_id, self.sigma_px = trials, star_vec, star_id, sigma_px
        self.params, self.cone, self.lens_terms = params, cone, lens_terms
        self.width, self.height, self.cx, self.cy = width, height, float(cx), float(cy)

    def __call__(self, img, cat, b, f, cos_fov, eps, pos=None):
        """:meth:`verify` with the match radius of :attr:`params` at focal length ``f``: ``(matches, dcm, p_false,
        pos)``."""
        radius_px = _match_radius_px(self.params, self.sigma_px, f)
        matches, dcm, p_false, _, pos = self.verify(img, cat, b, f, cos_fov, eps, radius_px, pos)
        return matches, dcm, p_false, pos

    def verify(self, img, cat, b, f, cos_fov, eps, radius_px, pos=None):
        """One verification (:func:`_verify_blind`) of image stars ``img`` (int64) as rows ``cat`` (int64) of
        :attr:`star_vec`, directions ``b`` (C-contiguous) at focal length ``f``; ``pos``: the rows' positions in the
        cone when known (the matches of a verification through it).  Returns ``(matches, dcm, p_false, reason,
        pos)``: ``pos`` the matches' positions in the cone, None when the whole catalog answered."""
        from startrack.identify.verify import false_match_probability

        params = self.params
        if len(img) < 2:
            return None, None, None, "fewer than two stars identified", None
        radius = radius_px / f
        star_vec, star_id = self.star_vec, self.star_id
        n_cat = len(star_vec)
        geometry = (f, self.cx, self.cy, float(self.width), float(self.height), *self.lens_terms, radius, 2)
        # A proposal star agrees when the refined attitude puts its catalog star within the match radius of it
        # (whether or not the star-by-star matching, which refuses ambiguous neighbours, kept it).  With the
        # confidence's numbers, in one kernel call (startrack._kernels.verify.blind_confidence): the chance
        # that a pattern of the proposal's first four stars (three when that is all) matches by coincidence,
        # and the chance that each other star falls on a predicted catalog star by accident.  On the cone's rows,
        # the refinement and the confidence in one call (startrack._kernels.verify.verify_in_cone).
        cone = self.cone
        got = cone.verify(b, img, cat, cos_fov, geometry, n_cat, float(eps), pos) if cone is not None else None
        if got is not None:
            match, q, n_pred, cat, dcm, agree, core_agree, p_local, e_pyr = got
            star_vec, star_id, rows_of = cone.vec, cone.ids, cone.rows
        else:
            from startrack._kernels.attitude import quat_to_dcm, refine
            from startrack._kernels.verify import blind_confidence

            match, q, n_pred = refine(b, star_vec, img, cat, cos_fov, *geometry)
            rows_of = None
            dcm = quat_to_dcm(q)
            agree, core_agree, p_local, e_pyr = blind_confidence(b, img, cat, star_vec, dcm, cos_fov, radius,
                                                                 n_cat, float(eps))
        matched = match >= 0
        n_matched = int(np.count_nonzero(matched))
        if agree < min(len(img), params.min_matches):
            return None, dcm, None, "the proposal's stars do not agree with the refined attitude", None
        if n_matched < params.min_matches and not (len(b) == 3 and n_matched == 3):
            return None, dcm, None, f"only {n_matched} stars matched (need {params.min_matches})", None
        p_hit = _local_hit_probability(p_local, self, n_pred, radius_px)     # (the image size is ours)
        others = len(b) - min(len(img), 4)
        p_false = false_match_probability(e_pyr, self.trials, n_matched - core_agree, others, p_hit)
        if p_false > params.max_false_probability:
            return None, dcm, p_false, (f"false-match probability {p_false:.2g} above the limit "
                                        f"{params.max_false_probability:g}"), None
        rows = np.flatnonzero(matched)
        cat_rows = match[rows]
        ids = star_id[cat_rows]
        pos = None
        if rows_of is not None:
            pos = cat_rows
            cat_rows = rows_of[cat_rows]
        return (rows, ids, cat_rows), dcm, p_false, None, pos


_NO_SKY = (np.zeros(0, dtype=np.int64), np.zeros(0))      # screen_in_cone without a sky index: every row

#: The screens' rows read one by one (every row of their catalog prefix), in units of the pattern index's stars,
#: after which a process builds the index's sky index (_screen_sky).  A build reads each star once at ~70 times the
#: cost of a screen's row (~8 ms for the default index's 106,000 stars, ~1 ns a row): after about as much work as the
#: build costs, never more than twice the work of the better choice made in hindsight.  Speed only: the same
#: answer either way.
SKY_SCREEN_AFTER = 64.0

_SKY_SCREEN: dict = {}      # id(index) -> [index, rows read one by one, sky cells, sky ra] (_screen_sky)
_HINT_ROWS: dict = {}       # (id(index), hint vector, reach) -> (index, mask) (_hint_rows)


def _hint_rows(index: PatternIndex, hint_vec, reach: float) -> np.ndarray:
    """The uint8 mask of ``index``'s stars within ``reach`` (rad) of the unit vector ``hint_vec``: those a position
    hint lets the look-up compare.  Kept for the next frame of the same hint (a batch's ``--ra/--dec/--radius``; the
    mask of the 106,261 stars takes ~0.17 ms): callers must not modify it (writeable, as the kernels' builds take it)."""
    key = (id(index), *map(float, hint_vec), float(reach))
    got = _HINT_ROWS.get(key)
    if got is None or got[0] is not index:
        if len(_HINT_ROWS) >= 8:
            _HINT_ROWS.clear()
        mask = (np.asarray(index.star_vec) @ hint_vec >= math.cos(reach)).astype(np.uint8)
        got = _HINT_ROWS[key] = (index, mask)
    return got[1]


def _screen_sky(index: PatternIndex, n_rows: int, cone_radius: float) -> tuple:
    """The sky index (``cells``, ``ra``: :class:`startrack.skyindex.SkyIndex`) of ``index``'s stars for a screen of
    the first ``n_rows`` rows within ``cone_radius`` (rad) of a boresight
    (:func:`startrack._kernels.verify.screen_in_cone`), or :data:`_NO_SKY` (every row read): the sky index when the
    cone holds under a tenth of the prefix's stars on average.  An index opened from a file has it from the cache
    (:func:`_file_sky`: ~0.5 ms a process to map and check, where a screen without it read 20,000-50,000 rows, 0.1-0.4
    ms on the ESA images); another one once this process's screens have read :data:`SKY_SCREEN_AFTER` times the
    index's stars one by one (a solve or two never pays for the build; a session of many does, once)."""
    m = len(index.star_id)
    state = _SKY_SCREEN.get(id(index))
    if state is None or state[0] is not index:
        if len(_SKY_SCREEN) > 4:
            _SKY_SCREEN.clear()
        state = _SKY_SCREEN[id(index)] = [index, 0, None, None]
        # An index file's sky index is kept in the cache: read from there, or built at once and kept (once on a
        # machine, ~10 ms, as the index itself once).
        sky = _file_sky(index)
        if sky is not None:
            state[2], state[3] = sky.cells, sky.ra
    if m * (1.0 - math.cos(min(cone_radius, math.pi))) / 2.0 >= n_rows / 10.0:
        state[1] += n_rows
        return _NO_SKY
    if state[2] is None:
        if state[1] < SKY_SCREEN_AFTER * m:
            state[1] += n_rows
            return _NO_SKY
        from startrack.skyindex import SkyIndex

        sky = SkyIndex(np.array(index.star_vec))      # (a writable copy: the sky index kernel's one compiled type)
        state[2], state[3] = sky.cells, sky.ra
    return state[2], state[3]


#: The kind of the cache's copy of a pattern index file's sky index (:func:`_file_sky`).
_SKY_COPY = "startrack.patterns.sky/1"


def _file_sky(index: PatternIndex):
    """The :class:`startrack.skyindex.SkyIndex` of the stars of ``index`` when it was opened from a file: its copy in
    the cache (:mod:`startrack.formats.flatcopy`, named by the file's path, inode, size and modification time, and
    checked against its sha256 when new), else built now and written there (and used, written or not).  None for an
    index held in memory only, and when the cache directory cannot be written (the screens then build it when they
    have read as many rows, :data:`SKY_SCREEN_AFTER`)."""
    from startrack.errors import ParameterError
    from startrack.formats.flatcopy import copy_path, read_copy, write_copy
    from startrack.skyindex import SkyIndex

    if index.path is None:
        return None
    path = copy_path(index.path, _SKY_COPY)
    if path is None:
        return None
    got = read_copy(path)
    if got is None and not os.access(os.path.dirname(path), os.W_OK):
        return None         # (a cache that cannot take the copy: not built here for nothing, every process again)
    if got is not None:
        try:
            return SkyIndex.from_arrays(index.star_vec, got[1]["cells"], got[1]["ra"])
        except (KeyError, ParameterError):
            pass            # (a copy of another index's stars: made again below)
    sky = SkyIndex(np.array(index.star_vec))      # (a writable copy: the sky index kernel's one compiled type)
    write_copy(path, {"stars": len(index.star_id)}, {"cells": sky.cells, "ra": sky.ra})   # (built: used either way)
    return sky


#: How far (rad) beyond a candidate's field the catalog rows its verification reads are kept (_CatalogCone): room
#: for the refined attitudes and fitted focal lengths to move the field.  Speed only: an attitude whose field
#: leaves the cone is refined on the whole catalog (the answer is the same either way).
_CONE_SLACK_RAD = math.radians(1.0)


class _CatalogCone:
    """The catalog rows within ``radius`` (rad) of a candidate's boresight ``axis`` (ascending ``rows`` of the
    verification's ``star_vec``, their vectors ``vec`` and ids ``ids``): what its refinement and confidence
    read instead of every row (:func:`startrack._kernels.verify.verify_in_cone`)."""

    def __init__(self, rows, star_vec, star_id, axis, radius):
        self.rows = rows
        self.vec = np.ascontiguousarray(star_vec[rows])
        # As writable as the catalog (a memory-mapped index's is not): then verify_in_cone, refine and
        # blind_confidence share their callees' compiled code (numba compiles a read-only array's kernels apart).
        self.vec.flags.writeable = star_vec.flags.writeable
        self.ids = star_id[rows]
        self.axis = axis
        self.radius = radius

    def verify(self, b, img, cat, cos_fov, geometry, n_cat, eps, pos=None):
        """:func:`startrack._kernels.attitude.refine` and :func:`startrack._kernels.verify.blind_confidence` on the
        cone's rows (:func:`startrack._kernels.verify.verify_in_cone`): ``(match, q, n_predicted, cat, dcm, agree,
        core_agree, p_local, e_core)`` with ``match`` and ``cat`` (the proposal's rows) indexing :attr:`vec`, or
        ``None`` when the cone cannot answer for the whole catalog (a proposal star outside it, or an attitude whose
        field leaves it).  ``pos``: the positions of ``cat`` in :attr:`rows` when the caller knows them (the matches of
        an earlier verification through the cone), else looked up."""
        from startrack._kernels.verify import verify_in_cone

        reach = self.radius - math.acos(max(-1.0, min(1.0, cos_fov))) - 1e-9
        if reach <= 0.0:
            return None
        if pos is None:
            pos = np.searchsorted(self.rows, cat)
            n = len(self.rows)
            # Every proposal row in the cone: each position inside it and holding that row (a pattern's few rows
            # compared one by one).
            if cat.size and (n == 0 or not all(q < n and self.rows[q] == c
                                               for q, c in zip(pos.tolist(), cat.tolist()))):
                return None
        ok, match, q, n_pred, dcm, agree, core_agree, p_local, e_core = verify_in_cone(
            b, self.vec, img, pos, cos_fov, *geometry, self.axis, math.cos(reach), n_cat, eps)
        return (match, q, n_pred, pos, dcm, agree, core_agree, p_local, e_core) if ok else None


def _cone_cos(camera, margin_deg: float) -> float:
    """``camera.cone_cos(margin_deg)``; an undistorted pinhole's from its farthest corner without projecting it."""
    if not camera.is_pinhole or camera.has_distortion:
        return camera.cone_cos(margin_deg)
    dx = max(abs(-0.5 - camera.cx), abs(camera.width - 0.5 - camera.cx))
    dy = max(abs(-0.5 - camera.cy), abs(camera.height - 0.5 - camera.cy))
    return math.cos(math.atan(math.hypot(dx, dy) / camera.focal_length_px) + math.radians(margin_deg))


def _local_hit_probability(p_local: float, camera, n_pred: int, radius_px: float) -> float:
    """Mean chance that one of the other detections lands within the match radius of a predicted catalog star
    by accident.

    The density of catalog stars is taken around each image star (within ten
    match radii, ``p_local`` of :func:`startrack._kernels.verify.blind_confidence`), not over the whole
    image: in a cluster (the Hyades, the Pleiades) chance coincidences are far more likely than the field
    average suggests.  The global average (``n_pred`` stars predicted in the image) is the floor.  ``camera``:
    anything with the image's ``width`` and ``height``.
    """
    floor = min(1.0, n_pred * math.pi * radius_px**2 / (camera.width * camera.height))
    return float(max(floor, p_local))
