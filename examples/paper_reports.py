"""Write one reproduction report per paper, the paper's numbers beside ours (examples/results/paper-00N.md).

    .venv/bin/python examples/paper_reports.py [--results examples/results]

It reads what `make reproduce` measured (the evaluate JSON files of examples/reproduce-papers.sh and
paper-000.json of examples/paper000.py) and writes Markdown; it measures nothing itself except the
catalog counts of paper 003 Table 2, which take a second.  A table whose measurement is missing says so.
"""
from __future__ import annotations

import argparse
import json
import math
import os

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)

# The papers' published numbers (file names in ../shared/papers/).
P003_TABLE2 = [("< 3", None, 3.0, 165), ("3-4", 3.0, 4.0, 315), ("4-5", 4.0, 5.0, 991), ("5-6", 5.0, 6.0, 3088),
               ("6-7", 6.0, 7.0, 9381)]
P003_TABLE3 = {   # scenario -> method -> (success %, mean ms, ID failures, bad matches)
    "no false star": {"brightness": (99.82, 0.77, 18, 0), "pyramid": (99.91, 3.93, 9, 0),
                      "voting": (98.72, 28.87, 106, 22)},
    "one false star, >= 4 stars": {"brightness": (98.76, 5.12, 118, 6), "pyramid": (99.25, 10.65, 0, 75),
                                   "voting": (97.87, 43.38, 175, 38)},
    "one false star, >= 5 stars": {"brightness": (99.70, 4.78, 14, 16), "pyramid": (100.0, 10.36, 0, 0),
                                   "voting": (99.14, 44.27, 84, 2)},
}
P003_FILES = {"no false star": "p003-table3-no-false.json", "one false star, >= 4 stars": "p003-table3-false-4.json",
              "one false star, >= 5 stars": "p003-table3-false-5.json"}
P004_TABLE2 = {"grid": 3.69, "pyramid": 3.09, "labelling": 0.76}
P000_TABLE5 = {"k-vector": 165379, "suggested (quadratic)": 51514}
P000_TABLE6_MS = {"k-vector": 0.228295, "suggested (quadratic)": 0.01581}
P000_DB_ROWS = 165380
P000_EXPERIMENT = {"correct": (25.1254, -15.6286, 120.0), "four brightest": (25.1239, -15.6266, 120.0101),
                   "four by label": (25.122, -15.625, 120.021), "loss brightest": 1.52420381e-10,
                   "loss by label": 5.24253951e-7}

HARDWARE = ("the paper's times are MATLAB (papers 003, 004) or C on an ARM Cortex-A8 (paper 000); ours are "
            "numba on one core of a 2-core machine shared with other jobs (load 6 to 12 during these runs), so "
            "only ratios between methods of one run compare, and even those within a factor of about 2")


def _load(path):
    try:
        with open(path) as fh:
            return json.load(fh)
    except (OSError, ValueError):
        return None


def _pct(x):
    return f"{100 * x:.2f} %"


def _table(headers, rows):
    out = ["| " + " | ".join(headers) + " |", "|" + "---|" * len(headers)]
    out += ["| " + " | ".join(str(c) for c in r) + " |" for r in rows]
    return "\n".join(out)


def _rows_by(doc, algorithm=None, condition_has=None):
    rows = (doc or {}).get("rows", [])
    return [r for r in rows if (algorithm is None or r["algorithm"] == algorithm)
            and (condition_has is None or condition_has(r))]


