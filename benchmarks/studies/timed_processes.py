#!/usr/bin/env python3
"""Study (issue 38, sessions 11-12), recorded in results/results-speed-2026-12-06.md: whole processes of two checkouts.

What a user pays beyond ``speed_path.py``'s sections: a frame with a time (a FITS file's ``DATE-OBS``, or ``--time``:
what stellar aberration needs), FITS files, a large 16-bit frame, ``attitude`` on a stream of timed frames,
``identify`` on star lists 12 hours apart, a batch of 64 TIFF files, and rendering 20 frames to TIFF files (each
checkout's own files, in a directory of its own).  Each case runs ``RUNS`` times per checkout, the checkouts
alternated run by run (one warm-up each, not counted); the median wall time of each and their ratio.  The inputs are
made here, in a temporary directory, with the second checkout's startrack: FITS copies of the ESA images with times a
minute apart (from the photos' own), a rendered 4000 x 3000 16-bit TIFF, 20 rendered star lists a day apart identified
with a k-vector database, 30 rendered star lists 12 hours apart.

    python benchmarks/studies/timed_processes.py BEFORE_CHECKOUT NOW_CHECKOUT [RUNS]
    python benchmarks/studies/timed_processes.py /tmp/before /work/main 8
"""
import glob
import os
import statistics
import subprocess
import sys
import tempfile
import time

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
ESA = sorted(glob.glob(os.path.join(ROOT, "tests", "data", "real", "*.tiff")))
ESA_TIME = "2019-07-29T20:47:26"


def _env(checkout):
    env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
    env["PYTHONPATH"] = checkout
    return env


def _inputs(tmp, checkout):
    """The files the cases read, made with ``checkout``'s startrack."""
    import numpy as np

    from startrack.imageio import read_image, write_image

    fits = []
    for k, path in enumerate(ESA):
        out = os.path.join(tmp, f"esa{k}.fits")
        # Each its own time, a minute apart (as a camera's frames): each frame's own epoch.
        write_image(out, read_image(path, whole_dn=True)[0].astype(np.uint16), {"DATE-OBS": f"2019-07-29T20:{47 + k}:26"})
        fits.append(out)
    st = [sys.executable, "-m", "startrack"]
    run = {"cwd": checkout, "env": _env(checkout), "check": True, "capture_output": True}
    big = os.path.join(tmp, "big16.tiff")
    subprocess.run(st + ["render", "--fov-deg", "20", "--size", "4000x3000", "--bit-depth", "16", "--ra", "83.8",
                         "--dec", "-1.2", "--seed", "21", "-o", big], **run)
    db = os.path.join(tmp, "db15.h5")
    subprocess.run(st + ["build-kvector", "--fov-deg", "15", "--mag-max", "5.5", "-o", db], **run)
    frames = subprocess.run(st + ["render", "--stars-only", "--frames", "20", "--frame-interval-s", "86400",
                                  "--rate-deg-s", "0.0001,0.00005,0", "--fov-deg", "15", "--size", "1024x1024",
                                  "--sigma-px", "0.3", "--seed", "3", "--time", "2026-09-22T12:00:00Z"], **run).stdout
    ids = os.path.join(tmp, "ids.jsonl")
    with open(ids, "wb") as fh:
        fh.write(subprocess.run(st + ["identify", "-d", db], input=frames, **run).stdout)
    lists = os.path.join(tmp, "lists.jsonl")
    with open(lists, "wb") as fh:
        fh.write(subprocess.run(st + ["render", "--stars-only", "--frames", "30", "--frame-interval-s", "43200",
                                      "--rate-deg-s", "0.001,0.0005,0", "--fov-deg", "15", "--size", "1024x1024",
                                      "--sigma-px", "0.3", "--seed", "4", "--time", "2026-09-22T12:00:00Z"],
                                **run).stdout)
    return fits, big, ids, db, lists


def main(argv=None):
    argv = sys.argv[1:] if argv is None else argv
    if len(argv) < 2:
        sys.exit(__doc__.split("\n\n")[-1])
    before, now = (os.path.abspath(a) for a in argv[:2])
    runs = int(argv[2]) if len(argv) > 2 else 8
    with tempfile.TemporaryDirectory() as tmp:
        fits, big, ids, db, lists = _inputs(tmp, now)
        for label in ("before", "now"):
            os.makedirs(os.path.join(tmp, "render-" + label))
        solve = ["-m", "startrack", "solve", "-q", "-o", os.devnull]
        cases = {
            "solve one 16-bit FITS with DATE-OBS": solve + [fits[0]],
            "solve one TIFF with --time": solve + [ESA[0], "--time", ESA_TIME + "Z"],
            "solve one TIFF, no time": solve + [ESA[0], "--no-aberration"],
            "solve the 8 FITS with DATE-OBS, one process": solve + fits,
            "solve a 4000 x 3000 16-bit TIFF": solve + [big, "--no-aberration"],
            "attitude, 20 star lists a day apart": ["-m", "startrack", "attitude", ids, "-q", "-o", os.devnull],
            "identify 30 star lists 12 h apart (final match)": ["-m", "startrack", "identify", "-d", db, lists, "-q",
                                                                 "-o", os.devnull],
            "solve 64 ESA TIFF files (8 names each), -j 1": solve + ["-j", "1", "--no-aberration"] + ESA * 8,
            "render 20 frames 1024 x 768 to 16-bit TIFF files": lambda where: [
                "-m", "startrack", "render", "--fov-deg", "12", "--size", "1024x768", "--frames", "20", "--bit-depth",
                "16", "--seed", "2", "--no-aberration", "-o",
                os.path.join(tmp, "render-" + ("before" if where == before else "now"), "frame.tif")],
        }
        print(f"{runs} runs each, alternated; start {time.strftime('%H:%M:%S', time.gmtime())} UTC, load "
              f"{os.getloadavg()[0]:.2f}\n\n| process | before s | now s | now / before |\n|---|---|---|---|")
        for name, args in cases.items():
            t = {before: [], now: []}
            for rep in range(runs + 1):
                for where in ((before, now) if rep % 2 == 0 else (now, before)):
                    t0 = time.perf_counter()
                    proc = subprocess.run([sys.executable, *(args(where) if callable(args) else args)], cwd=where,
                                          env=_env(where), capture_output=True)
                    if proc.returncode != 0:
                        raise RuntimeError(f"{name} ({where}): {proc.stderr.decode()[-500:]}")
                    if rep:
                        t[where].append(time.perf_counter() - t0)
            a, b = statistics.median(t[before]), statistics.median(t[now])
            print(f"| {name} | {a:.3f} | {b:.3f} | {b / a:.2f} |", flush=True)
        print(f"\nend {time.strftime('%H:%M:%S', time.gmtime())} UTC, load {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
