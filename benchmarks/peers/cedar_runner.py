#!/usr/bin/env python3
"""cedar-solve (tetra3's maintained fork) as a JSON Lines solver, for benchmarks only.

cedar-solve pins ``numpy<2`` so it lives in its own venv: run this file with
``.venv-cedar/bin/python`` (``bash benchmarks/peers/setup_peers.sh`` creates it).

Solve (default command)::

    .venv-cedar/bin/python benchmarks/peers/cedar_runner.py [--db default|PATH.npz]
        [--build-fov F --mag M] [--timeout-ms 5000] < requests.jsonl > results.jsonl

One request per input line::

    {"id": 1, "centroids": [[y, x], ...], "size": [height, width], "fov_deg": 11.4}
    {"id": 2, "image": "/path/to/img.tiff", "fov_deg": 11.4}

Optional request keys: ``fov_max_error`` (deg), ``timeout_ms``, ``distortion`` (number,
``[min, max]`` or null), ``match_radius``, ``match_threshold``, ``pixel_convention``
(``"startrack"``, the default, or ``"cedar"``), ``extract`` (dict of keyword arguments for
``tetra3.get_centroids_from_image`` in image mode), ``db`` (database for this request).

Centroids are ``[y, x]`` rows (cedar's order), brightest first. With
``pixel_convention="startrack"`` they are in startrack's pixel convention ((0, 0) = centre of
the top-left pixel) and 0.5 is added to both before calling cedar, whose convention is
(0.5, 0.5) = centre of the top-left pixel (0, 0 = its top-left corner).

One result per request line, same order::

    {"id", "ra", "dec", "roll", "fov", "matches", "t_solve_ms", "status", ...}

``ra``/``dec`` (deg) are of the image centre (cedar's boresight is pixel (H/2, W/2) in its own
convention, i.e. the geometric centre); ``roll`` is converted to startrack's convention (position
angle of image up, -y, east of north) = ``-Roll_cedar mod 360``; cedar's raw value is in
``roll_cedar`` (cedar: angle of celestial north counter-clockwise from image up). ``t_solve_ms``
is cedar's own ``T_solve``; ``t_extract_ms`` (image mode) is its ``T_extract``; ``t_wall_ms``
wraps the whole call. ``status`` is one of MATCH_FOUND, NO_MATCH, TIMEOUT, CANCELLED, TOO_FEW,
ERROR (with ``error``).

Build a database (cached; also done on demand by ``--build-fov/--mag``)::

    .venv-cedar/bin/python benchmarks/peers/cedar_runner.py build-db --max-fov 20 --mag 5.0
    .venv-cedar/bin/python benchmarks/peers/cedar_runner.py build-db --max-fov 12 --min-fov 11

The star catalogue is startrack's own ``catalogs/hip2.h5`` (Hipparcos New Reduction, Hp <= 8,
epoch J1991.25), written once in the ``hip_main.dat`` layout that cedar reads (Hp in the Vmag
column).  Databases are cached in ``bench-output/peers/cedar/``.
"""
from __future__ import annotations

import argparse
import json
import logging
import math
import os
import sys
import time
import traceback
from pathlib import Path

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(os.path.dirname(HERE))
CACHE_DIR = os.path.join(ROOT, "bench-output", "peers", "cedar")
HIP2 = os.path.join(ROOT, "catalogs", "hip2.h5")

STATUS = {1: "MATCH_FOUND", 2: "NO_MATCH", 3: "TIMEOUT", 4: "CANCELLED", 5: "TOO_FEW"}


def _import_tetra3():
    try:
        import tetra3  # cedar-solve installs the package as ``tetra3``
    except ImportError as exc:  # pragma: no cover - environment problem
        sys.exit(f"cedar_runner: cannot import tetra3 (cedar-solve): {exc}; "
                 "run with .venv-cedar/bin/python after benchmarks/peers/setup_peers.sh")
    return tetra3


