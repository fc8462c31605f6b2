"""Feeds results/results-sparse-2026-12-06.md: random detections (no star) through the blind search, any ok wrong.

Point lists of 5-40 uniformly random positions on three sensors (1024x768, 1600x1200, 640x480), each through
:func:`startrack.patterns.solve_blind` with the shipped pattern index and a time limit per list; prints the count of
``ok`` (must be 0) and the reasons of the failures.

    python benchmarks/false_hunt.py --frames 270 --timeout 0.5 --seed 2026
"""
from __future__ import annotations

import argparse
import collections
import time

import numpy as np


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=270)
    ap.add_argument("--timeout", type=float, default=0.5, help="seconds per list")
    ap.add_argument("--seed", type=int, default=2026)
    args = ap.parse_args(argv)
    from startrack.patterns import BlindOptions, default_index, solve_blind

    idx = default_index()
    rng = np.random.default_rng(args.seed)
    wrong = 0
    reasons = collections.Counter()
    t0 = time.time()
    for k in range(args.frames):
        npts = (5, 6, 7, 8, 10, 12, 16, 24, 40)[k % 9]
        w, h = ((1024, 768), (1600, 1200), (640, 480))[k % 3]
        xy = rng.uniform([0, 0], [w, h], size=(npts, 2))
        stars = [{"x": float(x), "y": float(y), "flux": float(1000 - i)} for i, (x, y) in enumerate(xy)]
        _, res, _ = solve_blind(stars, w, h, idx, BlindOptions(timeout_s=args.timeout))
        if res.status == "ok":
            wrong += 1
            print(f"WRONG: list {k} ({npts} points, {w}x{h}) ok, false-match probability "
                  f"{res.false_match_probability:.2g}", flush=True)
        else:
            reasons[(res.reason or "").split(" (")[0]] += 1
    print(f"{args.frames} random lists, seed {args.seed}: {wrong} ok (wrong), {time.time() - t0:.0f} s")
    for r, c in reasons.most_common():
        print(f"  {c:5d}  {r}")
    return 1 if wrong else 0


if __name__ == "__main__":
    raise SystemExit(main())
