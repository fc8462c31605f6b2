#!/usr/bin/env python3
"""Exercise every peer harness for real and report timings and accuracy.  Bench-only.

    .venv/bin/python benchmarks/peers/selftest_peers.py [--quick] [--skip astrometry,cedar,...]

* ESA images (``/work/shared/data/real`` or ``$STARTRACK_REAL_DATA``): SEP extraction
  timing; cedar-solve ``solve_from_image`` and ``solve_from_centroids`` (SEP centroids);
  tetra3rs on its own centroids and on SEP centroids; ``solve-field``.  Each solution is
  compared with ``solutions.csv`` (centre) and with the roll derived from our own
  solve-field WCS (see README.md: the CSV's ``up_deg_east_of_north`` is astrometry.net's
  +Y angle at CRPIX, not startrack's roll).
* Synthetic centroids: random attitudes, pinhole projection of ``catalogs/hip2.h5`` stars in
  startrack's conventions (pixel centres on integers, roll = PA of image up east of north),
  solved by tetra3rs and cedar-solve; boresight and roll errors against the truth.

Writes ``bench-output/peers/selftest.json`` and prints a Markdown summary.
"""
from __future__ import annotations

import argparse
import csv
import json
import math
import os
import statistics
import subprocess
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(os.path.dirname(HERE))
sys.path.insert(0, HERE)
OUT = os.path.join(ROOT, "bench-output", "peers")
REAL = os.environ.get("STARTRACK_REAL_DATA", os.path.join(os.path.dirname(ROOT), "shared", "data", "real"))
CEDAR_PY = os.path.join(ROOT, ".venv-cedar", "bin", "python")
CEDAR_RUNNER = os.path.join(HERE, "cedar_runner.py")


# startrack roll (PA of image up, -y, east of north) at the image centre of the ESA images,
# from astrometry.net 0.93's WCS (astrometry_peer.wcs_solution); cedar and tetra3rs agree
# to 0.02 deg.
ESA_CENTRE_ROLL = {"Alt40_Azi-135": 27.720, "Alt40_Azi-45": 56.577, "Alt40_Azi135": 335.108,
                   "Alt40_Azi45": 306.691, "Alt60_Azi-135": 30.951, "Alt60_Azi-45": 91.676,
                   "Alt60_Azi135": 331.369, "Alt60_Azi45": 270.599}


# ----------------------------------------------------------------------------- geometry
def radec_vec(ra, dec):
    ra, dec = np.radians(ra), np.radians(dec)
    return np.stack([np.cos(ra) * np.cos(dec), np.sin(ra) * np.cos(dec), np.sin(dec)], -1)


def sep_arcsec(ra0, dec0, ra1, dec1):
    c = float(np.clip(radec_vec(ra0, dec0) @ radec_vec(ra1, dec1), -1, 1))
    return math.degrees(math.acos(c)) * 3600.0


def dang(a, b):
    """Signed smallest difference a - b in degrees."""
    return (a - b + 180.0) % 360.0 - 180.0


def attitude(ra, dec, roll):
    """startrack's A: rows camera +x (right), +y (down), +z (boresight) in ICRS."""
    a, d, r = map(math.radians, (ra, dec, roll))
    bore = radec_vec(ra, dec)
    east = np.array([-math.sin(a), math.cos(a), 0.0])
    north = np.array([-math.sin(d) * math.cos(a), -math.sin(d) * math.sin(a), math.cos(d)])
    y_axis = -(math.cos(r) * north + math.sin(r) * east)
    x_axis = np.cross(y_axis, bore)
    return np.stack([x_axis, y_axis, bore])


def load_hip2():
    import h5py

    with h5py.File(os.path.join(ROOT, "catalogs", "hip2.h5"), "r") as f:
        return f["id"][:], f["ra"][:], f["dec"][:], f["mag"][:], f["pm_ra"][:], f["pm_dec"][:]


