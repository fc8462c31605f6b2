#!/usr/bin/env python3
"""Study (issue 21), recorded in 84dbd40:benchmarks/results-accuracy-2026-12-02b.md: error / reported sigma per star.

On paper 000's sensor, by neighbour and SNR.

Frames of ``accuracy_bench.py --sensor p000`` (seed 0); each detection matched to a reference of
``blended_references`` (photocentres of companions closer than 2 px) projected at the true attitude; its
error against that position divided by the sigma ``star_covariance`` reports.  Grouped by ``misfit`` and
by the distance to the nearest other rendered star farther than 2 px (a companion the merge left apart),
and for isolated stars by SNR.  Then the background noise on star-free frames against the true noise:
the detection mesh's and the one centroid's weighted fit uses (``_pixel_noise_mesh``).

    python benchmarks/studies/accuracy_star_diagnosis.py 1000
"""
import math
import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # benchmarks/: common, the tools
from accuracy_bench import EPOCH  # noqa: E402
from common import sensor_spec  # noqa: E402

from startrack.accuracy import blended_references, star_covariance  # noqa: E402
from startrack.catalog import load_catalog  # noqa: E402
from startrack.centroid import (  # noqa: E402
    CentroidOptions,
    _pixel_noise_mesh,
    estimate_background,
    find_stars,
)
from startrack.render import Scene, project_stars, render_image  # noqa: E402
from startrack.rotations import quaternion_to_dcm, random_quaternions  # noqa: E402


def main():
    n = int(sys.argv[1]) if len(sys.argv) > 1 else 200
    seed = 0
    cam, sensor, mags, render_mag = sensor_spec("p000")
    base = load_catalog().propagate(EPOCH)
    rcat = base.filter_magnitude(None, render_mag)
    rvec = rcat.vectors()
    refs = blended_references(base.filter_magnitude(*mags), rcat, cam)
    vec = refs.vectors()
    dcms = quaternion_to_dcm(random_quaternions(n, np.random.default_rng(seed)))
    rows = []
    for k in range(n):
        img, truth = render_image(rcat, cam, dcms[k], sensor, Scene(), np.random.default_rng([seed, k]), vectors=rvec)
        res = find_stars(img, CentroidOptions(gain_e_per_dn=sensor.gain), saturation=sensor.max_dn)
        index, tx, ty = project_stars(vec, dcms[k], cam, margin_px=2.0)
        ax = np.array([t["x"] for t in truth["stars"]])
        ay = np.array([t["y"] for t in truth["stars"]])
        for s in res.stars:
            if s.get("saturated") or not len(tx):
                continue
            d = np.hypot(tx - s["x"], ty - s["y"])
            j = int(np.argmin(d))
            c = star_covariance(s, sensor.gain, res.background_sigma)
            if d[j] > 1 or c is None:
                continue
            dd = np.hypot(ax - tx[j], ay - ty[j])
            far = dd[dd > 2.0]
            rows.append((s["x"] - tx[j], s["y"] - ty[j], math.sqrt(0.5 * (c[0, 0] + c[1, 1])), s["snr"],
                         bool(s.get("misfit")), float(far.min()) if len(far) else 1e9))
    a = np.array(rows, dtype=np.float64)
    z2 = (a[:, 0] ** 2 + a[:, 1] ** 2) / a[:, 2] ** 2
    mis, nn, snr = a[:, 4] > 0, a[:, 5], a[:, 3]
    print(f"paper 000's sensor, {n} frames (seed {seed}): RMS of centroid error / reported sigma per axis\n")
    print("| stars | n | z | beyond the chi-square(2) 0.1 % point |")
    print("|---|---|---|---|")

    def row(name, m):
        if m.sum():
            print(f"| {name} | {int(m.sum())} | {math.sqrt(np.mean(z2[m]) / 2):.3f} | {100 * np.mean(z2[m] > 13.8):.2f} % |")

    row("all", np.ones(len(a), bool))
    row("misfit", mis)
    row("not misfit", ~mis)
    for lo, hi in [(2, 3), (3, 4), (4, 6), (6, 10), (10, 1e9)]:
        row(f"not misfit, nearest other star {lo}-{hi:g} px", ~mis & (nn >= lo) & (nn < hi))
    for lo, hi in [(0, 15), (15, 30), (30, 60), (60, 1e9)]:
        row(f"isolated (>= 10 px), SNR {lo}-{hi:g}", ~mis & (nn >= 10) & (snr >= lo) & (snr < hi))
    # The noise centroid weights with: star-free frames of the same sensor.
    empty = base.filter_magnitude(None, -5.0)
    true = math.sqrt(sensor.background_e + sensor.read_noise_e ** 2 + sensor.gain ** 2 / 12) / sensor.gain
    sig, fit = [], []
    for k in range(20):
        img, _ = render_image(empty, cam, np.eye(3), sensor, Scene(), np.random.default_rng([seed, 10**6 + k]))
        f32 = img.astype(np.float32)
        _, mesh, level, _ = estimate_background(f32, CentroidOptions())
        sig.append(mesh.ravel())
        fit.append(_pixel_noise_mesh(f32 - np.float32(level), mesh, 64).ravel())
    print(f"\nbackground noise, 20 star-free frames: true {true:.3f} DN")
    for name, s in (("detection mesh (1.4826 MAD, ~100 samples a tile)", np.concatenate(sig)),
                    ("the fit's (clipped std of every pixel, truncation-corrected)", np.concatenate(fit))):
        print(f"- {name}: mean {s.mean():.3f} DN, E[1/s^2]^(-1/2) {1 / math.sqrt(np.mean(1 / s ** 2)):.3f} DN")


if __name__ == "__main__":
    main()
