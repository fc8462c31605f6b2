"""The pyramid kernel's confirmation by a fourth star, against a brute-force search of the database.

Every row ``(r, I, J, K, R)`` of :func:`startrack._kernels.pyramid.pyramid_candidates` must name
the first fourth star ``r`` (after ``i, j, k``) for which exactly one catalog star ``R`` has its three
angles to ``I, J, K`` within the tolerances, and that ``R``; no earlier fourth star may have exactly
one.  Frames with 1 px noise and false stars give triads with several catalog triangles.
"""
import math

import numpy as np

from startrack.evaluate import Condition, make_frames
from startrack.identify import IdentifyParams, verify


def _window(b, tol, margin, u, v):
    """The cosine window of the image pair (u, v), as the kernel makes it."""
    th = math.acos(min(1.0, max(-1.0, float(b[u] @ b[v]))))
    e = math.sqrt(tol[u] ** 2 + tol[v] ** 2) + margin
    return math.cos(min(th + e, math.pi)), math.cos(max(th - e, 0.0))


def _unique_r(db, b, tol, margin, i, j, k, r, I, J, K):
    """The catalog stars R with the pair (I, R) in the database and the three angles in tolerance."""
    lo, hi = _window(b, tol, margin, i, r)
    sel = ((db.pair_i == I) | (db.pair_j == I)) & (db.pair_cos >= lo) & (db.pair_cos <= hi)
    cand = np.where(db.pair_i[sel] == I, db.pair_j[sel], db.pair_i[sel]).astype(np.int64)
    cand = cand[(cand != J) & (cand != K)]
    sv = db.star_vector
    for other, (u, v) in ((J, (j, r)), (K, (k, r))):
        lo, hi = _window(b, tol, margin, u, v)
        d = sv[cand] @ sv[other]
        cand = cand[(d >= lo) & (d <= hi)]
    return cand


def _triads(sensor15, cond, count, seed, sigma_px, n_triads):
    """``(b, tol, margin, i, j, k)`` of the first ``n_triads`` triads (smart index order) of ``count``
    frames of ``cond``: the search stars' vectors and tolerances as the driver makes them."""
    from startrack._kernels.pyramid import smart_triads

    cam, _, stars = sensor15
    params = IdentifyParams(sigma_px=sigma_px)
    margin = math.radians(params.margin_arcsec / 3600.0)
    for frame, _, _ in make_frames(stars, cam, cond, count, seed, mag_limit=5.5):
        xs = np.array([s["x"] for s in frame])
        ys = np.array([s["y"] for s in frame])
        b = np.ascontiguousarray(verify._pixels_to_vectors(cam, xs, ys)[:params.max_stars])
        tol = params.tolerance_sigma * np.full(len(b), sigma_px) / cam.focal_length_px
        for i, j, k in smart_triads(len(b))[:n_triads].tolist():
            yield b, tol, margin, i, j, k


def _brute_triangles(db, b, i, j, k, windows):
    """Every catalog triangle (I, J, K) of triad (i, j, k) by brute force: (I, J) a database pair in the
    window of (i, j) (either orientation), (I, K) one in that of (i, k), J-K's cosine in that of
    (j, k), and the triad's handedness.  ``windows``: the three cosine windows in that order."""
    (lo_ij, hi_ij), (lo_ik, hi_ik), (lo_jk, hi_jk) = windows
    sv = db.star_vector
    sel = (db.pair_cos >= lo_ij) & (db.pair_cos <= hi_ij)
    ij = np.concatenate([np.stack([db.pair_i[sel], db.pair_j[sel]], 1),
                         np.stack([db.pair_j[sel], db.pair_i[sel]], 1)]).astype(np.int64)
    sel = (db.pair_cos >= lo_ik) & (db.pair_cos <= hi_ik)
    partners = {}
    for a, z in zip(db.pair_i[sel].tolist(), db.pair_j[sel].tolist()):
        partners.setdefault(a, []).append(z)
        partners.setdefault(z, []).append(a)
    hand = np.linalg.det(np.stack([b[i], b[j], b[k]])) > 0
    for I, J in ij.tolist():
        for K in partners.get(I, []):
            d = float(sv[J] @ sv[K])
            if K != J and lo_jk <= d <= hi_jk and (np.linalg.det(np.stack([sv[I], sv[J], sv[K]])) > 0) == hand:
                yield I, J, K


