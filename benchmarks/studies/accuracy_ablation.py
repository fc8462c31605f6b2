#!/usr/bin/env python3
"""Study (issue 21), recorded in 84dbd40:benchmarks/results-accuracy-2026-12-02b.md: where the 1.6x / 2.1x came from.

An ablation on paper 000's sensor (752 x 480, 30.1"/px).

Same rendered frames (seed 0) as benchmarks/pipeline_bench.py's paper 000 end to end, stars matched to the truth.  Rows:
A measured centroids, centroid's sigma_px (floor 0.02 px) as weights, gate; B measured, each star's
Cramér-Rao bound as weights, gate; C truth + noise drawn from each star's bound (an ideal centroider);
D as C with equal weights; E as B without the gate.  Ratios are RMS error / RMS per-frame bound.
Then the per-star centroid error against the centroid bound, by signal.

    python benchmarks/studies/accuracy_ablation.py 200
"""
import math
import os
import sys

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # benchmarks/: common, the tools
from common import sensor_spec  # noqa: E402

from startrack.accuracy import attitude_crb, centroid_crb  # noqa: E402
from startrack.attitude import estimate_attitude  # noqa: E402
from startrack.catalog import load_catalog  # noqa: E402
from startrack.centroid import CentroidOptions, find_stars  # noqa: E402
from startrack.render import Scene, render_image  # noqa: E402
from startrack.rotations import _rotation_vector_rad, quaternion_to_dcm, random_quaternions  # noqa: E402


def err(dcm, truth):
    return _rotation_vector_rad(dcm @ truth.T)


def main():
    n = int(sys.argv[1]) if len(sys.argv) > 1 else 200
    cam, sensor, mags, render_mag = sensor_spec("p000")
    cat = load_catalog().filter_magnitude(*mags)
    render_cat = load_catalog().filter_magnitude(None, render_mag)
    vec = render_cat.vectors()
    cvec = {int(i): v for i, v in zip(cat.id, cat.vectors())}
    v_e = sensor.background_e + sensor.read_noise_e**2
    rng = np.random.default_rng(0)
    dcms = quaternion_to_dcm(random_quaternions(n, rng))
    f = cam.focal_length_px
    res = {k: [] for k in ["A", "B", "C", "D", "E"]}
    crbs = []; cent = []; nst=[]
    for k in range(n):
        img, truth = render_image(render_cat, cam, dcms[k], sensor, Scene(), np.random.default_rng([0, k]), vectors=vec)
        r = find_stars(img, CentroidOptions(max_stars=30, gain_e_per_dn=sensor.gain), saturation=65535)
        ts = [t for t in truth["stars"] if int(t["id"]) in cvec and not t["saturated"]]
        meas = r.stars
        pairs = []
        for t in ts:
            if not meas: break
            d = [math.hypot(s["x"]-t["x"], s["y"]-t["y"]) for s in meas]
            j = int(np.argmin(d))
            if d[j] < 2: pairs.append((t, meas[j]))
        if len(pairs) < 3: continue
        covs = np.array([centroid_crb(t["electrons"], 1.0, v_e, t["x"], t["y"]) for t, _ in pairs])
        bt = cam.pixels_to_vectors(np.array([t["x"] for t, _ in pairs]), np.array([t["y"] for t, _ in pairs]))
        P = attitude_crb(cam, bt, covs).cov_rad2
        crbs.append(np.diag(P)); nst.append(len(pairs))
        ref = np.array([cvec[int(t["id"])] for t, _ in pairs])
        xm = np.array([s["x"] for _, s in pairs]); ym = np.array([s["y"] for _, s in pairs])
        bm = cam.pixels_to_vectors(xm, ym)
        sig_est = np.array([max(s["sigma_px"], 0.02) for _, s in pairs]) / f
        sig_crb = np.sqrt(0.5*(covs[:,0,0]+covs[:,1,1])) / f
        cent.extend(list(zip([s["x"]-t["x"] for t, s in pairs], [s["y"]-t["y"] for t,s in pairs], sig_crb*f, [t["electrons"] for t,_ in pairs], [s["sigma_px"] for _,s in pairs])))
        res["A"].append(err(estimate_attitude(bm, ref, sig_est).dcm, dcms[k]))
        res["B"].append(err(estimate_attitude(bm, ref, sig_crb).dcm, dcms[k]))
        g = np.random.default_rng([9, k])
        noise = np.array([g.multivariate_normal([0, 0], c) for c in covs])
        bn = cam.pixels_to_vectors(np.array([t["x"] for t,_ in pairs]) + noise[:, 0], np.array([t["y"] for t,_ in pairs]) + noise[:, 1])
        res["C"].append(err(estimate_attitude(bn, ref, sig_crb, gate=1e9).dcm, dcms[k]))
        res["D"].append(err(estimate_attitude(bn, ref, np.full(len(bn), 1e-5), gate=1e9).dcm, dcms[k]))
        res["E"].append(err(estimate_attitude(bm, ref, sig_crb, gate=1e9).dcm, dcms[k]))
    crbs = np.array(crbs)
    ARC = math.degrees(1)*3600
    cb = math.sqrt(np.mean(crbs[:, :2])) * ARC; rb = math.sqrt(np.mean(crbs[:, 2])) * ARC
    print(f"frames {len(crbs)}, mean stars {np.mean(nst):.1f}; RMS CRB cross {cb:.3f}\" roll {rb:.2f}\"")
    names = {"A": "measured centroids, estimated sigma (floor .02), gate", "B": "measured, CRB weights, gate",
             "C": "truth+CRB noise, CRB weights", "D": "truth+CRB noise, equal weights", "E": "measured, CRB weights, no gate"}
    for key, v in res.items():
        e = np.array(v) * ARC
        print(f"{key} {names[key]:55s} cross {math.sqrt(np.mean(e[:, :2]**2)):.3f}\" ({math.sqrt(np.mean(e[:, :2]**2))/cb:.2f}x)  roll {math.sqrt(np.mean(e[:, 2]**2)):.2f}\" ({math.sqrt(np.mean(e[:, 2]**2))/rb:.2f}x)")
    c = np.array(cent)
    for lo, hi in [(0, 2000), (2000, 5000), (5000, 20000), (20000, 1e9)]:
        m = (c[:, 3] >= lo) & (c[:, 3] < hi)
        if m.sum() == 0: continue
        rms = math.sqrt(np.mean(c[m, 0]**2 + c[m, 1]**2) / 2)
        print(f"electrons {lo:>6}-{hi:<6} n={m.sum():4d} centroid rms {rms:.4f} px, CRB {math.sqrt(np.mean(c[m,2]**2)):.4f}, est sigma {math.sqrt(np.mean(c[m,4]**2)):.4f}, mean bias x {np.mean(c[m,0]):+.4f} y {np.mean(c[m,1]):+.4f}")


if __name__ == "__main__":
    main()
