#!/usr/bin/env python3
"""`make bench`'s one entry, feeds bench-output/report.md (kept: results/results-2026-11-22.md): run SECTION ...

    python benchmarks/run.py [SECTION ...]     # every section when none is named
    python benchmarks/run.py --list            # the sections and what each measures

Each section prints a table of medians (and ratios against peers where the issue names
them) and the whole report is written to bench-output/report.md.  Speed targets live
here, never in unit tests.  A section is a function ``bench_NAME`` below whose docstring's
first line says what it measures, registered in ``SECTIONS``.
"""
from __future__ import annotations

import argparse
import os
import platform
import time

import numpy as np
from common import OUT_DIR, ROOT, table, timed


def bench_render():
    """Rendering speed: a 1024x1024 16-bit frame with every noise (target <= 20 ms), with PRNU; star lists."""
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


def bench_centroid():
    """Centroids: accuracy against the Cramer-Rao bound, paper 000's COM experiment, pixel-phase bias, sep."""
    import centroid_bench as cb

    rows, ok = cb.accuracy_table()
    parts = ["Accuracy: RMS error per axis (px) of each method on 300 rendered stars at random sub-pixel "
             "phases (background 100 e-, read noise 5 e-), beside the Cramer-Rao bound (CRB).\n",
             table(["PSF sigma", "SNR", "CRB", "com", "iwc", "quine", "gauss", "best", "best/CRB", "detected"], rows),
             f"\nBest method within 1.3x of the CRB at SNR >= 20: {'yes' if ok else 'NO'}\n"]
    p000 = cb.paper000_experiment()
    paper = {"noise-free": (0.0269, 0.00050488, 0.0269, 0.00050580), "noise sd 2.55 DN": (0.0371, 0.000846, 0.0391, 0.0015),
             "noise sd 25.5 DN": (0.0371, 0.000846, 0.0391, 0.0015)}
    prow = [[k, f"{v[0]:.4f}", f"{v[1]:.6f}", f"{v[2]:.4f}", f"{v[3]:.6f}",
             f"{paper[k][0]} / {paper[k][1]}", f"{paper[k][2]} / {paper[k][3]}"] for k, v in p000.items()]
    parts += ["\nPaper 000's COM experiment (500 runs; our reconstruction of its unstated set-up, see "
              "benchmarks/centroid_bench.py):\n",
              table(["case", "mean |err x|", "var x", "mean |err y|", "var y", "paper x mean / var", "paper y mean / var"],
                    prow)]
    plot_path = os.path.join(ROOT, "examples", "centroid-pixel-phase.png")
    path, curves = cb.pixel_phase_plot(plot_path)
    amp = {m: float(np.nanmax(np.abs(v))) for m, v in curves.items()}
    parts.append("\nPixel-phase bias (max |error| over sub-pixel phase, sigma 0.8 px, SNR 2000): "
                 + ", ".join(f"{m} {a:.4f} px" for m, a in amp.items())
                 + (f"; plot: {os.path.relpath(path, ROOT)}" if path else " (matplotlib missing: no plot)"))
    stats, real, sep_error = cb.speed_and_completeness()
    srows = []
    for tool, v in stats.items():
        if v:
            srows.append([tool, f"{v[0]:.2f}", f"{100 * v[1]:.1f}%", f"{v[2]:.2f}", f"{v[3]:.3f}"])
    if "sep" in stats and stats["sep"] and stats["startrack"]:
        srows.append(["ratio sep/startrack", f"{stats['sep'][0] / stats['startrack'][0]:.2f}x", "", "", ""])
    parts += ["\n\nSpeed on 12 rendered 1024x1024 16-bit frames (PSF sigma 1.2, stars to mag 6.3, threshold 5 sigma; median over frames of each frame's median of 5 warm runs), "
              "completeness for stars <= mag 5.5, false detections per frame, RMS error of matched stars <= 5.5:\n",
              table(["tool", "median ms", "completeness", "false/frame", "RMS px"], srows)]
    if sep_error:
        parts.append(f"\nsep not available: {sep_error} (run `make bench-peers`)")
    parts += ["\n\nReal ESA images (1024x768 16-bit):\n",
              table(["image", "startrack ms", "stars", "sep ms", "sep detections"],
                    [[n, f"{a:.2f}", b, f"{c:.2f}", d] for n, a, b, c, d in real])]
    beside = cb.beside_tetra3rs()
    if beside:
        parts += ["\n\nfind_stars beside tetra3rs's extract_centroids (issue 38; the 8 ESA images alternated image by "
                  "image in one process, each image's median of 9 warm runs; find_stars on its default threads and "
                  "on one; goal ratio <= 1.0):\n",
                  table(["find_stars ms", "threads", "extract_centroids ms", "ratio of medians", "median ratio",
                         "find_stars 1 thread ms", "ratio 1 thread", "load"],
                        [[f"{beside['find_stars_ms']:.2f}", beside["threads"], f"{beside['extract_centroids_ms']:.2f}",
                          f"{beside['ratio_of_medians']:.2f}", f"{beside['median_ratio']:.2f}",
                          f"{beside['find_stars_1_thread_ms']:.2f}", f"{beside['ratio_1_thread']:.2f}",
                          f"{beside['load']:.1f}"]])]
    return "centroid", "\n".join(parts)


