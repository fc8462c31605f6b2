"""astrometry.net's ``solve-field`` as a benchmark peer.  Bench-only.

Needs the Debian packages ``astrometry.net`` and ``astrometry-data-tycho2-10-19`` (the
Tycho-2 index files 10-19, skymark diameters ~ 6' .. 2000', i.e. fields ~0.1 to ~10+ deg):
``bash benchmarks/peers/setup_peers.sh`` installs them as root.

    from astrometry_peer import solve_field
    r = solve_field("img.tiff", 10.0, 13.0, timeout_s=60)
    # {'status': 'solved', 'ra':..., 'dec':..., 'orientation':..., 'elapsed_ms':..., ...}

Conventions (measured, see README.md):

* For a TIFF/PNG/JPEG input, astrometry.net's FITS pixel ``(X, Y)`` (1-based) is startrack's
  ``(x + 1, y + 1)``: the rows are **not** flipped, so astropy's 0-based pixel coordinates on
  the ``.wcs`` equal startrack's pixel coordinates directly.
* ``ra``/``dec`` here are of the geometric image centre, pixel ``((W-1)/2, (H-1)/2)``,
  evaluated through the full TAN-SIP WCS (astrometry.net's own "Field center" agrees).
* ``orientation`` is startrack's roll: the position angle, east of north, of image *up*
  (``-y``, towards row 0) at the image centre, computed from the WCS.  astrometry.net's log
  line "up is X degrees E of N" (kept as ``orientation_an``) is a different angle: it is the
  direction of FITS ``+Y`` (i.e. image *down* for a TIFF) and is evaluated at CRPIX, not at
  the image centre, so ``orientation ~= orientation_an + 180`` up to the meridian convergence
  between CRPIX and the centre (~0.4 deg on the ESA images).
"""
from __future__ import annotations

import math
import os
import re
import shutil
import subprocess
import tempfile
import time
import warnings

import numpy as np

SOLVE_FIELD = "solve-field"


def is_available() -> bool:
    return shutil.which(SOLVE_FIELD) is not None


def _image_size(path):
    """(width, height) of the image, from astropy (FITS) or OpenCV / Pillow (others)."""
    if path.lower().endswith((".fits", ".fit", ".fts")):
        from astropy.io import fits

        h = fits.getheader(path)
        return int(h["NAXIS1"]), int(h["NAXIS2"])
    try:
        import cv2

        im = cv2.imread(path, cv2.IMREAD_UNCHANGED)
        if im is not None:
            return int(im.shape[1]), int(im.shape[0])
    except ImportError:
        pass
    from PIL import Image

    with Image.open(path) as im:
        return im.size


def _pa_deg(ra0, dec0, ra1, dec1):
    """Position angle (deg, east of north, [0, 360)) of point 1 seen from point 0."""
    ra0, dec0, ra1, dec1 = map(math.radians, (ra0, dec0, ra1, dec1))
    d = ra1 - ra0
    pa = math.atan2(math.sin(d) * math.cos(dec1),
                    math.cos(dec0) * math.sin(dec1) - math.sin(dec0) * math.cos(dec1) * math.cos(d))
    return math.degrees(pa) % 360.0


def wcs_solution(wcs_path, width, height):
    """Centre RA/Dec, roll (PA of image up, startrack convention), FOV and pixel scale."""
    from astropy.io import fits
    from astropy.wcs import WCS

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        w = WCS(fits.getheader(wcs_path))
    cx, cy = (width - 1) / 2.0, (height - 1) / 2.0
    pts = np.array([[cx, cy], [cx, cy - 1.0], [-0.5, cy], [width - 0.5, cy],
                    [cx, -0.5], [cx, height - 0.5]])
    sky = w.all_pix2world(pts, 0)
    ra, dec = float(sky[0, 0]), float(sky[0, 1])

    def sep_deg(a, b):
        a, b = np.radians(a), np.radians(b)
        va = np.array([np.cos(a[0]) * np.cos(a[1]), np.sin(a[0]) * np.cos(a[1]), np.sin(a[1])])
        vb = np.array([np.cos(b[0]) * np.cos(b[1]), np.sin(b[0]) * np.cos(b[1]), np.sin(b[1])])
        return math.degrees(math.acos(max(-1.0, min(1.0, float(va @ vb)))))

    return {
        "ra": ra % 360.0, "dec": dec,
        "orientation": _pa_deg(ra, dec, sky[1, 0], sky[1, 1]),
        "fov_x_deg": sep_deg(sky[2], sky[3]), "fov_y_deg": sep_deg(sky[4], sky[5]),
    }