def report_000(results):
    d = _load(os.path.join(results, "paper-000.json"))
    lines = ["# Paper 000 — Hashemi, Mousavi Mashhadi & Fiuzy (2019), modified pyramid", "",
             "Produced by `make reproduce` (`examples/paper000.py`, then `examples/paper_reports.py`).", ""]
    if d is None:
        return "\n".join(lines + ["**Not measured**: examples/results/paper-000.json is missing "
                                  "(run `.venv/bin/python examples/paper000.py`)."])
    lines += _headline_000(d, results)
    lines += [f"Command: `{d.get('command', 'examples/paper000.py')}`", "",
              "## Catalog", "",
              _table(["", "paper", "ours", "why they differ"],
                     [["stars, magnitude 2.5 to 6.59", d["catalog"]["paper_n_stars"], d["catalog"]["n_stars"],
                       "the paper's magnitudes are 'M_I' of an unnamed 19.9 MB catalog; Hipparcos Hp gives "
                       "8,841 to 6.59. Which filter gives 7,457 is not stated."]]), ""]
    for label, e in d["sensors"].items():
        t5, db, ident = e["table5"], e["databases"], e["identification"]
        lines += [f"## Sensor: {label} — {e['fov_deg'][0]} x {e['fov_deg'][1]} deg", ""]
        lines += ["### Table 4 — the triangle database", "",
                  _table(["", "paper", "ours", "why"],
                         [["triangles stored", f"{P000_DB_ROWS:,} (Table 5's last index)", f"{db['triangles']['n']:,}",
                           f"we keep every triple whose sides are all <= {db['triangles']['max_side_deg']:.2f} deg "
                           "(the field's shorter side); the paper's rule ('stars that can be neighbours') and "
                           "catalog are not given"],
                          ["size / build time", "not given", f"{db['triangles']['mb']} MB / {db['triangles']['build_s']} s",
                           "HDF5 with gzip; numba build"]]), "",
                  "First rows (smallest smallest-angle first, degrees), as in the paper's Table 4:", "",
                  _table(["stars (HIP)", "theta1", "theta2", "theta3"],
                         [[" ".join(map(str, r["stars"])), *r["angles_deg"]] for r in e["table4"][:6]]), "",
                  "Like the paper's rows, the first triangles are nearly collinear (theta1 of a few "
                  "thousandths of a degree) and the three angles sum to 180 deg.", ""]
        lines += ["### Table 5 — interval searched per look-up", "",
                  _table(["search", "paper", "ours (mean over look-ups)"],
                         [["k-vector line", f"{P000_TABLE5['k-vector']:,}", f"{t5['mean_linear']:.0f}"],
                          ["fitted quadratic (Eqs. 7-12)", f"{P000_TABLE5['suggested (quadratic)']:,}",
                           f"{t5['mean_quadratic']:.0f}"],
                          ["exact (triangles really in the window)", "-", f"{t5['mean_exact']:.0f}"]]), "",
                  f"Over {t5['lookups']} look-ups (the first measured triangle of each frame, tolerance from "
                  f"sigma {e['sigma_px']} px). The paper's k-vector interval is the whole database "
                  "(165,379 of 165,380), which a k-vector never gives: Mortari's line through the first and last "
                  "values returns the window plus at most a few entries. Its quadratic then looks 3x shorter "
                  "only against that. With a correct k-vector both searches return the exact window within "
                  f"{abs(t5['mean_linear'] - t5['mean_exact']):.1f} and "
                  f"{abs(t5['mean_quadratic'] - t5['mean_exact']):.1f} entries: the smallest angles of the sorted "
                  "database grow almost linearly with the index, so a line already fits.", ""]
        rows = []
        for name, r in ident.items():
            rows.append([name, r["frames"], r["success"], r["failure"], r["bad"], f"{r['median_ms']:.3f}",
                         f"{r['p95_ms']:.3f}"])
        q = ident.get("modified-pyramid (quadratic, Eqs. 10-12)", {})
        ln = ident.get("modified-pyramid (k-vector line)", {})
        lines += ["### Table 6 and the modified pyramid beside Mortari's pyramid", "",
                  _table(["method", "frames", "success", "failed", "wrong", "median ms", "p95 ms"], rows), "",
                  _table(["", "paper", "ours"],
                         [["time, k-vector line (ms)", P000_TABLE6_MS["k-vector"], f"{ln.get('median_ms', float('nan')):.3f}"],
                          ["time, quadratic (ms)", P000_TABLE6_MS["suggested (quadratic)"],
                           f"{q.get('median_ms', float('nan')):.3f}"],
                          ["ratio line / quadratic", f"{P000_TABLE6_MS['k-vector'] / P000_TABLE6_MS['suggested (quadratic)']:.1f}",
                           f"{ln.get('median_ms', float('nan')) / max(q.get('median_ms', float('nan')), 1e-9):.2f}"]]),
                  "", "The paper's 14x follows from its 3x shorter interval (and, we suspect, from a linear scan of "
                  "the whole table as its 'k-vector'); with equal intervals the two searches cost the same. "
                  f"Times: {HARDWARE}.", ""]
    lines += ["## Paper 000's quadratic on the pair k-vector (retired)", "", RETIRED_QUADRATIC, ""]
    lines += _p000_pipeline(results)
    real = d.get("real_image")
    lines += ["## Sec. 4 — the real-image experiment (Eqs. 27-29)", ""]
    if not real:
        lines += ["Not measured (no photo with a known camera at hand)."]
    else:
        rows = [["four brightest (paper)", f"{P000_EXPERIMENT['loss brightest']:.3g}", "0.0015 / 0.002 / 0.0101 deg"],
                ["four by label (paper)", f"{P000_EXPERIMENT['loss by label']:.3g}", "0.0034 / 0.0036 / 0.021 deg"]]
        for label, r in real["runs"].items():
            if r.get("status") == "ok":
                err = (f"image centre {r['centre_error_arcsec']:.1f}\" from astrometry.net's; "
                       if "centre_error_arcsec" in r else "")
                rows.append([f"{label} (ours)", f"{r['wahba_loss']:.3g}",
                             f"{err}RMS residual {r['rms_residual_arcsec']:.1f}\" (stars {', '.join(map(str, r['ids']))})"])
            else:
                rows.append([f"{label} (ours)", "-", f"failed: {r.get('reason')}"])
        lines += [f"Redone on `{real['image']}` (ESA, 11.4 x 8.6 deg) instead of the paper's unpublished photo.", "",
                  _table(["stars used", "Wahba loss", "error"], rows), "",
                  "The paper's claim is that the four brightest stars give the better attitude (their centroids "
                  "are better); the Wahba loss of each choice above tests it on our photo. A photo's brightest "
                  "stars are often saturated, and a saturated centroid is no better than a faint one: the "
                  "paper's camera (threshold 60 of 255) may not have saturated its four."]
    return "\n".join(lines) + "\n"


# History: the algorithm startrack had under paper 000's name before modified-pyramid (measured at commit 51376af).
RETIRED_QUADRATIC = (
    "Before the triangle database, startrack's stand-in for this search was `pyramid-quadratic`: paper 000's "
    "quadratic applied to Mortari's pair cosines and clipped to the k-vector range. Run beside `pyramid` on the same "
    "1,000 frames (15 x 15 deg, 1024 x 1024, Hp <= 6.0; sigma 0.3 and 1 px, 3 and 10 false stars, 3-4 stars; commit "
    "51376af) it returned the same status and the same star ids on every frame, so it was retired: "
    "`--algorithm pyramid-quadratic` now exits 2 saying to use pyramid or modified-pyramid.")


P000_DESIGN = {"cross": 20.0, "roll": 100.0, "identify_ms": 25.0}


