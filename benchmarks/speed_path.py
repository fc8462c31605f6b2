"""Issue 38's must-show beside tetra3rs, feeds `make bench` section speed and results/results-speed-2026-12-05.md.

Solve, identify's final match, start-up, -j.

Four sections, each beside tetra3rs where the issue asks for it, every figure a median:

* ``solve``: ``startrack.Solver().solve(pixels)`` blind, beside tetra3rs's ``extract_centroids`` +
  ``solve_from_centroids`` given the field of view, on the 8 ESA images decoded once, image by
  image alternated (which tool goes first alternates too) in one process.
* ``identify``: ``identify_stars`` with the CLI's defaults (every detection matched against the
  shipped catalog after the attitude) and with ``--database-only``, beside tetra3rs's
  ``solve_from_centroids``, on issue 14's 15 deg star lists (:mod:`identify_compare`), passes alternated.
* ``startup``: a warm ``startrack solve IMAGE`` process beside a tetra3rs script (import tetra3rs and
  cv2, load the database, read the image, extract and solve), runs alternated, wall time; and the same
  pixels as a 16-bit FITS file with the photo's time (DATE-OBS), solved with stellar aberration corrected.
* ``jobs``: ``startrack solve -j 1`` and ``-j 2`` on 64 images (the 8 ESA images, 8 names each; and the
  photos of ../shared/data/real-extra when present), images per second, alternated, with the most -j 2 can
  reach given what a one-image process takes.

    .venv/bin/python benchmarks/speed_path.py                    # every section
    .venv/bin/python benchmarks/speed_path.py solve identify     # some
    PYTHONPATH=/path/to/other/checkout .venv/bin/python benchmarks/speed_path.py solve   # another startrack

Each section states the load average (``os.getloadavg``) at its start and end: timings on a
loaded machine (load above about the core count) are not meaningful.
"""
from __future__ import annotations

import argparse
import glob
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, HERE)
sys.path.insert(0, os.path.join(HERE, "peers"))
REAL = sorted(glob.glob(os.path.join(ROOT, "tests", "data", "real", "*.tiff")))
ESA_FOV_DEG = 11.42          # the ESA images' horizontal field (tests/data/real/camera.json)
ESA_TIME = "2019-07-29T20:47:26"     # the ESA images' time, from their names (taken as UTC)


def _load():
    return " ".join(f"{v:.2f}" for v in os.getloadavg())


def _startrack_where():
    import startrack

    return os.path.dirname(os.path.dirname(os.path.abspath(startrack.__file__)))


def _process_env():
    """The environment of the timed processes (run in the checkout's directory: ``python -m`` puts the working
    directory before ``PYTHONPATH``): this startrack, and Python's byte-code cache on (as an
    installation has it; ``PYTHONDONTWRITEBYTECODE`` would recompile every module in every process),
    kept under bench-output/pycache so that no checkout is written to."""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
    env["PYTHONPATH"] = _startrack_where()
    env.setdefault("PYTHONPYCACHEPREFIX", os.path.join(ROOT, "bench-output", "pycache"))
    return env


def _footer(load0):
    return (f"\n\nLoad average at the start: {load0}; at the end: {_load()} ({os.cpu_count()} cores); "
            f"startrack from {_startrack_where()}.")


