"""Issue 43's fisheye must-show: blind `startrack solve` on rendered all-sky frames, per projection and field.

Every frame is rendered by `startrack render` and solved by `startrack solve` (no hint, `--projection auto`, the
default) as a user runs them (subprocesses, the real CLI): each fisheye projection (equidistant, equisolid,
stereographic, orthographic) at 120, 150 and 180 deg across the width of a square sensor, stars to magnitude
5.5, a random horizon (`--horizon random`: a ridge, buildings and trees from the frame's seed; the ground dark,
no star below it), 0.2 mag per air mass of extinction, random attitudes (the boresight is the zenith). A solve
is right when its boresight is within 10 pixels' angle (at the principal point) and its roll within 1 deg of
the truth, wrong when it says ok otherwise. For every right frame: the centre error (the image centre's
direction against the truth's), the projection fitted against the rendered one, the focal length's relative
error and the distortion terms fitted (the truth has none).

    python benchmarks/allsky_solve.py --count 200 --out bench-output/allsky
    python benchmarks/allsky_solve.py --count 20 --size 800 --projections equidistant --fovs 180
    python benchmarks/allsky_solve.py --count 200 --ground-lights 20 --out bench-output/allsky-lights
"""
from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import subprocess
import sys

from common import cached_truth, rendered_image_path, save_truth, solve_saved

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PROJECTIONS = ("equidistant", "equisolid", "stereographic", "orthographic")
FOVS = (120.0, 150.0, 180.0)


def _cli(args, pythonpath, **kw):
    env = dict(os.environ, PYTHONPATH=pythonpath)
    env.pop("STARTRACK_DEBUG", None)
    return subprocess.run([sys.executable, "-m", "startrack", *args], capture_output=True, text=True, env=env,
                          cwd=pythonpath, **kw)


def render_set(projection: str, fov: float, count: int, size: int, out: str, seed: int, pythonpath: str,
               lights: int = 0) -> list:
    """Render ``count`` frames into ``out``: their frame documents (truth); reused when already there."""
    os.makedirs(out, exist_ok=True)
    docs = cached_truth(out, count)
    if docs is not None:
        return docs
    args = ["render", "--projection", projection, "--fov-deg", f"{fov:g}", "--size", f"{size}x{size}",
            "--mag-max", "5.5", "--horizon", "random", "--extinction-mag", "0.2", "--no-aberration", "--count", str(count),
            "--seed", str(seed), "-o", os.path.join(out, "f-.png"), "-q"]
    if lights:
        args[-3:-3] = ["--ground-lights", str(lights)]
    proc = _cli(args, pythonpath)
    if proc.returncode != 0:
        raise SystemExit(f"render failed: {' '.join(args)}\n{proc.stderr}")
    return save_truth(out, [json.loads(line) for line in proc.stdout.splitlines() if line.strip()])


def score(truth: dict, solved: dict) -> dict:
    """``verdict`` (``right``, ``wrong``, ``failed``) and, when right, what was fitted against the truth."""
    import numpy as np

    from startrack.camera import Camera
    from startrack.rotations import attitude_error, quaternion_to_dcm

    status = (solved.get("solve") or {}).get("status")
    if status != "ok" or "attitude" not in solved:
        return {"verdict": "failed", "reason": (solved.get("solve") or {}).get("reason", "no document")}
    cam = Camera.from_dict(truth["camera"])
    px_deg = math.degrees(1.0 / cam.focal_length_px)
    true = quaternion_to_dcm(truth["truth"]["quaternion"])
    _, cross, roll = attitude_error(quaternion_to_dcm(solved["attitude"]["quaternion"]), true)   # degrees
    if not (cross < 10 * px_deg and abs(roll) < 1.0):
        return {"verdict": "wrong", "cross_deg": cross, "roll_deg": roll}
    centre = true.T @ cam.pixels_to_vectors((cam.width - 1) / 2.0, (cam.height - 1) / 2.0)
    ra, dec = math.radians(solved["solve"]["center_ra"]), math.radians(solved["solve"]["center_dec"])
    got = np.array([math.cos(dec) * math.cos(ra), math.cos(dec) * math.sin(ra), math.sin(dec)])
    fitted = Camera.from_dict(solved["camera"])
    return {"verdict": "right", "centre_arcmin": math.degrees(math.acos(min(1.0, float(got @ centre)))) * 60,
            "projection": fitted.projection, "f_err": fitted.focal_length_px / cam.focal_length_px - 1,
            "terms": {k: getattr(fitted, k) for k in ("k1", "k2", "k3", "k4") if getattr(fitted, k)}}