def synth_frames(n, fov_deg, width, height, mag_max, seed=1, noise_px=0.1, epoch=2025.0):
    """Pinhole projection of hip2 stars (propagated to ``epoch``), startrack conventions."""
    hip, ra, dec, mag, pmra, pmde = load_hip2()
    keep = mag <= mag_max
    dt = epoch - 1991.25
    dec_e = dec + np.nan_to_num(pmde) * dt / 3.6e6
    ra_e = ra + np.nan_to_num(pmra) * dt / 3.6e6 / np.cos(np.radians(dec))
    vec = radec_vec(ra_e[keep], dec_e[keep])
    mags = mag[keep]
    f = (width / 2.0) / math.tan(math.radians(fov_deg) / 2.0)
    cx, cy = (width - 1) / 2.0, (height - 1) / 2.0
    rng = np.random.default_rng(seed)
    frames = []
    while len(frames) < n:
        v = rng.normal(size=3)
        v /= np.linalg.norm(v)
        tra = math.degrees(math.atan2(v[1], v[0])) % 360.0
        tdec = math.degrees(math.asin(v[2]))
        troll = float(rng.uniform(0, 360))
        cam = vec @ attitude(tra, tdec, troll).T
        front = cam[:, 2] > 0
        x = cx + f * cam[:, 0] / np.where(front, cam[:, 2], 1)
        y = cy + f * cam[:, 1] / np.where(front, cam[:, 2], 1)
        inside = front & (x > -0.5) & (x < width - 0.5) & (y > -0.5) & (y < height - 0.5)
        if inside.sum() < 6:
            continue
        order = np.argsort(mags[inside], kind="stable")
        xy = np.c_[x[inside], y[inside]][order] + rng.normal(0, noise_px, (inside.sum(), 2))
        frames.append({"ra": tra, "dec": tdec, "roll": troll, "xy": xy})
    return frames


# ----------------------------------------------------------------------------- helpers
def read_image(path):
    import cv2

    im = cv2.imread(path, cv2.IMREAD_UNCHANGED)
    if im is None:
        raise RuntimeError(f"cannot read {path}")
    return im


def references():
    rows = {}
    with open(os.path.join(REAL, "solutions.csv")) as fh:
        for r in csv.DictReader(fh):
            rows[r["file"]] = r
    return rows


def med(v):
    v = [x for x in v if x is not None]
    return statistics.median(v) if v else float("nan")


def run_cedar(requests, args):
    """Run cedar_runner.py once over all requests; returns the result dicts (same order)."""
    if not os.path.exists(CEDAR_PY):
        return None
    cmd = [CEDAR_PY, CEDAR_RUNNER, "--warmup", *args]
    inp = "".join(json.dumps(r) + "\n" for r in requests)
    p = subprocess.run(cmd, input=inp, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                       text=True, timeout=1800)
    if p.returncode != 0:
        print(p.stderr[-3000:], file=sys.stderr)
        return None
    return [json.loads(l) for l in p.stdout.splitlines() if l.strip()]


def cedar_db(max_fov, mag=None, min_fov=None):
    args = [CEDAR_PY, CEDAR_RUNNER, "build-db", "--max-fov", f"{max_fov:g}"]
    if mag is not None:
        args += ["--mag", f"{mag:g}"]
    if min_fov is not None:
        args += ["--min-fov", f"{min_fov:g}"]
    p = subprocess.run(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                       timeout=3600)
    if p.returncode != 0:
        raise RuntimeError(p.stderr[-2000:])
    return json.loads(p.stdout.strip().splitlines()[-1])


