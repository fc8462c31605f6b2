"""Study (issue 14), recorded in 84dbd40:benchmarks/results-identify-2026-12-03f.md: Python part of time_ms.

The Python part of the fused pyramid's ``time_ms``: per frame, ``time_ms`` minus the time inside its kernel.

The frames and sensor are issue 14's (:func:`common.add_sensor_arguments`' options: 15 deg 1280x960,
database Hp <= 6, stars to 5.5).  Every frame is identified ``--reps`` times; per frame the
minimum over the repetitions is kept (the least disturbed by other processes) and the median
over frames reported: ``time_ms``, the kernel's time (its entry wrapped with a clock, which adds
a little to it), their difference, the fused call's Python part (``Algorithm.fused`` minus the
kernel) and the driver's (``time_ms`` minus ``Algorithm.fused``).  A hash of every result
(status, reason, matches, trials, quaternion, false-match probability, details) tells whether two
trees decide alike.  Run it from each tree to compare, alternating:

    PYTHONPATH=. .venv/bin/python benchmarks/studies/identify_overhead.py --conditions 0.3:0,1.0:0 --count 1000

``--tables``: the stars as :class:`startrack.records.StarTable` columns.  ``--reported-sigmas``: the stars
carry their own ``sigma_px`` (as ``centroid`` writes them) instead of one fixed value.
"""
from __future__ import annotations

import argparse
import hashlib
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # benchmarks/: common, the tools


def _clocked(fn, spent, k):
    """``fn`` adding its time to ``spent[k]``."""
    def call(*a):
        t = time.perf_counter()
        try:
            return fn(*a)
        finally:
            spent[k] += time.perf_counter() - t
    return call


def main(argv=None):
    from common import add_sensor_arguments, load_average, sensor_setup

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_sensor_arguments(ap, 300)
    ap.add_argument("--reps", type=int, default=5)
    ap.add_argument("--reported-sigmas", action="store_true",
                    help="every star carries its own sigma_px (the condition's sigma times 0.5-1.5, drawn per star) "
                         "and IdentifyParams.sigma_px is None: the tolerance is the frame's")
    ap.add_argument("--tables", action="store_true",
                    help="give the stars as StarTables (the columns, as identify_speed.py's StarTable input)")
    args = ap.parse_args(argv)

    import startrack
    from startrack.evaluate import Condition, make_frames
    from startrack.identify import IdentifyParams, get_algorithm, identify_stars
    from startrack.kvector import build_kvector, max_separation_deg
    from startrack.records import StarTable

    cam, _, db_cat, star_cat = sensor_setup(args)
    kv = build_kvector(db_cat, max_separation_deg(camera=cam))
    alg = get_algorithm("pyramid")
    print(f"startrack at {os.path.dirname(startrack.__file__)}, load {load_average()}")
    for spec in args.conditions.split(","):
        sigma, false_stars = spec.split(":")
        cond = Condition(sigma_px=float(sigma), false_stars=int(false_stars), min_catalog_stars=args.min_stars)
        params = IdentifyParams(sigma_px=float(sigma))
        frames = make_frames(star_cat, cam, cond, args.count, args.seed, mag_limit=args.star_mag)
        if args.reported_sigmas:
            rng = np.random.default_rng(args.seed)
            frames = [([dict(s, sigma_px=float(sigma) * u) for s, u in zip(stars, rng.uniform(0.5, 1.5, len(stars)))],
                       truth, rest) for stars, truth, rest in frames]
            params = IdentifyParams()
        inputs = [StarTable.from_list(s) if args.tables else s for s, _, _ in frames]
        identify_stars(frames[0][0], cam, kv, "pyramid", params)      # loads the kernels, makes the plan
        plan = kv.__dict__["_pyramid_plan"]
        kernel, fused = plan[3], alg.fused
        spent = [0.0, 0.0]

        plan[3] = _clocked(kernel, spent, 0)
        object.__setattr__(alg, "fused", _clocked(fused, spent, 1))
        shape = (args.reps, len(frames))
        t_ms, t_kernel, t_fused = np.zeros(shape), np.zeros(shape), np.zeros(shape)
        results = []
        try:
            for rep in range(args.reps):
                for f, stars in enumerate(inputs):
                    spent[0] = spent[1] = 0.0
                    r = identify_stars(stars, cam, kv, "pyramid", params)
                    t_ms[rep, f], t_kernel[rep, f], t_fused[rep, f] = r.time_ms / 1000, spent[0], spent[1]
                    if rep == 0:
                        q = None if r.quaternion_estimate is None else r.quaternion_estimate.tolist()
                        results.append((str(r.status), r.reason, [tuple(m) for m in r.matches], r.trials, q,
                                        r.false_match_probability, r.details))
        finally:
            plan[3] = kernel
            object.__setattr__(alg, "fused", fused)

        def med(a):
            return float(np.median(a.min(axis=0))) * 1e6

        ok = sum(1 for r in results if r[0] == "ok")
        print(f"{spec}: {len(frames)} frames, {ok} ok, results {hashlib.sha1(repr(results).encode()).hexdigest()[:12]}; "
              f"median us: time_ms {med(t_ms):.1f}, kernel {med(t_kernel):.1f}, time_ms - kernel "
              f"{med(t_ms - t_kernel):.2f} (fused call {med(t_fused - t_kernel):.2f}, driver {med(t_ms - t_fused):.2f})")


if __name__ == "__main__":
    main()
