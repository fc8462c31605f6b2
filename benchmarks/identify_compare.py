"""Identification side by side, feeds `make bench` section identify-compare, README.md and results/ (identify).

startrack's six algorithms, tetra3rs and cedar-solve on the same star lists.

The star lists are those of ``startrack evaluate`` (:func:`startrack.evaluate.make_frames`,
same seed, same conditions); startrack's rows come from :func:`startrack.evaluate.evaluate`,
the function behind the command.  Peers get the same centroids (brightest first) and the
true field of view; a peer answer counts as correct when its boresight is within 0.1 deg
and its roll within 1 deg of the truth, wrong otherwise (peers report an attitude, not
star ids).  Database loading is outside every timing.

    .venv/bin/python benchmarks/identify_compare.py --count 1000            # the issue-14 table
    .venv/bin/python benchmarks/identify_compare.py --triangles tri15.h5    # modified-pyramid on build-triangles' file
    .venv/bin/python benchmarks/identify_compare.py --fov 12 --size 1024x768 --count 300
    .venv/bin/python benchmarks/identify_compare.py --conditions 0.3:0:1,0.3:3:2 --count 300   # 1 %, 2 % focal error

A condition is ``sigma_px:false_stars[:focal_error_pct]``: with a focal-length error the star lists are
those of a camera whose focal length is that much off the one every tool is given.
"""
from __future__ import annotations

import argparse
import os
import time

import numpy as np
from common import OUT_DIR, add_sensor_arguments, load_average, peer_correct, sensor_setup

ALGORITHMS = ["pyramid", "modified-pyramid", "voting", "brightness", "labelling", "grid"]


