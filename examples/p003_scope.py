"""Paper 003's claim measured: the brightness-referenced search's scope and time beside the pyramid's.

    examples/p003_scope.py [--frames N] [--calibration-frames M] [-o examples/results/p003-scope.json]

Paper 003's sensor (20 x 20 deg, 1024 x 1024, catalog to 5.0, 5" (3 sigma), 0.2 mag noise,
the 10 brightest stars, at least 3 per frame), no false star: Table 3's first block.

1. The Eq. 9 calibration the paper's way ("In_k is obtained by averaging the intensity
   values of an identified bright star in different images"): M other frames (seed + 1000)
   are identified with the pyramid and the brightest identified star of each gives
   ``In_3 = In 2.512^(m - 3)``; their mean is the sensor calibration ``3:In_3``
   (examples/intensity_calibration.py).
2. N other frames identified by ``brightness`` with that calibration (reference-star mode
   where a star brighter than magnitude 3 is seen), by ``brightness`` without one (the
   four-star mode only), by ``brightness`` with the calibration carried frame to frame as
   ``startrack identify`` does over a stream (no start: each identified frame's brightest
   star calibrates the next, the mean of the last 10; :mod:`startrack.identify.calibration`)
   and by ``pyramid``.  Per frame: outcome, identification time
   (``time_ms``), mode and scope.  The scope is the number of oriented pair entries the
   look-ups examined (Eqs. 13-14 on the narrowed ranges) beside what the unnarrowed
   k-vector ranges of the same look-ups hold; for the pyramid, the entries of the k-vector
   ranges of the two sides (theta_ij, theta_ik) of every triad it tried (both
   orientations; its fourth-star confirmation is not counted).  Besides the identification
   time (search and the shared verification), the search alone is timed: the time spent
   inside each algorithm's proposal generator, and of it the time inside the compiled search kernels.

The database is built here from the shipped catalog (``build-kvector --fov-deg 20 --size
1024x1024 --mag-max 5.0``) unless ``--database`` names one.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

import numpy as np


def pyramid_scope(b, eps_pairs, db, triads_tried):
    """Oriented entries in the k-vector ranges of theta_ij and theta_ik of the first triads (smart order)."""
    from startrack._kernels.pyramid import smart_triads

    total = 0
    for i, j, k in smart_triads(len(b))[:triads_tried].tolist():
        for u, v in ((i, j), (i, k)):
            th = math.acos(min(1.0, float(b[u] @ b[v])))
            e = eps_pairs(u, v)
            s, t = db.range_linear(math.cos(th + e), math.cos(max(th - e, 0.0)))
            total += 2 * (t - s)
    return total


SEARCH_S = [0.0]
KERNEL_S = [0.0]


def time_kernels():
    """Wrap the compiled search kernels (brightness's and the pyramid's) so that the time inside them accumulates in
    ``KERNEL_S``: the search time less this is the Python around them."""
    import startrack._kernels.brightness as kb
    import startrack._kernels.pyramid as ki

    def wrap(module, name):
        inner = getattr(module, name)

        def timed_kernel(*args):
            t0 = time.perf_counter()
            try:
                return inner(*args)
            finally:
                KERNEL_S[0] += time.perf_counter() - t0

        setattr(module, name, timed_kernel)

    wrap(kb, "brightness_search")
    wrap(ki, "pyramid_candidates")


def timed(alg):
    """``alg`` under the name ``alg.name + '/timed'``: the time spent inside its generator (the search,
    without the shared verification) accumulates in ``SEARCH_S``."""
    from dataclasses import replace

    def search(ctx, config):
        gen = alg.search(ctx, config)
        while True:
            t0 = time.perf_counter()
            try:
                proposal = next(gen)
            except StopIteration:
                SEARCH_S[0] += time.perf_counter() - t0
                return
            SEARCH_S[0] += time.perf_counter() - t0
            yield proposal

    return replace(alg, name=alg.name + "/timed", search=search)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=1000)
    ap.add_argument("--calibration-frames", type=int, default=100)
    ap.add_argument("--database", default=None)
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("-o", "--output", default="examples/results/p003-scope.json")
    a = ap.parse_args(argv)

    from startrack.camera import Camera
    from startrack.catalog import load_catalog, merge_radius_arcsec
    from startrack.evaluate import Condition, make_frames, score
    from startrack.identify import (
        IdentifyParams,
        SearchContext,
        get_algorithm,
        identify_stars,
        make_config,
        register,
        warm_up,
    )
    from startrack.identify.params import star_sigmas_px
    from startrack.kvector import build_kvector, load_kvector, max_separation_deg

    cam = Camera.from_fov(20, 1024, 1024)
    lim = 5.0
    cat = load_catalog(None, mag_max=lim).filter_magnitude(None, lim)
    if a.database:
        db = load_kvector(a.database)
    else:
        db = build_kvector(cat.merge_close(merge_radius_arcsec(cam)), max_separation_deg(20.0))
    sigma = (5.0 / 3.0) / cam.pixel_scale_arcsec
    params = IdentifyParams(sigma_px=sigma)
    cond = Condition(sigma_px=sigma, mag_noise=0.2, max_stars=10, min_stars=3)
    frames = make_frames(cat, cam, cond, a.frames + 1, a.seed, mag_limit=lim)
    warm_up("pyramid", db, params)

    # 1. Calibration from identified bright stars (one per frame; examples/intensity_calibration.py).
    sys.path.insert(0, str(Path(__file__).parent))
    from intensity_calibration import calibrate

    k, in_k, n_cal = calibrate(db, cam, cat, a.calibration_frames, a.seed + 1000, sigma, 0.2, lim)
    calibration = f"{k:g}:{in_k:.6g}"

    runs = {"brightness (calibrated)": ("brightness", make_config("brightness", {"brightness_calibration": calibration})),
            "brightness (no calibration)": ("brightness", make_config("brightness")),
            "brightness (carried frame to frame)": ("brightness", "carried"),
            "pyramid": ("pyramid", make_config("pyramid"))}
    for name in ("brightness", "pyramid"):
        register(timed(get_algorithm(name)))
    time_kernels()
    from startrack.identify.calibration import CalibrationCarry

    for name, cfg in runs.values():
        identify_stars(frames[0][0], cam, db, name + "/timed", params,
                       make_config(name) if cfg == "carried" else cfg)         # compile / load kernels
    test = frames[1:]
    rows = {}
    for label, (name, cfg) in runs.items():
        per = []
        carry = CalibrationCarry("", 10) if cfg == "carried" else None
        t0 = time.perf_counter()
        for n_frame, (stars, truth, _) in enumerate(test):
            SEARCH_S[0] = KERNEL_S[0] = 0.0
            if carry is not None:
                frame_cfg, used = carry.config_for(make_config(name))
                res = identify_stars(stars, cam, db, name + "/timed", params, frame_cfg)
                res.details.update(used)
                carry.update(res, n_frame)
            else:
                res = identify_stars(stars, cam, db, name + "/timed", params, cfg)
            search_ms, kernel_ms = SEARCH_S[0] * 1000, KERNEL_S[0] * 1000
            d = res.details or {}
            if name == "pyramid":
                b = cam.pixels_to_vectors(np.array([s["x"] for s in stars]), np.array([s["y"] for s in stars]))
                use = min(len(stars), params.max_stars)
                sig = star_sigmas_px(stars, params)[:use]
                tol = params.tolerance_sigma * sig / cam.focal_length_px
                margin = math.radians(params.margin_arcsec / 3600.0)
                ctx = SearchContext(b[:use], stars[:use], cam, db, 0.0, tol, margin, params)
                scope, unnarrowed = pyramid_scope(b[:use], ctx.pair_eps, db, int(d.get("patterns", 0))), None
            else:
                scope, unnarrowed = d.get("scope"), d.get("scope_unnarrowed")
            per.append({"outcome": score(res, truth), "ms": res.time_ms, "search_ms": search_ms, "kernel_ms": kernel_ms, "mode": d.get("mode"), "scope": scope,
                        "unnarrowed": unnarrowed, "stars": len(stars)})
        wall = time.perf_counter() - t0
        ms = np.array([p["ms"] for p in per])
        sms = np.array([p["search_ms"] for p in per])
        kms = np.array([p["kernel_ms"] for p in per])
        sc = np.array([p["scope"] for p in per if p["scope"] is not None], dtype=float)
        un = np.array([p["unnarrowed"] for p in per if p["unnarrowed"] is not None], dtype=float)
        modes = {}
        for p in per:
            modes[p["mode"] or "none"] = modes.get(p["mode"] or "none", 0) + 1
        by_mode = {}
        for m in modes:
            sel = [p for p in per if (p["mode"] or "none") == m]
            by_mode[m] = {"frames": len(sel), "mean_ms": float(np.mean([p["ms"] for p in sel])),
                          "mean_search_ms": float(np.mean([p["search_ms"] for p in sel])),
                          "mean_scope": float(np.mean([p["scope"] for p in sel])) if sel[0]["scope"] is not None
                          else None,
                          "mean_unnarrowed": float(np.mean([p["unnarrowed"] for p in sel]))
                          if sel[0]["unnarrowed"] is not None else None}
        rows[label] = {"algorithm": name, "frames": len(per),
                       "success": sum(p["outcome"] == "success" for p in per),
                       "failure": sum(p["outcome"] == "failure" for p in per),
                       "bad": sum(p["outcome"] == "bad" for p in per),
                       "mean_ms": float(ms.mean()), "median_ms": float(np.median(ms)), "wall_s": wall,
                       "mean_search_ms": float(sms.mean()), "median_search_ms": float(np.median(sms)),
                       "median_kernel_ms": float(np.median(kms)) if kms.any() else None,
                       "mean_kernel_ms": float(kms.mean()) if kms.any() else None,
                       "mean_scope": float(sc.mean()) if len(sc) else None,
                       "mean_unnarrowed": float(un.mean()) if len(un) else None, "modes": by_mode}
    out = {"command": f"examples/p003_scope.py --frames {a.frames} --calibration-frames {a.calibration_frames} "
                      f"--seed {a.seed}",
           "calibration": calibration, "calibration_samples": n_cal,
           "sensor": "20 x 20 deg, 1024 x 1024, catalog to 5.0, 5\" (3 sigma), 0.2 mag, 10 brightest, >= 3 stars",
           "database_pairs": int(db.n_pairs), "rows": rows}
    Path(a.output).parent.mkdir(parents=True, exist_ok=True)
    Path(a.output).write_text(json.dumps(out, indent=1) + "\n")
    for label, r in rows.items():
        print(f"{label:28s} success {r['success']}/{r['frames']} bad {r['bad']}  mean {r['mean_ms']:.3f} ms  "
              f"median {r['median_ms']:.3f} ms  search mean {r['mean_search_ms']:.3f} median {r['median_search_ms']:.3f} ms  scope {r['mean_scope']}  unnarrowed {r['mean_unnarrowed']}")
    print(f"calibration {calibration} from {n_cal} frames -> {a.output}")


if __name__ == "__main__":
    main()