def bench_databases():
    """Databases: build time, size, entries; range and label query throughput; paper 000 Table 5 recomputed."""
    import database_bench as dbb

    rows, dbs = dbb.builds()
    parts = ["Builds (median of one warm run):\n",
             table(["database", "build", "file", "entries", "paper"], rows)]
    for key in ("(a)", "(b)"):
        qrows, truth = dbb.queries(dbs[key])
        lin = float(qrows[0][1].split()[0])
        for r in qrows:
            r.append(f"{lin / float(r[1].split()[0]):.2f}")
        parts += [f"\n\nRange queries on database {key} (200,000 random angles, +-15 arcsec; "
                  f"{truth:.2f} true pairs per query on average):\n",
                  table(["search", "queries/s", "pairs scanned/query", "time vs k-vector"], qrows)]
    rate, per = dbb.label_queries(dbs["labels"])
    parts.append(f"\n\nLabel look-ups (trend line + bisection within its error bound): {rate / 1e6:.2f} M/s, "
                 f"{per:.2f} entries per label")
    t, lin, pure, quad = dbb.table5(dbs["(b)"])
    parts += ["\n\nPaper 000 Table 5 recomputed on database (b): mean interval scanned for a query of +-0.6 deg "
              "(the paper's epsilon) around random angles:\n",
              table(["search", "pairs scanned", "paper (its triangle database)"],
                    [["true pairs in the interval", f"{t:.0f}", ""],
                     ["k-vector (linear)", f"{lin:.0f}", "165,379"],
                     ["quadratic alone (Eqs. 10-12)", f"{pure:.0f}", "51,514"],
                     ["quadratic clipped to the k-vector range", f"{quad:.0f}", ""]])]
    return "databases", "\n".join(parts)


def bench_identify():
    """Identification: pyramid beside tetra3rs and cedar-solve, 20 deg, 1000 frames x 3 conditions."""
    import identify_bench as ib

    rows, notes = ib.run()
    text = ("Same star lists for every tool (20 x 20 deg, 1024 x 1024, Hipparcos Hp <= 5.0 for every tool's "
            "database, 1000 random attitudes per row, 0.1 mag noise).  Success: boresight within 0.1 deg and roll "
            "within 1 deg of the truth; false: an attitude farther off.  Times: startrack's time_ms (search + verification + "
            "confidence), tetra3rs's wall time of solve_from_centroids, cedar-solve's own T_solve.\n\n"
            + table(["centroids", "tool", "success", "false", "median ms", "p95 ms", "time vs startrack"], rows))
    if notes:
        text += "\n\n" + "\n".join(notes)
    return "identify (peers)", text


