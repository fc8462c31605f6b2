"""Study (issue 14), recorded in 84dbd40:benchmarks/results-idrobust-2026-12-02.md ("Causes found"): failure reasons.

The failure reasons of chosen algorithms, counted per condition.

The frames and the database are those of ``benchmarks/identify_compare.py`` (same seed, same
conditions, same merged k-vector database); each failed frame is listed by its reason (the
driver's, with numbers blanked so that like reasons group), with the frame's catalog and
false star counts, so that a cause can be told from a symptom.

    .venv/bin/python benchmarks/studies/identify_failures.py -a voting,grid --count 300
    .venv/bin/python benchmarks/studies/identify_failures.py -a grid --count 300 --conditions 0.3:0 --frames
"""
from __future__ import annotations

import argparse
import collections
import os
import re
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # benchmarks/: common, the tools
from common import add_sensor_arguments, sensor_setup  # noqa: E402


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("-a", "--algorithms", default="voting,brightness,grid")
    add_sensor_arguments(ap, count=300)
    ap.add_argument("--start", type=int, default=0, help="first frame of the sequence")
    ap.add_argument("--frames", action="store_true", help="list every failed frame")
    args = ap.parse_args(argv)

    from startrack.evaluate import Condition, make_frames, score
    from startrack.identify import IdentifyParams, identify_stars
    from startrack.kvector import build_kvector, max_separation_deg

    cam, _, db_cat, star_cat = sensor_setup(args)
    kv = build_kvector(db_cat, max_separation_deg(camera=cam))
    for spec in args.conditions.split(","):
        sigma, nfalse = spec.split(":")
        cond = Condition(sigma_px=float(sigma), false_stars=int(nfalse), min_catalog_stars=args.min_stars)
        params = IdentifyParams(sigma_px=float(sigma))
        frames = make_frames(star_cat, cam, cond, args.count, args.seed, mag_limit=args.star_mag, start=args.start)
        for alg in args.algorithms.split(","):
            identify_stars(frames[0][0], cam, kv, alg, params)     # kernels compiled outside the timing
            reasons = collections.Counter()
            outcomes = collections.Counter()
            listed = []
            t0 = time.perf_counter()
            for stars, truth, seed in frames:
                r = identify_stars(stars, cam, kv, alg, params)
                s = score(r, truth)
                outcomes[s] += 1
                if s == "success":
                    continue
                n_cat = sum(1 for i in truth["star_ids"] if i is not None)
                why = "WRONG" if s == "bad" else re.sub(r"\d+(\.\d+)?(e-?\d+)?", "N", r.reason or "")
                reasons[why] += 1
                listed.append(f"    seed {seed}: {n_cat} catalog + {len(stars) - n_cat} false, trials {r.trials}, "
                              f"{r.time_ms:.0f} ms: {r.reason}")
            wall = time.perf_counter() - t0
            print(f"{alg} [{cond.label()}]: {outcomes['success']} of {len(frames)} "
                  f"({100 * outcomes['success'] / len(frames):.1f} %), failed {outcomes['failure']}, "
                  f"wrong {outcomes['bad']}, {wall:.1f} s")
            for why, n in reasons.most_common():
                print(f"  {n:4d}  {why}")
            if args.frames:
                print("\n".join(listed))


if __name__ == "__main__":
    main()
