"""Issue 43's must-show (part A): blind `startrack solve` of 1 and 1.5 degree fields with at least 10 Gaia stars in view.

Frames are rendered by `startrack render --catalog gaia` (Gaia DR3 to G 10 with Hipparcos for the brightest) at
random attitudes (``--seed``), 1024 x 768 pixels, a 2 s exposure (G 10 at about 500 e-), a camera at rest at the
catalog's epoch (``--no-aberration``: the solve is told no time, and aberration would move the truth by up to 20");
the frames with at least ``--min-stars`` catalog stars to G 10 inside the image are kept, the first ``--count`` of
them, and solved by `startrack solve` with no hint, as a user runs it (subprocesses, the real CLI).

A solve is *right* when its image centre is within ``--tolerance-px`` pixels' angle (5) of the truth's and every
matched catalog id names a truth star under its detection (within 3 px of it, so either star of a blend: its Gaia
id, or, for a frame the Hipparcos index identified, the HIP number of a Hipparcos star within 3" of it at 2016.0); *wrong* when it says ok otherwise (``ids not in truth`` counts the matches that name another star);
*failed* when it says failed.  ``--score-only`` scores the frames and solutions an earlier run left in ``--out``.

    python benchmarks/narrow_solve.py --fov-deg 1.0,1.5 --count 200 --out bench-output/narrow
"""
from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys

from common import solve_saved

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
WIDTH, HEIGHT, EXPOSURE_MS = 1024, 768, 2000


def _cli(args, **kw):
    env = dict(os.environ, PYTHONPATH=ROOT)
    env.pop("STARTRACK_DEBUG", None)
    return subprocess.run([sys.executable, "-m", "startrack", *args], capture_output=True, text=True, env=env,
                          cwd=ROOT, **kw)


def in_view(doc: dict, mag_max: float = 10.0) -> int:
    """Catalog stars to ``mag_max`` whose centre falls on the image (the truth lists a margin around it too)."""
    w, h = doc["image"]["width"], doc["image"]["height"]
    return sum(1 for s in doc["truth"]["stars"]
               if -0.5 <= s["x"] <= w - 0.5 and -0.5 <= s["y"] <= h - 0.5 and s["mag"] <= mag_max)


def render_set(fov: float, count: int, min_stars: int, out: str, seed: int) -> tuple[list, int]:
    """Render batches until ``count`` frames hold ``min_stars`` stars: ``(kept documents, frames rendered)``."""
    os.makedirs(out, exist_ok=True)
    docs_path = os.path.join(out, "truth.jsonl")
    if os.path.exists(docs_path):
        with open(docs_path) as f:
            lines = f.read().splitlines()
        return [json.loads(ln) for ln in lines[1:]], json.loads(lines[0])["rendered"]
    kept, rendered, batch = [], 0, 0
    while len(kept) < count:
        n = max(20, int((count - len(kept)) * 2.5))
        args = ["render", "--catalog", "gaia", "--fov-deg", str(fov), "--size", f"{WIDTH}x{HEIGHT}",
                "--exposure-ms", str(EXPOSURE_MS), "--no-aberration", "--count", str(n), "--seed", str(seed + batch),
                "-o", os.path.join(out, f"b{batch:02d}-.png"), "-q"]
        proc = _cli(args)
        if proc.returncode != 0:
            raise SystemExit(f"render failed: {' '.join(args)}\n{proc.stderr}")
        for line in proc.stdout.splitlines():
            if not line.strip():
                continue
            rendered += 1
            doc = json.loads(line)
            path = os.path.join(out, os.path.basename(doc["image"]["path"]))
            if in_view(doc) >= min_stars and len(kept) < count:
                doc["image"]["path"] = path
                kept.append(doc)
            else:
                os.remove(path)
        batch += 1
    with open(docs_path, "w") as f:
        f.write(json.dumps({"rendered": rendered}) + "\n")
        f.writelines(json.dumps(d) + "\n" for d in kept)
    return kept, rendered


def _sep_deg(ra1, dec1, ra2, dec2) -> float:
    r1, d1, r2, d2 = map(math.radians, (ra1, dec1, ra2, dec2))
    c = math.sin(d1) * math.sin(d2) + math.cos(d1) * math.cos(d2) * math.cos(r1 - r2)
    s = math.hypot(math.cos(d2) * math.sin(r1 - r2),
                   math.cos(d1) * math.sin(d2) - math.sin(d1) * math.cos(d2) * math.cos(r1 - r2))
    return math.degrees(math.atan2(s, c))


class Positions:
    """Unit vectors at 2016.0 of the Gaia catalog's stars and of every Hipparcos star, by id."""

    def __init__(self):
        from startrack.catalog import load_catalog

        gaia = load_catalog("gaia")
        hip = load_catalog().propagate(2016.0)
        self.vec = {}
        for cat in (hip, gaia):
            self.vec.update(zip(cat.id.tolist(), cat.vectors()))

    def same_star(self, a: int, b: int, arcsec: float = 3.0) -> bool:
        if a == b:
            return True
        if a not in self.vec or b not in self.vec:
            return False
        return float(self.vec[a] @ self.vec[b]) > math.cos(math.radians(arcsec / 3600.0))