# ------------------------------------------------------------------------ catalogue
def write_hip_main(path: str, hip2: str = HIP2) -> str:
    """Write ``hip2.h5`` in the pipe-separated ``hip_main.dat`` layout cedar parses.

    cedar reads fields 1 (HIP), 5 (Vmag), 8 (RAdeg), 9 (DEdeg), 12 (pmRA = mu_a*cos d, mas/yr)
    and 13 (pmDE, mas/yr), positions at epoch J1991.25: exactly what hip2.h5 holds (with Hp
    instead of V).  Returns the path.
    """
    import h5py

    if os.path.exists(path):
        return path
    os.makedirs(os.path.dirname(path), exist_ok=True)
    with h5py.File(hip2, "r") as f:
        hip = f["id"][:]
        ra, dec, mag = f["ra"][:], f["dec"][:], f["mag"][:]
        pmra, pmde = f["pm_ra"][:], f["pm_dec"][:]
    tmp = path + ".part"
    with open(tmp, "w") as out:
        for i in range(len(hip)):
            pr = "" if not np.isfinite(pmra[i]) else f"{pmra[i]:.2f}"
            pd = "" if not np.isfinite(pmde[i]) else f"{pmde[i]:.2f}"
            fields = ["H", f"{hip[i]:6d}", " ", " ", " ", f"{mag[i]:5.2f}", " ", " ",
                      f"{ra[i]:12.8f}", f"{dec[i]:12.8f}", " ", " ",
                      pr or " ", pd or " ", " "]
            out.write("|".join(fields) + "\n")
    os.replace(tmp, path)
    return path


def db_cache_path(max_fov, min_fov=None, mag=None, epoch=2025.0, cache_dir=CACHE_DIR):
    name = f"cedar_fov{max_fov:g}"
    if min_fov is not None and min_fov != max_fov:
        name += f"-{min_fov:g}"
    name += f"_mag{mag:g}" if mag is not None else "_magauto"
    name += f"_ep{epoch:g}.npz"
    return os.path.join(cache_dir, name)


def build_db(max_fov, min_fov=None, mag=None, epoch=2025.0, cache_dir=CACHE_DIR,
             force=False, log=sys.stderr, **kw):
    """Generate (or reuse) a cedar database; returns (path, seconds spent generating)."""
    tetra3 = _import_tetra3()
    path = db_cache_path(max_fov, min_fov, mag, epoch, cache_dir)
    if os.path.exists(path) and not force:
        return path, 0.0
    cat = write_hip_main(os.path.join(cache_dir, "hip_main.dat"))
    t3 = tetra3.Tetra3(load_database=None)
    print(f"cedar_runner: generating {os.path.basename(path)} (max_fov={max_fov}, "
          f"min_fov={min_fov}, mag={mag}, epoch={epoch}) ...", file=log, flush=True)
    t0 = time.perf_counter()
    tmp = path[:-4] + ".part.npz"
    t3.generate_database(max_fov=max_fov, min_fov=min_fov, save_as=Path(tmp), star_catalog=cat,
                         star_max_magnitude=mag, epoch_proper_motion=epoch, **kw)
    dt = time.perf_counter() - t0
    os.replace(tmp, path)
    props = {k: (v.tolist() if hasattr(v, "tolist") else v)
             for k, v in t3.database_properties.items()}
    with open(path[:-4] + ".json", "w") as fh:
        json.dump({"generation_s": dt, "properties": props,
                   "num_stars": int(t3.star_table.shape[0])}, fh, indent=1, default=str)
    print(f"cedar_runner: generated in {dt:.1f} s: {props.get('num_patterns')} patterns, "
          f"{t3.star_table.shape[0]} stars", file=log, flush=True)
    return path, dt


