"""Paper 003 Fig. 1 redone on a rendered slew: one bright star followed over 50 frames of a pure cross-axis
slew, centroided by centre of mass (Eqs. 1-3) and by Quine's Gaussian interpolation (Eqs. 4-6); a straight
line is fitted to each track and its R^2 and scatter reported (the paper: COM's R^2 is the larger).

    .venv/bin/python examples/p003_fig1.py [--out examples/results/p003-fig1.json]
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _run(args, stdin=None):
    proc = subprocess.run([sys.executable, "-m", "startrack", *args], input=stdin, capture_output=True, text=True)
    if proc.returncode not in (0, 1):
        raise SystemExit(f"startrack {' '.join(args)}: {proc.stderr.strip()}")
    return proc.stdout


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=os.path.join(ROOT, "examples", "results", "p003-fig1.json"))
    ap.add_argument("--seed", type=int, default=3)
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as work:
        # ZY-3-like: 20 x 20 deg, 1024 x 1024; Nunki region (a 2.0 and several 3rd-magnitude stars);
        # a pure cross-axis slew of 0.02 deg/s about the camera x axis, 50 frames 0.2 s apart.
        seq = _run(["render", "--fov-deg", "20", "--size", "1024x1024", "--ra", "283.8", "--dec", "-26.3",
                    "--roll", "0", "--frames", "50", "--rate-deg-s", "0.02,0,0", "--frame-interval-s", "0.2",
                    "--exposure-ms", "50", "--psf-sigma-px", "0.8", "--seed", str(args.seed), "-q",
                    "-o", os.path.join(work, "frame.png")])
        tracks = {}
        for method in ("com", "quine"):
            out = _run(["centroid", "-", "--method", method, "-q"], stdin=seq)
            docs = [json.loads(line) for line in out.splitlines() if line.strip()]
            pos = []
            for d in docs:
                truth = {s["id"]: s for s in d["truth"]["stars"]}
                # The paper's star: magnitude 2.9; ours: the truth star closest to it in brightness.
                star_id = min(truth, key=lambda i: abs(truth[i]["mag"] - 2.9)) if not pos else pos[0][0]
                t = truth.get(star_id)
                if t is None:
                    continue
                best = min(d["stars"], key=lambda s: (s["x"] - t["x"]) ** 2 + (s["y"] - t["y"]) ** 2)
                pos.append((star_id, best["x"], best["y"], t["x"], t["y"], t["mag"]))
            tracks[method] = pos
    result = {"description": "", "methods": {}}
    for method, pos in tracks.items():
        r = np.array([np.hypot(p[1] - 511.5, p[2] - 511.5) for p in pos])
        k = np.arange(len(r), dtype=float)
        coef = np.polyfit(k, r, 1)
        fit = np.polyval(coef, k)
        ss_res = float(np.sum((r - fit) ** 2))
        ss_tot = float(np.sum((r - r.mean()) ** 2))
        truth_err = np.hypot([p[1] - p[3] for p in pos], [p[2] - p[4] for p in pos])
        result["methods"][method] = {"r2": 1 - ss_res / ss_tot, "rms_px": float(np.sqrt(ss_res / len(r))),
                                     "rms_error_vs_truth_px": float(np.sqrt(np.mean(truth_err ** 2))),
                                     "frames": len(r)}
        result["description"] = (f"Star HIP {pos[0][0]} (Hp {pos[0][5]:.2f}), {len(r)} frames, distance from the "
                                  "image centre against frame number.")
    with open(args.out + ".part", "w") as fh:
        json.dump(result, fh, indent=1)
    os.replace(args.out + ".part", args.out)
    print(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