def bench_identify_compare():
    """Identification: six algorithms beside tetra3rs and cedar-solve, issue 14's lists (IDENTIFY_COMPARE_COUNT)."""
    import identify_compare as ic

    path = os.path.join(OUT_DIR, "identify_compare.md")
    ic.main(["--count", os.environ.get("IDENTIFY_COMPARE_COUNT", "1000"), "--out", path])
    with open(path) as fh:
        text = fh.read()
    return "identify: six algorithms beside tetra3rs and cedar-solve (issue 14)", text.split("\n", 2)[2]


def bench_identify_speed():
    """Identification speed: pyramid beside tetra3rs at 12/15/20 deg, alternated passes (IDENTIFY_SPEED_COUNT)."""
    import identify_speed as isp

    path = os.path.join(OUT_DIR, "identify_speed.md")
    rows = []
    for fov in ("12", "15", "20"):
        isp.main(["--fov", fov, "--size", "1280x960", "--count", os.environ.get("IDENTIFY_SPEED_COUNT", "1000"),
                  "--out", path])
        with open(path) as fh:
            rows.append(fh.read())
    return ("identify: pyramid's median time beside tetra3rs's, alternated passes in one process (issue 14: ratio "
            "<= 1)", "\n".join(rows))


def bench_attitude():
    """Attitude: solver speed per method (10 stars); paper 000's sensor end to end (1000 frames)."""
    import pipeline_bench as pb

    rows = pb.attitude_speed()
    text = "Median microseconds per solve, 10 stars (Python call included):\n\n" + table(["method", "us"], rows)
    e2e = pb.paper000_end_to_end()
    text += ("\n\nPaper 000's sensor end to end (render -> centroid -> identify -> attitude; 752 x 480 px, 6 um, "
             f"f 41.1 mm = {e2e['fov_deg'][0]:.2f} x {e2e['fov_deg'][1]:.2f} deg, {e2e['pixel_arcsec']:.1f}\"/px, "
             f"catalog Hp 2.5-6.59, rendered to Hp 7.5; {e2e['frames']} random attitudes):\n\n"
             + table(["quantity", "startrack", "paper 000 requirement", "Liebe (2002) prediction"], [
                 ["identified frames (correct / failed / wrong)", f"{e2e['ok']} / {e2e['failed']} / {e2e['bad']}", "", ""],
                 ["RMS pitch/yaw (per axis)", f"{e2e['rms_pitch_yaw_arcsec']:.2f}\"", "< 20\"",
                  f"{e2e['liebe_pitch_yaw_arcsec']:.2f}\""],
                 ["RMS roll", f"{e2e['rms_roll_arcsec']:.2f}\"", "< 100\"", f"{e2e['liebe_roll_arcsec']:.2f}\""],
                 ["stars per solution (mean)", f"{e2e['mean_stars']:.1f}", "4 (adaptive selection)", ""],
                 ["centroid sigma (median, px)", f"{e2e['median_centroid_sigma_px']:.3f}", "", ""]]))
    return "attitude", text


def bench_track():
    """Tracking: tracking vs lost-in-space speed; accuracy over rates, a blackout and few stars; speed by mode."""
    import pipeline_bench as pb
    import track_bench

    track_ms, lis_ms, n = pb.tracking_speed()
    return "track", table(["mode (1024 x 768, 12 deg, image in memory)", "median ms per frame", "frames/s"], [
        ["tracking (predict + windows + QUEST)", f"{track_ms:.3f}", f"{1000 / track_ms:.0f}"],
        ["lost in space (centroid + identify + attitude)", f"{lis_ms:.3f}", f"{1000 / lis_ms:.0f}"],
        ["ratio", f"{lis_ms / track_ms:.1f}x faster", ""]]) + f"\n\n({n} tracked frames)\n\n" + track_bench.report()