def test_fourth_star_confirmation_matches_brute_force(sensor15):
    from startrack._kernels.pyramid import pyramid_candidates, smart_triads
    from startrack.identify.pyramid import pair_adjacency

    cam, db, stars = sensor15
    line = np.asarray(db.line, dtype=np.float64)
    quad = np.asarray(db.quad, dtype=np.float64)
    cond = Condition(sigma_px=1.0, false_stars=3, min_catalog_stars=4)
    params = IdentifyParams(sigma_px=1.0)
    margin = math.radians(params.margin_arcsec / 3600.0)
    rows = multi = 0
    for frame, _, _ in make_frames(stars, cam, cond, 40, 7, mag_limit=5.5):
        xs = np.array([s["x"] for s in frame])
        ys = np.array([s["y"] for s in frame])
        b = np.ascontiguousarray(verify._pixels_to_vectors(cam, xs, ys)[:params.max_stars])
        n = len(b)
        tol = params.tolerance_sigma * np.full(n, 1.0) / cam.focal_length_px
        for i, j, k in smart_triads(n)[:6].tolist():
            out, n_tri = pyramid_candidates(b, tol, margin, i, j, k, db.star_vector, db.pair_i, db.pair_j,
                                            db.pair_cos, db.kvector, line, db.kquad, quad, False, 64, 256,
                                            *pair_adjacency(db), 0.0)
            multi += len(out) >= 2
            for r, I, J, K, R in out.tolist():
                rows += 1
                fourth = [s for s in range(n) if s not in (i, j, k)]
                for s in fourth[:fourth.index(r)]:
                    assert len(_unique_r(db, b, tol, margin, i, j, k, s, I, J, K)) != 1
                assert _unique_r(db, b, tol, margin, i, j, k, r, I, J, K).tolist() == [R]
    assert rows >= 100 and multi >= 5, (rows, multi)


def test_triangles_match_brute_force(sensor15):
    """The number of catalog triangles of a triad is that of a brute-force search: every ordered pair
    (I, J) of the database at theta_ij, K paired with I at theta_ik, the angle J-K within its window
    and the same handedness.  At 20 deg of pair range and 1 px noise windows hold hundreds of
    pairs, so stars left out by any shortcut (the theta_jk pre-filter) would change the count."""
    from startrack._kernels.pyramid import pyramid_candidates
    from startrack.identify.pyramid import pair_adjacency

    _, db, _ = sensor15
    line = np.asarray(db.line, dtype=np.float64)
    quad = np.asarray(db.quad, dtype=np.float64)
    checked = found = 0
    for b, tol, margin, i, j, k in _triads(sensor15, Condition(sigma_px=1.0, false_stars=3, min_catalog_stars=4),
                                           15, 3, 1.0, 8):
        _, n_tri = pyramid_candidates(b, tol, margin, i, j, k, db.star_vector, db.pair_i, db.pair_j,
                                      db.pair_cos, db.kvector, line, db.kquad, quad, False, 10_000, 256,
                                      *pair_adjacency(db), 0.0)
        want = sum(1 for _ in _brute_triangles(db, b, i, j, k, [_window(b, tol, margin, u, v)
                                                                for u, v in ((i, j), (i, k), (j, k))]))
        assert n_tri == want, (i, j, k, n_tri, want)
        checked += 1
        found += want
    assert checked >= 100 and found >= 150, (checked, found)


