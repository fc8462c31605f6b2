#!/usr/bin/env python3
"""Study (issue 16), recorded in results/results-track-2026-12-02b.md: a frame's streak rate with and without refit.

The rate from one frame's streaks with and without refitting the streaks off the common motion.

    python benchmarks/studies/streak_rate_refit.py

For each rate, 6 random attitudes x 4 frames (12 deg, 1024 x 768, Hp <= 6.5, 100 ms): detection with the
matched filter, line-segment fits of the 12 brightest, the rate from the significant ones among the first
8 ("old"); then :func:`startrack.streak.refit_off_motion` and the rate again, twice ("new"), as the
tracker's acquisition does.  Errors against the true rate (sign from the truth), the estimate's median
sigma and the RMS of error / sigma.
"""
import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # benchmarks/: common, the tools
import track_bench as tb  # noqa: E402

from startrack.centroid import CentroidOptions, find_stars  # noqa: E402
from startrack.streak import fit_streaks, rate_from_streaks, refit_off_motion  # noqa: E402


def sig_ok(f):
    return f is not None and f.length_px > 2 * max(f.sigma_length_px, 0.5)



def main():
    cam, cat, _ = tb.setup()
    for rate in (0.1, 0.5, 1.0, 2.0, 3.0):
        w = rate * tb.AXIS
        E = {"old": [], "new": []}; S = {"old": [], "new": []}; nrep = []
        for seed in range(6):
            frames = tb.render(cat, cam, w, 4, 500 + seed, tb.random_start(500 + seed))
            for _doc, img in frames:
                res = find_stars(img, CentroidOptions(deblend=False, max_elongation=1e9, matched_filter=True, filter_sigma_px=2.0), saturation=65535.0)
                st = res.stars[:12]
                xs = [s["x"] for s in st]; ys = [s["y"] for s in st]
                fits = fit_streaks(img, xs, ys)
                est = rate_from_streaks(cam, [f if sig_ok(f) else None for f in fits][:8], 0.1)
                if est is None: continue
                E["old"].append(np.degrees(est.resolved(np.radians(w))) - w); S["old"].append(np.degrees(np.sqrt(np.diag(est.cov))))
                f2 = fits
                for _ in range(2):
                    f2, n = refit_off_motion(img, cam, f2, xs, ys, est.rate, 0.1, significant=sig_ok)
                    nrep.append(n)
                    est2 = rate_from_streaks(cam, [f if sig_ok(f) else None for f in f2][:8], 0.1)
                    if est2 is None: break
                    est = est2
                E["new"].append(np.degrees(est.resolved(np.radians(w))) - w); S["new"].append(np.degrees(np.sqrt(np.diag(est.cov))))
        for k in ("old", "new"):
            e = np.array(E[k]); s = np.array(S[k])
            print(f"rate {rate} {k}: n {len(e)} rms err {np.sqrt(np.mean(e**2,0)).round(4)} median |err| {np.median(np.abs(e),0).round(4)} median sigma {np.median(s,0).round(4)} pull rms {np.sqrt(np.mean((e/s)**2,0)).round(2)}")
        print("   replaced per pass", np.mean(nrep).round(2))


if __name__ == "__main__":
    main()
