"""Study (issue 14), recorded in 84dbd40:benchmarks/results-idrobust-2026-12-02.md ("What limits grid"): why grid fails.

Each frame classified by what its reference stars allow.

On the frames of ``benchmarks/identify_compare.py`` (same seed, conditions, merged database), each
frame is put in one of three classes and crossed with the grid's outcome:

* fewer than two true reference stars with ``min_overlap`` true neighbours between the buffer and
  the pattern radius (the grid needs two references that confirm each other: a structural limit of
  the field);
* fewer than two true references whose true catalog pattern is among the ``matches_per_reference``
  best even when every tie goes against it (chance patterns share as many cells: false stars add
  cells);
* two or more such references.

(Since the grid also proposes each reference match alone -- ``single_references`` -- the second
class can succeed.)

    .venv/bin/python benchmarks/studies/grid_reasons.py --count 1000 --conditions 0.3:0,0.3:10
"""
from __future__ import annotations

import argparse
import collections
import math
import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # benchmarks/: common, the tools
from common import add_sensor_arguments, sensor_setup  # noqa: E402


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_sensor_arguments(ap, count=300)
    args = ap.parse_args(argv)

    from startrack.evaluate import Condition, make_frames, score
    from startrack.identify import IdentifyParams, identify_stars
    from startrack.identify.grid import GridConfig, _pattern, catalog_patterns, grid_geometry
    from startrack.kvector import build_kvector, max_separation_deg

    cam, _, db_cat, star_cat = sensor_setup(args)
    kv = build_kvector(db_cat, max_separation_deg(camera=cam))
    index = {int(i): k for k, i in enumerate(kv.star_id)}
    cfg = GridConfig()
    keep, k_or = cfg.matches_per_reference, cfg.catalog_orientations
    for spec in args.conditions.split(","):
        sigma, nfalse = spec.split(":")
        params = IdentifyParams(sigma_px=float(sigma))
        eps = math.sqrt(2) * params.tolerance_sigma * float(sigma) / cam.focal_length_px + \
            math.radians(params.margin_arcsec / 3600)
        pr, br, g = grid_geometry(cam, kv, cfg, eps)
        ptr, inv_ptr, inv_stars, _ = catalog_patterns(kv, pr, br, g, k_or)
        n_pat = len(ptr) - 1
        cond = Condition(sigma_px=float(sigma), false_stars=int(nfalse), min_catalog_stars=args.min_stars)
        table = collections.Counter()
        for stars, truth, _ in make_frames(star_cat, cam, cond, args.count, args.seed, mag_limit=args.star_mag):
            use = min(len(stars), params.max_stars)
            b = cam.pixels_to_vectors(np.array([s["x"] for s in stars[:use]]), np.array([s["y"] for s in stars[:use]]))
            ids = truth["star_ids"][:use]
            true = [i for i in range(use) if ids[i] is not None and int(ids[i]) in index]
            enough = findable = 0
            for r in true:
                others = np.delete(np.arange(use), r)
                ang = np.arccos(np.clip(b[[t for t in true if t != r]] @ b[r], -1, 1))
                enough += int(np.count_nonzero((ang >= br) & (ang <= pr)) >= cfg.min_overlap)
                k = index[int(ids[r])]
                for which in range(cfg.orientations):
                    cells, _ = _pattern(b[r], b[others], pr, br, g, which)
                    if cells is None or len(cells) < cfg.min_overlap:
                        continue
                    votes = np.zeros(n_pat, dtype=np.int64)
                    for c in cells:
                        votes[inv_stars[inv_ptr[c]:inv_ptr[c + 1]]] += 1
                    per_star = votes.reshape(-1, k_or).max(axis=1)
                    if per_star[k] >= cfg.min_overlap and np.count_nonzero(per_star >= per_star[k]) - 1 < keep:
                        findable += 1
                        break
            cls = ("fewer than 2 references with enough true neighbours" if enough < 2 else
                   "fewer than 2 references with the true pattern among the best" if findable < 2 else
                   "2 or more findable references")
            table[(cls, score(identify_stars(stars, cam, kv, "grid", params), truth))] += 1
        print(f"grid [{cond.label()}], {args.count} frames:")
        for (cls, outcome), n in sorted(table.items()):
            print(f"  {n:5d}  {cls}: {outcome}")


if __name__ == "__main__":
    main()
