"""Feeds results/results-sparse-2026-12-06.md: sparse fields (issue 38's generalisation gap), the blind search on
rendered frames of 5-20 degrees holding ~5-20 detectable stars, beside tetra3rs given the field of view.  A
documented study, not a `make bench` section (a few minutes per 100 frames and setting).

Every frame is rendered in this process (startrack.render, the same sensor model as ``startrack render``) with a
random pointing (``--seed``), a few hot pixels, and an exposure chosen so that the sensor's detection limit
(``Sensor.detection_limit_mag``) is the setting's limiting magnitude; then ``Solver.solve`` (blind: no field of
view) and, with ``--peer``, tetra3rs's ``extract_centroids`` + ``solve_from_centroids`` given the field of view.
A solution is right when its boresight is within 0.05 degree of the truth and its roll within 0.5 degree.

    PYTHONPATH=$PWD .venv/bin/python benchmarks/sparse_bench.py --frames 100 --out bench-output/sparse-branch.jsonl
    PYTHONPATH=/work/main .venv/bin/python benchmarks/sparse_bench.py --frames 100 --out bench-output/sparse-main.jsonl
    .venv/bin/python benchmarks/sparse_bench.py --table bench-output/sparse-main.jsonl bench-output/sparse-branch.jsonl
    PYTHONPATH=$PWD .venv/bin/python benchmarks/sparse_bench.py --why bench-output/sparse-branch.jsonl

The first two run the code on PYTHONPATH (its own pattern index from the cache, built once); ``--table`` prints
one row per setting and file: frames, solved, wrong, failed, median ms of the solved frames, median stars.
``--why`` re-solves a run's failed frames and sorts them by cause: too few catalog stars detected, no pattern of
them in the pattern index, or a pattern in the index that the search did not accept.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
sys.path.insert(0, os.path.join(HERE, "peers"))

#: (horizontal field of view in degrees, limiting magnitude): two densities per field, whose frames hold a median
#: of about 6 and 10 detected catalog stars (fewer at high galactic latitude, more in the Milky Way; the sensor's
#: 5-sigma limit is about 0.5 mag deeper than what find_stars detects on these frames).
SETTINGS = ((5.0, 7.3), (5.0, 7.9), (7.3, 6.6), (7.3, 7.1), (10.0, 6.1), (10.0, 6.6), (15.0, 5.3), (15.0, 5.9),
            (20.0, 4.9), (20.0, 5.4))
SIZE = (1280, 960)


def sensor_for(limit_mag: float, hot_pixels: int):
    """A 12-bit sensor (read noise 12 e-, background 200 e-/s, PSF sigma 1.6 px) whose exposure puts its 5-sigma
    detection limit at ``limit_mag``."""
    from startrack.render import Sensor

    base = dict(psf_sigma_px=1.6, read_noise_e=12.0, background_e_per_s=200.0, bit_depth=12, hot_pixels=hot_pixels)
    lo, hi = 1.0, 20000.0
    for _ in range(40):         # the limit grows with the exposure: bisect on log(exposure)
        mid = math.sqrt(lo * hi)
        if Sensor(exposure_ms=mid, **base).detection_limit_mag() < limit_mag:
            lo = mid
        else:
            hi = mid
    return Sensor(exposure_ms=round(hi, 2), **base)


def frames(fov: float, limit: float, n: int, seed: int, hot_pixels: int, first: int = 0):
    """``(index, image, truth, sensor)`` of ``n`` random pointings (frames ``first`` to ``first + n - 1``)."""
    from startrack.camera import Camera
    from startrack.catalog import load_catalog
    from startrack.render import RenderRun, Scene

    w, h = SIZE
    f = (w / 2.0) / math.tan(math.radians(fov) / 2.0)
    cam = Camera(w, h, f, (w - 1) / 2.0, (h - 1) / 2.0)
    sensor = sensor_for(limit, hot_pixels)
    cat = load_catalog(mag_max=limit + 0.5).filter_magnitude(None, limit + 0.5)
    run = RenderRun(cat, cam, sensor, Scene(limit + 0.5), seed, count=n, first_index=first)
    for k, (doc, image, _) in enumerate(run.frames_iter(), start=first):
        yield k, image, doc["truth"], sensor


def _sep_deg(ra1, dec1, ra2, dec2):
    a = np.radians([ra1, dec1, ra2, dec2])
    c = math.sin(a[1]) * math.sin(a[3]) + math.cos(a[1]) * math.cos(a[3]) * math.cos(a[0] - a[2])
    return math.degrees(math.acos(max(-1.0, min(1.0, c))))


def _verdict(ra, dec, roll, truth):
    if ra is None:
        return "failed"
    d_roll = abs((roll - truth["roll"] + 180.0) % 360.0 - 180.0)
    return "ok" if _sep_deg(ra, dec, truth["ra"], truth["dec"]) < 0.05 and d_roll < 0.5 else "wrong"


def run(args):
    import startrack

    solver = startrack.Solver()
    peer = None
    if args.peer:
        import tetra3rs_peer
        peer = tetra3rs_peer
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    settings = [s for s in SETTINGS if not args.fov or s[0] in args.fov]
    with open(args.out, "w", encoding="utf-8") as out:
        for fov, limit in settings:
            db = peer.build_or_load(fov, None, args.peer_cache) if peer else None
            for k, image, truth, sensor in frames(fov, limit, args.frames, args.seed, args.hot_pixels):
                sat = float(2 ** sensor.bit_depth - 1)
                t0 = time.perf_counter()
                res = solver.solve(image, fov_deg=fov if args.fov_hint else None, saturation=sat)
                ms = (time.perf_counter() - t0) * 1000.0
                row = {"fov": fov, "limit": limit, "frame": k, "seed": args.seed, "n_truth": len(truth["stars"]),
                       "exposure_ms": sensor.exposure_ms, "tool": args.label, "ms": ms}
                stars = [] if res.stars is None else res.stars.to_list()
                row["n_det"] = len(stars)
                row["n_real"] = sum(any(math.hypot(s["x"] - t["x"], s["y"] - t["y"]) < 2.0 for t in truth["stars"])
                                    for s in stars)
                row["hypotheses"] = res.hypotheses
                if res.status == "ok":
                    a = res.attitude
                    row["verdict"] = _verdict(a.ra, a.dec, a.roll, truth)
                else:
                    row["verdict"] = "failed"
                    row["reason"] = res.reason
                out.write(json.dumps(row) + "\n")
                if peer:
                    r = peer.solve_image(np.asarray(image, dtype=np.float32), fov, db=db)
                    prow = dict(row, tool="tetra3rs", ms=r["total_ms"], reason=r["status"])
                    prow["verdict"] = _verdict(r["ra"], r["dec"], r["roll"], truth) if r["ra"] is not None \
                        else "failed"
                    out.write(json.dumps(prow) + "\n")
                out.flush()
            print(f"fov {fov:g} limit {limit:g}: done", file=sys.stderr, flush=True)


def _in_index(index, rows) -> bool:
    """Whether the pattern index holds the four catalog rows ``rows`` as a pattern (at the level of its largest
    edge; its key computed as the build does, the neighbouring bins searched too against rounding)."""
    import itertools

    from startrack._kernels.patterns import NBINS

    v = np.asarray(index.star_vec)[list(rows)]
    e = sorted(math.atan2(np.linalg.norm(np.cross(v[a], v[b])), float(v[a] @ v[b]))
               for a, b in itertools.combinations(range(4), 2))
    want = sorted(int(r) for r in rows)
    for lv, rho in enumerate(np.asarray(index.level_rho)):
        if not rho / math.sqrt(2.0) < e[5] <= rho * (1 + 1e-9):
            continue
        s0, n = int(index.level_start[lv]), int(index.level_count[lv])
        keys = np.asarray(index.keys[s0:s0 + n])
        bins = [min(NBINS - 1, int(x / e[5] * NBINS)) for x in e[:5]]
        for delta in itertools.product((-1, 0, 1), repeat=5):
            b = [q + d for q, d in zip(bins, delta, strict=True)]
            if min(b) < 0 or max(b) >= NBINS:
                continue
            key = 0
            for q in b:
                key = key * NBINS + q
            lo, hi = np.searchsorted(keys, key), np.searchsorted(keys, key, side="right")
            for j in range(lo, hi):
                if sorted(int(r) for r in index.patterns[s0 + j]) == want:
                    return True
    return False


def why(args):
    """Re-solve each failed frame of ``args.why`` (startrack's rows) with the code on PYTHONPATH and say why it
    failed: fewer than four catalog stars among the detections the search used, no pattern of four of them in
    the index, or a pattern in the index (the look-up or the verification refused it)."""
    import collections
    import itertools

    import startrack
    from startrack.solve import _process_index

    index = _process_index("default")
    row_of = {int(i): r for r, i in enumerate(np.asarray(index.star_id))}
    with open(args.why, encoding="utf-8") as fh:
        rows = [json.loads(line) for line in fh if line.strip()]
    failed = [r for r in rows if r["tool"] != "tetra3rs" and r["verdict"] == "failed"]
    solver = startrack.Solver()
    causes = collections.Counter()
    per = collections.defaultdict(collections.Counter)
    for r in failed:
        _, image, truth, sensor = next(frames(r["fov"], r["limit"], 1, r["seed"], args.hot_pixels, r["frame"]))
        res = solver.solve(image, saturation=float(2 ** sensor.bit_depth - 1))
        stars = [] if res.stars is None else res.stars.to_list()
        stars = sorted(stars, key=lambda s: (-s.get("peak", s.get("flux", 0.0)), -s.get("flux", 0.0)))[:24]
        real = []
        for s in stars:
            hit = [t for t in truth["stars"] if math.hypot(s["x"] - t["x"], s["y"] - t["y"]) < 2.0]
            if hit and hit[0]["id"] in row_of and row_of[hit[0]["id"]] not in real:
                real.append(row_of[hit[0]["id"]])
        if len(real) < 4:
            cause = "fewer than 4 catalog stars detected"
        elif not any(_in_index(index, q) for q in itertools.combinations(real, 4)):
            cause = "no pattern of them in the index"
        else:
            cause = "a pattern in the index: refused or not reached"
        causes[cause] += 1
        per[(r["fov"], r["limit"])][cause] += 1
    print(f"{len(failed)} failed frames of {args.why}:")
    for cause, n in causes.most_common():
        print(f"  {n:4d}  {cause}")
    for key in sorted(per):
        print(f"  field {key[0]:g} deg, limit {key[1]:g}: " + ", ".join(f"{c} {n}" for c, n in per[key].most_common()))


def table(paths):
    rows = []
    for path in paths:
        with open(path, encoding="utf-8") as fh:
            rows += [json.loads(line) for line in fh if line.strip()]
    groups = {}
    for r in rows:
        groups.setdefault((r["fov"], r["limit"], r["tool"]), []).append(r)
    print("| field (deg) | limit (mag) | tool | frames | catalog stars detected (median) | solved | wrong | failed | "
          "median ms (solved) |")
    print("|---|---|---|---|---|---|---|---|---|")
    for (fov, limit, tool), g in sorted(groups.items()):
        ok = [r for r in g if r["verdict"] == "ok"]
        wrong = sum(r["verdict"] == "wrong" for r in g)
        med = statistics.median(r["ms"] for r in ok) if ok else float("nan")
        print(f"| {fov:g} | {limit:g} | {tool} | {len(g)} | {statistics.median(r.get('n_real', 0) for r in g):g} | "
              f"{len(ok)} | {wrong} | {len(g) - len(ok) - wrong} | {med:.1f} |")


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--frames", type=int, default=100, help="frames per setting")
    ap.add_argument("--seed", type=int, default=38)
    ap.add_argument("--hot-pixels", type=int, default=5)
    ap.add_argument("--fov", type=float, action="append", help="only these fields (repeatable)")
    ap.add_argument("--label", default="startrack", help="the tool column of this run (e.g. main, branch)")
    ap.add_argument("--peer", action="store_true", help="also tetra3rs given the field of view")
    ap.add_argument("--fov-hint", action="store_true", help="give startrack the field of view too (fov_deg)")
    ap.add_argument("--peer-cache", default=os.path.join(os.path.dirname(HERE), "bench-output", "peers"))
    ap.add_argument("--out", default=os.path.join(os.path.dirname(HERE), "bench-output", "sparse.jsonl"))
    ap.add_argument("--table", nargs="+", metavar="JSONL", help="print the table of these runs instead")
    ap.add_argument("--why", metavar="JSONL", help="say why each failed frame of this run failed instead")
    args = ap.parse_args()
    if args.table:
        table(args.table)
    elif args.why:
        why(args)
    else:
        run(args)


if __name__ == "__main__":
    main()
