"""Shared set-up of the benchmarks (feeds no figure itself): paths, peers, sensors, frames, scoring, timing, tables.

Every script of ``benchmarks/`` and ``benchmarks/studies/`` takes these from here instead of keeping a copy:

* paths: ``ROOT`` (the checkout), ``OUT_DIR`` (``bench-output/``), ``ESA_DIR`` and :func:`esa_images` /
  :func:`esa_references` (the 8 ESA images of ``tests/data/real`` and astrometry.net's solutions);
  importing this module also puts ``benchmarks/peers`` on ``sys.path`` (``import tetra3rs_peer``);
* sensors: :func:`sensor_spec` (paper 000's, paper 003's and a 15-degree tracker's camera and sensor),
  :func:`add_sensor_arguments` / :func:`sensor_setup` (issue 14's 15-degree sensor, its catalogs and
  conditions, shared by the identification scripts);
* scoring: :func:`attitude_correct` / :func:`peer_correct` (boresight within 0.1 deg and roll within 1 deg);
  :func:`sep_deg` (great-circle distance);
* timing and reports: :func:`timed` (median and p95 of repeated calls), :func:`load_average`, :func:`table`
  (a padded Markdown table).

Nothing here runs a benchmark or imports another benchmark script, so no import can run in a circle.
"""
from __future__ import annotations

import csv
import glob
import json
import math
import os
import statistics
import sys
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
PEERS = os.path.join(HERE, "peers")
OUT_DIR = os.path.join(ROOT, "bench-output")
ESA_DIR = os.path.join(ROOT, "tests", "data", "real")
if PEERS not in sys.path:
    sys.path.insert(0, PEERS)


# --- paths and data ------------------------------------------------------------------------------------------

def esa_images():
    """The 8 ESA test images (1024 x 768, 16-bit TIFF), sorted by name."""
    return sorted(glob.glob(os.path.join(ESA_DIR, "*.tiff")))


def esa_references(path=None):
    """astrometry.net's blind solutions of the ESA images (or of ``path``, a solutions.csv): ``{file name: row}``
    (``ra_deg``, ``dec_deg``, ``fov_x_deg``, ...)."""
    with open(path or os.path.join(ESA_DIR, "solutions.csv")) as fh:
        return {r["file"]: r for r in csv.DictReader(fh)}


# --- sensors -------------------------------------------------------------------------------------------------

def sensor_spec(name, psf_sigma=None, faint_snr=None):
    """``(camera, sensor, id magnitude range, render magnitude limit)`` of a named sensor.

    ``p000``: paper 000's 752 x 480, 6 um, f 41.1 mm (30.1"/px), Hp 2.5-6.59, 200 ms, rendered to Hp 7.5;
    ``p003``: paper 003's 20 x 20 deg, 1024 x 1024, 15 um, f 43.3 mm, Hp <= 5.0; ``15deg``: a 15-degree
    tracker, 1024 x 1024, Hp <= 5.5.  ``psf_sigma`` overrides the PSF; ``faint_snr`` sets the zero point so
    that the faintest identification star has that SNR.
    """
    from startrack.camera import Camera
    from startrack.render import Sensor

    if name == "p000":
        cam = Camera.from_focal_length_mm(41.1, 6.0, 752, 480)
        sensor = Sensor(psf_sigma_px=1.0, exposure_ms=200.0)
        mags, render_mag = (2.5, 6.59), 7.5
    elif name == "p003":
        cam = Camera.from_focal_length_mm(43.3, 15.0, 1024, 1024)
        sensor = Sensor(psf_sigma_px=1.0, exposure_ms=100.0)
        mags, render_mag = (None, 5.0), 6.0
    elif name == "15deg":
        cam = Camera.from_fov(15.0, 1024, 1024)
        sensor = Sensor(psf_sigma_px=1.0, exposure_ms=100.0)
        mags, render_mag = (None, 5.5), 6.5
    else:
        raise SystemExit(f"unknown sensor {name!r}")
    if psf_sigma is not None:
        sensor.psf_sigma_px = psf_sigma
    if faint_snr is not None:
        # Zero point such that the faintest identification star has SNR = faint_snr.
        from startrack.centroid_accuracy import flux_for_snr

        v = sensor.background_e + sensor.read_noise_e**2
        f = flux_for_snr(faint_snr, sensor.psf_sigma_px, v)
        sensor.zero_point_e_per_s = f / sensor.exposure_s * 10 ** (0.4 * mags[1])
        # (full well and gain unchanged: stars that saturate leave the bound and the estimate alike)
    return cam, sensor, mags, render_mag


def add_sensor_arguments(ap, count):
    """The sensor, catalogs and conditions of issue 14's comparison (15 deg 1280x960, database Hp <= 6, stars
    to Hp 5.5, seed 14), as options of ``ap``."""
    ap.add_argument("--fov", type=float, default=15.0)
    ap.add_argument("--size", default="1280x960")
    ap.add_argument("--db-mag", type=float, default=6.0)
    ap.add_argument("--star-mag", type=float, default=5.5)
    ap.add_argument("--min-stars", type=int, default=4,
                    help="catalog stars per frame at least (false stars not counted)")
    ap.add_argument("--count", type=int, default=count)
    ap.add_argument("--seed", type=int, default=14)
    ap.add_argument("--conditions", default="0.3:0,1.0:0,0.3:3,0.3:10",
                    help="sigma_px:false_stars, ... (identify_compare.py also takes "
                         "sigma_px:false_stars:focal_error_pct)")


