"""Hints against blind solve on the 8 ESA images, feeds `make bench` section hints and results/results-hints-2026-12-05.md.

One process, one :class:`startrack.Solver` (databases and kernels warm): each image solved blind, with a position
hint (astrometry.net's RA/Dec with a radius), with a scale hint (the reference field +-10 %), with both, and with
a wrong position hint, each ``--repeat`` times, interleaved image by image so that the machine's drift hits every
mode alike.  Reports per mode the median over images of each image's median solve time (``SolveResult.time_ms``:
detection, search, attitude) and search time (``identification.time_ms``), the median per-image ratio to blind,
and the candidates verified; then rendered frames with 25 false stars, where the blind search verifies hundreds of
candidates (:func:`run_rendered`).

    PYTHONPATH=$PWD python benchmarks/hint_bench.py [--repeat 7] [--radius 5]
"""
from __future__ import annotations

import argparse
import os
import statistics
import sys

from common import esa_images, esa_references, load_average, table


def modes(ref, radius):
    ra, dec, fov = float(ref["ra_deg"]), float(ref["dec_deg"]), float(ref["fov_x_deg"])
    sky = {"ra_deg": ra, "dec_deg": dec, "radius_deg": radius}
    scale = {"fov_min_deg": fov * 0.9, "fov_max_deg": fov * 1.1}
    wrong = {"ra_deg": (ra + 120.0) % 360.0, "dec_deg": -dec, "radius_deg": radius}
    return {"blind": {}, "--ra --dec --radius": sky, "--scale-low --scale-high": scale, "both": {**sky, **scale},
            "wrong position": wrong}


def run(repeat: int = 7, radius: float = 5.0):
    import startrack

    images = esa_images()
    refs = esa_references()
    solver = startrack.Solver()
    solver.solve(images[0])                      # databases, index and kernels ready
    names = list(modes(next(iter(refs.values())), radius))
    total = {m: {} for m in names}
    search = {m: {} for m in names}
    verified = {m: {} for m in names}
    status = {m: {} for m in names}
    for path in images:
        ref = refs[os.path.basename(path)]
        for k in range(repeat):
            for mode, kw in modes(ref, radius).items():
                if mode == "wrong position" and k:
                    continue        # a failure spends the search's whole budget: once is its figure
                r = solver.solve(path, **kw)
                total[mode].setdefault(path, []).append(r.time_ms)
                search[mode].setdefault(path, []).append(r.identification.time_ms or 0.0)
                verified[mode][path] = (r.identification.details or {}).get("verified")
                status[mode][path] = str(r.status)
    rows = []
    for mode in names:
        t_img = [statistics.median(total[mode][p]) for p in images]
        s_img = [statistics.median(search[mode][p]) for p in images]
        ratio = [statistics.median(total[mode][p]) / statistics.median(total["blind"][p]) for p in images]
        sratio = [statistics.median(search[mode][p]) / max(1e-9, statistics.median(search["blind"][p]))
                  for p in images]
        ok = sum(s == "ok" for s in status[mode].values())
        ver = [v for v in verified[mode].values() if v is not None]
        rows.append([mode, f"{ok}/{len(images)}", f"{statistics.median(t_img):.1f}", f"{statistics.median(ratio):.3f}",
                     f"{statistics.median(s_img):.2f}", f"{statistics.median(sratio):.3f}",
                     f"{statistics.median(ver):.0f}" if ver else "-"])
    head = ["mode", "ok", "solve ms (median of images)", "ratio to blind (median per image)",
            "search ms", "search ratio", "candidates verified (median)"]
    return table(head, rows), f"load average {load_average()}; {repeat} runs per image and mode, interleaved (the wrong hint: one run)"


def run_rendered(n: int = 8, repeat: int = 3, false_stars: int = 25, radius: float = 5.0):
    """Rendered 12 x 9 deg frames with ``false_stars`` false stars (the blind search verifies hundreds of
    candidates there): blind against a position hint 2.8 deg off the truth, radius ``radius``."""
    import numpy as np

    import startrack
    from startrack.camera import Camera
    from startrack.catalog import load_catalog
    from startrack.render import Scene, Sensor, render_image
    from startrack.rotations import dcm_to_radec_roll, quaternion_to_dcm, random_quaternions

    cat = load_catalog().filter_magnitude(None, 7.5)
    cam = Camera.from_fov(12.0, 1024, 768)
    solver = startrack.Solver()
    frames = []
    for k, q in enumerate(random_quaternions(n, np.random.default_rng(40))):
        dcm = quaternion_to_dcm(q)
        image, _ = render_image(cat, cam, dcm, Sensor(), Scene(false_stars=false_stars), np.random.default_rng(k))
        ra, dec, _ = dcm_to_radec_roll(dcm)
        frames.append((image, {"ra_deg": float(ra) + 2.0, "dec_deg": float(max(-88.0, min(88.0, dec - 2.0))),
                               "radius_deg": radius}))
    solver.solve(frames[0][0])
    rows = []
    times = {"blind": [], "hint": []}
    for k, (image, hint) in enumerate(frames):
        got = {}
        for mode, kw in (("blind", {}), ("hint", hint)):
            runs = [solver.solve(image, **kw) for _ in range(repeat)]
            got[mode] = (statistics.median(r.time_ms for r in runs), runs[0])
            times[mode].append(got[mode][0])
        (tb, rb), (th, rh) = got["blind"], got["hint"]
        rows.append([k, f"{rb.status} / {rh.status}", f"{tb:.0f}", f"{th:.0f}", f"{th / tb:.2f}",
                     f"{rb.hypotheses} / {rh.hypotheses}"])
    ratio = statistics.median(h / b for h, b in zip(times["hint"], times["blind"]))
    head = ["frame", "status blind / hint", "blind ms", "hint ms", "ratio", "candidates verified blind / hint"]
    return table(head, rows), (f"median per-frame ratio hint/blind {ratio:.2f}; load average {load_average()}; "
                               f"{repeat} runs per frame and mode")


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeat", type=int, default=7)
    parser.add_argument("--radius", type=float, default=5.0)
    args = parser.parse_args(argv)
    text, note = run(args.repeat, args.radius)
    print("The 8 ESA images:\n")
    print(text)
    print(note)
    text, note = run_rendered(radius=args.radius)
    print("\nRendered 12 deg frames with 25 false stars:\n")
    print(text)
    print(note)


if __name__ == "__main__":
    sys.exit(main())