def _headline_000(d, results):
    rows = []
    e = next((v for k, v in d["sensors"].items() if k.startswith("8x8")), None)
    if e:
        db = e["databases"]["triangles"]
        q = e["identification"].get("modified-pyramid (quadratic, Eqs. 10-12)", {})
        p = e["identification"].get("pyramid (Mortari, k-vector pairs)", {})
        rows.append(["triangle database, 8 x 8 deg, Hp 2.5-6.59", f"{P000_DB_ROWS:,} triangles (Table 5)",
                     f"{db['n']:,} triangles, {db['mb']} MB, built in {db['build_s']} s",
                     "our rule keeps every triple with sides <= 8 deg; the paper's rule and catalog are not given"])
        if q and p:
            rows.append([f"modified pyramid vs pyramid, {q['frames']} frames (success / failed / wrong, median ms)",
                         "0.01581 ms (quadratic) vs 0.228295 ms (k-vector line), no success rate",
                         f"{q['success']} / {q['failure']} / {q['bad']}, {q['median_ms']:.3f} ms vs pyramid "
                         f"{p['success']} / {p['failure']} / {p['bad']}, {p['median_ms']:.3f} ms",
                         f"ARM C vs numba on a loaded machine; each smallest-angle look-up returns "
                         f"{e['table5']['mean_exact']:,.0f} triangles on average (Table 5) to check against the "
                         "other two angles"])
        t5 = e["table5"]
        rows.append(["interval searched: line vs quadratic", "165,379 vs 51,514 (3.2x)",
                     f"{t5['mean_linear']:.0f} vs {t5['mean_quadratic']:.0f} (exact {t5['mean_exact']:.0f})",
                     "a k-vector line already returns the exact window; the paper's 'k-vector' interval is the "
                     "whole table"])
    pipe = _load(os.path.join(results, "p000-pipeline.json"))
    if pipe:
        for s in pipe["sensors"].values():
            r = s["rows"].get("paper")
            if r:
                rows.append([f"the paper's pipeline, {s['label']}", "< 20\" pitch/yaw, < 100\" roll (design)",
                             f"{r['success']}/{r['frames']} frames, median {r['median_cross_boresight_arcsec'] or 0:.1f}\" "
                             f"/ roll {r['median_roll_arcsec'] or 0:.1f}\"",
                             "rendered images; see the pipeline section"])
    if not rows:
        return []
    return ["## Headline", "", _table(["", "paper", "ours", "why they differ"], rows), ""]


def _p000_pipeline(results):
    """The paper's pipeline on rendered images beside startrack's default (examples/paper000_pipeline.sh)."""
    doc = _load(os.path.join(results, "p000-pipeline.json"))
    lines = ["## The paper's pipeline beside startrack's default (rendered images)", ""]
    if doc is None:
        return lines + ["Not measured (p000-pipeline.json missing: run `bash examples/paper000_pipeline.sh`).", ""]
    lines += ["Command: `bash examples/paper000_pipeline.sh 300` (then `examples/paper000_pipeline.py`). "
              "Paper 000's pipeline: " + doc["pipelines"]["paper"].split(": ", 1)[1] + ". startrack's default: "
              + doc["pipelines"]["default"].split(": ", 1)[1] + ". The same rendered 8-bit frames for both; the "
              "photometry is not in the paper (a magnitude-6.59 star peaks near the 60 DN threshold). Success: "
              "boresight within 60\" of the truth; wrong: an attitude farther off.", ""]
    rows = []
    for s in doc["sensors"].values():
        for p, r in s["rows"].items():
            f = lambda v, fmt="{:.1f}": "-" if v is None else fmt.format(v)  # noqa: E731
            rows.append([s["label"], "paper 000" if p == "paper" else "startrack default", r["frames"], r["success"],
                         r["failed"], r["wrong"], f(r["median_cross_boresight_arcsec"]), f(r["median_roll_arcsec"]),
                         f(r["median_identify_ms"], "{:.2f}"),
                         ", ".join(f"{k} {v}" for k, v in sorted(r["failure_reasons"].items())) or "-"])
    lines += [_table(["sensor", "pipeline", "frames", "success", "failed", "wrong", "median cross-boresight (\")",
                      "median roll (\")", "median identify ms", "failures"], rows), "",
              f"Paper 000's design figures: < {P000_DESIGN['cross']:.0f}\" pitch/yaw, < {P000_DESIGN['roll']:.0f}\" "
              f"roll, identification < {P000_DESIGN['identify_ms']:.0f} ms on an ARM Cortex-A8; it reports no "
              "success rate for its pipeline. " + _p000_why(doc), ""]
    return lines


def _p000_why(doc):
    """Why the paper's pipeline and ours differ, from the failures actually seen (and their causes in the truth)."""
    import math

    out = ["Why they differ: four stars leave the attitude to four centroids (the roll to a baseline of a few "
           "hundred pixels) where the default pipeline uses every star. The paper's identification runs with a "
           "fixed tolerance (from 0.25 px, the 95th percentile of the COM error on these frames), as the paper "
           "does, not COM's own per-star sigma."]
    for sensor in doc["sensors"].values():
        r = sensor["rows"].get("paper") or {}
        if r.get("centroid_median_sigma_px") is not None:
            out.append(f"On {sensor['label']}, COM's sigma_px (its simulated error: pixel phase, rounding, noise) "
                       f"has median {r['centroid_median_sigma_px']:.3f} px against a measured robust scatter of "
                       f"{r['centroid_error_robust_px']:.3f} px (errors / sigma: robust spread "
                       f"{r['centroid_z_robust']:.2f}; 95th percentile of the error {r['centroid_error_p95_px']:.2f} "
                       "px).")
    for sensor in doc["sensors"].values():
        r = sensor["rows"].get("paper")
        if r and r.get("failure_causes"):
            parts = ", ".join(f"{k}: {v}" for k, v in sorted(r["failure_causes"].items(), key=lambda kv: -kv[1]))
            out.append(f"The paper's pipeline's {r['failed']} failures on {sensor['label']}, by their cause in the "
                       f"render's truth: {parts}.")
    out.append("Fewer than four stars: the 60 DN threshold is fixed, and a magnitude-6.59 star reaches it only "
               "when centred on a pixel; the default's threshold follows the noise (5 sigma) and finds fainter "
               "stars. A star outside Hp 2.5-6.59: the sky has stars brighter than 2.5, and they are among the "
               "four brightest, but the paper's catalog leaves them out. Stars farther apart than the longest "
               "triangle side: the database keeps triangles with sides up to the field's shorter side (the "
               "paper's rule), 4.01 deg on the camera reading, whose four brightest are often spread along "
               "its 6.28 deg.")
    parts = []
    for (w, h), sensor in zip(((8.0, 8.0), (6.284, 4.013)), doc["sensors"].values()):
        lam = 8752 * w * h / 41253.0
        p3 = sum(math.exp(-lam) * lam**k / math.factorial(k) for k in range(4))
        r = sensor["rows"].get("default")
        measured = f", the default pipeline failed {100 * r['failed'] / r['frames']:.0f} %" if r else ""
        parts.append(f"{lam:.1f} on {w:g} x {h:g} deg ({100 * p3:.0f} % of fields with fewer than four{measured})")
    out.append("Database stars (Hp 2.5-6.59) per field, on average: " + "; ".join(parts) + ": fainter "
               "detections cannot be identified, so a small field fails for want of catalog stars.")
    return " ".join(out)