def test_first_at_or_above_is_searchsorted():
    """The fourth star's look-up in a star's pairs (:func:`_first_at_or_above`) is ``np.searchsorted``'s
    left index for any ascending values, query, and spread bounds (true ones, wrong ones, equal ones),
    with ties, values outside the bounds and empty ranges; the neighbours outside the range are never
    taken."""
    from startrack._kernels.common import _first_at_or_above

    rng = np.random.default_rng(1)
    for _ in range(5000):
        n = int(rng.integers(0, 60))
        if rng.random() < 0.7:
            a = np.sort(rng.uniform(-0.2, 1.0, n))
        else:
            a = np.sort(rng.choice(np.linspace(0.0, 1.0, 7), n))        # ties
        arr = np.concatenate([[-9.0, -8.0], a, [8.0, 9.0]])
        x = float(rng.uniform(-0.5, 1.5)) if n == 0 or rng.random() < 0.5 else float(a[rng.integers(n)])
        lo, hi = (-0.2, 1.0) if rng.random() < 0.7 else tuple(np.sort(rng.uniform(-1.0, 2.0, 2)))
        assert _first_at_or_above(arr, 2, 2 + n, x, lo, hi) == 2 + np.searchsorted(a, x)


def test_sort_indices_is_a_sort():
    """The cone's sort of star indices (insertion up to 24, radix beyond) orders any distinct non-negative
    integers as ``np.sort`` does, for one to five bytes of value, and leaves the rest of the array alone."""
    from startrack._kernels.common import _sort_indices

    rng = np.random.default_rng(3)
    for _ in range(400):
        top = int(rng.choice([30, 256, 257, 5000, 117955, 2**33]))
        n = int(rng.integers(0, min(top, 400)))
        a = rng.choice(top, size=n, replace=False).astype(np.int64)
        arr = np.concatenate([a, [-5, 7]])
        _sort_indices(arr, n)
        assert np.array_equal(arr[:n], np.sort(a)) and list(arr[n:]) == [-5, 7]


def test_triangles_with_a_free_focal_length_match_brute_force(sensor15):
    """With the focal length free within 3 % (``focal_error``), a triad's triangles are the brute-force
    ones: the three sides within the widened windows ``[theta (1 - f) - e, theta (1 + f) + e]``, the
    same handedness, and one scale for all three (the scales each side allows, ``[(a - e) / theta,
    (a + e) / theta]``, overlap within ``1 +- f``).  The frames are seen through a focal length 2 %
    off, so the true triangles are found only this way."""
    from startrack._kernels.pyramid import pyramid_candidates
    from startrack.identify.pyramid import pair_adjacency

    _, db, _ = sensor15
    line = np.asarray(db.line, dtype=np.float64)
    quad = np.asarray(db.quad, dtype=np.float64)
    sv = db.star_vector
    ferr = 0.03
    checked = found = 0
    for b, tol, margin, i, j, k in _triads(sensor15, Condition(sigma_px=0.3, focal_error_pct=2.0, min_catalog_stars=4),
                                           6, 5, 0.3, 4):
        _, n_tri = pyramid_candidates(b, tol, margin, i, j, k, sv, db.pair_i, db.pair_j, db.pair_cos,
                                      db.kvector, line, db.kquad, quad, False, 100_000, 256,
                                      *pair_adjacency(db), ferr)
        sides = []
        for u, v in ((i, j), (i, k), (j, k)):
            th = math.acos(min(1.0, float(b[u] @ b[v])))
            e = math.sqrt(tol[u] ** 2 + tol[v] ** 2) + margin
            sides.append((th, e, (math.cos(min(th * (1 + ferr) + e, math.pi)), math.cos(max(th * (1 - ferr) - e, 0)))))
        want = 0
        for I, J, K in _brute_triangles(db, b, i, j, k, [w for _, _, w in sides]):
            lo, hi = 1 - ferr, 1 + ferr
            for (th, e, _), (P, Q) in zip(sides, ((I, J), (I, K), (J, K))):
                a = math.acos(min(1.0, max(-1.0, float(sv[P] @ sv[Q]))))
                lo, hi = max(lo, (a - e) / th), min(hi, (a + e) / th)
            want += lo <= hi
        assert n_tri == want, (i, j, k, n_tri, want)
        checked += 1
        found += want
    assert checked >= 20 and found >= 20, (checked, found)
