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

import functools
import math
import os
import time
from dataclasses import dataclass

import numpy as np


__all__ = ["FOV_BANDS", "SolveOptions", "band_database", "cache_dir", "fov_hypotheses", "solve_image"]

# (smallest FOV, largest FOV, faintest magnitude of the k-vector database, of the label databases,
#  field sizes of the label databases).  Which stars are "the 8 brightest of a field" depends on the
#  field's size, so a band may carry label databases for two sizes.
FOV_BANDS = ((4.0, 9.0, (6.5,), 6.5, (6.5,)), (9.0, 13.0, (6.5, 6.0), 6.0, (12.7, 10.8)),
             (13.0, 20.0, (6.0,), 5.5, (16.0,)), (20.0, 32.0, (5.0,), 5.0, (25.0,)))


def cache_dir() -> str:
    path = os.environ.get("STARTRACK_CACHE") or os.path.join(
        os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache"), "startrack")
    os.makedirs(path, exist_ok=True)
    return path


_DB_MEMO: dict = {}


def band_database(band: int, catalog=None, progress=None, which: int = 0):
    """A cached k-vector database of a FOV band (``which`` of its magnitude limits; built on first use)."""
    from startrack.catalog import load_catalog
    from startrack.kvector import build_kvector, load_kvector, save_kvector

    lo, hi, mags, _, _ = FOV_BANDS[band]
    mag = mags[which]
    cat = (catalog or load_catalog()).filter_magnitude(None, mag)
    key = (band, mag, cat.checksum())
    # A 4:3 sensor at the band's largest horizontal field.
    diag = 2 * math.degrees(math.atan(math.tan(math.radians(hi) / 2) * 1.25))
    path = os.path.join(cache_dir(), f"kvector-fov{lo:g}-{hi:g}-mag{mag:g}-{key[2][:12]}.h5")
    return _cached(key, path, load_kvector, save_kvector, lambda: build_kvector(
        cat, diag + 0.5, progress=progress,
        params={"band_fov_deg": [lo, hi], "mag_max": mag, "purpose": "startrack solve default"}))


def _cached(key, path, load, save, build):
    """A database from memory, else from the cache file (when its catalog checksum matches), else built and saved."""
    from startrack.formats.hdf5 import cached_database

    if key in _DB_MEMO:
        return _DB_MEMO[key]
    db = cached_database(path, load, save, build, valid=lambda d: d.catalog_sha256 == key[-1])
    _DB_MEMO[key] = db
    return db


def band_labels(band: int, catalog=None, progress=None, which: int = 0):
    """A cached label database (paper 004) of a FOV band (``which`` of its field sizes)."""
    from startrack.catalog import load_catalog
    from startrack.labels import build_labels, load_labels, save_labels

    lo, hi, _, mag, sizes = FOV_BANDS[band]
    fov = sizes[which]
    cat = (catalog or load_catalog()).filter_magnitude(None, mag)
    key = ("labels", band, which, cat.checksum())
    path = os.path.join(cache_dir(), f"labels-fov{fov:.1f}-mag{mag:g}-{key[3][:12]}.h5")
    return _cached(key, path, load_labels, save_labels, lambda: build_labels(
        cat, fov, step_deg=min(1.0, fov / 12.0), progress=progress,
        params={"band_fov_deg": [lo, hi], "purpose": "startrack solve default"}))


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


class _SearchClock:
    """The per-image time limit, counting search time only.

    Building or loading a cached database and a kernel's first use in this
    process (numba compiles it, or loads it from its cache) are one-time set-up:
    on a fresh installation they take longer than the whole search, and a time
    limit that counted them would fail every first image.
    """

    _used: set = set()      # (kind) of first uses already paid in this process

    def __init__(self, limit_s: float):
        self.t0 = time.perf_counter()
        self.limit_s = limit_s
        self.setup_s = 0.0

    def setup(self, fn, *args, **kwargs):
        t = time.perf_counter()
        try:
            return fn(*args, **kwargs)
        finally:
            self.setup_s += time.perf_counter() - t

    def first_use(self, kind, fn, *args, **kwargs):
        """``fn(...)``, counted as set-up the first time ``kind`` runs in this process."""
        if kind in _SearchClock._used:
            return fn(*args, **kwargs)
        try:
            return self.setup(fn, *args, **kwargs)
        finally:
            _SearchClock._used.add(kind)

    def expired(self) -> bool:
        return time.perf_counter() - self.t0 - self.setup_s > self.limit_s


def _label_scale(lab):
    """The focal-length scale a label match measured (also when the frame was not confirmed)."""
    return lab.focal_scale if lab.focal_scale is not None else lab.details.get("label_focal_scale")


def _pyramid_config(algorithm, max_triads):
    from startrack.identify import config_fields, make_config

    has = any(f["name"] == "max_triads" and algorithm in f["algorithms"] for f in config_fields())
    return make_config(algorithm, {"max_triads": max_triads} if has else {})


def _identify_in_band(stars, camera, band, catalog, algorithm, params, clock, config=None):
    """Identify ``stars`` with each k-vector database of FOV band ``band`` in turn.

    Returns ``((camera, database, result) or None, databases tried)``.
    """
    from startrack.identify import identify_stars

    for which in range(len(FOV_BANDS[band][2])):
        db = clock.setup(band_database, band, catalog, which=which)
        res = clock.first_use(algorithm, identify_stars, stars, camera, db, algorithm, params, config)
        if res.status == "ok":
            return (camera, db, res), which + 1
    return None, len(FOV_BANDS[band][2])


def pointing(dcm, camera) -> dict:
    """Where the camera points: the image centre's and the principal point's RA/Dec (degrees).

    The attitude's boresight is the principal point (the optical axis); an
    observer asks where the middle of the picture is.  They differ when the
    principal point is not at the image centre (a calibrated camera).
    """
    def radec(x, y):
        v = np.asarray(dcm).T @ camera.pixels_to_vectors(np.array([x]), np.array([y]))[0]
        return {"ra": math.degrees(math.atan2(v[1], v[0])) % 360.0,
                "dec": math.degrees(math.asin(max(-1.0, min(1.0, float(v[2])))))}

    c = radec((camera.width - 1) / 2.0, (camera.height - 1) / 2.0)
    return {"center_ra": c["ra"], "center_dec": c["dec"], "principal_point": radec(camera.cx, camera.cy)}


def _solve_with_patterns(stars, w, h, opts, index, clock):
    """Blind identification with the scale-invariant pattern index (:mod:`startrack.patterns`)."""
    from startrack.patterns import BlindOptions, solve_blind

    if index is None:
        index = clock.setup(_process_index)
    bo = BlindOptions(sigma_px=opts.sigma_px, max_false_probability=opts.max_false_probability,
                      timeout_s=max(0.0, opts.timeout_s - (time.perf_counter() - clock.t0 - clock.setup_s)))
    if opts.fov_deg is not None:
        bo.fov_min_deg = opts.fov_deg * (1 - opts.fov_tolerance)
        bo.fov_max_deg = opts.fov_deg * (1 + opts.fov_tolerance)
    clock.setup(_warm, index)
    cam, res, info = solve_blind(stars, w, h, index, bo)
    if cam is None:
        return None, info["verified"]
    return (cam, index, res), info["verified"]


@functools.lru_cache(maxsize=1)
def _process_index():
    """The default pattern index, opened (or built) once per process, its kernels ready."""
    from startrack.patterns import default_index

    index = default_index(notice=_notice)
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


def _warm(index):
    """Compile or load the solver's kernels (a notice first when numba has no cached copy yet)."""
    from startrack.centroid import CentroidOptions, find_stars
    from startrack.patterns import warm_kernels

    if not _kernels_cached():
        _notice("compiling the solver's kernels once, ~30 s (cached afterwards)")
    yy, xx = np.mgrid[0:64, 0:64]
    tiny = (100.0 + 1000.0 * np.exp(-((xx - 30.3) ** 2 + (yy - 20.7) ** 2) / 2.0)).astype(np.float32)
    find_stars(tiny, CentroidOptions(max_stars=5, mesh_px=16))
    warm_kernels(index)


def _notice(text: str) -> None:
    """A one-line notice on stderr, shown whether or not stderr is a terminal (long one-time set-up)."""
    import sys

    sys.stderr.write(f"startrack: {text}\n")
    sys.stderr.flush()


def solve_image(image, width_height=None, options: SolveOptions | None = None, camera=None, catalog=None,
                saturation=None, centroid_options=None, index=None):
    """Solve one image.

    Returns a dict with the frame sections ``camera``, ``stars``,
    ``centroid``, ``identification``, ``attitude`` and ``solve`` (status,
    fitted FOV, hypotheses tried, time).  Never raises for an unsolvable
    image: ``solve.status`` is ``"failed"`` with a reason.
    """
    from startrack.attitude import estimate_attitude
    from startrack.camera import Camera
    from startrack.catalog import load_catalog
    from startrack.centroid import CentroidOptions, find_stars
    from startrack.formats.sections import to_section
    from startrack.identify import IdentifyParams, identify_stars, make_config

    opts = options or SolveOptions()
    clock = _SearchClock(opts.timeout_s)
    t0 = clock.t0
    h, w = image.shape
    cres = clock.first_use("centroid", find_stars, image, centroid_options or CentroidOptions(max_stars=opts.max_stars),
                           saturation=saturation)
    out = {"stars": cres.stars, "centroid": cres.section()}
    if len(cres.stars) < 4:
        out["solve"] = {"status": "failed", "reason": cres.reason or f"only {len(cres.stars)} stars detected",
                        "time_ms": (time.perf_counter() - t0) * 1000}
        return out
    tried = 0
    result = None
    id_config = _pyramid_config(opts.algorithm, opts.max_triads)
    params = IdentifyParams(sigma_px=opts.sigma_px, max_stars=opts.search_stars,
                            max_false_probability=opts.max_false_probability)
    if camera is not None:
        result, n = _identify_in_band(cres.stars, camera, _band_of(camera.fov_deg[0]), catalog, opts.algorithm,
                                      params, clock, id_config)
        tried += n
    elif opts.algorithm == "patterns" or opts.blind == "patterns":
        result, n = _solve_with_patterns(cres.stars, w, h, opts, index, clock)
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
            labels = clock.setup(band_labels, band, catalog, which=which)
            guess = opts.fov_deg if opts.fov_deg is not None else labels.fov_deg
            cam = Camera.from_fov(guess, w, h)
            for _ in range(3):
                tried += 1
                lab = clock.first_use("labelling", identify_stars, cres.stars, cam, labels, "labelling", lab_params,
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
                continue
            if opts.fov_deg is not None and abs(cam.fov_deg[0] / opts.fov_deg - 1) > opts.fov_tolerance:
                continue
            if not 0.7 * lo <= cam.fov_deg[0] <= 1.4 * hi:
                continue
            b = _band_of(cam.fov_deg[0])
            params.max_false_probability = opts.max_false_probability / (len(attempts) * len(FOV_BANDS[b][2]))
            result, n = _identify_in_band(cres.stars, cam, b, catalog, opts.algorithm, params, clock,
                                      id_config)
            tried += n
            if result is not None:
                break
    if result is None and camera is None and opts.fov_deg is not None and opts.blind != "patterns" \
            and not clock.expired():
        # With a hint, the hinted lens itself (the pyramid tolerates a few percent, and the
        # verification measures and corrects the focal length).
        cam = Camera.from_fov(opts.fov_deg, w, h)
        result, n = _identify_in_band(cres.stars, cam, _band_of(opts.fov_deg), catalog, opts.algorithm, params, clock,
                                      id_config)
        tried += n
    if result is None:
        reason = (f"no star pattern identified ({tried} attempts)"
                  if not clock.expired() else f"no solution within {opts.timeout_s:g} s of search")
        if camera is None and opts.fov_deg is None:
            reason += "; a field-of-view hint (--fov-deg) may help"
        out["solve"] = {"status": "failed", "reason": reason, "hypotheses": tried,
                        "time_ms": (time.perf_counter() - t0) * 1000}
        out["identification"] = {"status": "failed", "algorithm": opts.algorithm, "matches": [], "reason": reason}
        return out
    cam, db, res = result
    scale = res.focal_scale
    if scale:
        cam = cam.with_focal_length(cam.focal_length_px / scale)
    if db is not None and hasattr(db, "star_vec") and opts.epoch is None and catalog is None:
        vec = db.star_vec
        rows = {int(m["id"]): int(m["index"]) for m in res.matches}
    else:
        cat = catalog or load_catalog()
        if opts.epoch is not None:
            cat = cat.propagate(opts.epoch)
        rows = cat.rows_by_id()
        vec = cat.vectors()
    body, ref, sig, labels = [], [], [], []
    for m in res.matches:
        s = cres.stars[m.star]
        body.append(cam.pixels_to_vectors(s["x"], s["y"]))
        ref.append(vec[rows[m.id]])
        sig.append(max(s.get("sigma_px", 0.1), 0.05) / cam.focal_length_px)
        labels.append((m.star, m.id))
    att = estimate_attitude(np.array(body), np.array(ref), np.array(sig), opts.method, labels)
    out["camera"] = cam.to_dict()
    out["identification"] = to_section(res)
    out["attitude"] = att.section()
    fx, fy = cam.fov_deg
    out["solve"] = {"status": "ok" if att.status == "ok" else "failed", "fov_deg": [fx, fy],
                    "hypotheses": tried, "database": os.path.basename(getattr(db, "path", "") or ""),
                    "time_ms": (time.perf_counter() - t0) * 1000}
    if att.dcm is not None:
        out["solve"].update(pointing(att.dcm, cam))
    if att.status != "ok":
        out["solve"]["reason"] = att.reason
    return out