# ------------------------------------------------------------------------ solving
class Solver:
    def __init__(self, default_db="default", timeout_ms=5000.0):
        self.tetra3 = _import_tetra3()
        self.default_db = default_db
        self.timeout_ms = timeout_ms
        self._dbs = {}

    def t3(self, db=None):
        db = db or self.default_db
        if db not in self._dbs:
            if db == "default":
                self._dbs[db] = self.tetra3.Tetra3()  # ships default_database.npz
            else:
                # a str would be looked up in tetra3's own data/ folder: pass a Path
                self._dbs[db] = self.tetra3.Tetra3(load_database=Path(os.path.abspath(db)))
        return self._dbs[db]

    def solve(self, req: dict) -> dict:
        out = {"id": req.get("id")}
        try:
            t3 = self.t3(req.get("db"))
            kw = dict(fov_estimate=req.get("fov_deg"),
                      fov_max_error=req.get("fov_max_error"),
                      solve_timeout=req.get("timeout_ms", self.timeout_ms),
                      distortion=req.get("distortion", 0),
                      return_matches=bool(req.get("return_matches", False)))
            for k in ("match_radius", "match_threshold", "match_max_error"):
                if k in req:
                    kw[k] = req[k]
            if "distortion" in req and isinstance(req["distortion"], list):
                kw["distortion"] = tuple(req["distortion"])
            t0 = time.perf_counter()
            if req.get("image"):
                from PIL import Image
                img = Image.open(req["image"])
                img.load()
                t0 = time.perf_counter()  # file decoding is not timed
                res = t3.solve_from_image(img, **kw, **(req.get("extract") or {}))
                size = (img.size[1], img.size[0])
            else:
                cents = np.asarray(req.get("centroids") or [], dtype=np.float64).reshape(-1, 2)
                if req.get("pixel_convention", "startrack") == "startrack":
                    cents = cents + 0.5
                size = tuple(int(v) for v in req["size"])
                res = t3.solve_from_centroids(cents, size, **kw)
            t_wall = (time.perf_counter() - t0) * 1000.0
            roll_c = res.get("Roll")
            out.update({
                "ra": res.get("RA"), "dec": res.get("Dec"),
                "roll": None if roll_c is None else (-roll_c) % 360.0,
                "roll_cedar": roll_c,
                "fov": res.get("FOV"), "matches": res.get("Matches"),
                "rmse_arcsec": res.get("RMSE"), "prob": res.get("Prob"),
                "distortion": res.get("distortion"),
                "t_solve_ms": res.get("T_solve"), "t_extract_ms": res.get("T_extract"),
                "t_wall_ms": t_wall, "size": list(size),
                "status": STATUS.get(res.get("status"), str(res.get("status"))),
            })
            if kw["return_matches"] and res.get("matched_centroids") is not None:
                mc = np.asarray(res["matched_centroids"], dtype=float)
                if req.get("pixel_convention", "startrack") == "startrack":
                    mc = mc - 0.5
                out["matched_centroids"] = mc.tolist()
                out["matched_catID"] = [int(v) for v in np.ravel(res["matched_catID"])]
        except Exception as exc:  # one bad request never kills the stream
            out.update({"status": "ERROR", "error": f"{type(exc).__name__}: {exc}"})
            if os.environ.get("STARTRACK_DEBUG"):
                traceback.print_exc()
        return {k: _jsonable(v) for k, v in out.items()}


def _jsonable(v):
    if isinstance(v, (np.floating, float)):
        v = float(v)
        return v if math.isfinite(v) else None
    if isinstance(v, np.integer):
        return int(v)
    return v


def main(argv=None):
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv and argv[0] == "build-db":
        p = argparse.ArgumentParser(prog="cedar_runner.py build-db")
        p.add_argument("--max-fov", type=float, required=True)
        p.add_argument("--min-fov", type=float)
        p.add_argument("--mag", type=float, help="star_max_magnitude (Hp); default: cedar's auto")
        p.add_argument("--epoch", type=float, default=2025.0, help="proper-motion epoch")
        p.add_argument("--lattice-field-oversampling", type=int, default=100)
        p.add_argument("--patterns-per-lattice-field", type=int, default=50)
        p.add_argument("--verification-stars-per-fov", type=int, default=150)
        p.add_argument("--cache-dir", default=CACHE_DIR)
        p.add_argument("--force", action="store_true")
        a = p.parse_args(argv[1:])
        logging.basicConfig(level=logging.INFO, stream=sys.stderr)
        path, dt = build_db(a.max_fov, a.min_fov, a.mag, a.epoch, a.cache_dir, a.force,
                            lattice_field_oversampling=a.lattice_field_oversampling,
                            patterns_per_lattice_field=a.patterns_per_lattice_field,
                            verification_stars_per_fov=a.verification_stars_per_fov)
        print(json.dumps({"db": path, "generation_s": dt}))
        return 0

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--db", default="default",
                   help="'default' (cedar's shipped database) or a .npz path")
    p.add_argument("--build-fov", type=float, help="use (building if needed) a cached DB")
    p.add_argument("--build-min-fov", type=float)
    p.add_argument("--mag", type=float)
    p.add_argument("--epoch", type=float, default=2025.0)
    p.add_argument("--timeout-ms", type=float, default=5000.0)
    p.add_argument("--warmup", action="store_true",
                   help="load the database before reading stdin (keeps load time out of t_wall)")
    a = p.parse_args(argv)
    logging.getLogger("tetra3.Tetra3").setLevel(logging.WARNING)
    logging.basicConfig(level=logging.WARNING, stream=sys.stderr)
    db = a.db
    if a.build_fov:
        db, _ = build_db(a.build_fov, a.build_min_fov, a.mag, a.epoch)
    solver = Solver(db, a.timeout_ms)
    if a.warmup:
        solver.t3()
    for line in sys.stdin:
        line = line.strip()
        if not line:
            continue
        try:
            req = json.loads(line)
        except json.JSONDecodeError as exc:
            res = {"id": None, "status": "ERROR", "error": f"bad JSON: {exc}"}
        else:
            res = solver.solve(req)
        sys.stdout.write(json.dumps(res) + "\n")
        sys.stdout.flush()
    return 0


if __name__ == "__main__":
    sys.exit(main())