def report_001(results):
    track = [f for f in sorted(os.listdir(results)) if f.startswith("track") and f.endswith(".json")] \
        if os.path.isdir(results) else []
    lines = ["# Paper 001 — Masood-Ur-Rehman et al., single-star identification and attitude in tracking mode", "",
             "Produced by `make reproduce` (`examples/tracking.sh`, `examples/paper001_single_star.sh`, then "
             "`examples/paper_reports.py`).", "",
             "## Tables 1-2 (predictive centroiding, windows)", "",
             "**Cannot be run as published**: the paper gives neither the boresight sequence nor the camera "
             "(focal length, pixel size, field) behind its tables, so no input reproduces them. What the "
             "tables demonstrate — that a star predicted from the previous attitude is found in a small window "
             "around its prediction, and that the attitude follows from one identified star plus empirical "
             "stars (Case 2) — is exercised by `startrack track` on rendered sequences instead:", ""]
    if track:
        rows = []
        for f in track:
            d = _load(os.path.join(results, f)) or {}
            modes = d.get("modes") or {}
            rows.append([f, ", ".join(f"{k} {100 * v:.0f} %" for k, v in modes.items() if v),
                         *(f"{d.get(k, float('nan')):.1f}" if isinstance(d.get(k), (int, float)) else "-"
                           for k in ("rms_cross_tracking_arcsec", "rms_roll_tracking_arcsec"))])
        lines += [_table(["sequence", "frames by mode", "RMS cross-boresight (\")", "RMS roll (\")"], rows)]
    else:
        lines += ["(No tracking results in examples/results: run `make reproduce`.)"]
    single = [(f, (_load(os.path.join(results, f)) or {}).get("modes", {}).get("single-star", 0.0)) for f in track]
    ran = [f"{f} ({100 * v:.0f} % of frames)" for f, v in single if v]
    lines += ["", "Case 2 (one identified star, empirical stars shifted by the observed offset, weighted QUEST) is "
              "the `single-star` mode of `startrack track`; "
              + (f"it ran in {', '.join(ran)}." if ran else
                 "**none of the sequences above runs it** (no frame was solved in that mode): "
                 "single-star mode is not exercised by an example yet.")]
    lines += _p001_single_star(results)
    return "\n".join(lines) + "\n"


def _p001_single_star(results):
    """The single-star example (examples/paper001_single_star.sh): its frames with one star, mode by mode."""
    d = _load(os.path.join(results, "track-single-star.json"))
    lines = ["", "## Case 2 — single-star attitude in tracking mode", ""]
    if not d or "rows" not in d:
        return lines + ["Not measured (track-single-star.json missing: run `examples/paper001_single_star.sh`)."]
    n = d["frames_per_phase"]
    rows = []
    for mode in ("lost-in-space", "tracking", "single-star"):
        sel = [r for r in d["rows"] if r["mode"] == mode and r["cross_arcsec"] is not None]
        if sel:
            rms = [math.sqrt(sum(r[k] ** 2 for r in sel) / len(sel)) for k in ("cross_arcsec", "roll_arcsec")]
            found = sorted({r["found"] for r in sel if r["found"] is not None})
            rows.append([mode, len(sel), ", ".join(map(str, found)) or "-", f"{rms[0]:.1f}", f"{rms[1]:.1f}",
                         f"{max(abs(r['roll_arcsec']) for r in sel):.1f}"])
    one, single = d["one_star_frames"], d["single_star_frames"]
    lines += [f"Command: `{d['command']}` (12 x 9 deg, 1024 x 768 px, Sirius's field at 0.1, 0.05 deg/s; frames "
              f"{n}-{2 * n - 1} exposed 0.2 ms instead of 100 ms, so that only Sirius is detected: paper 001's "
              "situation of one star in the field of view).", "",
              _table(["mode", "frames", "stars found", "RMS cross-boresight (\")", "RMS roll (\")", "max roll (\")"],
                     rows), "",
              f"{len(one)} frames had one star found in the prediction windows; {len(single)} ran the single-star "
              f"mode ({'all of them' if set(one) <= set(single) else 'not all of them'}). The paper gives no "
              "accuracy for Case 2 to compare with. One star fixes the boresight to its one centroid's noise (no "
              "average over a score of stars, hence a cross-boresight error several times tracking's) but not the "
              "roll about it: the empirical stars carry the roll the rate filter propagates, so the roll error "
              "grows frame by frame until more stars are found again."]
    return lines


def _p003_counts():
    from startrack.catalog import load_catalog

    cat = load_catalog()
    out = []
    for label, lo, hi, paper in P003_TABLE2:
        m = cat.mag
        n = int(((m >= lo) if lo is not None else (m == m)).__and__(m < hi).sum())
        out.append([label, paper, n, "equal" if n == paper else f"{n - paper:+d}"])
    return out


