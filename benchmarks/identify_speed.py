"""Identification speed, feeds `make bench` section identify-speed and results/results-identify-2026-12-04b.md.

Pyramid's identification time beside tetra3rs's ``solve_from_centroids``, frame by frame in one process.

Issue 14's sensor and star lists (:mod:`identify_compare`'s options and frames).  Each frame is given to
startrack twice -- as the list of star dicts a frame document holds, and as a
:class:`startrack.records.StarTable` (its columns, as tetra3rs gets an array) -- and to tetra3rs,
in whole passes over the frames, alternated, so that the three see the same machine state.  startrack's time is the result's ``time_ms`` (the
identification from the star list to the matches); tetra3rs's the wall time of its
``solve_from_centroids`` call with the centroids already an array.  Every input is prepared before the
timings.  Reports medians, p95 and the ratios, with the success counts.

    .venv/bin/python benchmarks/identify_speed.py --count 1000 --conditions 0.3:0
"""
from __future__ import annotations

import argparse
import os

import numpy as np
from common import add_sensor_arguments, load_average, peer_correct, sensor_setup


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_sensor_arguments(ap, count=1000)
    ap.set_defaults(conditions="0.3:0")
    ap.add_argument("--algorithm", default="pyramid")
    ap.add_argument("--passes", type=int, default=3, help="passes over the frames per input kind (alternated)")
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)

    import tetra3rs_peer

    from startrack.evaluate import Condition, make_frames, score
    from startrack.identify import IdentifyParams, identify_stars
    from startrack.kvector import build_kvector, max_separation_deg
    from startrack.records import StarTable

    load_start = load_average()
    cam, _, db_cat, star_cat = sensor_setup(args)
    w, h = cam.width, cam.height
    kv = build_kvector(db_cat, max_separation_deg(camera=cam))
    peer = tetra3rs_peer.build_or_load(args.fov * max(w, h) / w if w >= h else args.fov, args.db_mag, catalog="hip2")
    lines = [f"# {args.algorithm} beside tetra3rs, {args.fov:g} deg {args.size}, stars to Hp {args.star_mag:g}, "
             f"database Hp <= {args.db_mag:g}, {args.count} frames, seed {args.seed}", "",
             "| condition | input | success | median ms | p95 ms | median / tetra3rs |", "|---|---|---|---|---|---|"]
    for spec in args.conditions.split(","):
        sigma, nfalse = spec.split(":")
        cond = Condition(sigma_px=float(sigma), false_stars=int(nfalse), min_catalog_stars=args.min_stars)
        params = IdentifyParams(sigma_px=float(sigma))
        frames = make_frames(star_cat, cam, cond, args.count, args.seed, mag_limit=args.star_mag)
        inputs = [(stars, StarTable.from_list(stars), [[s["x"], s["y"]] for s in stars], truth)
                  for stars, truth, _ in frames]
        # The first call in the process loads the compiled kernels: not timed.
        identify_stars(inputs[0][0], cam, kv, args.algorithm, params)
        tetra3rs_peer.solve(inputs[0][2], w, h, args.fov, db=peer)
        times = {"star dicts": [], "StarTable": [], "tetra3rs": []}
        ok = {k: 0 for k in times}
        # Whole passes over the frames, one input kind (or tool) a pass, the passes alternated: a frame
        # identified right after the same frame would find its database stars in the cache (a frame is
        # identified once in use).
        for rep in range(args.passes):
            for key in times:
                for stars, table, xy, truth in inputs:
                    if key == "tetra3rs":
                        r = tetra3rs_peer.solve(xy, w, h, args.fov, db=peer)
                        times[key].append(r["elapsed_ms"])
                        good = r.get("ra") is not None and peer_correct(r, truth)
                    else:
                        res = identify_stars(stars if key == "star dicts" else table, cam, kv, args.algorithm, params)
                        times[key].append(res.time_ms)
                        good = score(res, truth) == "success"
                    ok[key] += good and rep == 0
        ref = float(np.median(times["tetra3rs"]))
        lines.append(f"| {cond.label()} | ({args.passes} alternated passes of {len(inputs)} frames) | | | | |")
        for key, t in times.items():
            med = float(np.median(t))
            lines.append(f"| {cond.label()} | {key if key == 'tetra3rs' else args.algorithm + ', ' + key} | "
                         f"{100 * ok[key] / len(inputs):.1f} % | {med:.4f} | {float(np.percentile(t, 95)):.4f} | "
                         f"{med / ref:.2f} |")
    lines += ["", f"Load average at the start: {load_start}; at the end: "
              + load_average() + f" ({os.cpu_count()} cores)"]
    text = "\n".join(lines) + "\n"
    if args.out:
        with open(args.out, "w") as fh:
            fh.write(text)
    print(text)


if __name__ == "__main__":
    main()