# ----------------------------------------------------------------------------- main
def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="fewer repeats and synthetic frames")
    ap.add_argument("--skip", default="", help="comma list: sep,tetra3rs,cedar,astrometry,synthetic")
    ap.add_argument("--sigma", type=float, default=5.0, help="SEP / tetra3rs detection sigma")
    a = ap.parse_args()
    skip = set(filter(None, a.skip.split(",")))
    reps = 5 if a.quick else 20
    nsyn = 20 if a.quick else 100
    os.makedirs(OUT, exist_ok=True)
    report = {"machine": os.uname().nodename, "time": time.strftime("%Y-%m-%dT%H:%M:%S")}
    lines = []

    refs = references() if os.path.exists(os.path.join(REAL, "solutions.csv")) else {}
    files = sorted(refs)
    imgs = {fn: read_image(os.path.join(REAL, fn)) for fn in files}

    # -- astrometry.net first: its WCS gives the reference roll for the others
    an_roll = {}
    if "astrometry" not in skip and files:
        import astrometry_peer as AN

        res = []
        for fn in files:
            r = AN.solve_field(os.path.join(REAL, fn), 10.0, 13.0, timeout_s=60)
            ref = refs[fn]
            r["file"] = fn
            if r["status"] == "solved":
                r["err_arcsec"] = sep_arcsec(r["ra"], r["dec"], float(ref["ra_deg"]), float(ref["dec_deg"]))
                an_roll[fn] = r["orientation"]
            res.append(r)
        report["astrometry"] = res
        ok = sum(r["status"] == "solved" for r in res)
        lines.append(f"| solve-field (Tycho-2 10-19, scale 10-13 deg width) | {ok}/{len(res)} solved | "
                     f"median {med([r['elapsed_ms'] for r in res]):.0f} ms/image (whole process) | "
                     f"max centre err {max([r.get('err_arcsec', float('nan')) for r in res]):.1f}\" |")
    # Without a solve-field run: the centre rolls measured from its WCS (README.md); the CSV's
    # up_deg_east_of_north + 180 is only good to ~2 deg (it is taken at CRPIX).
    ref_roll = {fn: an_roll.get(fn, ESA_CENTRE_ROLL.get(
        fn.split("T204726_")[-1].replace("_Try1.tiff", ""),
        (float(refs[fn]["up_deg_east_of_north"]) + 180.0) % 360.0)) for fn in files}

    # -- SEP
    sep_xy = {}
    if "sep" not in skip and files:
        import sep_peer

        per = []
        for fn in files:
            im = imgs[fn].astype(np.float32)
            times = []
            for _ in range(reps):
                x, y, flux, ms = sep_peer.extract(im, a.sigma)
                times.append(ms)
            sep_xy[fn] = np.c_[x, y]
            per.append({"file": fn, "median_ms": statistics.median(times), "n": int(len(x))})
        report["sep"] = per
        lines.append(f"| SEP Background+extract, {a.sigma:g} sigma, 1024x768 | "
                     f"median {med([p['median_ms'] for p in per]):.2f} ms/image | "
                     f"{min(p['n'] for p in per)}-{max(p['n'] for p in per)} sources | |")

    def score(fn, ra, dec, roll):
        ref = refs[fn]
        e = sep_arcsec(ra, dec, float(ref["ra_deg"]), float(ref["dec_deg"]))
        return e, (dang(roll, ref_roll[fn]) if roll is not None else None)

    # -- tetra3rs
    if "tetra3rs" not in skip:
        import tetra3rs_peer as T

        dbinfo = {}
        db114 = T.build_or_load(11.4, None)
        dbinfo["gaia_11.4_auto"] = dict(T.LAST_BUILD)
        if files:
            for label, fn_solve in [
                ("tetra3rs own extract_centroids", lambda fn: T.solve_image(
                    imgs[fn].astype(np.float32), 11.4, db=db114, sigma_threshold=a.sigma)),
                ("tetra3rs on SEP centroids", (lambda fn: T.solve(
                    sep_xy[fn][:40], 1024, 768, 11.4, db=db114)) if sep_xy else None),
            ]:
                if fn_solve is None:
                    continue
                res = []
                for fn in files:
                    fn_solve(fn)  # warm
                    rr = [fn_solve(fn) for _ in range(max(1, reps // 4))]
                    r = rr[-1]
                    r["elapsed_ms_median"] = statistics.median([x["elapsed_ms"] for x in rr])
                    r["file"] = fn
                    if r["ra"] is not None:
                        r["err_arcsec"], r["roll_err_deg"] = score(fn, r["ra"], r["dec"], r["roll"])
                    for k in ("matched_catalog_ids", "matched_centroids"):
                        r.pop(k, None)
                    res.append(r)
                report[label] = res
                ok = [r for r in res if r["status"] == "match_found"]
                ext = (f"; extract median {med([r.get('extract_ms') for r in res]):.1f} ms"
                       if "extract_ms" in res[0] else "")
                lines.append(
                    f"| {label} (gaia db 11.4 deg) | {len(ok)}/{len(res)} solved | solve median "
                    f"{med([r['elapsed_ms_median'] for r in res]):.2f} ms{ext} | max centre err "
                    f"{max([r.get('err_arcsec', float('nan')) for r in ok] or [float('nan')]):.1f}\", "
                    f"max |roll err| {max([abs(r['roll_err_deg']) for r in ok] or [float('nan')]):.3f} deg |")
        report["tetra3rs_db"] = dbinfo

    # -- cedar-solve
    if "cedar" not in skip and os.path.exists(CEDAR_PY) and files:
        b = cedar_db(11.4)
        report["cedar_db_11.4"] = b
        reqs = [{"id": fn, "image": os.path.join(REAL, fn), "fov_deg": 11.4} for fn in files]
        variants = [("cedar solve_from_image (default db)", reqs, ["--db", "default"]),
                    ("cedar solve_from_image (own 11.4 db)", reqs, ["--db", b["db"]])]
        if sep_xy:
            creqs = [{"id": fn, "centroids": sep_xy[fn][:40, ::-1].tolist(), "size": [768, 1024],
                      "fov_deg": 11.4} for fn in files]
            variants.append(("cedar solve_from_centroids on SEP (default db)", creqs,
                             ["--db", "default"]))
        for label, rq, args in variants:
            res = run_cedar(rq * 3, args)  # 3 passes: median of the per-image timings
            if res is None:
                lines.append(f"| {label} | FAILED to run | | |")
                continue
            byid = {}
            for r in res:
                byid.setdefault(r["id"], []).append(r)
            out = []
            for fn in files:
                rr = byid[fn]
                r = dict(rr[-1], file=fn)
                r["t_solve_ms_median"] = med([x["t_solve_ms"] for x in rr])
                r["t_extract_ms_median"] = med([x.get("t_extract_ms") for x in rr])
                r["t_wall_ms_median"] = med([x["t_wall_ms"] for x in rr])
                if r["status"] == "MATCH_FOUND":
                    r["err_arcsec"], r["roll_err_deg"] = score(fn, r["ra"], r["dec"], r["roll"])
                out.append(r)
            report[label] = out
            ok = [r for r in out if r["status"] == "MATCH_FOUND"]
            ext = (f"; extract median {med([r['t_extract_ms_median'] for r in out]):.1f} ms"
                   if out and out[0].get("t_extract_ms") is not None else "")
            lines.append(
                f"| {label} | {len(ok)}/{len(out)} solved | T_solve median "
                f"{med([r['t_solve_ms_median'] for r in out]):.2f} ms{ext}; wall "
                f"{med([r['t_wall_ms_median'] for r in out]):.1f} ms | max centre err "
                f"{max([r['err_arcsec'] for r in ok] or [float('nan')]):.1f}\", max |roll err| "
                f"{max([abs(r['roll_err_deg']) for r in ok] or [float('nan')]):.3f} deg |")

    # -- synthetic centroids
    if "synthetic" not in skip:
        cases = [("20x20 deg 1024x1024 Hp<=5.0", 20.0, 1024, 1024, 5.0),
                 ("11.4 deg 1024x768 Hp<=6.5", 11.4, 1024, 768, 6.5)]
        for name, fov, w, h, mag in cases:
            frames = synth_frames(nsyn, fov, w, h, mag, seed=7)
            if "tetra3rs" not in skip:
                import tetra3rs_peer as T

                for cat in ("gaia", "hip2"):
                    magdb = mag if fov == 20.0 else None
                    db = T.build_or_load(fov, magdb, catalog=cat)
                    report.setdefault("tetra3rs_db", {})[f"{cat}_{fov:g}_{magdb}"] = dict(T.LAST_BUILD)
                    res = [T.solve(fr["xy"], w, h, fov, db=db) for fr in frames]
                    ok, errs, rerr = 0, [], []
                    for fr, r in zip(frames, res):
                        if r["status"] == "match_found":
                            e = sep_arcsec(r["ra"], r["dec"], fr["ra"], fr["dec"])
                            if e < 60:
                                ok += 1
                            errs.append(e)
                            rerr.append(abs(dang(r["roll"], fr["roll"])))
                    report[f"synthetic {name} tetra3rs/{cat}"] = {
                        "n": len(frames), "solved": sum(r["status"] == "match_found" for r in res),
                        "correct": ok, "median_err_arcsec": med(errs),
                        "max_roll_err_deg": max(rerr) if rerr else None,
                        "median_ms": med([r["elapsed_ms"] for r in res])}
                    s = report[f"synthetic {name} tetra3rs/{cat}"]
                    lines.append(
                        f"| synthetic {name}: tetra3rs ({cat} db, mag {magdb or 'auto'}) | "
                        f"{s['correct']}/{s['n']} correct ({s['solved']} returned) | median "
                        f"{s['median_ms']:.2f} ms | median err {s['median_err_arcsec']:.1f}\", "
                        f"max |roll err| {s['max_roll_err_deg'] if s['max_roll_err_deg'] is None else round(s['max_roll_err_deg'], 3)} deg |")
            if "cedar" not in skip and os.path.exists(CEDAR_PY):
                if fov == 20.0:
                    b = cedar_db(20.0, 5.0)
                else:
                    b = cedar_db(11.4)
                report[f"cedar_db_{fov:g}"] = b
                reqs = [{"id": i, "centroids": fr["xy"][:, ::-1].tolist(), "size": [h, w],
                         "fov_deg": fov} for i, fr in enumerate(frames)]
                res = run_cedar(reqs, ["--db", b["db"]])
                ok, errs, rerr = 0, [], []
                for fr, r in zip(frames, res or []):
                    if r["status"] == "MATCH_FOUND":
                        e = sep_arcsec(r["ra"], r["dec"], fr["ra"], fr["dec"])
                        ok += e < 60
                        errs.append(e)
                        rerr.append(abs(dang(r["roll"], fr["roll"])))
                s = {"n": len(frames), "solved": sum(r["status"] == "MATCH_FOUND" for r in res or []),
                     "correct": int(ok), "median_err_arcsec": med(errs),
                     "max_roll_err_deg": max(rerr) if rerr else None,
                     "median_t_solve_ms": med([r.get("t_solve_ms") for r in res or []])}
                report[f"synthetic {name} cedar"] = s
                lines.append(
                    f"| synthetic {name}: cedar ({os.path.basename(b['db'])}) | {s['correct']}/{s['n']} "
                    f"correct ({s['solved']} returned) | median T_solve {s['median_t_solve_ms']:.2f} ms | "
                    f"median err {s['median_err_arcsec']:.1f}\", max |roll err| "
                    f"{s['max_roll_err_deg'] if s['max_roll_err_deg'] is None else round(s['max_roll_err_deg'], 3)} deg |")

    with open(os.path.join(OUT, "selftest.json"), "w") as fh:
        json.dump(report, fh, indent=1, default=float)
    print("| harness | result | timing | accuracy |\n|---|---|---|---|")
    print("\n".join(lines))
    print(f"\nDetails: {os.path.relpath(os.path.join(OUT, 'selftest.json'), ROOT)}")


if __name__ == "__main__":
    main()