def _headline_003(results):
    rows = []
    doc = _load(os.path.join(results, P003_FILES["no false star"]))
    if doc:
        by = {r["algorithm"]: r for r in doc["rows"]}
        for m in ("brightness", "pyramid"):
            if m in by:
                succ, ms, fail, bad = P003_TABLE3["no false star"][m]
                rows.append([f"Table 3, no false star: {m}", f"{succ} %, {ms} ms, {bad} bad",
                             f"{_pct(by[m]['success_rate'])}, {by[m]['mean_ms']:.3f} ms, {by[m]['bad']} bad "
                             f"({doc['params']['count']:,} frames)", "MATLAB vs numba; shared verification"])
    sc = _load(os.path.join(results, "p003-scope.json"))
    if sc:
        b, p = sc["rows"].get("brightness (calibrated)"), sc["rows"].get("pyramid")
        ref = (b or {}).get("modes", {}).get("reference-star")
        if b and p and ref:
            rows.append(["search scope, reference-star mode", "narrowed (not counted in the paper)",
                         f"{ref['mean_scope']:.1f} entries vs {ref['mean_unnarrowed']:.1f} unnarrowed, pyramid "
                         f"{p['mean_scope']:.1f}", "reproduced"])
            rows.append(["search time vs pyramid", "5.1x faster (0.77 vs 3.93 ms)",
                         f"{p['median_search_ms'] / max(b['median_search_ms'], 1e-9):.2f}x "
                         f"({b['median_search_ms']:.3f} vs {p['median_search_ms']:.3f} ms median)",
                         (f"inside the compiled kernels {b['median_kernel_ms']:.4f} vs {p['median_kernel_ms']:.4f} ms "
                          f"({p['median_kernel_ms'] / max(b['median_kernel_ms'], 1e-9):.2f}x); the rest of brightness's "
                          "search is Python around its kernel (sorting, Eq. 9 magnitudes, the bands)")
                         if b.get("median_kernel_ms") and p.get("median_kernel_ms") else
                         "fixed per-frame cost dominates a compiled search of a few dozen entries"])
    return ["## Headline", "", _table(["", "paper", "ours", "why they differ"], rows), ""] if rows else []


def _p003_scope(results):
    """Sec. 4.3's claim: the search scope narrowed by brightness, and the time beside the pyramid."""
    doc = _load(os.path.join(results, "p003-scope.json"))
    lines = ["## Sec. 4.3 — the narrowed search scope, and the claim of 4-5x the pyramid's speed", ""]
    if doc is None:
        return lines + ["Not measured (p003-scope.json missing: run `examples/p003_scope.py`).", ""]
    rows = []
    for label, r in doc["rows"].items():
        for mode, m in sorted(r["modes"].items()):
            rows.append([label, mode, m["frames"], f"{m['mean_scope']:.1f}" if m["mean_scope"] is not None else "-",
                         f"{m['mean_unnarrowed']:.1f}" if m.get("mean_unnarrowed") is not None else "-",
                         f"{m['mean_search_ms']:.3f}", f"{m['mean_ms']:.3f}"])
    tot = [[label, r["frames"], r["success"], r["failure"], r["bad"], f"{r['mean_scope']:.1f}",
            f"{r['median_search_ms']:.3f}", f"{r['mean_search_ms']:.3f}", f"{r['median_ms']:.3f}",
            f"{r['mean_ms']:.3f}"] for label, r in doc["rows"].items()]
    b = doc["rows"].get("brightness (calibrated)", {})
    p = doc["rows"].get("pyramid", {})
    ref = b.get("modes", {}).get("reference-star", {})
    lines += [f"Command: `{doc['command']}` ({doc['sensor']}; calibration `{doc['calibration']}` from "
              f"{doc['calibration_samples']} identified frames). The scope is the number of oriented star-pair "
              "entries the k-vector look-ups (Eqs. 13-14) examine; 'unnarrowed' is what the whole star-pair "
              "catalog's ranges of the same look-ups hold (what a search filtering inside the full range "
              "examines); the pyramid's is the entries of the ranges of theta_ij and theta_ik of every triad it "
              "tried. Search time is the time inside the algorithm's proposal generator; identification time "
              "adds the shared verification.", "",
              _table(["search", "frames", "success", "failed", "bad", "mean scope", "median search ms",
                      "mean search ms", "median identify ms", "mean identify ms"], tot), "",
              _table(["search", "mode", "frames", "mean scope", "mean unnarrowed", "mean search ms",
                      "mean identify ms"], rows), ""]
    if ref and p:
        lines += [f"The scope saving appears: in the reference-star mode ({ref['frames']} of {b['frames']} frames) "
                  f"the look-ups examine {ref['mean_scope']:.1f} entries against {ref['mean_unnarrowed']:.1f} in "
                  f"the unnarrowed ranges ({ref['mean_unnarrowed'] / max(ref['mean_scope'], 1e-9):.1f}x fewer) "
                  f"and the pyramid's {p['mean_scope']:.1f}. "]
        ratio = p["median_search_ms"] / max(b["median_search_ms"], 1e-9)
        lines[-1] += (f"Median search time: brightness {b['median_search_ms']:.3f} ms, pyramid "
                      f"{p['median_search_ms']:.3f} ms ({ratio:.2f}x; paper, Table 3: 0.77 against 3.93 ms, 5.1x). ")
        if ratio >= 4:
            lines[-1] += "The paper's 4-5x speed-up is reproduced."
        else:
            bk, pk = b.get("median_kernel_ms"), p.get("median_kernel_ms")
            kern = (f"Inside the compiled kernels alone (median) the brightness search takes {bk:.4f} ms and the "
                    f"pyramid's {pk:.4f} ms ({pk / max(bk, 1e-9):.2f}x): examining fewer entries saves little when "
                    "either examines a few dozen, and brightness's other "
                    f"{b['median_search_ms'] - bk:.3f} ms is Python around its kernel (sorting the stars, Eq. 9's "
                    f"magnitudes, the bands) against the pyramid's {p['median_search_ms'] - pk:.3f} ms. "
                    if bk and pk else "")
            lines[-1] += ("The paper's 4-5x speed-up is **not reproduced**: both searches take a few tens of "
                          "microseconds at most. " + kern + "A MATLAB search whose cost grows with the entries it "
                          "examines gains from the narrower scope; a compiled one that examines a few dozen does "
                          "not. The identification time is dominated by the shared verification. The scope "
                          "narrowing is reproduced.")
        carried = doc["rows"].get("brightness (carried frame to frame)")
        if carried:
            cref = carried.get("modes", {}).get("reference-star", {})
            lines.append("")
            lines.append(f"Eqs. 7-9's calibration carried frame to frame (`startrack identify` over a stream, here "
                         f"with no calibration to start from: each identified frame's brightest star calibrates the "
                         f"next ones, the mean of the last 10): {cref.get('frames', 0)} of {carried['frames']} frames "
                         f"ran the reference-star mode (with the sensor calibration given: {ref['frames']}), mean "
                         f"scope {carried['mean_scope']:.1f} entries (given: {b['mean_scope']:.1f}; none: "
                         f"{doc['rows'].get('brightness (no calibration)', {}).get('mean_scope', float('nan')):.1f}), "
                         f"{carried['success']} identified, {carried['bad']} wrong.")
        lines.append("")
    return lines