# ---------------------------------------------------------------------------------------------- solve
def section_solve(passes: int = 15) -> str:
    """Solver.solve blind beside tetra3rs extract_centroids + solve_from_centroids (FOV given)."""
    import tetra3rs_peer

    import startrack
    from startrack.imageio import read_image

    load0 = _load()
    images = [read_image(p) for p in REAL]
    db = tetra3rs_peer.build_or_load(ESA_FOV_DEG)
    solver = startrack.Solver()
    for image, meta in images:          # first uses (kernels, index, databases): not timed
        solver.solve(image, saturation=meta["saturation"])
        tetra3rs_peer.solve_image(image, ESA_FOV_DEG, db=db)
    ours = [[] for _ in images]
    theirs = [[] for _ in images]
    solved = [0, 0]
    matched = [[], []]
    for rep in range(passes):
        for k, (image, meta) in enumerate(images):
            for tool in ((0, 1) if (rep + k) % 2 == 0 else (1, 0)):
                if tool == 0:
                    t0 = time.perf_counter()
                    res = solver.solve(image, saturation=meta["saturation"])
                    ours[k].append((time.perf_counter() - t0) * 1000)
                    if rep == 0:
                        solved[0] += res.status == "ok"
                        matched[0].append(len(res.identification.matches) if res.identification else 0)
                else:
                    r = tetra3rs_peer.solve_image(image, ESA_FOV_DEG, db=db)
                    theirs[k].append(r["total_ms"])
                    if rep == 0:
                        solved[1] += r["status"] == "match_found"
                        matched[1].append(r["matches"])
    a = statistics.median(statistics.median(t) for t in ours)
    b = statistics.median(statistics.median(t) for t in theirs)
    # The ratio of each pass alone (the median over the images of each tool's time in that pass): how much the
    # figure moves from one pass to the next on this machine.
    per_pass = sorted(statistics.median(t[rep] for t in ours) / statistics.median(t[rep] for t in theirs)
                      for rep in range(passes))
    rows = [["startrack `Solver().solve(pixels)` (blind)", f"{solved[0]}/8", f"{statistics.median(matched[0]):.0f}",
             f"{a:.2f}", f"{a / b:.2f}"],
            [f"tetra3rs `extract_centroids` + `solve_from_centroids` (FOV {ESA_FOV_DEG} deg given)", f"{solved[1]}/8",
             f"{statistics.median(matched[1]):.0f}", f"{b:.2f}", "1.00"]]
    text = (f"The 8 ESA images (1024 x 768), decoded once; {passes} passes, the two tools alternated image by "
            "image; per image the median of its passes, then the median over the images.\n\n"
            + _table(["tool", "solved", "median matches", "median ms", "ratio to tetra3rs"], rows)
            + f"\n\nThe ratio of each pass alone: {per_pass[0]:.2f} to {per_pass[-1]:.2f} (median "
              f"{statistics.median(per_pass):.2f})."
            + "\n\nPer image (ms, startrack / tetra3rs): "
            + ", ".join(f"{statistics.median(x):.1f}/{statistics.median(y):.1f}" for x, y in zip(ours, theirs)))
    return text + _footer(load0)


# ------------------------------------------------------------------------------------------- identify
def section_identify(count: int = 300, passes: int = 3) -> str:
    """identify with defaults (final match against the shipped catalog) beside tetra3rs on issue 14's lists."""
    import tetra3rs_peer
    from common import add_sensor_arguments, peer_correct, sensor_setup

    from startrack.catalog import load_catalog
    from startrack.evaluate import Condition, make_frames, score
    from startrack.identify import IdentifyParams, identify_stars
    try:
        from startrack.identify.catalog_match import CatalogStars
    except ImportError:         # a checkout from before identify/'s split (the baseline of issue 38)
        from startrack.identify.base import CatalogStars
    from startrack.kvector import build_kvector, max_separation_deg

    load0 = _load()
    ap = argparse.ArgumentParser()
    add_sensor_arguments(ap, count=count)
    args = ap.parse_args([])
    cam, _, db_cat, star_cat = sensor_setup(args)
    w, h = cam.width, cam.height
    kv = build_kvector(db_cat, max_separation_deg(camera=cam))
    deep = CatalogStars.from_catalog(load_catalog())         # `identify`'s default --catalog, --match-all
    peer = tetra3rs_peer.build_or_load(args.fov, args.db_mag, catalog="hip2")
    cond = Condition(sigma_px=0.3, false_stars=0, min_catalog_stars=args.min_stars)
    params = IdentifyParams(sigma_px=0.3)
    frames = make_frames(star_cat, cam, cond, count, args.seed, mag_limit=args.star_mag)
    inputs = [(stars, [[s["x"], s["y"]] for s in stars], truth) for stars, truth, _ in frames]
    identify_stars(inputs[0][0], cam, kv, "pyramid", params, catalog=deep)   # first use: not timed
    identify_stars(inputs[0][0], cam, kv, "pyramid", params)
    tetra3rs_peer.solve(inputs[0][1], w, h, args.fov, db=peer)
    kinds = ("defaults (--match-all)", "--database-only", "tetra3rs")
    times = {k: [] for k in kinds}
    ok = {k: 0 for k in kinds}
    n_matched = {k: [] for k in kinds}
    for rep in range(passes):
        for key in (kinds if rep % 2 == 0 else kinds[::-1]):
            for stars, xy, truth in inputs:
                if key == "tetra3rs":
                    r = tetra3rs_peer.solve(xy, w, h, args.fov, db=peer)
                    times[key].append(r["elapsed_ms"])
                    good = r.get("ra") is not None and peer_correct(r, truth)
                    got = r["matches"]
                else:
                    res = identify_stars(stars, cam, kv, "pyramid", params, catalog=deep if key == kinds[0] else None)
                    times[key].append(res.time_ms)
                    good = score(res, truth) == "success"
                    got = len(res.matches)
                if rep == 0:
                    ok[key] += bool(good)
                    n_matched[key].append(got)
    ref = float(np.median(times["tetra3rs"]))
    rows = [[("startrack identify, " + k) if k != "tetra3rs" else "tetra3rs solve_from_centroids",
             f"{100 * ok[k] / len(inputs):.1f} %", f"{np.median(n_matched[k]):.0f}", f"{np.median(times[k]):.4f}",
             f"{np.percentile(times[k], 95):.4f}", f"{np.median(times[k]) / ref:.2f}"] for k in kinds]
    text = (f"Issue 14's sensor ({args.fov:g} deg, {args.size}, database Hp <= {args.db_mag:g} for both tools, stars "
            f"to Hp {args.star_mag:g}, sigma 0.3 px, no false stars), {len(inputs)} frames, seed {args.seed}, {passes} "
            "alternated passes.  startrack's time is the result's time_ms (search, verification and final match); "
            "tetra3rs's the wall time of solve_from_centroids.\n\n"
            + _table(["tool", "success", "median matches", "median ms", "p95 ms", "median / tetra3rs"], rows))
    return text + _footer(load0)


