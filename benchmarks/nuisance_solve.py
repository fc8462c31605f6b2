"""Issue 37's must-show: blind `startrack solve` on rendered frames carrying each nuisance of real cameras, and a
false-solution hunt on star-less frames carrying the same nuisances (success / wrong / false ok per nuisance).

Every frame is rendered by `startrack render` and solved by `startrack solve` as a user runs them (subprocesses,
the real CLI): a dark-subtracted 8-bit frame clipped at 0, 50 hot pixels, an opaque foreground body over 30 % and
50 % of the frame (a disc, an edge, branches in turn), nebulosity, a 10x sky gradient, and a mirrored image
(columns and rows in turn); with ``--no-stars`` the same nuisances on frames without a catalog star, with 30
false point sources each (the false-solution hunt: any ok is wrong). The frames are spread over four sensors (6.1 deg 1392x1040 at 500 ms, 8 deg
1024x768 at 300 ms, 12 deg 1280x960 and 20 deg 1024x1024 at 100 ms) and random attitudes. A solve is right when its boresight is within 10 pixels'
angle and its roll within 1 deg of the truth, wrong when it says ok otherwise.

    python benchmarks/nuisance_solve.py --count 200 --out bench-output/nuisance
    python benchmarks/nuisance_solve.py --count 200 --solve-pythonpath /path/to/older/checkout   # the same frames

``--solve-pythonpath`` solves with another checkout of startrack (rendering stays with this one), so that two
versions are measured on the very same frames.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys

from common import cached_truth, rendered_image_path, save_truth, solve_saved

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

#: (fov deg, width, height, exposure ms): the frames of a nuisance are spread over these in turn.  The narrow
#: fields expose longer, as a star tracker of that field does to see stars to magnitude 7-8.
SENSORS = [(6.1, 1392, 1040, 500), (8.0, 1024, 768, 300), (12.0, 1280, 960, 100), (20.0, 1024, 1024, 100)]

#: name -> list of render arguments, one list per sensor slot (cycled), for the nuisances of issue 37.
NUISANCES = {
    "clipped": [["--bit-depth", "8", "--gain-e-per-dn", "2", "--dark-subtracted"]],
    "hot50": [["--hot-pixels", "50"]],
    "body30": [["--foreground", k, "--foreground-fraction", "0.3"] for k in ("disc", "edge", "branches")],
    "body50": [["--foreground", k, "--foreground-fraction", "0.5"] for k in ("disc", "edge", "branches")],
    "nebula": [["--nebulosity-e-per-s", "500"]],
    "gradient10": [["--gradient", "10"]],
    "mirrored": [["--mirror", "x"], ["--mirror", "y"]],
}


def _cli(args, pythonpath, **kw):
    env = dict(os.environ, PYTHONPATH=pythonpath)
    env.pop("STARTRACK_DEBUG", None)
    return subprocess.run([sys.executable, "-m", "startrack", *args], capture_output=True, text=True, env=env,
                          cwd=pythonpath, **kw)


def render_set(name: str, count: int, out: str, seed: int, stars: bool, pythonpath: str = ROOT) -> list:
    """Render ``count`` frames of nuisance ``name`` into ``out``: their frame documents (truth)."""
    os.makedirs(out, exist_ok=True)
    docs = cached_truth(out, count)
    if docs is not None:
        return docs
    docs = []
    variants = NUISANCES[name]
    slots = [(s, v) for s in range(len(SENSORS)) for v in range(len(variants))]
    per = [count // len(slots) + (1 if i < count % len(slots) else 0) for i in range(len(slots))]
    for i, ((s, v), n) in enumerate(zip(slots, per)):
        if n == 0:
            continue
        fov, w, h, exposure = SENSORS[s]
        args = ["render", "--fov-deg", str(fov), "--size", f"{w}x{h}", "--exposure-ms", str(exposure),
                "--seed", str(seed + i),
                "-o", os.path.join(out, f"s{i:02d}-.png"), "-q", *variants[v]]
        # Star-less frames: a sequence rendered blacked out (no catalog star), with 30 false point sources
        # besides the nuisance's own detections, the patterns a false solution would be made of.
        args += ["--count", str(n)] if stars else ["--frames", str(n), "--blackout", f"0:{n}", "--false-stars", "30"]
        proc = _cli(args, pythonpath)
        if proc.returncode != 0:
            raise SystemExit(f"render failed: {' '.join(args)}\n{proc.stderr}")
        docs += [json.loads(line) for line in proc.stdout.splitlines() if line.strip()]
    return save_truth(out, docs)


def score(truth: dict, solved: dict) -> str:
    """``right``, ``wrong`` (status ok, attitude off) or ``failed``.

    A frame mirrored in y is the camera's mirrored in x turned by 180 degrees about the boresight: a solver
    that reports the x-mirrored camera (startrack.parity) is right with the truth's roll + 180 degrees.
    """
    import numpy as np

    from startrack.rotations import attitude_error, quaternion_to_dcm

    status = (solved.get("solve") or {}).get("status")
    if status != "ok" or "attitude" not in solved:
        return "failed"
    cam = truth["camera"]
    px_deg = math.degrees(2 * math.atan(cam["width"] / 2 / cam["focal_length_px"]) / cam["width"])
    true = quaternion_to_dcm(truth["truth"]["quaternion"])
    if truth["truth"].get("mirror") == "y":
        true = np.diag([-1.0, -1.0, 1.0]) @ true
    _, cross, roll = attitude_error(quaternion_to_dcm(solved["attitude"]["quaternion"]), true)   # degrees
    return "right" if cross < 10 * px_deg and abs(roll) < 1.0 else "wrong"


def solve_set(docs: list, out: str, pythonpath: str, label: str, score_only: bool = False) -> dict:
    paths = [rendered_image_path(d, out) for d in docs]
    solved, wall = solve_saved(lambda a: _cli(a, pythonpath), ["solve", "-q", *paths],
                               os.path.join(out, f"solved-{label}.jsonl"), score_only)
    counts = {"right": 0, "wrong": 0, "failed": 0}
    reasons: dict = {}
    for d, p in zip(docs, paths):
        s = solved.get(os.path.basename(p), {})
        verdict = score(d, s)
        counts[verdict] += 1
        if verdict == "failed":
            r = (s.get("solve") or {}).get("reason", "no document")
            r = r.split(" (")[0].split(";")[0]
            reasons[r] = reasons.get(r, 0) + 1
    return {**counts, "n": len(docs), "wall_s": wall, "reasons": reasons}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--count", type=int, default=200, help="frames per nuisance (default 200)")
    ap.add_argument("--seed", type=int, default=37)
    ap.add_argument("--out", default=os.path.join(ROOT, "bench-output", "nuisance"))
    ap.add_argument("--nuisances", default=",".join(NUISANCES), help="comma-separated subset")
    ap.add_argument("--solve-pythonpath", default=ROOT, help="the checkout whose solve is measured (default: this)")
    ap.add_argument("--render-pythonpath", default=ROOT, help="the checkout whose render makes the frames")
    ap.add_argument("--label", default="this", help="names the solved-LABEL.jsonl files")
    ap.add_argument("--no-stars", action="store_true", help="the false-solution hunt: frames without stars")
    ap.add_argument("--score-only", action="store_true", help="score the solved-LABEL.jsonl files of an earlier run")
    args = ap.parse_args(argv)
    rows = []
    for name in args.nuisances.split(","):
        sub = os.path.join(args.out, ("noise-" if args.no_stars else "") + name)
        docs = render_set(name, args.count, sub, args.seed + 1000 * list(NUISANCES).index(name), not args.no_stars,
                          os.path.abspath(args.render_pythonpath))
        r = solve_set(docs, sub, os.path.abspath(args.solve_pythonpath), args.label, args.score_only)
        rows.append((name, r))
        top = ", ".join(f"{k} {v}" for k, v in sorted(r["reasons"].items(), key=lambda kv: -kv[1])[:3])
        print(f"| {name} | {r['n']} | {100 * r['right'] / r['n']:.1f} % ({r['right']}) | {r['wrong']} | "
              f"{r['wall_s'] / r['n'] * 1000:.0f} ms | {top} |", flush=True)
    return rows


if __name__ == "__main__":
    main()
