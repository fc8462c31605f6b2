"""Identification beside cedar-solve and tetra3rs, feeds `make bench` section identify (results/results-2026-11-22.md).

The three tools get the same centroid lists (20 x 20 deg, Hp <= 5.0).

Scoring is the same for every tool: a frame is a success when the tool returns an
attitude whose boresight is within 0.1 degree of the truth and whose roll is within
1 degree (at 1 px centroid noise a correct identification of a few stars still errs by
several arcminutes in roll), a false match when it returns one farther off, a failure
when it returns none.
"""
from __future__ import annotations

import numpy as np
from common import attitude_correct, peer_correct


def _frames(cat, cam, sigma_px, false_stars, n, seed):
    from startrack.evaluate import Condition, make_frames

    return make_frames(cat, cam, Condition(sigma_px=sigma_px, false_stars=false_stars, mag_noise=0.1), n, seed,
                       mag_limit=5.0)


def run(n=1000, seed=11):
    from startrack.camera import Camera
    from startrack.catalog import load_catalog
    from startrack.identify import IdentifyParams, identify_stars
    from startrack.kvector import build_kvector, max_separation_deg
    from startrack.rotations import quaternion_to_dcm
    cat = load_catalog().filter_magnitude(None, 5.0)
    cam = Camera.from_fov(20, 1024, 1024)
    db = build_kvector(cat, max_separation_deg(20.0))
    peers = {}
    notes = []
    try:
        import tetra3rs_peer

        if tetra3rs_peer.is_available():
            peers["tetra3rs"] = tetra3rs_peer.build_or_load(20.0, 5.0, catalog="hip2")
    except Exception as exc:  # noqa: BLE001
        notes.append(f"tetra3rs unavailable: {type(exc).__name__}: {exc}")
    cedar = None
    try:
        import cedar_peer

        if cedar_peer.is_available():
            cedar = cedar_peer.CedarSolver(build_fov=20, mag=5.0)
    except Exception as exc:  # noqa: BLE001
        notes.append(f"cedar-solve unavailable: {type(exc).__name__}: {exc}")
    if not peers:
        notes.append("tetra3rs not installed (run `make bench-peers`)")
    if cedar is None:
        notes.append("cedar-solve not installed (run `make bench-peers`)")
    rows = []
    try:
        for label, sigma, nfalse in (("0.3 px", 0.3, 0), ("1 px", 1.0, 0), ("0.3 px + 10 false stars", 0.3, 10)):
            frames = _frames(cat, cam, sigma, nfalse, n, seed)
            results = {"startrack pyramid": [], "tetra3rs": [], "cedar-solve": []}
            params = IdentifyParams(sigma_px=sigma, max_stars=12 if nfalse == 0 else 16)
            identify_stars(frames[0][0], cam, db, "pyramid", params)  # load the kernels
            for stars, truth, _ in frames:
                res = identify_stars(stars, cam, db, "pyramid", params)
                if res.status == "ok":
                    good = attitude_correct(quaternion_to_dcm(res.quaternion_estimate), truth)
                    results["startrack pyramid"].append(("ok", good, res.time_ms))
                else:
                    results["startrack pyramid"].append(("fail", None, res.time_ms))
                xy = [[s["x"], s["y"]] for s in stars]
                if "tetra3rs" in peers:
                    r = tetra3rs_peer.solve(xy, 1024, 1024, 20.0, db=peers["tetra3rs"])
                    if r["ra"] is not None:
                        results["tetra3rs"].append(("ok", peer_correct(r, truth),
                                                     r["elapsed_ms"]))
                    else:
                        results["tetra3rs"].append(("fail", None, r["elapsed_ms"]))
                if cedar is not None:
                    r = cedar.solve_centroids(xy, 1024, 1024, 20.0)
                    t = r.get("t_solve_ms") or r.get("t_wall_ms") or float("nan")
                    if r.get("ra") is not None:
                        results["cedar-solve"].append(("ok", peer_correct(r, truth), t))
                    else:
                        results["cedar-solve"].append(("fail", None, t))
            base = None
            for tool, res in results.items():
                if not res:
                    continue
                ok = sum(1 for s, good, _ in res if s == "ok" and good)
                false = sum(1 for s, good, _ in res if s == "ok" and not good)
                times = np.array([t for _, _, t in res], dtype=float)
                med = float(np.nanmedian(times))
                if tool == "startrack pyramid":
                    base = med
                rows.append([label, tool, f"{100 * ok / len(res):.2f}%", f"{100 * false / len(res):.2f}%",
                             f"{med:.3f}", f"{np.nanpercentile(times, 95):.3f}",
                             f"{med / base:.1f}x" if base else ""])
    finally:
        if cedar is not None:
            cedar.close()
    return rows, notes
