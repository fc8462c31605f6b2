"""The pyramid kernel's confirmation by a fourth star, against a brute-force search of the database.

Every row ``(r, I, J, K, R)`` of :func:`startrack._kernels.identify.pyramid_candidates` must name
the first fourth star ``r`` (after ``i, j, k``) for which exactly one catalog star ``R`` has its three
angles to ``I, J, K`` within the tolerances, and that ``R``; no earlier fourth star may have exactly
one.  Frames with 1 px noise and false stars give triads with several catalog triangles.
"""
import math

import numpy as np
import pytest

from startrack.camera import Camera
from startrack.evaluate import Condition, make_frames
from startrack.identify import IdentifyParams, base


@pytest.fixture(scope="module")
def setup(catalog):
    from startrack.catalog import merge_radius_arcsec
    from startrack.kvector import build_kvector, max_separation_deg

    cam = Camera.from_fov(15, 1280, 960)
    db = build_kvector(catalog.filter_magnitude(None, 6.0).merge_close(merge_radius_arcsec(cam)),
                       max_separation_deg(camera=cam))
    return cam, db, catalog.filter_magnitude(None, 5.5)


def _unique_r(db, b, tol, margin, i, j, k, r, I, J, K):
    """The catalog stars R with the pair (I, R) in the database and the three angles in tolerance."""
    def window(u, v):
        th = math.acos(min(1.0, float(b[u] @ b[v])))
        e = math.sqrt(tol[u] ** 2 + tol[v] ** 2) + margin
        return math.cos(min(th + e, math.pi)), math.cos(max(th - e, 0.0))

    lo, hi = window(i, r)
    sel = ((db.pair_i == I) | (db.pair_j == I)) & (db.pair_cos >= lo) & (db.pair_cos <= hi)
    cand = np.where(db.pair_i[sel] == I, db.pair_j[sel], db.pair_i[sel]).astype(np.int64)
    cand = cand[(cand != J) & (cand != K)]
    sv = db.star_vector
    for other, (u, v) in ((J, (j, r)), (K, (k, r))):
        lo, hi = window(u, v)
        d = sv[cand] @ sv[other]
        cand = cand[(d >= lo) & (d <= hi)]
    return cand


def test_fourth_star_confirmation_matches_brute_force(setup):
    from startrack._kernels.identify import pyramid_candidates, smart_triads
    from startrack.identify.pyramid import pair_adjacency

    cam, db, stars = setup
    line = np.asarray(db.line, dtype=np.float64)
    quad = np.asarray(db.quad, dtype=np.float64)
    cond = Condition(sigma_px=1.0, false_stars=3, min_catalog_stars=4)
    params = IdentifyParams(sigma_px=1.0)
    margin = math.radians(params.margin_arcsec / 3600.0)
    rows = multi = 0
    for frame, _, _ in make_frames(stars, cam, cond, 40, 7, mag_limit=5.5):
        xs = np.array([s["x"] for s in frame])
        ys = np.array([s["y"] for s in frame])
        b = np.ascontiguousarray(base._pixels_to_vectors(cam, xs, ys)[:params.max_stars])
        n = len(b)
        tol = params.tolerance_sigma * np.full(n, 1.0) / cam.focal_length_px
        for i, j, k in smart_triads(n)[:6].tolist():
            out, n_tri = pyramid_candidates(b, tol, margin, i, j, k, db.star_vector, db.pair_i, db.pair_j,
                                            db.pair_cos, db.kvector, line, db.kquad, quad, False, 64, 256,
                                            *pair_adjacency(db))
            multi += len(out) >= 2
            for r, I, J, K, R in out.tolist():
                rows += 1
                fourth = [s for s in range(n) if s not in (i, j, k)]
                for s in fourth[:fourth.index(r)]:
                    assert len(_unique_r(db, b, tol, margin, i, j, k, s, I, J, K)) != 1
                assert _unique_r(db, b, tol, margin, i, j, k, r, I, J, K).tolist() == [R]
    assert rows >= 100 and multi >= 5, (rows, multi)