def report_003(results):
    lines = ["# Paper 003 — Zhang, Zhao, Liu & Liu (2014), brightness-referenced star identification", "",
             "Produced by `make reproduce` (`examples/reproduce-papers.sh`, then `examples/paper_reports.py`).", "",
             *_headline_003(results),
             "## Table 2 — Hipparcos stars per magnitude", "",
             _table(["Hp", "paper", "ours", "difference"], _p003_counts()), "",
             "Identical: the paper's 'HC' is Hipparcos in Hp.", "",
             "## Table 3 — simulations (20 x 20 deg, 1024 x 1024, catalog to 5.0, 5\" (3 sigma), 0.2 mag, "
             "10 brightest)", ""]
    for scenario, fname in P003_FILES.items():
        doc = _load(os.path.join(results, fname))
        lines += [f"### {scenario}", ""]
        if doc is None:
            lines += [f"Not measured ({fname} missing).", ""]
            continue
        rows = []
        for method, (succ, ms, fail, bad) in P003_TABLE3[scenario].items():
            ours = _rows_by(doc, method)
            if not ours:
                rows.append([method, f"{succ} %", "-", ms, "-", fail, "-", bad, "-"])
                continue
            r = ours[0]
            rows.append([method, f"{succ} %", _pct(r["success_rate"]), ms, f"{r['mean_ms']:.3f}", fail, r["failure"],
                         bad, r["bad"]])
        lines += [f"{doc['params']['count']:,} attitudes (paper: 10,000), seed {doc['params']['seed']}.", "",
                  _table(["method", "success (paper)", "success (ours)", "mean ms (paper)", "mean ms (ours)",
                          "ID failures (paper)", "(ours)", "bad matches (paper)", "(ours)"], rows), ""]
    first = _load(os.path.join(results, P003_FILES["no false star"])) or {}
    cal = ((first.get("params") or {}).get("settings") or {}).get("brightness", {}).get("brightness_calibration")
    lines += ["Why they differ: our verification refuses any identification whose false-match probability is "
              "above 1e-6, so a doubtful frame is an ID failure rather than a bad match (the paper's pyramid has "
              "75 bad matches with one false star); the paper's magnitudes come from in-orbit calibration, ours "
              "from the renderer's photometry with 0.2 mag noise, and brightness's Eq. 9 calibration "
              + (f"(`--brightness-calibration {cal}`) was measured the paper's way, from the brightest identified "
                 "star of 100 other frames (examples/intensity_calibration.py)" if cal else
                 "was not recorded with this run (without one, brightness runs the four-star mode only)")
              + f"; {HARDWARE}.", ""]
    lines += _p003_scope(results)
    lines += ["## Table 4 — 1000 in-orbit ZY-3 images", "",
              "**No data**: the ZY-3 images are not published, so Table 4 cannot be reproduced.", "",
              "## Fig. 1 — centre of mass vs Gaussian interpolation on a slewing star", ""]
    fig1 = _load(os.path.join(results, "p003-fig1.json"))
    if fig1:
        lines += [_table(["method", "R^2 of the linear fit (ours)", "RMS about the line (px)"],
                         [[m, f"{v['r2']:.6f}", f"{v['rms_px']:.4f}"] for m, v in fig1["methods"].items()]), "",
                  f"{fig1['description']} The paper reports only that COM's R^2 is the larger (its Fig. 1 plots "
                  "ZY-3 data we do not have)."]
    else:
        lines += ["Not measured (p003-fig1.json missing)."]
    return "\n".join(lines) + "\n"


