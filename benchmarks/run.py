#!/usr/bin/env python3
"""startrack benchmarks: `make bench` (or `python benchmarks/run.py [SECTION ...]`).

Each section prints a table of medians (and ratios against peers where the issue names
them) and the whole report is written to bench-output/report.md.  Speed targets live
here, never in unit tests.
"""
from __future__ import annotations

import argparse
import math
import os
import platform
import statistics
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)

OUT_DIR = os.path.join(os.path.dirname(HERE), "bench-output")


def timed(fn, repeat=20, warmup=2):
    """Median and 95th percentile wall time of ``fn()`` in milliseconds."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append((time.perf_counter() - t0) * 1000.0)
    return statistics.median(times), float(np.percentile(times, 95))


def table(headers, rows):
    widths = [max(len(str(h)), *(len(str(r[i])) for r in rows)) for i, h in enumerate(headers)]
    line = "| " + " | ".join(str(h).ljust(w) for h, w in zip(headers, widths)) + " |"
    sep = "|" + "|".join("-" * (w + 2) for w in widths) + "|"
    body = ["| " + " | ".join(str(c).ljust(w) for c, w in zip(r, widths)) + " |" for r in rows]
    return "\n".join([line, sep, *body])


def bench_render():
    from startrack.camera import Camera
    from startrack.catalog import load_catalog
    from startrack.render import Scene, Sensor, render_image, star_list
    from startrack.rotations import quaternion_to_dcm, random_quaternions

    cat = load_catalog().filter_magnitude(None, 6.3)
    vec = cat.vectors()
    cam = Camera.from_fov(20, 1024, 1024)
    rng = np.random.default_rng(0)
    dcms = quaternion_to_dcm(random_quaternions(200, rng))
    sensor = Sensor(prnu=0.0, hot_pixels=20)
    scene = Scene(mag_noise=0.2, false_stars=2)
    counts = []
    state = {"k": 0}

    def one():
        k = state["k"] = (state["k"] + 1) % len(dcms)
        _, truth = render_image(cat, cam, dcms[k], sensor, scene, np.random.default_rng(k), vectors=vec)
        counts.append(len(truth["stars"]))

    med, p95 = timed(one, repeat=60)
    prnu_sensor = Sensor(prnu=0.01, hot_pixels=20)
    med_prnu, p95_prnu = timed(lambda: render_image(cat, cam, dcms[1], prnu_sensor, scene, np.random.default_rng(1),
                                                    vectors=vec), repeat=20)
    cat5 = load_catalog().filter_magnitude(None, 5.0)
    vec5 = cat5.vectors()

    def lists():
        for k in range(200):
            star_list(cat5, cam, dcms[k], Sensor(), Scene(mag_limit=5.0, mag_noise=0.2), np.random.default_rng(k),
                      sigma_px=0.1, max_stars=10, vectors=vec5)

    lmed, _ = timed(lists, repeat=5, warmup=1)
    rows = [
        ["render 1024x1024 16-bit, shot+dark+read+sky noise, 20 hot px, 2 false stars, mag noise",
         f"{np.mean(counts):.0f}", f"{med:.2f}", f"{p95:.2f}", "<= 20 ms", "yes" if med <= 20 else "NO"],
        ["same with PRNU 1% (every pixel on the full Poisson path)", "", f"{med_prnu:.2f}", f"{p95_prnu:.2f}", "", ""],
        ["star-list frame (20 deg, mag 5, 10 brightest)", "", f"{lmed / 200:.3f}", "",
         f"{200 / (lmed / 1000):.0f} frames/s", ""],
    ]
    return "render", table(["case", "stars", "median ms", "p95 ms", "target", "met"], rows)


SECTIONS = {"render": bench_render}


def main():
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("sections", nargs="*", help="sections to run (default: all): " + ", ".join(SECTIONS))
    args = parser.parse_args()
    chosen = args.sections or list(SECTIONS)
    os.makedirs(OUT_DIR, exist_ok=True)
    import numba

    from startrack import __version__

    header = (f"# startrack {__version__} benchmarks\n\n{platform.processor() or platform.machine()}, "
              f"{os.cpu_count()} cores, Python {platform.python_version()}, numpy {np.__version__}, "
              f"numba {numba.__version__}; {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}\n")
    parts = [header]
    print(header)
    for name in chosen:
        title, text = SECTIONS[name]()
        block = f"## {title}\n\n{text}\n"
        print(block, flush=True)
        parts.append(block)
    with open(os.path.join(OUT_DIR, "report.md"), "w") as fh:
        fh.write("\n".join(parts))
    print(f"report: {os.path.join(OUT_DIR, 'report.md')}")


if __name__ == "__main__":
    main()
