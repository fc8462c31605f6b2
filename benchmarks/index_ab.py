"""A study: two pattern indexes on the same frames, in one process (patterns tried, candidates verified, time, right).

A study tool for the blind search's index (``startrack.patterns.BUILD_PARAMS``), not a `make bench` section.  Each
frame is solved blind (``startrack.solve.solve_image`` with ``index=``) with every index given, three times, the
indexes alternated; a frame with a ``startrack render`` document beside it (``NAME.json`` for ``NAME.tiff``) is
scored against its truth (right: boresight within 0.05 deg).  Session 10's study (the default index's
``max_per_anchor``, 40 against 100: not kept) is in ``results/results-speed-2026-12-06.md``.

    # an index file of given build parameters (the rest the default's)
    python benchmarks/index_ab.py --build '{"max_per_anchor": 100}' bench-output/mpa100.idx
    # 80 frames nothing was tuned on (random sky, vignetting, magnitude noise, hot pixels)
    python benchmarks/index_ab.py --render bench-output/ev --count 80 --seed 11
    python benchmarks/index_ab.py default bench-output/mpa100.idx 'bench-output/ev/*.tiff' 'tests/data/real/*.tiff'

An index argument is a file, or ``default`` (the cached default index).
"""
from __future__ import annotations

import argparse
import glob
import json
import math
import os
import random
import statistics
import subprocess
import sys
import time

import numpy as np


def _boresight(q):
    from startrack.rotations import quaternion_to_dcm

    return quaternion_to_dcm(np.asarray(q, dtype=np.float64))[2]


def build(params: dict, out: str) -> None:
    from startrack.patterns import build_index, save_index

    t0 = time.perf_counter()
    idx = build_index(params=params)
    save_index(idx, out)
    print(f"{out}: {len(idx.keys):,} patterns, {idx.size_bytes / 1e6:.1f} MB, built in {time.perf_counter() - t0:.1f} s; "
          f"patterns per level {idx.params['patterns_per_level']}")


def render(out: str, count: int, seed: int, first_frame_seed: int = 500) -> None:
    """``count`` frames: 6-25 deg, 1024 x 768, random pointing, vignetting 0.3-1, magnitude noise 0-0.4, 20 hot
    pixels, a time (aberration in the truth); ``seed`` draws the settings, frame ``i`` is rendered with seed
    ``first_frame_seed + i``."""
    os.makedirs(out, exist_ok=True)
    rng = random.Random(seed)
    for i in range(count):
        fov, ra = rng.uniform(6, 25), rng.uniform(0, 360)
        dec, roll = math.degrees(math.asin(rng.uniform(-1, 1))), rng.uniform(0, 360)
        vig, mag_noise = rng.uniform(0.3, 1.0), rng.uniform(0.0, 0.4)
        name = os.path.join(out, f"e{i:02d}")
        with open(name + ".json", "w") as fh:
            subprocess.run([sys.executable, "-m", "startrack", "render", "--fov-deg", f"{fov:.2f}", "--size", "1024x768",
                            "--ra", f"{ra:.3f}", "--dec", f"{dec:.3f}", "--roll", f"{roll:.2f}", "--vignetting",
                            f"{vig:.2f}", "--mag-noise", f"{mag_noise:.2f}", "--hot-pixels", "20", "--seed",
                            str(first_frame_seed + i), "--time", "2026-03-01T00:00:00Z", "-q", "-o", name + ".tiff"],
                           stdout=fh, check=True)
    print(f"{count} frames in {out}")


def compare(index_args: list, patterns: list) -> None:
    from startrack.imageio import read_image
    from startrack.patterns import default_index, open_index
    from startrack.solve import BandDatabases, solve_image

    indexes = [default_index() if a == "default" else open_index(a) for a in index_args]
    files = [f for p in patterns for f in sorted(glob.glob(p))]
    dbs = BandDatabases(None)
    rows = []
    for f in files:
        image, meta = read_image(f)
        truth = None
        doc = os.path.splitext(f)[0] + ".json"
        if os.path.exists(doc):
            with open(doc) as fh:
                truth = json.loads(fh.readline())["truth"]["quaternion"]
        for idx in indexes:         # first uses
            solve_image(image, index=idx, saturation=meta["saturation"], databases=dbs)
        times = [[] for _ in indexes]
        last = [None] * len(indexes)
        for rep in range(3):
            for k in (range(len(indexes)) if rep % 2 == 0 else reversed(range(len(indexes)))):
                t0 = time.perf_counter()
                last[k] = solve_image(image, index=indexes[k], saturation=meta["saturation"], databases=dbs)
                times[k].append((time.perf_counter() - t0) * 1000)
        row = [os.path.basename(f)]
        for k, res in enumerate(last):
            details = (res.identification.details or {}) if res.identification else {}
            verdict = "ok" if res.status == "ok" else "failed"
            if res.status == "ok" and truth is not None:
                cos = abs(float(_boresight(res.attitude.quaternion) @ _boresight(truth)))
                sep = math.degrees(math.acos(min(1.0, cos)))
                verdict = "ok" if sep < 0.05 else f"wrong ({sep:.2f} deg)"
            row.append((verdict, details.get("patterns_tried"), details.get("verified"), statistics.median(times[k])))
        rows.append(row)
        print(row[0], " | ".join(f"{v} {p} patterns {c} verified {t:.2f} ms" for v, p, c, t in row[1:]), flush=True)
    print()
    print("| index | frames | ok | wrong | patterns tried: mean / median / 90th pct / max | ms: median / mean |")
    print("|---|---|---|---|---|---|")
    for k, name in enumerate(index_args):
        got = [r[k + 1] for r in rows]
        tried = [g[1] for g in got if g[1] is not None] or [0]
        ms = [g[3] for g in got]
        print(f"| {name} | {len(got)} | {sum(g[0] == 'ok' for g in got)} | {sum(g[0].startswith('wrong') for g in got)} "
              f"| {np.mean(tried):.1f} / {np.median(tried):.0f} / {np.percentile(tried, 90):.0f} / {max(tried)} "
              f"| {np.median(ms):.2f} / {np.mean(ms):.2f} |")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--build", metavar="PARAMS_JSON", help="build an index of these parameters into the one path given")
    ap.add_argument("--render", metavar="DIR", help="render the evaluation frames into DIR")
    ap.add_argument("--count", type=int, default=80)
    ap.add_argument("--seed", type=int, default=11, help="the settings' random seed (--render)")
    ap.add_argument("--first-frame-seed", type=int, default=500, help="frame i's render seed is this + i (--render)")
    ap.add_argument("args", nargs="*", help="indexes (files or 'default'), then frame globs")
    a = ap.parse_args(argv)
    if a.build:
        if len(a.args) != 1:
            ap.error("--build takes one output path")
        build(json.loads(a.build), a.args[0])
    elif a.render:
        render(a.render, a.count, a.seed, a.first_frame_seed)
    else:
        indexes = [x for x in a.args if x == "default" or x.endswith(".idx")]
        frames = [x for x in a.args if x not in indexes]
        if not indexes or not frames:
            ap.error("give one or more indexes and one or more frame globs")
        compare(indexes, frames)


if __name__ == "__main__":
    main()