def _headline_004(results):
    rows = []
    doc = _load(os.path.join(results, "p004-table2.json"))
    if doc:
        by = {r["algorithm"]: r for r in doc["rows"]}
        if "labelling" in by and "pyramid" in by:
            rows.append(["Table 2: labelling / pyramid time", f"{0.76 / 3.09:.2f} (0.76 vs 3.09 ms)",
                         f"{by['labelling']['mean_ms'] / by['pyramid']['mean_ms']:.2f} "
                         f"({by['labelling']['mean_ms']:.3f} vs {by['pyramid']['mean_ms']:.3f} ms, "
                         f"{doc['params']['count']:,} frames)",
                         "MATLAB vs numba; each identification time includes the shared verification, most of it (next row)"])
    split = _load(os.path.join(results, "p004-time-split.json"))
    if split and {"labelling", "pyramid"} <= set(split["rows"]):
        lab, pyr = split["rows"]["labelling"], split["rows"]["pyramid"]
        rows.append(["Table 2: labelling / pyramid, the search alone (mean)", f"{0.76 / 3.09:.2f}",
                     f"{lab['mean_search_ms'] / pyr['mean_search_ms']:.2f} ({lab['mean_search_ms']:.3f} vs "
                     f"{pyr['mean_search_ms']:.3f} ms; median {lab['median_search_ms']:.3f} vs "
                     f"{pyr['median_search_ms']:.3f}; {lab['frames']:,} frames)",
                     f"the rest (verification, matching: {lab['mean_rest_ms']:.3f} / {pyr['mean_rest_ms']:.3f} ms mean) "
                     "is most of each identification time and hides most of the search's difference"])
    doc = _load(os.path.join(results, "p004-fig7-focal.json"))
    if doc:
        top = max(r["focal_error_pct"] for r in doc["rows"])
        by = {r["algorithm"]: r for r in doc["rows"] if r["focal_error_pct"] == top}
        if "labelling" in by and "pyramid" in by:
            rows.append([f"Fig. 7 at {top:g} % focal error: labelling / pyramid success",
                         "no failure / < 40 %",
                         f"{_pct(by['labelling']['success_rate'])} / {_pct(by['pyramid']['success_rate'])}; "
                         f"{sum(r['bad'] for r in doc['rows'])} wrong in the sweep",
                         "reproduced" if by["labelling"]["success_rate"] >= 0.99 and by["pyramid"]["success_rate"] < 0.4
                         else "not reproduced: see Figs. 7-8"])
    doc = _load(os.path.join(results, "p004-fig9-false-stars.json"))
    if doc:
        top = max(r["false_stars"] for r in doc["rows"])
        by = {r["algorithm"]: r for r in doc["rows"] if r["false_stars"] == top}
        if all(a in by for a in ("labelling", "pyramid", "grid")):
            rows.append([f"Fig. 10 at {top} false stars: labelling / pyramid / grid success", "> 95 % / > 95 % / 85 %",
                         f"{_pct(by['labelling']['success_rate'])} / {_pct(by['pyramid']['success_rate'])} / "
                         f"{_pct(by['grid']['success_rate'])}",
                         "labelling and pyramid reproduced; grid keeps looking (see Figs. 9-10)"
                         if min(by["labelling"]["success_rate"], by["pyramid"]["success_rate"]) >= 0.95 else
                         "false-star brightness not given; see Figs. 9-10"])
    return ["## Headline", "", _table(["", "paper", "ours", "why they differ"], rows), ""] if rows else []


