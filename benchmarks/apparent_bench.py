#!/usr/bin/env python3
"""Stellar aberration (issue 39): error / Cramér-Rao bound per axis with and without the correction.

Star lists (15 deg, 1024 x 1024, 0.3 px centroids) as a camera sees them (``render --stars-only``
simulates proper motion, solar deflection and aberration for the Earth's velocity at the frame's
time plus a spacecraft velocity), through the default ``identify | attitude`` pipeline and through
``attitude --no-aberration``.  Each frame's bound is the attitude Cramér-Rao bound of the stars the
attitude used with the simulated centroid noise (:func:`startrack.accuracy.attitude_crb`); the error
is the rotation between the reported and the rendered attitude, per camera axis (x, y cross-boresight,
z roll).  Frames whose identification failed or was wrong are counted, not scored.

    python benchmarks/apparent_bench.py --frames 1000            # four dates, with and without LEO velocity
    python benchmarks/apparent_bench.py --frames 200 --dates 2026-09-22T12:00:00Z --no-leo
"""
from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile

import numpy as np

ARCSEC = math.degrees(1.0) * 3600.0
DATES = ("2026-03-20T12:00:00Z", "2026-06-21T12:00:00Z", "2026-09-22T12:00:00Z", "2026-12-21T12:00:00Z")
LEO_KM_S = "5.3,-4.1,3.6"      # 7.6 km/s, a low-Earth-orbit speed in an arbitrary direction
FOV, SIZE, SIGMA_PX = 15, "1024x1024", 0.3


def _cli(*args, stdin=None, stdout=None):
    cmd = [sys.executable, "-m", "startrack", *map(str, args)]
    proc = subprocess.run(cmd, stdin=stdin, stdout=stdout, stderr=subprocess.PIPE, text=True)
    if proc.returncode not in (0, 1):
        raise SystemExit(f"{' '.join(cmd)}: exit {proc.returncode}\n{proc.stderr}")
    return proc


def score(path):
    """Per-axis error / bound over the frames of an attitude stream (and the counts)."""
    from startrack.accuracy import attitude_crb, error_vector
    from startrack.camera import Camera
    from startrack.rotations import quaternion_to_dcm

    errors, bounds = [], []
    failed = wrong = 0
    for line in open(path):
        doc = json.loads(line)
        att = doc.get("attitude") or {}
        truth_ids = doc["truth"]["star_ids"]
        if att.get("status") != "ok":
            failed += 1
            continue
        if any(truth_ids[m["star"]] != m["id"] for m in doc["identification"]["matches"]):
            wrong += 1
            continue
        cam = Camera.from_dict(doc["camera"])
        used = [r["star"] for r in att["residuals"]]
        body = np.array([cam.pixels_to_vectors(doc["stars"][k]["x"], doc["stars"][k]["y"]) for k in used])
        bound = attitude_crb(cam, body, np.full(len(used), SIGMA_PX ** 2))
        errors.append(error_vector(quaternion_to_dcm(np.array(att["quaternion"])),
                                   quaternion_to_dcm(np.array(doc["truth"]["quaternion"]))))
        bounds.append(np.diag(bound.cov_rad2))
    e, b = np.array(errors), np.array(bounds)
    ratio = np.sqrt(np.mean(e ** 2, axis=0) / np.mean(b, axis=0))
    cross = math.sqrt(float(np.mean(e[:, :2] ** 2)))
    # An efficient estimator's ratio has the 95 % band 1 +- 1.96 sqrt(2 / n_eff) / 2 (summarise's normal approx.).
    n_eff = [float(np.sum(b[:, k])) ** 2 / float(np.sum(b[:, k] ** 2)) for k in range(3)]
    return {"frames": len(e), "failed": failed, "wrong": wrong,
            "ratio_xyz": [round(float(r), 3) for r in ratio],
            "band_half_xyz": [round(0.5 * 1.96 * math.sqrt(2 / n), 3) for n in n_eff],
            "median_cross_err_arcsec": round(float(np.median(np.hypot(e[:, 0], e[:, 1]))) * ARCSEC, 2),
            "rms_cross_arcsec": round(cross * ARCSEC, 2)}


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=1000)
    ap.add_argument("--dates", nargs="*", default=list(DATES))
    ap.add_argument("--no-leo", action="store_true", help="only the Earth's velocity")
    ap.add_argument("--seed", type=int, default=39)
    ap.add_argument("--workdir", default=None)
    args = ap.parse_args()
    work = args.workdir or tempfile.mkdtemp(prefix="apparent_bench_")
    db = os.path.join(work, "db15.h5")
    if not os.path.exists(db):
        _cli("build-kvector", "--fov-deg", FOV, "--size", SIZE, "-o", db)
    rows = []
    for date in args.dates:
        for leo in ((None,) if args.no_leo else (None, LEO_KM_S)):
            tag = f"{date[:10]}{'-leo' if leo else ''}"
            frames = os.path.join(work, f"{tag}.jsonl")
            with open(frames, "w") as out:
                _cli("render", "--stars-only", "--count", args.frames, "--fov-deg", FOV, "--size", SIZE,
                     "--sigma-px", SIGMA_PX, "--seed", args.seed, "--time", date, "-q",
                     *(("--velocity-km-s", leo) if leo else ()), stdout=out)
            ident = os.path.join(work, f"{tag}.id.jsonl")
            with open(frames) as inp, open(ident, "w") as out:
                _cli("identify", "-d", db, "-q", stdin=inp, stdout=out)
            for correction in (True, False):
                att = os.path.join(work, f"{tag}.{'corr' if correction else 'none'}.jsonl")
                with open(ident) as inp, open(att, "w") as out:
                    _cli("attitude", "-q", *(() if correction else ("--no-aberration",)), stdin=inp, stdout=out)
                row = {"date": date[:10], "leo_km_s": leo, "correction": correction, **score(att)}
                rows.append(row)
                print(json.dumps(row), flush=True)
    print(f"# work files in {work}", file=sys.stderr)


if __name__ == "__main__":
    main()