# -------------------------------------------------------------------------------------------- startup
TETRA3RS_SCRIPT = """
import sys
import cv2
import numpy as np
import tetra3rs
db = tetra3rs.SolverDatabase.load_from_file(sys.argv[1])
img = cv2.imread(sys.argv[2], cv2.IMREAD_UNCHANGED)
ext = tetra3rs.extract_centroids(np.ascontiguousarray(img), sigma_threshold=5.0)
res = db.solve_from_centroids(ext.centroids, fov_estimate_deg=float(sys.argv[3]), image_width=img.shape[1],
                              image_height=img.shape[0], solve_timeout_ms=5000)
print(res.status, res.ra_deg, res.dec_deg)
"""


def section_startup(runs: int = 9) -> str:
    """A warm `startrack solve IMAGE` process beside the tetra3rs script, wall time, runs alternated."""
    import tetra3rs_peer

    load0 = _load()
    image = REAL[0]
    db = tetra3rs_peer.build_or_load(ESA_FOV_DEG)
    db_path = tetra3rs_peer.LAST_BUILD["cache_path"]
    del db
    with tempfile.TemporaryDirectory() as tmp:
        script = os.path.join(tmp, "tetra3rs_solve.py")
        with open(script, "w") as fh:
            fh.write(TETRA3RS_SCRIPT)
        # The same pixels as a 16-bit FITS file with the photo's time (DATE-OBS): the solve corrects stellar
        # aberration (apparent places), as a camera's FITS frames with their times are solved.
        from startrack.imageio import read_image, write_image

        fits_frame = os.path.join(tmp, "frame.fits")
        write_image(fits_frame, read_image(image, whole_dn=True)[0], {"DATE-OBS": ESA_TIME})
        env = _process_env()
        commands = {"startrack": [sys.executable, "-m", "startrack", "solve", image, "-q"],
                    "startrack FITS": [sys.executable, "-m", "startrack", "solve", fits_frame, "-q"],
                    "tetra3rs": [sys.executable, script, db_path, image, str(ESA_FOV_DEG)]}
        for cmd in commands.values():          # warm: caches built, files in the page cache
            proc = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=_startrack_where())
            if proc.returncode != 0:
                raise RuntimeError(f"{' '.join(cmd)} failed: {proc.stderr}")
        wall = {k: [] for k in commands}
        for rep in range(runs):
            for key in (list(commands) if rep % 2 == 0 else list(commands)[::-1]):
                t0 = time.perf_counter()
                subprocess.run(commands[key], capture_output=True, env=env, check=True, cwd=_startrack_where())
                wall[key].append(time.perf_counter() - t0)
    a, b = statistics.median(wall["startrack"]), statistics.median(wall["tetra3rs"])
    c = statistics.median(wall["startrack FITS"])
    from startrack._kernels._jit import aot_path

    # Without the ahead-of-time build of this code's kernels (`startrack cache build`, run by `make install`) a
    # process imports numba and loads its JIT cache: not the installed start-up.
    aot = os.path.exists(aot_path())
    rows = [["`startrack solve IMAGE -q` (blind)", f"{a:.3f}", f"{a / b:.2f}"],
            [f"`startrack solve FRAME.fits -q` (the same pixels, 16-bit FITS with DATE-OBS {ESA_TIME}: apparent "
             "places, stellar aberration corrected)", f"{c:.3f}", f"{c / b:.2f}"],
            [f"tetra3rs script (import tetra3rs + cv2, load {os.path.basename(db_path)}, extract, solve with FOV)",
             f"{b:.3f}", "1.00"]]
    text = (f"One ESA image ({os.path.basename(image)}), warm processes (database and compiled kernels cached, "
            f"files in the page cache), {runs} runs each, alternated; wall time of the whole process; "
            + ("kernels from their ahead-of-time build" if aot else "**no ahead-of-time build of these kernels "
               "(`startrack cache build`): numba's JIT cache, not an installation's start-up**") + ".\n\n"
            + _table(["process", "median s", "ratio to tetra3rs"], rows)
            + "\n\nThe script:\n\n```python" + TETRA3RS_SCRIPT + "```")
    return text + _footer(load0)