def report_004(results):
    lines = ["# Paper 004 — Kim & Cho (2019), the labelling technique", "",
             "Produced by `make reproduce` (`examples/reproduce-papers.sh`, then `examples/paper_reports.py`).", "",
             "Sensor as in the paper: 24 x 24 deg, 1200 x 1200 px, magnitude 5.2, 38\" (1 sigma).", "",
             *_headline_004(results),
             "## Table 2 — identification time", ""]
    doc = _load(os.path.join(results, "p004-table2.json"))
    if doc:
        rows = []
        base = {r["algorithm"]: r for r in doc["rows"]}
        for alg, ms in P004_TABLE2.items():
            r = base.get(alg)
            rows.append([alg, ms, f"{100 * ms / P004_TABLE2['grid']:.0f} %",
                         f"{r['mean_ms']:.3f}" if r else "-",
                         f"{100 * r['mean_ms'] / base['grid']['mean_ms']:.0f} %" if r and "grid" in base else "-",
                         _pct(r["success_rate"]) if r else "-"])
        lines += [f"{doc['params']['count']:,} attitudes (paper: 100,000).", "",
                  _table(["algorithm", "paper ms", "paper % of grid", "ours ms (mean)", "ours % of grid",
                          "ours success"], rows), "",
                  f"Why they differ: {HARDWARE}; our pyramid keeps looking after a refused proposal and every "
                  "algorithm shares one verification (the false-match test), most of each identification's time (below).", ""]
        split = _load(os.path.join(results, "p004-time-split.json"))
        if "labelling" in base and "pyramid" in base:
            ratio = base["labelling"]["mean_ms"] / base["pyramid"]["mean_ms"]
            lines[-2] += (f" Labelling / pyramid time: paper {0.76 / 3.09:.2f}, ours {ratio:.2f}: "
                          + ("the paper's 4x advantage of labelling is reproduced." if ratio <= 0.3 else
                             "the paper's 4x advantage of labelling is **not reproduced** in the identification "
                             "time." + ("" if split else " Where the time goes is not measured "
                                        "(p004-time-split.json missing: run `examples/p004_time_split.py`).")))
        if split and {"labelling", "pyramid"} <= set(split["rows"]):
            srows = [[name, r["frames"], r["success"], r["bad"], f"{r['mean_ms']:.3f}", f"{r['mean_search_ms']:.3f}",
                      f"{r['median_search_ms']:.3f}", f"{r['mean_rest_ms']:.3f}", f"{100 * r['search_share']:.0f} %",
                      f"{r['mean_proposals']:.2f}"] for name, r in split["rows"].items()]
            lab, pyr = split["rows"]["labelling"], split["rows"]["pyramid"]
            sratio = lab["mean_search_ms"] / pyr["mean_search_ms"]
            lines += [f"Where the time goes — command: `{split['command']}` (the same sensor and frames; the search is "
                      "the time inside the algorithm's proposal generator, the rest is the shared verification, the "
                      "false-match test and the final matching):", "",
                      _table(["algorithm", "frames", "success", "wrong", "identify ms (mean)", "search ms (mean)",
                              "search ms (median)", "rest ms (mean)", "search share", "proposals verified (mean)"],
                             srows), "",
                      f"The searches alone: labelling / pyramid {sratio:.2f} (paper {0.76 / 3.09:.2f}), labelling's "
                      f"search {1 / sratio:.1f}x faster than the pyramid's — "
                      + ("the paper's ~4x advantage holds for the search" if sratio <= 0.35 else
                         "short of the paper's 4x")
                      + f". Labelling and the pyramid verify {lab['mean_proposals']:.2f} and "
                      f"{pyr['mean_proposals']:.2f} proposals a frame on average; the rest of the time "
                      f"({lab['mean_rest_ms']:.3f} and {pyr['mean_rest_ms']:.3f} ms mean: verification, false-match "
                      f"test, matching every star) is {100 * (1 - lab['search_share']):.0f} % and "
                      f"{100 * (1 - pyr['search_share']):.0f} % of their identification times, so the whole "
                      f"identification times ({lab['mean_ms']:.3f} and {pyr['mean_ms']:.3f} ms, "
                      f"{lab['mean_ms'] / pyr['mean_ms']:.2f}) differ much less than the searches. Paper 004 does "
                      "not say what its times include.", ""]
    else:
        lines += ["Not measured (p004-table2.json missing).", ""]
    for title, fname, key, unit in (("Figs. 7-8 — focal-length error", "p004-fig7-focal.json", "focal_error_pct", "%"),
                                     ("Figs. 9-10 — false stars", "p004-fig9-false-stars.json", "false_stars", "")):
        doc = _load(os.path.join(results, fname))
        lines += [f"## {title}", ""]
        if doc is None:
            lines += [f"Not measured ({fname} missing).", ""]
            continue
        algs = sorted({r["algorithm"] for r in doc["rows"]})
        values = sorted({r[key] for r in doc["rows"]})
        rows = []
        for v in values:
            row = [f"{v:g}{unit}"]
            for a in algs:
                r = [x for x in doc["rows"] if x["algorithm"] == a and x[key] == v]
                row.append(f"{_pct(r[0]['success_rate'])} / {r[0]['bad']} wrong / {r[0]['mean_ms']:.2f} ms" if r else "-")
            rows.append(row)
        lines += [f"{doc['params']['count']:,} attitudes per value; success / wrong / mean time."
                  + (f" **Note: {doc['note']}.**" if doc.get("note") else ""), "",
                  _table([key] + algs, rows), ""]
        if key == "false_stars":
            lab = [r for r in doc["rows"] if r["algorithm"] == "labelling"]
            worst = min((r["success_rate"] for r in lab), default=float("nan"))
            pyr = [r for r in doc["rows"] if r["algorithm"] == "pyramid"]
            grid = [r for r in doc["rows"] if r["algorithm"] == "grid"]
            lines += [f"Paper (Fig. 10): labelling and pyramid keep > 95 % with up to 5 false stars, grid falls to "
                      f"85 %. Ours: lowest success over 0-5 false stars: labelling {_pct(worst)}, pyramid "
                      f"{_pct(min((r['success_rate'] for r in pyr), default=float('nan')))}, grid "
                      f"{_pct(min((r['success_rate'] for r in grid), default=float('nan')))}; wrong identifications "
                      f"in all: labelling {sum(r['bad'] for r in lab)}, pyramid {sum(r['bad'] for r in pyr)}, "
                      f"grid {sum(r['bad'] for r in grid)}. "
                      + ("Why labelling differs: the paper does not say how bright its false stars are; ours are "
                         "uniform in magnitude over the 5 magnitudes above the limit, so they are often among the 8 "
                         "brightest stars whose groups the labelling tries first, and a 4-star group that contains "
                         "one has a label no sky gives. " if worst < 0.95 else
                         "Labelling and pyramid keep > 95 % as in the paper: both keep looking past groups or "
                         "triads that contain a false star (the false stars here are uniform in magnitude over the "
                         "5 magnitudes above the limit; the paper does not say how bright its are). ")
                      + ("Our grid degrades less than the paper's: it keeps looking after a rejected pattern "
                         "(each reference's pattern also oriented by its 2nd and 3rd neighbours)."
                         if min((r["success_rate"] for r in grid), default=0.0) > 0.9 else ""), ""]
        else:
            by = {(r["algorithm"], r[key]): r for r in doc["rows"]}
            lab = [by[("labelling", v)]["success_rate"] for v in values if ("labelling", v) in by]
            pyr = [by[("pyramid", v)]["success_rate"] for v in values if ("pyramid", v) in by]
            wrong = sum(r["bad"] for r in doc["rows"])
            lines += ["Paper (Fig. 7): labelling shows no failure up to 1 % focal-length error, the pyramid "
                      f"falls below 40 %. Ours: labelling {_pct(min(lab))} at worst, the pyramid "
                      f"{_pct(min(pyr))} at {values[-1]:g} %: the paper's finding holds (distance ratios do not "
                      "depend on the focal length, angles do). "
                      + (f"**{wrong} wrong identifications** appear with focal-length errors (frame seeds in "
                         f"{fname}: " + "; ".join(f"{r['algorithm']} {r[key]:g} %: "
                                                   + ", ".join(str(b['frame_seed']) for b in r['bad_seeds'])
                                                   for r in doc["rows"] if r["bad"]) + ")."
                         if wrong else "No wrong identification: the shared verification measures the focal "
                         "scale on the whole field once a proposal is accepted (the run of commit fa28f95, before that, "
                         "had 8 wrong identifications at 0.5-2 %: a scale fitted to the few stars near the core "
                         "left outer stars matched to a neighbour)."), ""]
    return "\n".join(lines) + "\n"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--results", default=os.path.join(ROOT, "examples", "results"))
    args = ap.parse_args(argv)
    for name, fn in (("paper-000.md", report_000), ("paper-001.md", report_001), ("paper-003.md", report_003),
                     ("paper-004.md", report_004)):
        text = fn(args.results)
        path = os.path.join(args.results, name)
        with open(path + ".part", "w") as fh:
            fh.write(text)
        os.replace(path + ".part", path)
        print(f"wrote {os.path.relpath(path, ROOT)}")


if __name__ == "__main__":
    main()
