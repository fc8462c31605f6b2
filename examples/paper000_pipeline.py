"""Score the pipelines of examples/paper000_pipeline.sh against the rendered truth.

    .venv/bin/python examples/paper000_pipeline.py WORKDIR [-o examples/results/p000-pipeline.json]

Reads ``WORKDIR/{8deg,camera}-{paper,default}.jsonl`` (frame documents with the attitude and the
render's truth) and writes, per sensor and pipeline: frames, success (boresight within 60" of the
truth), wrong (an attitude farther off), failed (none), the median cross-boresight and roll errors of
the successes (paper 000's design: < 20" pitch/yaw, < 100" roll), and the median times of
centroiding and identification.
"""
from __future__ import annotations

import argparse
import json
import math
import os

import numpy as np

PIPELINES = {"paper": "paper 000: COM > 60 DN, 4 brightest, modified pyramid (triangles, fixed tolerance from "
                      "0.25 px), q-method",
             "default": "startrack default: Gaussian fit > 5 sigma, all stars, pyramid (k-vector), QUEST"}
SENSORS = {"8deg": "8 x 8 deg (the paper's assumption), 1024 x 1024 px",
           "camera": "752 x 480 px, 6 um, f = 41.1 mm (the paper's camera): 6.28 x 4.01 deg"}


def _cause(d, max_side_deg, mag_range=(2.5, 6.59)):
    """Why the paper's pipeline could not identify a frame, from the render's truth: fewer than four stars
    detected, one of the four outside the catalog's magnitudes, two of them farther apart than the
    triangle database's longest side, or none of these."""
    from startrack.camera import Camera

    st = d.get("stars", [])
    if len(st) < 4:
        return "fewer than 4 stars detected"
    truth = d["truth"]["stars"]
    mags = [min(truth, key=lambda t: (t["x"] - s["x"]) ** 2 + (t["y"] - s["y"]) ** 2).get("mag") for s in st]
    causes = []
    if any(m is not None and not mag_range[0] <= m <= mag_range[1] for m in mags):
        causes.append("a star outside Hp 2.5-6.59")
    cam = Camera.from_dict(d["camera"])
    b = cam.pixels_to_vectors(np.array([s["x"] for s in st]), np.array([s["y"] for s in st]))
    if max(math.degrees(math.acos(min(1.0, float(b[p] @ b[q])))) for p in range(len(b))
           for q in range(p + 1, len(b))) > max_side_deg:
        causes.append("stars farther apart than the longest triangle side")
    return " and ".join(causes) or "none of these"


def score(path, max_side_deg=None):
    from startrack.rotations import attitude_error, quaternion_to_dcm

    n = ok = wrong = 0
    cross, roll, t_id, t_cen, n_stars = [], [], [], [], []
    reasons = {}
    causes = {}
    errs, sigmas = [], []
    for line in open(path):
        d = json.loads(line)
        n += 1
        # The centroids against the render's truth (the nearest true star within 1.5 px): error and sigma_px.
        truth = (d.get("truth") or {}).get("stars") or []
        if truth:
            tx, ty = np.array([t["x"] for t in truth]), np.array([t["y"] for t in truth])
            for st in d.get("stars", []):
                dist = np.hypot(tx - st["x"], ty - st["y"])
                j = int(np.argmin(dist))
                if dist[j] < 1.5 and st.get("sigma_px") is not None:
                    errs += [st["x"] - tx[j], st["y"] - ty[j]]
                    sigmas += [st["sigma_px"], st["sigma_px"]]
        t_cen.append(float(d.get("centroid", {}).get("time_ms") or np.nan))
        ident = d.get("identification") or {}
        t_id.append(float(ident.get("time_ms") or np.nan))
        n_stars.append(len(d.get("stars", [])))
        att = d.get("attitude") or {}
        if att.get("status") != "ok":
            why = ident.get("reason_code") or ident.get("reason") or att.get("reason_code") or "no attitude"
            reasons[str(why)] = reasons.get(str(why), 0) + 1
            if max_side_deg is not None:
                c = _cause(d, max_side_deg)
                causes[c] = causes.get(c, 0) + 1
            continue
        _, c, r = attitude_error(quaternion_to_dcm(att["quaternion"]), quaternion_to_dcm(d["truth"]["quaternion"]))
        c, r = float(c) * 3600, abs(float(r)) * 3600       # attitude_error gives degrees
        if c <= 60.0:
            ok += 1
            cross.append(c)
            roll.append(r)
        else:
            wrong += 1
    med = lambda v: float(np.nanmedian(v)) if len(v) else None  # noqa: E731
    return {"frames": n, "success": ok, "wrong": wrong, "failed": n - ok - wrong, "failure_reasons": reasons,
            "failure_causes": causes,
            "median_cross_boresight_arcsec": med(cross), "median_roll_arcsec": med(roll),
            "p95_cross_boresight_arcsec": float(np.percentile(cross, 95)) if cross else None,
            "p95_roll_arcsec": float(np.percentile(roll, 95)) if roll else None,
            "median_identify_ms": med(t_id), "median_centroid_ms": med(t_cen), "median_stars": med(n_stars),
            "centroid_median_sigma_px": med(sigmas),
            "centroid_error_robust_px": float(1.4826 * np.median(np.abs(errs))) if errs else None,
            "centroid_error_p95_px": float(np.percentile(np.abs(errs), 95)) if errs else None,
            "centroid_z_robust": float(1.4826 * np.median(np.abs(np.array(errs) / np.array(sigmas)))) if errs
            else None}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("workdir")
    ap.add_argument("-o", "--output", default="examples/results/p000-pipeline.json")
    a = ap.parse_args(argv)
    out = {"command": "examples/paper000_pipeline.sh", "pipelines": PIPELINES, "sensors": {}}
    for s, label in SENSORS.items():
        rows = {}
        for p in PIPELINES:
            path = os.path.join(a.workdir, f"{s}-{p}.jsonl")
            if os.path.exists(path):
                side = None
                tri = os.path.join(a.workdir, f"{s}-triangles.h5")
                if p == "paper" and os.path.exists(tri):
                    from startrack.triangles import load_triangles

                    side = load_triangles(tri).max_separation_deg
                rows[p] = score(path, side)
        out["sensors"][s] = {"label": label, "rows": rows}
    with open(a.output, "w") as fh:
        json.dump(out, fh, indent=1)
        fh.write("\n")
    for e in out["sensors"].values():
        print(e["label"])
        for p, r in e["rows"].items():
            print(f"  {p:8s} {r['success']}/{r['frames']} ok, {r['wrong']} wrong, {r['failed']} failed; "
                  f"median error {r['median_cross_boresight_arcsec']}\" / roll {r['median_roll_arcsec']}\"; "
                  f"identify {r['median_identify_ms']} ms, centroid {r['median_centroid_ms']} ms; "
                  f"failures {r['failure_reasons']} {r['failure_causes']}")


if __name__ == "__main__":
    main()