# ----------------------------------------------------------------------------------------------- jobs
REAL_EXTRA = sorted(glob.glob(os.path.join(ROOT, "..", "shared", "data", "real-extra", "*.jpg")))


def _jobs_run(sources, n_images, runs, tmp, label):
    """`startrack solve -j 1` and `-j 2` on ``n_images`` names of ``sources``: medians and the start-up bound."""
    from startrack.cluster import idle_cpus

    paths = []
    for k in range(n_images):
        src = sources[k % len(sources)]
        dst = os.path.join(tmp, f"{label}-{k:03d}-{os.path.basename(src)}")
        os.symlink(src, dst)
        paths.append(dst)
    env = _process_env()
    base = [sys.executable, "-m", "startrack", "solve", *paths, "-q", "-o", os.devnull]
    one = base[:5] + ["-q", "-o", os.devnull]
    subprocess.run(one, capture_output=True, env=env, cwd=_startrack_where())        # warm
    rate = {1: [], 2: []}
    busy = {1: [], 2: []}
    alone = []
    loads = []
    idle = []
    for rep in range(runs):
        # A one-image process: start-up, first uses and one image, what no number of workers shares.
        t0 = time.perf_counter()
        subprocess.run(one, capture_output=True, env=env, cwd=_startrack_where())
        alone.append(time.perf_counter() - t0)
        for jobs in ((1, 2) if rep % 2 == 0 else (2, 1)):
            loads.append(os.getloadavg()[0])
            if jobs == 2:
                # What the command's gate will see a moment later (this process counts itself out, as the
                # command does): -j 2 uses two worker processes only with two idle CPUs.
                idle.append(idle_cpus())
            c0 = resource.getrusage(resource.RUSAGE_CHILDREN)
            t0 = time.perf_counter()
            proc = subprocess.run(base + ["-j", str(jobs)], capture_output=True, text=True, env=env,
                                  cwd=_startrack_where())
            dt = time.perf_counter() - t0
            c1 = resource.getrusage(resource.RUSAGE_CHILDREN)
            if proc.returncode not in (0, 1):
                raise RuntimeError(proc.stderr)
            rate[jobs].append(n_images / dt)
            # CPUs the run had on average (its processes' CPU seconds over its wall time): about 2 for a -j 2
            # run whose workers each had a core, about 1 when the machine gave it one.
            busy[jobs].append((c1.ru_utime + c1.ru_stime - c0.ru_utime - c0.ru_stime) / dt)
    a, b = statistics.median(rate[1]), statistics.median(rate[2])
    serial = n_images / a
    # Amdahl: a one-image process's wall time less one image's share of -j 1's (T1 / n) is what no number of
    # workers shares (F: interpreter, imports, index, first uses); the rest of -j 1's, T1 - F, at best halves.
    fixed = statistics.median(alone) - serial / n_images
    bound = serial / (fixed + (serial - fixed) / 2) if serial > fixed else float("nan")
    return {"rate": (a, b), "busy": busy, "loads": loads, "idle": idle, "fixed": fixed, "serial": serial,
            "bound": bound}