def solve_field(image_path, scale_low, scale_high, timeout_s=60.0, *, extra_args=(),
                keep_dir=None, downsample=None):
    """Run ``solve-field`` on one image and parse the result.

    ``scale_low``/``scale_high`` bound the image *width* in degrees (``--scale-units
    degwidth``).  ``timeout_s`` is passed as ``--cpulimit`` and also enforced on the
    process.  Runs in a fresh temporary directory (removed afterwards unless ``keep_dir``).

    Returns a dict: ``status`` ("solved", "unsolved", "timeout", "error", "unavailable"),
    ``ra``, ``dec`` (image centre, deg), ``orientation`` (startrack roll, deg),
    ``orientation_an`` (astrometry.net's printed "up is X deg E of N"), ``fov_x_deg``,
    ``fov_y_deg``, ``parity``, ``index`` (the index file that solved it) and ``elapsed_ms``
    (wall time of the whole solve-field process: image conversion, source extraction with
    its own simplexy, solving and writing the outputs).
    """
    out = {"status": "error", "ra": None, "dec": None, "orientation": None,
           "elapsed_ms": None, "image": image_path}
    if not is_available():
        out["status"] = "unavailable"
        out["error"] = "solve-field not found (run benchmarks/peers/setup_peers.sh as root)"
        return out
    image_path = os.path.abspath(image_path)
    tmp = keep_dir or tempfile.mkdtemp(prefix="anpeer-")
    os.makedirs(tmp, exist_ok=True)
    base = "field"
    cmd = [SOLVE_FIELD, "--no-plots", "--overwrite", "--scale-units", "degwidth",
           "--scale-low", f"{scale_low:g}", "--scale-high", f"{scale_high:g}",
           "--dir", tmp, "--out", base, "--temp-dir", tmp,
           "--cpulimit", str(max(1, int(math.ceil(timeout_s)))),
           "--new-fits", "none"]
    if downsample:
        cmd += ["--downsample", str(int(downsample))]
    cmd += list(extra_args) + [image_path]
    t0 = time.perf_counter()
    try:
        proc = subprocess.run(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                              timeout=timeout_s + 10.0)
        log = proc.stdout
    except subprocess.TimeoutExpired as exc:
        out["elapsed_ms"] = (time.perf_counter() - t0) * 1000.0
        out["status"] = "timeout"
        out["log_tail"] = (exc.stdout or "")[-2000:] if isinstance(exc.stdout, str) else ""
        if not keep_dir:
            shutil.rmtree(tmp, ignore_errors=True)
        return out
    out["elapsed_ms"] = (time.perf_counter() - t0) * 1000.0
    try:
        m = re.search(r"up is ([-+0-9.eE]+) degrees E of N", log)
        if m:
            out["orientation_an"] = float(m.group(1))
        m = re.search(r"Field parity: (\w+)", log)
        if m:
            out["parity"] = m.group(1)
        m = re.search(r"solved with index (\S+?)\.?\s*$", log, re.M)
        if m:
            out["index"] = m.group(1)
        wcs_path = os.path.join(tmp, base + ".wcs")
        if os.path.exists(os.path.join(tmp, base + ".solved")) and os.path.exists(wcs_path):
            width, height = _image_size(image_path)
            out.update(wcs_solution(wcs_path, width, height))
            out["status"] = "solved"
        else:
            out["status"] = "timeout" if "cpu time limit" in log.lower() or \
                "time limit" in log.lower() else "unsolved"
            if proc.returncode != 0:
                out["status"] = "error"
                out["returncode"] = proc.returncode
            out["log_tail"] = log[-2000:]
    finally:
        if not keep_dir:
            shutil.rmtree(tmp, ignore_errors=True)
    return out


if __name__ == "__main__":  # python benchmarks/peers/astrometry_peer.py IMG LOW HIGH
    import json
    import sys

    print(json.dumps(solve_field(sys.argv[1], float(sys.argv[2]), float(sys.argv[3])), indent=1))