def _row(tool, cond, outcomes, times):
    t = np.array(times, dtype=float)
    n = len(outcomes)
    return {"algorithm": tool, "condition": cond, "frames": n, "success": outcomes.count("success"),
            "failure": outcomes.count("failure"), "bad": outcomes.count("bad"),
            "median_ms": float(np.nanmedian(t)), "p95_ms": float(np.nanpercentile(t, 95))}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_sensor_arguments(ap, count=1000)
    ap.add_argument("--algorithms", default=",".join(ALGORITHMS))
    ap.add_argument("--triangles", default=None,
                    help="build-triangles database for modified-pyramid (default: built here from the same stars)")
    ap.add_argument("--no-peers", action="store_true")
    ap.add_argument("--jobs", type=int, default=1)
    ap.add_argument("--out", default=os.path.join(OUT_DIR, "identify_compare.md"))
    args = ap.parse_args(argv)

    from startrack.evaluate import Condition, evaluate, make_frames
    from startrack.identify import IdentifyParams
    from startrack.kvector import build_kvector, max_separation_deg
    from startrack.labels import build_labels
    from startrack.triangles import build_triangles, load_triangles

    load_start = load_average()
    cam, merge_arcsec, db_cat, star_cat = sensor_setup(args)
    w, h = cam.width, cam.height
    t0 = time.perf_counter()
    kv = build_kvector(db_cat, max_separation_deg(camera=cam))
    t_kv = time.perf_counter() - t0
    algos = [a for a in args.algorithms.split(",") if a]
    dbs = {"kvector": kv}
    t_lab = None
    if "labelling" in algos:
        t0 = time.perf_counter()
        dbs["labels"] = build_labels(db_cat, max(cam.fov_deg))
        t_lab = time.perf_counter() - t0
    tri_note = None
    if "modified-pyramid" in algos:
        if args.triangles:
            dbs["triangles"] = load_triangles(args.triangles)
            tri_note = f"triangle database {args.triangles}"
        else:
            dbs["triangles"] = build_triangles(db_cat, min(cam.fov_deg))
            tri_note = "triangle database built here"
        tri = dbs["triangles"]
        tri_note += (f": {tri.n_stars} stars, {tri.n_triangles} triangles, sides up to {tri.max_separation_deg:.2f} deg, "
                     f"built in {tri.params['build_seconds']:.1f} s")
    peers = {}
    notes = [f"startrack k-vector database: {kv.n_stars} stars (Hp <= {args.db_mag:g}, pairs closer than "
             f"{merge_arcsec:.0f}\" merged as build-kvector --size does), {kv.n_pairs} pairs, "
             f"built in {t_kv:.1f} s" + (f"; label database built in {t_lab:.1f} s" if t_lab else "")]
    if tri_note:
        notes.append(tri_note)
    if not args.no_peers:
        try:
            import tetra3rs_peer

            if tetra3rs_peer.is_available():
                peers["tetra3rs"] = tetra3rs_peer.build_or_load(args.fov * max(w, h) / w if w >= h else args.fov,
                                                                args.db_mag, catalog="hip2")
                notes.append(f"tetra3rs database (hip2, Hp <= {args.db_mag:g}): {tetra3rs_peer.LAST_BUILD}")
        except Exception as exc:  # noqa: BLE001
            notes.append(f"tetra3rs unavailable: {type(exc).__name__}: {exc}")
        try:
            import cedar_peer

            if cedar_peer.is_available():
                peers["cedar-solve"] = cedar_peer.CedarSolver(build_fov=args.fov, mag=args.db_mag)
        except Exception as exc:  # noqa: BLE001
            notes.append(f"cedar-solve unavailable: {type(exc).__name__}: {exc}")
    rows = []
    bad = []
    try:
        for spec in args.conditions.split(","):
            sigma, nfalse, *focal = spec.split(":")
            cond = Condition(sigma_px=float(sigma), false_stars=int(nfalse), min_catalog_stars=args.min_stars,
                             focal_error_pct=float(focal[0]) if focal else 0.0)
            params = IdentifyParams(sigma_px=float(sigma))
            got = evaluate(algos, [cond], args.count, dbs, cam, star_cat, args.seed, args.jobs, params, args.star_mag)
            rows += [dict(r, condition=cond.label()) for r in got]
            bad += [f"{r['algorithm']} [{cond.label()}]: frame seed {b['frame_seed']}: {b['wrong']}"
                    for r in got for b in r["bad_seeds"]]
            if not peers:
                continue
            frames = make_frames(star_cat, cam, cond, args.count, args.seed, mag_limit=args.star_mag)
            for tool, peer in peers.items():
                outcomes, times = [], []
                for stars, truth, _ in frames:
                    xy = [[s["x"], s["y"]] for s in stars]
                    if tool == "tetra3rs":
                        r = tetra3rs_peer.solve(xy, w, h, args.fov, db=peer)
                        t = r["elapsed_ms"]
                    else:
                        r = peer.solve_centroids(xy, w, h, args.fov)
                        t = r.get("t_solve_ms") or r.get("t_wall_ms") or float("nan")
                    times.append(t)
                    if r.get("ra") is None:
                        outcomes.append("failure")
                    else:
                        outcomes.append("success" if peer_correct(r, truth) else "bad")
                rows.append(_row(tool, cond.label(), outcomes, times))
    finally:
        if "cedar-solve" in peers:
            peers["cedar-solve"].close()
    lines = [f"# Identification, {args.fov:g} deg {args.size}, stars to Hp {args.star_mag:g}, database Hp <= "
             f"{args.db_mag:g}, >= {args.min_stars} catalog stars a frame, {args.count} frames, seed {args.seed}", ""]
    lines += [f"- {n}" for n in notes] + [""]
    lines += ["| condition | algorithm | success | failed | wrong | median ms | p95 ms | frames with a double: ok / wrong |",
              "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        dbl = f"{r['double_success']} of {r['double_frames']} / {r['double_bad']}" if "double_frames" in r else "-"
        lines.append(f"| {r['condition']} | {r['algorithm']} | {100 * r['success'] / r['frames']:.1f} % "
                     f"({r['success']}) | {r['failure']} | {r['bad']} | {r['median_ms']:.3f} | {r['p95_ms']:.3f} "
                     f"| {dbl} |")
    lines += ["", f"Load average (1, 5, 15 min) at the start: {load_start}; at the end: "
              + load_average() + f" ({os.cpu_count()} cores)"]
    if bad:
        lines += ["", "Wrong answers (frame seed, star, reported id, true id):", ""] + [f"- {b}" for b in bad]
    text = "\n".join(lines) + "\n"
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out, "w") as fh:
        fh.write(text)
    print(text)


if __name__ == "__main__":
    main()
