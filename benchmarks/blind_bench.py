"""Blind solving (issue 15), feeds `make bench` section blind and results/results-blind-2026-12-02c.md.

Every figure in one run: real photos beside astrometry.net and cedar-solve, time per image (whole
process, in one process, first use), -j 1 vs -j 2, rendered 2-70 degree fields, and non-star images.

    .venv/bin/python benchmarks/blind_bench.py [--out bench-output/blind.md] [--skip-peers]

The three astrophotographs of ../shared/data/real-extra/ are used when present (they are
copyrighted and never copied into the repository); the 8 ESA images are in tests/data/real/.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time

import numpy as np
from common import ESA_DIR, ROOT, esa_references, sep_deg, table

EXTRA = os.environ.get("STARTRACK_REAL_EXTRA", os.path.join(os.path.dirname(ROOT), "shared", "data", "real-extra"))
if not os.path.isdir(EXTRA):
    EXTRA = "/work/shared/data/real-extra"
ST = [sys.executable, "-m", "startrack"]


def references():
    """``{image path: astrometry.net's solution}`` of the ESA images and of the extra photographs when present."""
    refs = {}
    for d in (ESA_DIR, EXTRA):
        if os.path.exists(os.path.join(d, "solutions.csv")):
            refs.update({os.path.join(d, f): r for f, r in esa_references(os.path.join(d, "solutions.csv")).items()})
    return refs


CPU = {"last": 0.0}     # CPU seconds (user + system) of the last run_st child: the machine may be shared


def run_st(args, env=None, timeout=1200):
    import resource

    full = dict(os.environ)
    full.update(env or {})
    r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    proc = subprocess.run(ST + list(args), capture_output=True, text=True, env=full, timeout=timeout)
    r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    CPU["last"] = (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime)
    return proc, time.perf_counter() - t0


def real_photos(refs, cache_env, skip_peers):
    rows = []
    proc, _ = run_st(["cache", "build", "-q"], cache_env)
    walls = []
    for path, r in refs.items():
        proc, wall = run_st(["solve", path, "-q"], cache_env)
        walls.append((wall, CPU["last"]))
        name = os.path.basename(path)
        docs = [json.loads(line) for line in proc.stdout.splitlines() if line.strip()]
        d = docs[0] if docs else {"solve": {"status": "no output"}}
        s = d["solve"]
        if s["status"] == "ok":
            dist = sep_deg(s["center_ra"], s["center_dec"], float(r["ra_deg"]), float(r["dec_deg"]))
            width = s["fov_deg"][0] / float(r["fov_x_deg"]) - 1
            rows.append(["startrack", name, "ok", proc.returncode, f"{dist:.4f}", f"{100 * width:+.2f} %",
                         f"{wall:.2f} (CPU {CPU['last']:.2f})"])
        else:
            rows.append(["startrack", name, s["status"], proc.returncode, "", "",
                         f"{wall:.2f} (CPU {CPU['last']:.2f})"])
    if not skip_peers:
        rows += _peers(refs)
    return rows, walls


def _peers(refs):
    rows = []
    try:
        import astrometry_peer

        if astrometry_peer.is_available():
            for path, r in refs.items():
                res = astrometry_peer.solve_field(path, 1, 100, timeout_s=60)
                if res["status"] == "solved":
                    dist = sep_deg(res["ra"], res["dec"], float(r["ra_deg"]), float(r["dec_deg"]))
                    rows.append(["astrometry.net (scale 1-100 deg)", os.path.basename(path), "ok", "",
                                 f"{dist:.4f}", f"{100 * (res['fov_x_deg'] / float(r['fov_x_deg']) - 1):+.2f} %",
                                 f"{res['elapsed_ms'] / 1000:.2f}"])
                else:
                    rows.append(["astrometry.net (scale 1-100 deg)", os.path.basename(path), res["status"], "", "",
                                 "", f"{(res.get('elapsed_ms') or 0) / 1000:.2f}"])
        else:
            rows.append(["astrometry.net", "-", "not installed", "", "", "", ""])
    except Exception as exc:  # noqa: BLE001 - a broken peer is reported, not fatal
        rows.append(["astrometry.net", "-", f"error {type(exc).__name__}", "", "", "", ""])
    try:
        import cedar_peer

        if cedar_peer.is_available():
            with cedar_peer.CedarSolver(db="default") as cs:
                for path, r in refs.items():
                    res = cs.solve_image(path, float(r["fov_x_deg"]))
                    if res.get("ra") is not None:
                        dist = sep_deg(res["ra"], res["dec"], float(r["ra_deg"]), float(r["dec_deg"]))
                        rows.append(["cedar-solve (FOV given)", os.path.basename(path), "ok", "", f"{dist:.4f}",
                                     f"{100 * (res['fov'] / float(r['fov_x_deg']) - 1):+.2f} %",
                                     f"{res.get('t_wall_ms', float('nan')) / 1000:.3f} (in-process)"])
                    else:
                        rows.append(["cedar-solve (FOV given)", os.path.basename(path), str(res.get("status")), "",
                                     "", "", f"{res.get('t_wall_ms', float('nan')) / 1000:.3f} (in-process)"])
        else:
            rows.append(["cedar-solve", "-", "not installed", "", "", "", ""])
    except Exception as exc:  # noqa: BLE001
        rows.append(["cedar-solve", "-", f"error {type(exc).__name__}", "", "", "", ""])
    return rows


def in_process(esa, cache_env, repeats=5):
    """Median ms per ESA image of solve_image (image in memory, index open, kernels warm), wall and CPU.

    Both sides start from a decoded image and neither times the file's decoding: startrack's
    ``solve_image`` gets the float32 array of ``read_image``; cedar-solve's ``solve_from_image`` the
    loaded PIL image (cedar_runner times it after ``Image.load()``), so its time includes its own
    conversion to an array, star extraction and the solve.  cedar-solve is given the FOV (11.4 deg),
    startrack is not.  cedar-solve (when installed) runs in its own process, image by image between
    startrack's runs, so that both see the same load.

    Also returns startrack's split (median ms per image): detection and centroids (the centroid
    section's time), pattern search and verification (the identification's), the rest (attitude,
    records).
    """
    import contextlib

    os.environ.update(cache_env)
    from startrack.imageio import read_image
    from startrack.patterns import default_index
    from startrack.solve import SolveOptions, solve_image

    index = default_index()
    images = [read_image(p) for p in esa]
    for im, meta in images:
        solve_image(im, options=SolveOptions(), saturation=meta["saturation"], index=index)
    per, per_cpu, cedar, split = [], [], [], []
    with contextlib.ExitStack() as stack:
        cs = None
        try:
            import cedar_peer

            if cedar_peer.is_available():
                cs = stack.enter_context(cedar_peer.CedarSolver(db="default"))
        except Exception:  # noqa: BLE001 - a missing or broken peer leaves its column empty
            cs = None
        for path, (im, meta) in zip(esa, images, strict=True):
            ts, cpu, parts = [], [], []
            for _ in range(repeats):
                t0, c0 = time.perf_counter(), time.process_time()
                out = solve_image(im, options=SolveOptions(), saturation=meta["saturation"], index=index)
                ts.append((time.perf_counter() - t0) * 1000)
                cpu.append((time.process_time() - c0) * 1000)
                assert out.status == "ok", out.reason
                c_ms = float(out.centroid["time_ms"])
                i_ms = float(out.identification.time_ms)
                parts.append((c_ms, i_ms, ts[-1] - c_ms - i_ms))
            per.append(float(np.median(ts)))
            per_cpu.append(float(np.median(cpu)))
            split.append(np.median(np.array(parts), axis=0))
            if cs is not None:
                cs.solve_image(path, 11.4)
                cedar.append(float(np.median([cs.solve_image(path, 11.4).get("t_wall_ms", float("nan"))
                                              for _ in range(repeats)])))
    # The previous default (paper 004's labels, then a pyramid with the k-vector of the band), measured alike.
    labels = []
    for im, meta in images:
        solve_image(im, options=SolveOptions(blind="labels"), saturation=meta["saturation"])
        t0 = time.process_time()
        out = solve_image(im, options=SolveOptions(blind="labels"), saturation=meta["saturation"])
        labels.append(((time.process_time() - t0) * 1000, str(out.status)))
    return per, per_cpu, cedar, labels, np.median(np.array(split), axis=0)


def first_use(image):
    """Whole `startrack solve IMAGE` with an empty cache and an empty numba cache (kernels compiled)."""
    tmp = tempfile.mkdtemp(prefix="st-cold-")
    try:
        # Everything empty: the index, numba's cache and the ahead-of-time kernels.
        env = {"STARTRACK_CACHE": os.path.join(tmp, "cache"), "NUMBA_CACHE_DIR": os.path.join(tmp, "numba"),
               "STARTRACK_KERNELS": os.path.join(tmp, "kernels")}
        proc, wall = run_st(["solve", image], env)
        cpu = CPU["last"]
        notice = [line for line in proc.stderr.splitlines() if "once" in line]
        env2 = {"STARTRACK_CACHE": os.path.join(tmp, "cache2")}
        proc2, wall2 = run_st(["solve", image], env2)
        return wall, proc.returncode, notice, wall2, proc2.returncode, cpu, CPU["last"]
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def jobs(esa, cache_env, copies=2):
    tmp = tempfile.mkdtemp(prefix="st-jobs-")
    try:
        paths = []
        for k in range(copies):
            for p in esa:
                q = os.path.join(tmp, f"{k}-{os.path.basename(p)}")
                os.symlink(p, q)
                paths.append(q)
        out = {}
        for j in (1, 2):
            proc, wall = run_st(["solve", *paths, "-j", str(j), "-q"], cache_env)
            ok = sum(json.loads(line)["solve"]["status"] == "ok" for line in proc.stdout.splitlines())
            out[j] = (wall, ok, proc.returncode, CPU["last"])
        return out, len(paths)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


RENDERS = [  # fov, size, ra, dec, roll, k1, exposure ms
    (2.0, "1024x768", 83.8, -1.2, 30.0, 0.0, 1000),
    (5.0, "1024x768", 201.3, -11.2, 100.0, 0.0, 500),
    (40.0, "1280x960", 150.0, 40.0, -60.0, -0.05, 100),
    (70.0, "1280x960", 280.0, -30.0, 200.0, -0.1, 100),
]


def rendered(cache_env):
    rows = []
    tmp = tempfile.mkdtemp(prefix="st-render-")
    try:
        for i, (fov, size, ra, dec, roll, k1, exp) in enumerate(RENDERS):
            img = os.path.join(tmp, f"f{fov:g}.png")
            run_st(["render", "--fov-deg", str(fov), "--size", size, "--ra", str(ra), "--dec", str(dec), "--roll",
                    str(roll), "--k1", str(k1), "--exposure-ms", str(exp), "--seed", str(i + 1), "-o", img, "-q"])
            proc, wall = run_st(["solve", img, "-q"], cache_env)
            d = json.loads(proc.stdout.splitlines()[0])
            s = d["solve"]
            if s["status"] == "ok":
                dist = sep_deg(d["attitude"]["ra"], d["attitude"]["dec"], ra, dec)
                rows.append([f"{fov:g} deg {size}, k1 {k1:g}", "ok", proc.returncode, f"{dist * 3600:.1f}",
                             f"{s['fov_deg'][0]:.3f}", f"{d['camera'].get('distortion', {}).get('k1', 0):+.4f}",
                             d["attitude"]["n_stars"], f"{s['time_ms']:.0f}", f"{wall:.2f}"])
            else:
                rows.append([f"{fov:g} deg {size}, k1 {k1:g}", s["status"], proc.returncode, "", "", "", "", "",
                             f"{wall:.2f}"])
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return rows


def non_stars(cache_env):
    import cv2

    tmp = tempfile.mkdtemp(prefix="st-nonstar-")
    rows = []
    try:
        rng = np.random.default_rng(0)
        yy, xx = np.mgrid[0:768, 0:1024]
        day = (120 + 60 * np.sin(xx / 23.0) * np.cos(yy / 17.0) + rng.normal(0, 8, (768, 1024))).clip(0, 255)
        files = {"noise.png": rng.normal(1000, 40, (768, 1024)).astype(np.uint16),
                 "black.png": np.zeros((768, 1024), np.uint8), "daylight.png": day.astype(np.uint8)}
        for name, arr in files.items():
            p = os.path.join(tmp, name)
            cv2.imwrite(p, arr)
            proc, wall = run_st(["solve", p, "-q"], cache_env)
            d = json.loads(proc.stdout.splitlines()[0])
            rows.append([name, d["solve"]["status"], proc.returncode, d["solve"].get("reason", ""), f"{wall:.2f}"])
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return rows


SECTIONS = ("first_use", "real_photos", "in_process", "jobs", "rendered", "non_stars")


def report(skip_peers: bool = False, only=SECTIONS) -> str:
    """Run every measurement (or those of ``only``) once and return the Markdown report."""
    tmp_cache = tempfile.mkdtemp(prefix="st-bench-cache-")
    cache_env = {"STARTRACK_CACHE": tmp_cache}
    refs = references()
    esa = sorted(p for p in refs if p.endswith(".tiff"))
    parts = [f"Blind solving (issue 15), {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, "
             f"{os.cpu_count()} cores; command: `python benchmarks/blind_bench.py`"
             + (" --skip-peers" if skip_peers else "")
             + (f" --only {','.join(only)}" if tuple(only) != SECTIONS else "")
             + f"; load average at the start {os.getloadavg()[0]:.1f}\n"]

    def emit(text):
        print(text, flush=True)
        parts.append(text)

    try:
        if set(only) - {"first_use", "real_photos"}:
            run_st(["cache", "build", "-q"], cache_env)     # the index (and kernels) of the other sections
        if "first_use" in only:
            _first_use_section(esa, emit)
        if "real_photos" in only:
            _real_photos_section(refs, cache_env, skip_peers, emit)
        if "in_process" in only:
            _in_process_section(esa, cache_env, emit)
        if "jobs" in only:
            for copies in (2, 8):
                jb, n = jobs(esa, cache_env, copies)
                emit(f"### Batch of {n} images\n\n" + table(["-j", "wall (s)", "CPU (s)", "solved", "exit"],
                                                            [[j, f"{w:.2f}", f"{c:.2f}", f"{ok}/{n}", rc]
                                                             for j, (w, ok, rc, c) in jb.items()])
                     + f"\n\nLoad average at the end: {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores.\n")
        if "rendered" in only:
            emit("### Rendered fields, solved blind\n\n" + table(
                ["field", "status", "exit", "centre error (arcsec)", "fitted FOV (deg)", "fitted k1", "stars",
                 "solve ms", "process s"], rendered(cache_env)) + "\n")
        if "non_stars" in only:
            emit("### Not star fields\n\n" + table(["image", "status", "exit", "reason", "process s"],
                                                   non_stars(cache_env)) + "\n")
    finally:
        shutil.rmtree(tmp_cache, ignore_errors=True)
    return "\n".join(parts)


def _first_use_section(esa, emit):
    wall, rc, notice, wall2, rc2, cpu, cpu2 = first_use(esa[0])
    emit(f"### First use\n\n`startrack solve {os.path.basename(esa[0])}` with an empty cache and an empty "
         f"numba cache: **{wall:.1f} s** wall, {cpu:.1f} s CPU (exit {rc}); notices on stderr: {notice!r}. With "
         f"compiled kernels and an empty index cache: **{wall2:.1f} s** wall, {cpu2:.1f} s CPU (exit {rc2}).\n")


def _real_photos_section(refs, cache_env, skip_peers, emit):
    rows, walls = real_photos(refs, cache_env, skip_peers)
    emit("### Real photos, `startrack solve IMAGE` (no options), warm cache\n\nDistance: image centre vs the "
         "reference (astrometry.net) centre; width: fitted horizontal FOV vs the reference; time: whole "
         "process (s).\n\n" + table(["tool", "image", "status", "exit", "distance (deg)", "width", "time (s)"],
                                      rows)
         + f"\n\nstartrack whole process: median {np.median([w for w, _ in walls]):.2f} s wall, "
           f"{np.median([c for _, c in walls]):.2f} s CPU (user + system); max {max(w for w, _ in walls):.2f} s "
           f"wall.\n")


def _in_process_section(esa, cache_env, emit):
    per, per_cpu, cedar, labels, split = in_process(esa, cache_env)
    txt = (f"### In one process (ESA images, median of 5 runs each)\n\nstartrack solve_image (centroid + "
           f"identify + attitude), wall: per image {', '.join(f'{v:.0f}' for v in per)} ms; "
           f"**median {np.median(per):.1f} ms**; CPU: {', '.join(f'{v:.0f}' for v in per_cpu)} ms, "
           f"**median {np.median(per_cpu):.1f} ms**.\nThe previous blind solver (paper 004 labels + pyramid, "
           f"`SolveOptions(blind='labels')`): {sum(st == 'ok' for _, st in labels)}/{len(labels)} solved, "
           f"median {np.median([t for t, _ in labels]):.0f} ms CPU.\nstartrack's split (median ms per image, "
           f"wall): detection and centroids {split[0]:.1f}, pattern search and verification {split[1]:.1f}, "
           f"attitude and records {split[2]:.1f}.")
    if cedar:
        txt += (f"\ncedar-solve solve_from_image (FOV 11.4 given; its own process, run image by image between "
                f"startrack's runs), wall: {', '.join(f'{v:.0f}' for v in cedar)} ms; **median "
                f"{np.median(cedar):.1f} ms**; cedar / startrack (wall) = {np.median(cedar) / np.median(per):.2f}.")
    else:
        txt += "\ncedar-solve: not installed (CEDAR_PYTHON or .venv-cedar)."
    emit(txt + "\n")


def main():
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--out", default=os.path.join(ROOT, "bench-output", "blind.md"))
    parser.add_argument("--skip-peers", action="store_true")
    parser.add_argument("--only", default=",".join(SECTIONS),
                        help=f"comma-separated sections to run (default all: {','.join(SECTIONS)})")
    args = parser.parse_args()
    only = tuple(x.strip() for x in args.only.split(",") if x.strip())
    unknown = set(only) - set(SECTIONS)
    if unknown:
        parser.error(f"unknown sections {sorted(unknown)}; choose from {', '.join(SECTIONS)}")
    text = report(args.skip_peers, only)
    os.makedirs(os.path.dirname(args.out), exist_ok=True)
    with open(args.out, "w") as fh:
        fh.write(text)
    print(f"report: {args.out}")


if __name__ == "__main__":
    main()
