#!/usr/bin/env python3
"""Study (issue 21), recorded in 84dbd40:benchmarks/results-accuracy-2026-12-02b.md: why NEES was 3.57 (paper 000).

And what each fix does.

The same rendered frames and the same centroids (seed 0, as ``accuracy_bench.py --sensor p000``) solved
four ways, each adding one change to the one before:

  V0  before: reference = the identification star itself; weight = the centroid bound from the measured
      flux, PSF and noise; every matched star used
  V1  + the weighted fit's own covariance (cov_px2) as the star's sigma (edge-cut stars)
  V2  + stars whose fit fails its chi-square test (misfit) left out (startrack.accuracy.misfits_to_drop)
  V3  + references at the photocentre of unresolved companions (blended_references): the benchmark now

For each: the normalised error per axis against the frame's bound (z), NEES against the reported covariance
(frames within 0.1 deg), and the frames more than 0.1 deg off.  Then the per-star normalised centroid error
(error / reported sigma) by category, from V3's stars.

    python benchmarks/studies/accuracy_nees_ablation.py 1000
"""
import math
import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # benchmarks/: common, the tools
from accuracy_bench import EPOCH  # noqa: E402
from common import sensor_spec  # noqa: E402

from startrack.accuracy import (  # noqa: E402
    blended_references,
    error_vector,
    frame_bound,
    misfits_to_drop,
    reference_stars,
    star_covariance,
    stars_crb_from_frame,
    summarise,
)
from startrack.attitude import estimate_attitude  # noqa: E402
from startrack.catalog import load_catalog  # noqa: E402
from startrack.centroid import CentroidOptions, find_stars  # noqa: E402
from startrack.render import Scene, project_stars, render_image  # noqa: E402
from startrack.rotations import quaternion_to_dcm, random_quaternions  # noqa: E402

ARCSEC = math.degrees(1.0) * 3600.0


def match(stars, cam, dcm, cat, vec, max_px=1.0):
    index, tx, ty = project_stars(vec, dcm, cam, margin_px=2.0)
    pairs, seen = [], set()
    for k, s in enumerate(stars):
        if s.get("saturated") or not len(tx):
            continue
        d = np.hypot(tx - s["x"], ty - s["y"])
        j = int(np.argmin(d))
        tid = int(cat.id[index[j]])
        if d[j] <= max_px and tid not in seen:
            seen.add(tid)
            pairs.append((k, tid))
    return pairs


def main():
    n = int(sys.argv[1]) if len(sys.argv) > 1 else 200
    seed = 0
    cam, sensor, mags, render_mag = sensor_spec("p000")
    base = load_catalog().propagate(EPOCH)
    rcat = base.filter_magnitude(None, render_mag)
    rvec = rcat.vectors()
    plain = base.filter_magnitude(*mags)
    merged = blended_references(plain, rcat, cam)
    cats = {"plain": (plain, plain.vectors(), plain.rows_by_id()), "merged": (merged, merged.vectors(),
                                                                              merged.rows_by_id())}
    variants = {"V0": ("plain", False, False), "V1": ("plain", True, False), "V2": ("plain", True, True),
                "V3": ("merged", True, True)}
    rec = {v: {"err": [], "crb": [], "cov": [], "far": [], "failed": 0} for v in variants}
    per_star = []
    dcms = quaternion_to_dcm(random_quaternions(n, np.random.default_rng(seed)))
    f = cam.focal_length_px
    for k in range(n):
        img, truth = render_image(rcat, cam, dcms[k], sensor, Scene(), np.random.default_rng([seed, k]), vectors=rvec)
        bound, _ = frame_bound(cam, reference_stars(cam, dcms[k], merged, sensor, cats["merged"][1]), sensor)
        if bound is None:
            continue
        res = find_stars(img, CentroidOptions(gain_e_per_dn=sensor.gain), saturation=sensor.max_dn)
        for v, (which, fit_cov, drop_misfits) in variants.items():
            cat, vec, rows = cats[which]
            pairs = [(i, t) for i, t in match(res.stars, cam, dcms[k], cat, vec) if t in rows]
            drop = misfits_to_drop([res.stars[i].get("misfit") for i, _ in pairs]) if drop_misfits \
                else [False] * len(pairs)
            body, ref, sig, labels = [], [], [], []
            for (i, tid), dropped in zip(pairs, drop):
                s = res.stars[i]
                cov = star_covariance(s, sensor.gain, res.background_sigma) if fit_cov else \
                    stars_crb_from_frame([s], sensor.gain, res.background_sigma)[0]
                if cov is None or dropped:
                    continue
                sg = math.sqrt(0.5 * (cov[0, 0] + cov[1, 1]))
                body.append(cam.pixels_to_vectors(s["x"], s["y"]))
                ref.append(vec[rows[tid]])
                sig.append(sg / f)
                labels.append((i, tid))
                if v == "V3":
                    # the star's true position: its reference projected at the true attitude
                    tx, ty = cam.vectors_to_pixels((dcms[k] @ vec[rows[tid]])[None])
                    per_star.append((s["x"] - tx[0], s["y"] - ty[0], sg, s["x"], s["y"], bool(s.get("misfit"))))
            r = rec[v]
            att = estimate_attitude(np.array(body), np.array(ref), np.array(sig), "quest", labels) \
                if len(body) >= 2 else None
            if att is None or att.status != "ok":
                r["failed"] += 1
                continue
            e = error_vector(att.dcm, dcms[k])
            if np.linalg.norm(e) > math.radians(0.1):
                r["far"].append(float(e @ np.linalg.solve(att.cov_rad2, e)))
                continue
            r["err"].append(e)
            r["crb"].append(np.diag(bound.cov_rad2))
            r["cov"].append(att.cov_rad2)
        if (k + 1) % 200 == 0:
            print(f"  {k + 1}/{n}", file=sys.stderr, flush=True)
    print(f"paper 000's sensor, {n} frames (seed {seed})\n")
    print("| variant | frames | failed | >0.1 deg (NEES > 25) | z cross | z roll | NEES mean [95 % band] |")
    print("|---|---|---|---|---|---|---|")
    for v, r in rec.items():
        s = summarise(r["err"], r["crb"], r["cov"])
        wrong = sum(x > 25 for x in r["far"])
        print(f"| {v} | {s['frames']} | {r['failed']} | {len(r['far'])} ({wrong}) | {s['z_cross']:.2f} | "
              f"{s['z_roll']:.2f} | {s['nees_mean']:.3f} [{s['nees_band'][0]:.3f}, {s['nees_band'][1]:.3f}] |")
    ps = np.array([(a, b, c, x, y) for a, b, c, x, y, _ in per_star])
    z2 = (ps[:, 0] ** 2 + ps[:, 1] ** 2) / ps[:, 2] ** 2
    edge = np.minimum.reduce([ps[:, 3] + 0.5, cam.width - 0.5 - ps[:, 3], ps[:, 4] + 0.5, cam.height - 0.5 - ps[:, 4]])
    print(f"\nV3's {len(ps)} stars: RMS of error / reported sigma per axis {math.sqrt(np.mean(z2) / 2):.3f}, "
          f"{100 * np.mean(z2 > 13.8):.2f} % beyond the chi-square(2) 0.1 % point; within 2 px of the edge "
          f"{math.sqrt(np.mean(z2[edge < 2]) / 2):.3f} ({int(np.sum(edge < 2))} stars)")


if __name__ == "__main__":
    main()