def sensor_setup(args):
    """``(camera, merge_arcsec, database catalog, frame catalog)`` of :func:`add_sensor_arguments`' options."""
    from startrack.camera import Camera
    from startrack.catalog import DEFAULT_MERGE_PX, load_catalog, merge_radius_arcsec

    w, h = (int(v) for v in args.size.split("x"))
    cam = Camera.from_fov(args.fov, w, h)
    full = load_catalog()
    # As build-kvector --size does: stars closer than 2 px are one entry (the sensor sees one blob).
    merge_arcsec = merge_radius_arcsec(cam, DEFAULT_MERGE_PX)
    return (cam, merge_arcsec, full.filter_magnitude(None, args.db_mag).merge_close(merge_arcsec),
            full.filter_magnitude(None, args.star_mag))


# --- scoring -------------------------------------------------------------------------------------------------

def attitude_correct(dcm, truth):
    """True when ``dcm``'s boresight is within 0.1 deg and its roll within 1 deg of the truth's quaternion (at
    1 px centroid noise a correct identification of a few stars still errs by arcminutes in roll)."""
    from startrack.rotations import attitude_error, quaternion_to_dcm

    _, cross, roll = attitude_error(dcm, quaternion_to_dcm(truth["quaternion"]))
    return cross < 0.1 and abs(roll) < 1.0


def peer_correct(r, truth):
    """:func:`attitude_correct` of a peer's answer (a dict with ``ra``, ``dec``, ``roll`` in degrees)."""
    from startrack.rotations import radec_roll_to_dcm

    return attitude_correct(radec_roll_to_dcm(r["ra"], r["dec"], r["roll"]), truth)


def sep_deg(ra, dec, ra0, dec0):
    """Great-circle distance (deg) between two directions given in degrees."""
    a = np.radians([ra, dec, ra0, dec0])
    c = math.sin(a[1]) * math.sin(a[3]) + math.cos(a[1]) * math.cos(a[3]) * math.cos(a[0] - a[2])
    return math.degrees(math.acos(max(-1.0, min(1.0, c))))


# --- timing and reports --------------------------------------------------------------------------------------

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


def load_average():
    """The 1, 5 and 15 minute load averages, e.g. ``"0.52 0.61 0.70"`` (a timing means little above ~1.5)."""
    return " ".join(f"{v:.2f}" for v in os.getloadavg()) if hasattr(os, "getloadavg") else "n/a"


def table(headers, rows):
    """A Markdown table, columns padded to their widest cell."""
    widths = [max(len(str(h)), *(len(str(r[i])) for r in rows)) for i, h in enumerate(headers)]
    line = "| " + " | ".join(str(h).ljust(w) for h, w in zip(headers, widths)) + " |"
    sep = "|" + "|".join("-" * (w + 2) for w in widths) + "|"
    body = ["| " + " | ".join(str(c).ljust(w) for c, w in zip(r, widths)) + " |" for r in rows]
    return "\n".join([line, sep, *body])


def rendered_image_path(doc: dict, out: str) -> str:
    """The image of a rendered frame document: its ``image.path``, relative ones taken from ``out``."""
    p = doc["image"]["path"]
    return p if os.path.isabs(p) else os.path.join(out, os.path.basename(p))


def solve_saved(run, args: list, saved: str, score_only: bool = False) -> tuple[dict, float]:
    """``startrack solve`` of ``args`` through ``run(args)`` (a subprocess result), its documents kept in ``saved``
    (read back instead with ``score_only``): ``({image file name: document}, wall seconds)``."""
    t0 = time.perf_counter()
    if score_only:
        with open(saved) as f:
            stdout = f.read()
    else:
        proc = run(args)
        if proc.returncode == 2:
            raise SystemExit(f"solve refused its input:\n{proc.stderr}")
        stdout = proc.stdout
        with open(saved, "w") as f:
            f.write(stdout)
    wall = time.perf_counter() - t0
    solved = {}
    for line in stdout.splitlines():
        if line.strip():
            d = json.loads(line)
            solved[os.path.basename(d["image"]["path"])] = d
    return solved, wall


def cached_truth(out: str, count: int) -> list | None:
    """The frame documents a rendered set keeps in ``out/truth.jsonl``, when it holds ``count`` of them; else None
    (render the set again)."""
    path = os.path.join(out, "truth.jsonl")
    if not os.path.exists(path):
        return None
    with open(path) as f:
        docs = [json.loads(line) for line in f if line.strip()]
    return docs if len(docs) == count else None


def save_truth(out: str, docs: list) -> list:
    """Keep a rendered set's frame documents in ``out/truth.jsonl`` (read back by :func:`cached_truth`)."""
    with open(os.path.join(out, "truth.jsonl"), "w") as f:
        f.writelines(json.dumps(d) + "\n" for d in docs)
    return docs