def solve_set(docs, out, pythonpath, label, projection, score_only=False) -> dict:
    paths = [rendered_image_path(d, out) for d in docs]
    solved, wall = solve_saved(lambda a: _cli(a, pythonpath), ["solve", "-q", "--no-aberration", *paths],
                               os.path.join(out, f"solved-{label}.jsonl"), score_only)
    rows = [score(d, solved.get(os.path.basename(p), {})) for d, p in zip(docs, paths)]
    right = [r for r in rows if r["verdict"] == "right"]
    reasons: dict = {}
    for r in rows:
        if r["verdict"] == "failed":
            key = r["reason"].split(" (")[0].split(";")[0]
            reasons[key] = reasons.get(key, 0) + 1
    times = [float((solved.get(os.path.basename(p), {}).get("solve") or {}).get("time_ms") or 0) for p in paths]
    terms = {}
    for r in right:
        for k, v in r["terms"].items():
            terms.setdefault(k, []).append(abs(v))
    return {"n": len(rows), "right": len(right), "wrong": sum(r["verdict"] == "wrong" for r in rows),
            "failed": sum(r["verdict"] == "failed" for r in rows), "reasons": reasons, "wall_s": wall,
            "median_ms": statistics.median(times) if times else float("nan"),
            "centre_median_arcmin": statistics.median([r["centre_arcmin"] for r in right]) if right else float("nan"),
            "centre_max_arcmin": max([r["centre_arcmin"] for r in right], default=float("nan")),
            "projection_right": sum(r["projection"] == projection for r in right),
            "projections": {p: sum(r["projection"] == p for r in right) for p in {r["projection"] for r in right}},
            "f_err_median": statistics.median([abs(r["f_err"]) for r in right]) if right else float("nan"),
            "f_err_max": max([abs(r["f_err"]) for r in right], default=float("nan")),
            "terms": {k: (len(v), max(v)) for k, v in terms.items()}}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--count", type=int, default=200, help="frames per projection and field (default 200)")
    ap.add_argument("--size", type=int, default=960, help="sensor side, pixels (default 960)")
    ap.add_argument("--seed", type=int, default=43)
    ap.add_argument("--out", default=os.path.join(ROOT, "bench-output", "allsky"))
    ap.add_argument("--projections", default=",".join(PROJECTIONS))
    ap.add_argument("--fovs", default=",".join(f"{f:g}" for f in FOVS))
    ap.add_argument("--solve-pythonpath", default=ROOT, help="the checkout whose solve is measured (default: this)")
    ap.add_argument("--label", default="this", help="names the solved-LABEL.jsonl files")
    ap.add_argument("--score-only", action="store_true", help="score the solved-LABEL.jsonl files of an earlier run")
    ap.add_argument("--ground-lights", type=int, default=0, help="lights on the ground per frame (render --ground-lights)")
    ap.add_argument("--render-only", action="store_true", help="render the frames (kept in --out for a later run)")
    args = ap.parse_args(argv)
    print("| projection | field | frames | right | wrong | failed (reasons) | centre error median / max | "
          "projection fitted | f error median / max | distortion fitted (frames, largest) | median solve |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    out_rows = []
    for i, projection in enumerate(args.projections.split(",")):
        for j, fov in enumerate(float(f) for f in args.fovs.split(",")):
            sub = os.path.join(args.out, f"{projection}-{fov:g}")
            docs = render_set(projection, fov, args.count, args.size, sub, args.seed + 100 * i + j, ROOT,
                              args.ground_lights)
            if args.render_only:
                print(f"| {projection} | {fov:g} deg | {len(docs)} rendered |", flush=True)
                continue
            r = solve_set(docs, sub, os.path.abspath(args.solve_pythonpath), args.label, projection, args.score_only)
            out_rows.append((projection, fov, r))
            why = ", ".join(f"{k} {v}" for k, v in sorted(r["reasons"].items(), key=lambda kv: -kv[1])[:2])
            fitted = ", ".join(f"{p} {n}" for p, n in sorted(r["projections"].items(), key=lambda kv: -kv[1]))
            terms = ", ".join(f"{k} {n} (|{k}| <= {m:.2g})" for k, (n, m) in sorted(r["terms"].items())) or "none"
            print(f"| {projection} | {fov:g} deg | {r['n']} | {100 * r['right'] / r['n']:.1f} % ({r['right']}) | "
                  f"{r['wrong']} | {r['failed']}{' (' + why + ')' if why else ''} | "
                  f"{r['centre_median_arcmin']:.2f}' / {r['centre_max_arcmin']:.2f}' | {fitted} | "
                  f"{100 * r['f_err_median']:.3f} % / {100 * r['f_err_max']:.3f} % | {terms} | "
                  f"{r['median_ms']:.0f} ms |", flush=True)
    return out_rows


if __name__ == "__main__":
    main()
