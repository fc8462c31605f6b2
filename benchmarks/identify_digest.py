"""Feeds issue 42's must-show: a digest of identification results before/after a refactor.

Usage::

    PYTHONPATH=$PWD python benchmarks/identify_digest.py [--frames 100] [--skip-solve]

A fixed, seeded frame set (``--frames`` frames x 3 conditions -- 0.3 px noise; 3 false stars with
0.1 mag noise; a focal length 1 % off -- at 12 and 15 deg fields) is identified by every built-in
algorithm, once per path where two exist (the pyramid's fused search kernel and its Python loop; the
one-kernel verification and the step-by-step Python one), and a SHA-256 digest is printed over every
result's status, reason, reason code, matches, trials, quaternion, false-match probability, focal scale,
tolerance and details (``prepare_ms``, a time, left out).  The time budget is set out of reach
(``max_time_ms`` 1e7) so that only the proposal budgets end a search: the digest then does not depend on
the machine's load.  Then ``solve`` on the 8 ESA images of ``tests/data/real`` (statuses, matched ids,
attitude rounded to 1e-9).  Equal digests before and after a refactor: the same results.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import math
import os
import sys

import numpy as np
from common import esa_images

CONDITIONS = (("0.3 px", dict(sigma_px=0.3)),
              ("3 false, mag noise 0.1", dict(sigma_px=0.3, false_stars=3, mag_noise=0.1)),
              ("focal 1 % off", dict(sigma_px=0.3, focal_error_pct=1.0)))
FIELDS = ((12.0, 1024, 1024), (15.0, 1280, 960))
DB_MAG = 6.0


def _flags_module():
    """The module holding the driver's path switches (``FUSED_SEARCH``, ``FUSED_VERIFY``).

    (Before issue 42's split, ``startrack.identify.base``: run this script of that commit there.)"""
    from startrack.identify import driver

    return driver


def _number(v, nd=12):
    if v is None:
        return None
    v = float(v)
    return None if math.isnan(v) else float(f"{v:.{nd}g}")


def _plain(v):
    """A JSON-ready copy of a details value (numbers to 12 significant digits)."""
    if isinstance(v, dict):
        return {str(k): _plain(x) for k, x in sorted(v.items()) if k != "prepare_ms"}
    if isinstance(v, (list, tuple, np.ndarray)):
        return [_plain(x) for x in v]
    if isinstance(v, (bool, np.bool_)):
        return bool(v)
    if isinstance(v, (int, np.integer)):
        return int(v)
    if isinstance(v, (float, np.floating)):
        return _number(v)
    return str(v)


def record(res) -> list:
    """What the digest reads of one identification."""
    q = res.quaternion_estimate
    return [str(res.status), res.reason, None if res.reason_code is None else str(res.reason_code),
            [[int(m[0]), int(m[1])] for m in res.matches], res.trials,
            None if q is None else [_number(x) for x in np.asarray(q, dtype=float)],
            _number(res.false_match_probability), _number(res.focal_scale), _number(res.tolerance_arcsec),
            _plain(res.details)]


def identification_digests(n_frames: int) -> dict:
    from startrack.camera import Camera
    from startrack.catalog import load_catalog, merge_radius_arcsec
    from startrack.evaluate import Condition, make_frames
    from startrack.identify import IdentifyParams, identify_stars
    from startrack.kvector import build_kvector, max_separation_deg
    from startrack.labels import build_labels
    from startrack.triangles import build_triangles

    flags = _flags_module()
    catalog = load_catalog()
    out = {}
    for fov, w, h in FIELDS:
        cam = Camera.from_fov(fov, w, h)
        cat = catalog.filter_magnitude(None, DB_MAG).merge_close(merge_radius_arcsec(cam))
        dbs = {"kvector": build_kvector(cat, max_separation_deg(camera=cam)),
               "labels": build_labels(cat, fov, step_deg=1.0),
               "triangles": build_triangles(cat, max_separation_deg(camera=cam))}
        frames = []
        for k, (_, cond) in enumerate(CONDITIONS):
            frames += [s for s, _, _ in make_frames(cat, cam, Condition(**cond), n_frames, 420 + k, mag_limit=DB_MAG)]
        params = IdentifyParams(max_time_ms=1e7)
        for algorithm, kind, paths in (("pyramid", "kvector", ("fused", "python", "python-verify")),
                                       ("modified-pyramid", "triangles", ("fused-verify", "python-verify")),
                                       ("brightness", "kvector", ("fused-verify", "python-verify")),
                                       ("voting", "kvector", ("fused-verify", "python-verify")),
                                       ("labelling", "labels", ("fused-verify", "python-verify")),
                                       ("grid", "kvector", ("fused-verify", "python-verify"))):
            for path in paths:
                flags.FUSED_SEARCH = path == "fused"
                flags.FUSED_VERIFY = path != "python-verify"
                h_ = hashlib.sha256()
                ok = 0
                for stars in frames:
                    res = identify_stars(stars, cam, dbs[kind], algorithm, params)
                    ok += res.status == "ok"
                    h_.update(json.dumps(record(res), sort_keys=True).encode())
                key = f"{fov:g} deg {algorithm} {path}"
                out[key] = (h_.hexdigest(), ok, len(frames))
                print(f"{key:40s} {h_.hexdigest()}  ok {ok}/{len(frames)}", flush=True)
        flags.FUSED_SEARCH = flags.FUSED_VERIFY = True
    return out


def solve_digest() -> str:
    from startrack.solve import solve_image

    h_ = hashlib.sha256()
    for path in esa_images():
        res = solve_image(path)
        ident = res.identification
        att = res.attitude
        q = None if att is None or att.quaternion is None else [round(float(x), 9) for x in att.quaternion]
        row = [os.path.basename(path), str(res.status), None if ident is None else str(ident.status),
               None if ident is None else [[int(m[0]), int(m[1])] for m in ident.matches],
               None if att is None else str(att.status), q]
        print(f"  {os.path.basename(path)} {res.status} {0 if ident is None else len(ident.matches)} matches", flush=True)
        h_.update(json.dumps(row).encode())
    return h_.hexdigest()


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=100, help="frames per condition and field")
    ap.add_argument("--skip-solve", action="store_true", help="no digest of solve on the real images")
    ap.add_argument("--skip-identify", action="store_true", help="no digest of the identification frames")
    args = ap.parse_args(argv)
    digests = {} if args.skip_identify else identification_digests(args.frames)
    if digests:
        total = hashlib.sha256("".join(d for d, _, _ in digests.values()).encode()).hexdigest()
        print(f"{'all identification':40s} {total}")
    if not args.skip_solve:
        print(f"{'solve, 8 ESA images':40s} {solve_digest()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
