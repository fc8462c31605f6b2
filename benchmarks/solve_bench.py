"""Real photographs, feeds `make bench` section solve (results/results-2026-11-22.md).

startrack solve (no options) against cedar-solve and astrometry.net on the 8 ESA images.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import time

import numpy as np
from common import esa_images, esa_references, sep_deg


def _sep_arcsec(ra, dec, ra0, dec0):
    return sep_deg(ra, dec, ra0, dec0) * 3600


def run():
    images = esa_images()
    ref = esa_references()
    st = os.path.join(os.path.dirname(sys.executable), "startrack")
    subprocess.run([st, "solve", images[0], "-q"], capture_output=True)      # build the cache once
    rows = []
    # startrack: one process per image (whole-process time) and the batch (per-image in-process time).
    for path in images:
        t0 = time.perf_counter()
        proc = subprocess.run([st, "solve", path, "-q"], capture_output=True, text=True)
        wall = (time.perf_counter() - t0) * 1000
        d = json.loads(proc.stdout)
        r = ref[os.path.basename(path)]
        if d["solve"]["status"] == "ok":
            a = d["attitude"]
            rows.append(["startrack", os.path.basename(path)[18:40], "ok",
                         f"{_sep_arcsec(a['ra'], a['dec'], float(r['ra_deg']), float(r['dec_deg'])):.1f}",
                         f"{d['solve']['fov_deg'][0]:.3f} x {d['solve']['fov_deg'][1]:.3f}",
                         f"{d['solve']['time_ms']:.0f}", f"{wall:.0f}"])
        else:
            rows.append(["startrack", os.path.basename(path)[18:40], "failed", "", "", f"{d['solve']['time_ms']:.0f}",
                         f"{wall:.0f}"])
    # The batch: all 8 in one process; per-image in-process time.
    t0 = time.perf_counter()
    proc = subprocess.run([st, "solve", *images, "-q"], capture_output=True, text=True)
    batch_wall = (time.perf_counter() - t0) * 1000
    docs = [json.loads(l) for l in proc.stdout.splitlines()]
    for d in docs:
        r = ref[os.path.basename(d["image"]["path"])]
        ok = d["solve"]["status"] == "ok"
        a = d.get("attitude", {})
        rows.append(["startrack (batch)", os.path.basename(d["image"]["path"])[18:40], d["solve"]["status"],
                     f"{_sep_arcsec(a['ra'], a['dec'], float(r['ra_deg']), float(r['dec_deg'])):.1f}" if ok else "",
                     f"{d['solve']['fov_deg'][0]:.3f} x {d['solve']['fov_deg'][1]:.3f}" if ok else "",
                     f"{d['solve']['time_ms']:.0f}", f"{batch_wall / len(images):.0f}"])
    notes = []
    try:
        import cedar_peer

        if cedar_peer.is_available():
            t0 = time.perf_counter()
            with cedar_peer.CedarSolver(db="default") as cs:
                (time.perf_counter() - t0) * 1000
                for path in images:
                    res = cs.solve_image(path, 11.4)
                    r = ref[os.path.basename(path)]
                    ok = res.get("ra") is not None
                    rows.append(["cedar-solve", os.path.basename(path)[18:40], "ok" if ok else res.get("status"),
                                 f"{_sep_arcsec(res['ra'], res['dec'], float(r['ra_deg']), float(r['dec_deg'])):.1f}"
                                 if ok else "", f"{res.get('fov', float('nan')):.3f}" if ok else "",
                                 f"{res.get('t_wall_ms', float('nan')):.0f}", ""])
        else:
            notes.append("cedar-solve not installed (make bench-peers)")
    except Exception as exc:  # noqa: BLE001
        notes.append(f"cedar-solve failed: {type(exc).__name__}: {exc}")
    try:
        import astrometry_peer

        if astrometry_peer.is_available():
            for path in images:
                res = astrometry_peer.solve_field(path, 5, 30, timeout_s=60)
                r = ref[os.path.basename(path)]
                ok = res["status"] == "solved"
                rows.append(["astrometry.net", os.path.basename(path)[18:40], res["status"],
                             f"{_sep_arcsec(res['ra'], res['dec'], float(r['ra_deg']), float(r['dec_deg'])):.1f}"
                             if ok else "", f"{res.get('fov_x_deg', float('nan')):.3f}" if ok else "", "",
                             f"{res['elapsed_ms']:.0f}" if res.get("elapsed_ms") else ""])
        else:
            notes.append("astrometry.net not installed (make bench-peers, as root)")
    except Exception as exc:  # noqa: BLE001
        notes.append(f"astrometry.net failed: {type(exc).__name__}: {exc}")
    medians = {}
    for tool in ("startrack", "startrack (batch)", "cedar-solve", "astrometry.net"):
        vals = [float(r[5]) for r in rows if r[0] == tool and r[5] not in ("", "nan")]
        walls = [float(r[6]) for r in rows if r[0] == tool and r[6]]
        medians[tool] = (float(np.median(vals)) if vals else float("nan"), float(np.median(walls)) if walls else float("nan"),
                         sum(1 for r in rows if r[0] == tool and r[2] in ("ok", "solved")))
    return rows, medians, notes
