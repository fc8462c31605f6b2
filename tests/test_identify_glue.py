"""The Python around the identification's kernel (startrack.identify.driver.run, the pyramid's fused_pyramid, the
frame's arrays of startrack.identify.params) gives the same Identification as before it was made faster.

The oracle is a digest of every result (all fields but ``time_ms`` and the timed ``prepare_ms``) of a few hundred
frames of issue 14's comparison (``benchmarks/speed_path.py identify``: 15 deg 1280x960, database Hp <= 6,
stars to Hp 5.5, sigma 0.3 px), with the CLI's default final match against the shipped catalog and without it,
and of frames that take the other branches (false stars, a focal-length error, no fluxes, the stars' own
sigmas, a StarTable, frames too sparse to identify), made by the code before those changes (main 260aad2).
Floats are compared to 10 significant digits: a kernel compiled for another CPU may round the last bit
otherwise.  A change that *means* to change identification changes the digest: check that the change is the
intended one (``_records`` of both), then put the new digest here.

Beside it, oracles that need no stored value: a frame given as star dicts and as a StarTable (the two ways
:func:`run` reads a frame's arrays) identify alike, to the last bit.
"""
import hashlib
import json

import pytest
from conftest import kvector_sensor

from startrack.evaluate import Condition, make_frames
from startrack.identify import IdentifyParams, identify_stars
from startrack.identify.catalog_match import CatalogStars
from startrack.records import Match, StarTable

#: :func:`_digest` of :func:`_results` by the code of main 260aad2 (before the glue's cuts).
DIGEST = "fd0c190768b6a919be17b488db957ed0f6da0832f41223ae01c29ff5ccd3465a"


@pytest.fixture(scope="module")
def issue14(catalog):
    """Issue 14's 15 deg sensor (database Hp <= 6 merged for it, stars to Hp 5.5) and the shipped catalog for the
    final match."""
    return _sensor(catalog)


def _sensor(catalog):
    cam, db, stars = kvector_sensor(catalog, 15, 1280, 960, 6.0, 5.5)
    return cam, db, (stars, catalog.filter_magnitude(None, 6.5)), CatalogStars.from_catalog(catalog)


def _frames(cam, stars):
    """``(star list, params)`` of the frames: issue 14's 300, then the other branches' few (the last with stars
    to Hp 6.5, fainter than the database's: the final match adds them)."""
    stars, deeper = stars
    out = [(f, IdentifyParams(sigma_px=0.3)) for f, _, _ in
           make_frames(stars, cam, Condition(sigma_px=0.3, min_catalog_stars=4), 300, 14, mag_limit=5.5)]
    others = [(Condition(sigma_px=1.0, false_stars=3, min_catalog_stars=4), IdentifyParams(sigma_px=1.0)),
              (Condition(sigma_px=0.3, false_stars=10, mag_noise=0.2, min_catalog_stars=4), IdentifyParams(sigma_px=0.3)),
              (Condition(sigma_px=0.5, focal_error_pct=2.0, false_stars=1, min_catalog_stars=4), IdentifyParams()),
              (Condition(sigma_px=0.3, min_catalog_stars=2), IdentifyParams()),
              (Condition(sigma_px=0.3, min_catalog_stars=4), IdentifyParams(sigma_px=0.3))]
    for k, (cond, params) in enumerate(others):
        for i, (f, _, _) in enumerate(make_frames(deeper if k == 4 else stars, cam, cond, 20, 15 + k,
                                                  mag_limit=6.5 if k == 4 else 5.5)):
            out.append((f, params))
            if i % 4 == 0:
                out.append(([{"x": s["x"], "y": s["y"]} for s in f], params))                  # no fluxes
                out.append(([dict(s, sigma_px=0.2 + 0.01 * j) for j, s in enumerate(f)], params))   # own sigmas
                out.append((StarTable.from_list(f), params))
    return out


def _results(issue14):
    """Every frame's Identification with the final match (the CLI's default) and without it."""
    cam, db, stars, deep = issue14
    return [identify_stars(f, cam, db, "pyramid", params, catalog=catalog)
            for f, params in _frames(cam, stars) for catalog in (deep, None)]


def _number(v):
    return float(f"{v:.10g}") if isinstance(v, float) else v