def bench_solve():
    """Real photos: `startrack solve` on the 8 ESA images beside cedar-solve and astrometry.net (centre, FOV, times)."""
    import solve_bench as sb

    rows, med, notes = sb.run()
    text = ("The 8 ESA images (1024 x 768, 16-bit; reference: astrometry.net's blind solutions, 11.42 x 8.58 deg). "
            "startrack: `startrack solve IMAGE` with no options (field of view unknown); in-process ms is the "
            "solve itself, process ms the whole command (Python start-up, loading the cached databases and the compiled "
            "kernels); `startrack (batch)`: the 8 images in one process (process ms = its wall time / 8). "
            "cedar-solve: solve_from_image with its shipped database and an 11.4 deg FOV estimate, in a "
            "running process. astrometry.net: solve-field, scale 5-30 deg wide, the whole process.\n\n"
            + table(["tool", "image", "status", "centre vs reference (arcsec)", "FOV (deg)", "in-process ms",
                     "process ms"], rows)
            + "\n\n" + table(["tool", "solved", "median in-process ms", "median process ms"],
                               [[t, f"{v[2]}/8", f"{v[0]:.0f}", f"{v[1]:.0f}"] for t, v in med.items()]))
    if notes:
        text += "\n\n" + "\n".join(notes)
    return "solve (real images)", text


def bench_blind():
    """Blind solving (issue 15): real photos beside peers, first use, -j 1 vs -j 2, rendered fields, non-stars."""
    import blind_bench

    return "blind solving (issue 15)", blind_bench.report()


def bench_accuracy():
    """Attitude accuracy against each frame's Cramer-Rao bound (issue 21), beside peers; a sweep (ACCURACY_FRAMES)."""
    import accuracy_bench as ab

    n = int(os.environ.get("ACCURACY_FRAMES", "1000"))
    results = [ab.run(name, n, 0, peers=True, progress=False) for name in ("p000", "15deg")]
    sweep = ab.sweep(max(20, n // 10))
    text = (ab.__doc__.split("\n\n")[1].replace("\n", " ") + "\n\n" + ab.table(results)
            + f"\n\nSweep on the 15-degree sensor and papers 000/003 ({max(20, n // 10)} frames each, startrack):\n\n"
            + ab.table(sweep))
    return "accuracy against the Cramér-Rao bound", text


def bench_speed():
    """Issue 38: Solver.solve, identify with defaults, a warm solve process and -j 2, each beside tetra3rs."""
    import speed_path

    return "the whole path beside tetra3rs: solve, identify's final match, start-up, -j (issue 38)", speed_path.report()


def bench_hints():
    """Hints (--ra/--dec/--radius, --scale-low/--scale-high) against blind solve: the 8 ESA images, hard frames."""
    import hint_bench

    esa, esa_note = hint_bench.run(repeat=7)
    hard, hard_note = hint_bench.run_rendered()
    return "hints", "\n".join(["The 8 ESA images (one Solver, warm):\n", esa, f"\n{esa_note}\n",
                                "\nRendered 12 deg frames with 25 false stars:\n", hard, f"\n{hard_note}"])


SECTIONS = {"blind": bench_blind, "solve": bench_solve, "render": bench_render, "centroid": bench_centroid,
            "databases": bench_databases, "identify": bench_identify, "identify-compare": bench_identify_compare,
            "identify-speed": bench_identify_speed, "attitude": bench_attitude, "track": bench_track,
            "accuracy": bench_accuracy, "speed": bench_speed, "hints": bench_hints}


def section_list():
    """One line per section: its name and what it measures (the first line of its docstring)."""
    width = max(map(len, SECTIONS))
    return "\n".join(f"{name.ljust(width)}  {fn.__doc__.splitlines()[0]}" for name, fn in SECTIONS.items())


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter,
                                     epilog="sections:\n" + section_list())
    parser.add_argument("sections", nargs="*", metavar="SECTION", help="sections to run (default: all, in this order): "
                        + ", ".join(SECTIONS))
    parser.add_argument("--list", action="store_true", help="print the sections and what each measures, and exit")
    args = parser.parse_args(argv)
    if args.list:
        print(section_list())
        return
    unknown = [s for s in args.sections if s not in SECTIONS]
    if unknown:
        parser.error(f"unknown section(s) {', '.join(unknown)}; choose from {', '.join(SECTIONS)}")
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