def section_jobs(n_images: int = 64, runs: int = 3) -> str:
    """`startrack solve -j 1` and `-j 2` on 64 images, images per second: the 8 ESA images (and the photos from
    other cameras in ../shared/data/real-extra when they are there)."""
    load0 = _load()
    sets = [("the 8 ESA images, 8 names each", REAL)]
    if REAL_EXTRA:
        sets.append((f"the {len(REAL_EXTRA)} photos of ../shared/data/real-extra (4.5-33 deg, other cameras), "
                     f"{n_images // len(REAL_EXTRA)}-{-(-n_images // len(REAL_EXTRA))} names each", REAL_EXTRA))
    rows, notes = [], []
    with tempfile.TemporaryDirectory() as tmp:
        for k, (label, sources) in enumerate(sets):
            r = _jobs_run(sources, n_images, runs, tmp, f"s{k}")
            a, b = r["rate"]
            rows.append([label, f"{a:.1f}", f"{b:.1f}", f"{b / a:.2f}", f"{r['fixed']:.3f}", f"{r['serial']:.2f}",
                         f"{r['bound']:.2f}", "; ".join(", ".join(f"{v:.2f}" for v in r["busy"][j]) for j in (1, 2))])
            notes.append(f"{label}: 1-minute load before each run {', '.join(f'{v:.2f}' for v in r['loads'])}; "
                         f"idle CPUs seen just before each -j 2 run {', '.join(map(str, r['idle']))}"
                         + ("" if min(r["idle"]) >= 2 else " (not idle: a -j 2 run that saw fewer than 2 solved its "
                            "images in one process, and its figure is not the pool's)"))
    text = (f"`startrack solve IMAGES -q -o /dev/null -j N`, {n_images} images, {runs} runs each, alternated; images "
            "per second from the whole process's wall time.  -j 2 uses two worker processes only when the machine "
            "has two idle CPUs (`startrack.cluster.idle_cpus`).  T1 is the -j 1 run's wall time; F a one-image "
            "process's less T1 / n (interpreter, imports, index, first uses: what no number of workers shares); "
            "the most -j 2 can reach is T1 / (F + (T1 - F) / 2).\n\n"
            + _table(["images", "-j 1 images/s", "-j 2 images/s", "ratio", "F s", "T1 s", "most -j 2 can reach",
                      "CPUs used per run, -j 1; -j 2 (CPU s / wall s)"], rows)
            + "\n\n" + "\n".join(f"- {n}" for n in notes)
            + "\n\nA -j 2 run that used about one CPU had no second core to use (another process held it), "
            "whatever the idle count said when it started: its ratio is not the pool's.")
    return text + _footer(load0)


def _table(header, rows):
    out = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    out += ["| " + " | ".join(str(c) for c in r) + " |" for r in rows]
    return "\n".join(out)


SECTIONS = {"solve": section_solve, "identify": section_identify, "startup": section_startup, "jobs": section_jobs}


def report(sections=None) -> str:
    """The chosen sections (default: all) as one markdown text."""
    parts = []
    for name in sections or SECTIONS:
        text = SECTIONS[name]()
        print(f"### {name}\n\n{text}\n", flush=True)
        parts.append(f"### {name}\n\n{text}\n")
    return "\n".join(parts)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sections", nargs="*", help="default: all of " + ", ".join(SECTIONS))
    args = ap.parse_args(argv)
    unknown = [s for s in args.sections if s not in SECTIONS]
    if unknown:
        ap.error(f"unknown section(s) {', '.join(unknown)}: choose from {', '.join(SECTIONS)}")
    report(args.sections or None)


if __name__ == "__main__":
    main()