def _record(res) -> dict:
    """An Identification's fields but ``time_ms`` (and ``prepare_ms``, timed), with each value's type."""
    assert all(type(m) is Match for m in res.matches)
    q = res.quaternion_estimate
    details = {k: (v if k != "prepare_ms" else "timed") for k, v in res.details.items()}
    return {"status": str(res.status), "algorithm": res.algorithm, "matches": [list(m) for m in res.matches],
            "reason": res.reason, "reason_code": str(res.reason_code),
            "false_match_probability": _number(res.false_match_probability), "trials": res.trials,
            "tolerance_arcsec": _number(res.tolerance_arcsec), "focal_scale": _number(res.focal_scale),
            "quaternion": None if q is None else [q.dtype.str] + [_number(v) for v in q.tolist()],
            "parity": res.parity, "details": {k: _number(v) for k, v in details.items()},
            "types": [type(getattr(res, k)).__name__ for k in ("false_match_probability", "trials",
                                                                "tolerance_arcsec", "focal_scale")]
            + [f"{k}:{type(v).__name__}" for k, v in res.details.items()]}


def _digest(results) -> str:
    return hashlib.sha256(json.dumps([_record(r) for r in results], sort_keys=True).encode()).hexdigest()


def test_identifications_are_those_of_the_code_before(issue14):
    results = _results(issue14)
    assert len(results) == 2 * (300 + 5 * 20 + 3 * 5 * 5)
    ok = sum(r.ok for r in results)
    assert 0.8 * len(results) < ok < len(results)          # both outcomes, and the final match, are in it
    assert any(r.details.get("matched_beyond_database") for r in results)
    assert _digest(results) == DIGEST


def test_star_dicts_and_a_star_table_identify_alike(issue14):
    cam, db, stars, deep = issue14
    for f, params in _frames(cam, stars)[::7]:
        if isinstance(f, StarTable):
            continue
        for catalog in (deep, None):
            a = identify_stars(f, cam, db, "pyramid", params, catalog=catalog)
            b = identify_stars(StarTable.from_list(f), cam, db, "pyramid", params, catalog=catalog)
            ra, rb = _record(a), _record(b)
            assert ra == rb
            assert (a.false_match_probability, a.tolerance_arcsec) == (b.false_match_probability, b.tolerance_arcsec)
            assert (a.quaternion_estimate is None) == (b.quaternion_estimate is None)
            if a.quaternion_estimate is not None:
                assert a.quaternion_estimate.tobytes() == b.quaternion_estimate.tobytes()


def test_the_fused_search_follows_each_frames_camera(issue14, monkeypatch):
    """run keeps the last camera's pinhole test by identity: frames alternating between a pinhole camera and a
    distorted one (the same sensor with k1 != 0, a frozen copy) take the fused kernel for the first only, and
    identify as each camera alone does."""
    import dataclasses

    from startrack.identify import driver
    from startrack.identify import pyramid as P

    cam, db, (stars, _), _ = issue14
    bent = dataclasses.replace(cam, k1=1e-9)
    assert bent.has_distortion and not cam.has_distortion
    frames = [f for f, _, _ in make_frames(stars, cam, Condition(sigma_px=0.3, min_catalog_stars=4), 6, 21,
                                            mag_limit=5.5)]
    params = IdentifyParams(sigma_px=0.3)

    def record(res):
        res.details.pop("prepare_ms", None)      # (the first frame of a camera prepares its first tier)
        return _record(res)

    alone = {}
    for c in (cam, bent):
        driver._PLAIN = (None, False)
        alone[id(c)] = [record(identify_stars(f, c, db, "pyramid", params)) for f in frames]
    drive = P._drive
    kernel_calls = []

    def counted(plan, args, frame):
        kernel_calls.append(1)
        return drive(plan, args, frame)

    monkeypatch.setattr(P, "_drive", counted)
    for k, f in enumerate(frames):
        for c in ((cam, bent) if k % 2 else (bent, cam)):
            before = len(kernel_calls)
            assert record(identify_stars(f, c, db, "pyramid", params)) == alone[id(c)][k]
            assert (len(kernel_calls) > before) == (c is cam)


if __name__ == "__main__":      # print the digest of this checkout's code (PYTHONPATH=the checkout)
    import sys

    from startrack.catalog import load_catalog

    sys.exit(print(_digest(_results(_sensor(load_catalog())))))
