"""Paper 004's Table 2 taken apart: where labelling's and the pyramid's identification time goes.

    examples/p004_time_split.py [--frames N] [--kvector DB] [--labels DB] [-o examples/results/p004-time-split.json]

Paper 004's sensor (24 x 24 deg, 1200 x 1200 px, magnitude 5.2, 38" (1 sigma)), the frames of
``startrack evaluate`` (same seed as examples/reproduce-papers.sh's Table 2, 4).  Each frame is
identified by labelling and by the pyramid; the identification time (``time_ms``, what Table 2
compares) is split into the search (time inside the algorithm's proposal generator: label
look-ups, or k-vector triads and the fourth star) and the rest (the shared verification of the
proposals, the false-match test, the final matching), with the proposals verified per frame.
The databases are built here unless given.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from p003_scope import SEARCH_S, timed  # noqa: E402 - the same generator timing as paper 003's scope


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=2000)
    ap.add_argument("--kvector", default=None)
    ap.add_argument("--labels", default=None)
    ap.add_argument("--seed", type=int, default=4)
    ap.add_argument("-o", "--output", default="examples/results/p004-time-split.json")
    a = ap.parse_args(argv)

    from startrack.camera import Camera
    from startrack.catalog import load_catalog, merge_radius_arcsec
    from startrack.evaluate import Condition, make_frames, score
    from startrack.identify import IdentifyParams, get_algorithm, identify_stars, register, warm_up
    from startrack.kvector import build_kvector, load_kvector, max_separation_deg
    from startrack.labels import build_labels, load_labels

    cam = Camera.from_fov(24, 1200, 1200)
    lim = 5.2
    cat = load_catalog(None, mag_max=lim).filter_magnitude(None, lim)
    merged = cat.merge_close(merge_radius_arcsec(cam))
    dbs = {"kvector": load_kvector(a.kvector) if a.kvector else build_kvector(merged, max_separation_deg(24.0)),
           "labels": load_labels(a.labels) if a.labels else build_labels(merged, 24.0)}
    sigma = 38.0 / cam.pixel_scale_arcsec
    params = IdentifyParams(sigma_px=sigma)
    frames = make_frames(cat, cam, Condition(sigma_px=sigma, sigma_arcsec=38.0), a.frames, a.seed, mag_limit=lim)
    rows = {}
    for name in ("labelling", "pyramid"):
        alg = get_algorithm(name)
        db = dbs[alg.database]
        warm_up(name, db, params)
        register(timed(alg))
        identify_stars(frames[0][0], cam, db, name + "/timed", params)
        per = []
        for stars, truth, _ in frames:
            SEARCH_S[0] = 0.0
            t0 = time.perf_counter()
            res = identify_stars(stars, cam, db, name + "/timed", params)
            wall = (time.perf_counter() - t0) * 1000
            per.append((score(res, truth), res.time_ms, SEARCH_S[0] * 1000, wall, res.trials or 0))
        ms = np.array([p[1] for p in per])
        search = np.array([p[2] for p in per])
        trials = np.array([p[4] for p in per], dtype=float)
        rows[name] = {"frames": len(per), "success": sum(p[0] == "success" for p in per),
                      "bad": sum(p[0] == "bad" for p in per),
                      "mean_ms": float(ms.mean()), "median_ms": float(np.median(ms)),
                      "mean_search_ms": float(search.mean()), "median_search_ms": float(np.median(search)),
                      "mean_rest_ms": float((ms - search).mean()), "median_rest_ms": float(np.median(ms - search)),
                      "search_share": float(search.sum() / ms.sum()),
                      "mean_proposals": float(trials.mean()), "median_proposals": float(np.median(trials))}
        r = rows[name]
        print(f"{name:10s} {r['success']}/{r['frames']} ok, {r['bad']} bad; identify mean {r['mean_ms']:.3f} median "
              f"{r['median_ms']:.3f} ms; search mean {r['mean_search_ms']:.3f} median {r['median_search_ms']:.3f} ms "
              f"({100 * r['search_share']:.0f} % of the time); proposals mean {r['mean_proposals']:.1f}")
    out = {"command": f"examples/p004_time_split.py --frames {a.frames} --seed {a.seed}",
           "sensor": "24 x 24 deg, 1200 x 1200 px, magnitude 5.2, 38\" (1 sigma)", "rows": rows}
    Path(a.output).parent.mkdir(parents=True, exist_ok=True)
    Path(a.output).write_text(json.dumps(out, indent=1) + "\n")


if __name__ == "__main__":
    main()