def _wrong_ids(truth: dict, solved: dict, positions: Positions) -> int:
    """Matches whose id is none of the truth stars under the detection (within 3 px of it: a blend of two
    stars a pixel apart is one detection, and either star's id names it)."""
    stars = truth["truth"]["stars"]
    wrong = 0
    for m in solved["identification"]["matches"]:
        det = solved["stars"][m["star"]]
        under = [t for t in stars if math.hypot(t["x"] - det["x"], t["y"] - det["y"]) <= 3.0]
        if not any(positions.same_star(int(m["id"]), int(t["id"])) for t in under):
            wrong += 1
    return wrong


def score(truth: dict, solved: dict, tolerance_px: float, positions: Positions) -> tuple[str, float | None, int]:
    """``(verdict, centre error in pixels, matched ids that name another star)``."""
    from startrack.camera import Camera
    from startrack.rotations import quaternion_to_dcm

    s = solved.get("solve") or {}
    if s.get("status") != "ok":
        return "failed", None, 0
    cam = Camera.from_dict(truth["camera"])
    dcm = quaternion_to_dcm(truth["truth"]["quaternion"])
    v = dcm.T @ cam.pixels_to_vectors([(cam.width - 1) / 2.0], [(cam.height - 1) / 2.0])[0]
    ra, dec = math.degrees(math.atan2(v[1], v[0])) % 360.0, math.degrees(math.asin(max(-1.0, min(1.0, v[2]))))
    px_deg = math.degrees(math.atan(1.0 / cam.focal_length_px))
    err_px = _sep_deg(ra, dec, s["center_ra"], s["center_dec"]) / px_deg
    foreign = _wrong_ids(truth, solved, positions)
    return ("right" if err_px <= tolerance_px and foreign == 0 else "wrong"), err_px, foreign


def solve_set(docs: list, out: str, jobs: int, score_only: bool = False) -> tuple[list, float]:
    paths = [d["image"]["path"] for d in docs]
    by_path, wall = solve_saved(_cli, ["solve", "-q", "-j", str(jobs), *paths], os.path.join(out, "solved.jsonl"),
                                score_only)
    return [by_path.get(os.path.basename(p), {}) for p in paths], wall


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--fov-deg", default="1.0,1.5", help="comma list of horizontal fields (degrees)")
    parser.add_argument("--count", type=int, default=200, help="frames per field")
    parser.add_argument("--min-stars", type=int, default=10)
    parser.add_argument("--tolerance-px", type=float, default=5.0)
    parser.add_argument("--seed", type=int, default=43)
    parser.add_argument("-j", "--jobs", type=int, default=1)
    parser.add_argument("--out", default=os.path.join(ROOT, "bench-output", "narrow"))
    parser.add_argument("--score-only", action="store_true", help="score the frames and solutions in --out again")
    args = parser.parse_args(argv)
    sys.path.insert(0, ROOT)
    positions = Positions()
    rows = []
    for fov in (float(v) for v in args.fov_deg.split(",")):
        out = os.path.join(args.out, f"fov{fov:g}")
        docs, rendered = render_set(fov, args.count, args.min_stars, out, args.seed)
        solved, wall = solve_set(docs, out, args.jobs, args.score_only)
        verdicts, errs, reasons, catalogs, times = {"right": 0, "wrong": 0, "failed": 0}, [], {}, {}, []
        foreign_total = 0
        for d, s in zip(docs, solved, strict=True):
            verdict, err, foreign = score(d, s, args.tolerance_px, positions)
            verdicts[verdict] += 1
            foreign_total += foreign
            sec = s.get("solve") or {}
            if sec.get("time_ms") is not None:
                times.append(sec["time_ms"])
            if verdict == "failed":
                r = str(sec.get("reason", "no document")).split(" (")[0].split(";")[0]
                reasons[r] = reasons.get(r, 0) + 1
            else:
                errs.append(err)
                catalogs[sec.get("catalog")] = catalogs.get(sec.get("catalog"), 0) + 1
        errs.sort()
        times.sort()
        n_stars = sorted(in_view(d) for d in docs)
        rows.append({"fov_deg": fov, "frames": len(docs), "rendered": rendered, "min_stars": args.min_stars,
                     "median_stars_in_view": n_stars[len(n_stars) // 2], **verdicts,
                     "ids_not_in_truth": foreign_total, "catalog_of_solutions": catalogs,
                     "median_centre_error_px": errs[len(errs) // 2] if errs else None,
                     "max_centre_error_px": errs[-1] if errs else None,
                     "median_time_ms": times[len(times) // 2] if times else None,
                     "wall_s": None if args.score_only else round(wall, 1),
                     "failure_reasons": reasons})
        print(json.dumps(rows[-1]), flush=True)
    print("\n| field | frames (rendered) | stars in view, median | right | wrong | failed | success | "
          "centre error px, median / max | solve ms, median |")
    print("|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        med = f"{r['median_centre_error_px']:.2f} / {r['max_centre_error_px']:.2f}" if r["median_centre_error_px"] \
            is not None else "-"
        print(f"| {r['fov_deg']:g} deg | {r['frames']} ({r['rendered']}) | {r['median_stars_in_view']} | {r['right']} | "
              f"{r['wrong']} | {r['failed']} | {100 * r['right'] / r['frames']:.1f} % | {med} | "
              f"{r['median_time_ms']:.0f} |")


if __name__ == "__main__":
    main()
