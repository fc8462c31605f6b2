"""The scale-invariant pattern index: file round trip, blind identification at several fields, no wrong answer."""
import json
import math
import os

import numpy as np
import pytest

from startrack.camera import Camera
from startrack.patterns import BlindOptions, build_index, open_index, save_index, solve_blind
from startrack.records import Identification, Match
from startrack.render import Scene, Sensor, star_list
from startrack.rotations import _attitude_error_rad, quaternion_to_dcm, random_quaternions

# A small index (stars to Hp 6, pattern sizes 4-23 deg) keeps the test fast; the default index
# is the same code with more levels and a deeper catalog.
PARAMS = {"levels_deg": [4.0 * math.sqrt(2) ** k for k in range(6)]}


@pytest.fixture(scope="module")
def index(catalog, tmp_path_factory):
    idx = build_index(catalog.filter_magnitude(None, 6.0), params=PARAMS)
    path = tmp_path_factory.mktemp("idx") / "p.idx"
    save_index(idx, str(path))
    return idx, open_index(str(path))


def test_file_round_trip_is_exact(index):
    built, opened = index
    for name in ("star_id", "star_vec", "level_rho", "level_start", "level_prefix", "patterns", "keys", "shapes"):
        assert np.array_equal(np.asarray(getattr(built, name)), np.asarray(getattr(opened, name))), name
    assert opened.params["patterns_per_level"] == built.params["patterns_per_level"]
    assert len(opened.keys) > 10000


@pytest.mark.parametrize("fov", [10.0, 20.0, 30.0])
def test_blind_identification_measures_the_focal_length(index, catalog, fov):
    _, idx = index
    cat = catalog.filter_magnitude(None, 6.0)
    rng = np.random.default_rng(int(fov))
    cam = Camera.from_fov(fov, 1024, 768)
    rows, vec = cat.rows_by_id(), cat.vectors()
    solved = tried = 0
    for q in random_quaternions(10, rng):
        dcm = quaternion_to_dcm(q)
        stars, truth = star_list(cat, cam, dcm, Sensor(), Scene(mag_limit=6.0), rng, sigma_px=0.3, max_stars=40)
        if len(stars) < 8:
            continue
        tried += 1
        fitted, res, _ = solve_blind(stars, 1024, 768, idx, BlindOptions(timeout_s=5.0))
        if res.status != "ok":
            continue
        solved += 1
        # Every match is the true star; the focal length is right to 0.1 % (0.3 % above 25 deg,
        # where k1 is fitted with it).
        # (or its unresolved neighbour, within 2 px, when the centroid is a blend of the two).
        # The one identification type of every path (issue 42): an Identification of Match(star, id).
        assert type(res) is Identification and all(type(m) is Match for m in res.matches)
        ids = truth["star_ids"]
        for m in res.matches:
            if ids[m.star] != m.id:
                a, b = vec[rows[m.id]], vec[rows[ids[m.star]]]
                assert math.acos(min(1.0, float(a @ b))) * cam.focal_length_px < 2.0
        assert fitted.focal_length_px == pytest.approx(cam.focal_length_px, rel=1e-3 if fov < 25 else 3e-3)
        _, cross, roll = _attitude_error_rad(quaternion_to_dcm(res.quaternion_estimate), dcm)
        assert math.degrees(cross) * 3600 < 30 and abs(math.degrees(roll)) * 3600 < 300
    assert tried >= 5 and solved >= 0.8 * tried


def test_random_stars_are_never_identified(index):
    """Noise (random positions) must fail with a reason, never a wrong ok."""
    _, idx = index
    rng = np.random.default_rng(5)
    for _ in range(5):
        xy = rng.uniform([0, 0], [1024, 768], size=(40, 2))
        stars = [{"x": float(x), "y": float(y), "flux": float(1000 - i)} for i, (x, y) in enumerate(xy)]
        cam, res, _ = solve_blind(stars, 1024, 768, idx, BlindOptions(timeout_s=1.0))
        assert cam is None and res.status == "failed" and res.reason


def test_the_lookup_mask_drops_exactly_the_patterns_with_a_star_outside(index, catalog):
    """query_patterns with ``allowed``: its candidates are those of the whole sky whose four catalog stars are all
    allowed (the unmasked look-up filtered afterwards is the oracle), in the same order."""
    from startrack._kernels.patterns import query_patterns
    from startrack.patterns import LEVEL_RATIO, _combos

    _, idx = index
    cat = catalog.filter_magnitude(None, 6.0)
    cam = Camera.from_fov(15.0, 1024, 768)
    rng = np.random.default_rng(40)
    stars, _ = star_list(cat, cam, quaternion_to_dcm(random_quaternions(1, rng)[0]), Sensor(), Scene(mag_limit=6.0),
                         rng, sigma_px=0.3, max_stars=12)
    xy = np.array([[s["x"], s["y"]] for s in stars])
    combos = _combos(len(xy))
    args = (idx.level_rho, LEVEL_RATIO, idx.level_start, idx.level_prefix, idx.keys, idx.patterns, idx.shapes,
            idx.star_vec)
    every = np.ones(len(idx.star_id), dtype=np.uint8)
    ci, cf = query_patterns(xy, 511.5, 383.5, combos, *args, every, 1.0, 0.1, 500.0, 20000.0, 100000)
    assert len(ci) > 20
    allowed = (rng.uniform(size=len(idx.star_id)) < 0.7).astype(np.uint8)
    mi, mf = query_patterns(xy, 511.5, 383.5, combos, *args, allowed, 1.0, 0.1, 500.0, 20000.0, 100000)
    keep = np.all(allowed[ci[:, 2:6]] == 1, axis=1)
    assert 0 < len(mi) < len(ci)
    np.testing.assert_array_equal(mi, ci[keep])
    np.testing.assert_array_equal(mf, cf[keep])


def test_a_position_hint_keeps_the_answer_and_refuses_elsewhere(index, catalog):
    from startrack.rotations import dcm_to_radec_roll

    _, idx = index
    cat = catalog.filter_magnitude(None, 6.0)
    cam = Camera.from_fov(20.0, 1024, 768)
    rng = np.random.default_rng(41)
    done = 0
    for q in random_quaternions(6, rng):
        dcm = quaternion_to_dcm(q)
        stars, _ = star_list(cat, cam, dcm, Sensor(), Scene(mag_limit=6.0), rng, sigma_px=0.3, max_stars=40)
        if len(stars) < 8:
            continue
        _, blind, _ = solve_blind(stars, 1024, 768, idx, BlindOptions(timeout_s=5.0))
        if blind.status != "ok":
            continue
        ra, dec, _ = dcm_to_radec_roll(dcm)
        near = BlindOptions(timeout_s=5.0, sky_circle=(float(ra) + 1.0, float(np.clip(dec - 1.0, -90, 90)), 3.0))
        _, hinted, _ = solve_blind(stars, 1024, 768, idx, near)
        assert hinted.status == "ok" and hinted.matches == blind.matches
        far = BlindOptions(timeout_s=5.0, sky_circle=((float(ra) + 180.0) % 360.0, -float(dec), 10.0))
        _, elsewhere, _ = solve_blind(stars, 1024, 768, idx, far)
        assert elsewhere.status == "failed"
        done += 1
    assert done >= 3


def _confidence_reference(b, img, cat, star_vec, dcm, cos_fov, radius, eps):
    """The numpy form of the blind verification's confidence numbers (as the search computed them before
    startrack._kernels.verify.blind_confidence; a detection's own star, one predicted within ``radius``, not
    counted in the density around it)."""
    from startrack.patterns import _pattern_chance

    predicted = star_vec[cat] @ dcm.T
    ok = np.einsum("ij,ij->i", b[img], predicted) >= math.cos(radius)
    others = np.delete(np.arange(len(b)), img[:4])
    pred = star_vec[star_vec @ dcm[2] > cos_fov] @ dcm.T
    p_local = -1.0
    if len(others) and len(pred):
        dots = b[others] @ pred.T
        counts = np.sum(dots >= math.cos(10.0 * radius), axis=1) - np.any(dots >= math.cos(radius), axis=1)
        p_local = float(np.mean(np.minimum(1.0, counts * 0.01)))
    return int(ok.sum()), int(ok[:4].sum()), p_local, _pattern_chance(len(star_vec), eps, b[img[:4]])


@pytest.mark.parametrize("seed", range(6))
def test_blind_confidence_kernel_matches_its_numpy_reference(seed):
    from startrack._kernels.verify import blind_confidence

    rng = np.random.default_rng(seed)
    q = random_quaternions(1, rng)[0]
    dcm = quaternion_to_dcm(q)
    # Catalog stars around the boresight (and elsewhere), the image: some of them seen with noise, some not.
    star_vec = rng.normal(size=(400, 3)) * [0.08, 0.08, 1.0] * rng.choice([1, -1], size=(400, 1))
    star_vec = dcm.T @ (star_vec / np.linalg.norm(star_vec, axis=1)[:, None]).T
    star_vec = np.ascontiguousarray(star_vec.T)
    front = np.flatnonzero(star_vec @ dcm[2] > math.cos(0.15))
    seen = rng.choice(front, size=min(len(front), 3 + seed * 5), replace=False)
    b = (star_vec[seen] @ dcm.T) + rng.normal(scale=2e-4, size=(len(seen), 3))
    b = np.vstack([b, rng.normal(size=(seed, 3)) * [0.05, 0.05, 1.0] + [0, 0, 1.0]])
    b = np.ascontiguousarray(b / np.linalg.norm(b, axis=1)[:, None])
    n_img = min(len(seen), 4 + seed)
    img = np.arange(n_img, dtype=np.int64)
    cat = np.array(seen[:n_img], dtype=np.int64)
    if seed % 2:
        cat[-1] = front[0] if front[0] != cat[-1] else front[1]    # a proposal star that does not agree
    for radius in (3e-4, 2e-3):
        got = blind_confidence(b, img, cat, star_vec, dcm, math.cos(0.15), radius, len(star_vec), 1e-4)
        want = _confidence_reference(b, img, cat, star_vec, dcm, math.cos(0.15), radius, 1e-4)
        assert got[:2] == want[:2]
        assert got[2] == pytest.approx(want[2], rel=1e-12, abs=1e-15)
        assert got[3] == pytest.approx(want[3], rel=1e-9)


def test_blind_confidence_does_not_count_the_star_a_detection_landed_on():
    """The density around another detection is that of the stars it did not land on: a detection on a lone star
    has no neighbour (0), one on a star with three more within ten radii has three, an unmatched one with one
    star within ten radii has one.  (Counting the landed-on star gave 1, 4 and 1: every matched detection at least
    1/100, and sparse true fields refused.)"""
    from startrack._kernels.verify import blind_confidence

    def unit(x, y):
        v = np.array([x, y, 1.0])
        return v / np.linalg.norm(v)

    r = 1e-4
    core = [unit(0.01, 0.0), unit(-0.01, 0.005), unit(0.0, -0.01), unit(0.008, 0.008)]
    lone, crowded, unmatched = unit(0.02, 0.02), unit(-0.02, 0.02), unit(0.0, 0.03)
    neighbours = [unit(-0.02 + 5 * r, 0.02), unit(-0.02, 0.02 + 5 * r), unit(-0.02 - 5 * r, 0.02)]
    star_vec = np.ascontiguousarray(np.vstack(core + [lone, crowded] + neighbours + [unit(0.0, 0.03 + 3 * r)]))
    b = np.ascontiguousarray(np.vstack(core + [lone, crowded, unmatched]))
    img = np.arange(4, dtype=np.int64)
    got = blind_confidence(b, img, img.copy(), star_vec, np.eye(3), math.cos(0.1), r, len(star_vec), 1e-4)
    assert got[:2] == (4, 4)
    assert got[2] == pytest.approx((0 + 3 + 1) * 0.01 / 3, rel=1e-12)


@pytest.mark.parametrize("fov, cx_shift", [(2.0, 0.0), (11.4, 0.0), (30.0, 37.5), (70.0, -120.0)])
def test_pinhole_cone_without_corner_projection_is_the_cameras(fov, cx_shift):
    from startrack.patterns import _cone_cos

    cam = Camera.from_fov(fov, 1024, 768).replace(cx=511.5 + cx_shift)
    for margin in (0.0, 0.5):
        assert _cone_cos(cam, margin) == pytest.approx(cam.cone_cos(margin), rel=0, abs=1e-13)
    distorted = cam.replace(k1=-0.1)           # the camera's own computation
    assert _cone_cos(distorted, 0.5) == distorted.cone_cos(0.5)


@pytest.mark.parametrize("seed", range(4))
def test_median_is_numpys(seed):
    from startrack.patterns import _median

    rng = np.random.default_rng(seed)
    for n in range(1, 70):
        values = list(rng.lognormal(-1.0, 1.5, size=n))
        assert _median(values) == float(np.median(values))


def _pattern_edges(vectors):
    from startrack._kernels.patterns import _edges

    e = np.empty(6)
    _edges(*(np.ascontiguousarray(v) for v in vectors), e)
    return e


@pytest.mark.parametrize("seed", range(3))
def test_sorted_edge_prefilter_never_refuses_a_fitting_correspondence(seed):
    """_sorted_fit is a necessary condition of _best_permutation's misfit <= 1: on catalog patterns made from the
    image's own (stars relabelled, scaled, every edge moved by up to 1.5 tolerances), it never refuses one that
    some correspondence fits, and it does refuse most of those that none fits."""
    from startrack._kernels.patterns import _PAIRS, _PERMS, _best_permutation, _sort6, _sorted_fit

    rng = np.random.default_rng(seed)
    refused = fits = 0
    for _ in range(3000):
        spread = rng.uniform(0.005, 0.4)
        v = rng.normal(size=(4, 3)) * [spread, spread, 0.0] + [0.0, 0.0, 1.0]
        v /= np.linalg.norm(v, axis=1)[:, None]
        ie = _pattern_edges(v)
        sig_ang, rel_geom = rng.uniform(1e-5, 1e-3), rng.uniform(0.0, 0.06)
        perm = rng.permutation(4)
        ce = _pattern_edges(v[perm]) * rng.uniform(0.5, 2.0)
        ce *= 1.0 + rng.uniform(-1.5, 1.5, size=6) * (sig_ang / ie.mean() + rel_geom)
        ie_sorted = np.empty(6)
        _sort6(ie, ie_sorted)
        assert np.array_equal(ie_sorted, np.sort(ie))
        q, err, _ = _best_permutation(ie, ce, _PERMS, _PAIRS, sig_ang, rel_geom)
        ok = _sorted_fit(ie_sorted, ie, ce, sig_ang, rel_geom, np.empty(6))
        if err <= 1.0:
            fits += 1
            assert ok, (ie, ce, sig_ang, rel_geom, err)
        elif not ok:
            refused += 1
    assert fits > 200 and refused > 500


@pytest.mark.parametrize("passing", [("_sorted_fit",), ("_shape_passes",), ("_sorted_fit", "_shape_passes")])
def test_query_patterns_prefilter_changes_no_candidate(index, catalog, monkeypatch, passing):
    """query_patterns with its pre-filters (the catalog pattern's stored shape, then its sorted edges) returns the
    candidates it returns without them (the kernel's Python body with the filters passing everything is the
    oracle), in the same order, to the bit."""
    import startrack._kernels.patterns as kp
    from startrack.patterns import LEVEL_RATIO, _combos

    _, idx = index
    cat = catalog.filter_magnitude(None, 6.0)
    cam = Camera.from_fov(15.0, 1024, 768)
    rng = np.random.default_rng(41)
    stars, _ = star_list(cat, cam, quaternion_to_dcm(random_quaternions(1, rng)[0]), Sensor(), Scene(mag_limit=6.0),
                         rng, sigma_px=0.3, max_stars=8)
    xy = np.array([[s["x"], s["y"]] for s in stars])
    combos = _combos(len(xy))[:12]
    args = (xy, 511.5, 383.5, combos, idx.level_rho, LEVEL_RATIO, idx.level_start, idx.level_prefix, idx.keys,
            idx.patterns, idx.shapes, idx.star_vec, np.ones(len(idx.star_id), dtype=np.uint8), 1.0, 0.1, 500.0,
            20000.0, 10000)
    ci, cf = kp.query_patterns(*args)
    assert len(ci) > 5
    for name in passing:
        monkeypatch.setattr(kp, name, lambda *_: True)
    wi, wf = kp.query_patterns.py_func(*args)
    np.testing.assert_array_equal(ci, wi)
    np.testing.assert_array_equal(cf, wf)


@pytest.mark.parametrize("seed", range(3))
def test_shape_prefilter_never_refuses_what_the_sorted_edges_accept(seed):
    """The stored shape's bounds (_shape_bounds, _shape_passes) are a necessary condition of _sorted_fit: on catalog
    patterns made from the image's own (stars moved by up to 1.5 tolerances, scaled), every one _sorted_fit accepts
    passes them, and they refuse nearly all it refuses (they are its test, widened by the shape's rounding)."""
    from startrack._kernels.patterns import (
        _edges_rows,
        _shape_bounds,
        _shape_passes,
        _sort6,
        _sorted_fit,
        pattern_shapes,
    )

    rng = np.random.default_rng(100 + seed)
    accepted = refused_sorted = refused_both = 0
    for _ in range(3000):
        spread = rng.uniform(0.005, 0.4)
        xy = rng.normal(size=(4, 2)) * spread
        v = np.column_stack([xy, np.ones(4)])
        v /= np.linalg.norm(v, axis=1)[:, None]
        ie = np.empty(6)
        _edges_rows(v, 0, 1, 2, 3, ie)
        sig_ang, rel_geom = rng.uniform(1e-6, 1e-3), rng.uniform(0.0, 0.06)
        step = (sig_ang / ie.mean() + rel_geom) * spread
        c = np.column_stack([(xy[rng.permutation(4)] + rng.uniform(-1.5, 1.5, size=(4, 2)) * step)
                             * rng.uniform(0.5, 2.0), np.ones(4)])
        c /= np.linalg.norm(c, axis=1)[:, None]
        ce = np.empty(6)
        _edges_rows(c, 0, 1, 2, 3, ce)
        ie_sorted = np.empty(6)
        _sort6(ie, ie_sorted)
        q_lo, q_hi = np.empty(6), np.empty(6)
        _shape_bounds(ie_sorted, sig_ang, rel_geom, q_lo, q_hi)
        shape_ok = _shape_passes(pattern_shapes(c, np.arange(4).reshape(1, 4)), 0, q_lo, q_hi)
        if _sorted_fit(ie_sorted, ie, ce, sig_ang, rel_geom, np.empty(6)):
            accepted += 1
            assert shape_ok, (ie, ce, sig_ang, rel_geom)
        else:
            refused_sorted += 1
            refused_both += not shape_ok
    assert accepted > 300 and refused_sorted > 300
    assert refused_both >= 0.9 * refused_sorted


def _screen_reference(b, n_screen, star_vec, n_rows, img, cat, cos_fov, radius):
    """screen_in_cone's count in numpy: QUEST on the pattern, then the first ``n_screen`` non-pattern stars with a
    catalog star of the field (of the first ``n_rows``) within ``radius``."""
    from startrack._kernels.attitude import quat_to_dcm, quest

    dcm = quat_to_dcm(quest(b[img], star_vec[cat], np.ones(len(img)))[0])
    sv = star_vec[:n_rows]
    field = sv[sv @ dcm[2] >= cos_fov]
    ref = b[:n_screen] @ dcm
    hit = np.any(ref @ field.T >= math.cos(radius), axis=1) if len(field) else np.zeros(n_screen, bool)
    hit[[i for i in img if i < n_screen]] = False
    return int(hit.sum()), dcm[2]


@pytest.mark.parametrize("seed", range(4))
def test_verification_in_a_cone_is_the_whole_catalogs(seed):
    """The blind verification's screen and refinement on the catalog rows of a cone around the pattern's
    boresight give the whole catalog's answer (screen count, matches, attitude, stars predicted) to the bit; an
    attitude that leaves the cone is reported, not answered."""
    from startrack._kernels.attitude import refine
    from startrack._kernels.verify import refine_in_cone, screen_in_cone

    rng = np.random.default_rng(seed)
    dcm = quaternion_to_dcm(random_quaternions(1, rng)[0])
    star_vec = rng.normal(size=(20000, 3))
    star_vec = np.ascontiguousarray(star_vec / np.linalg.norm(star_vec, axis=1)[:, None])
    f, w, h = 3000.0, 1024.0, 768.0
    cos_fov = math.cos(math.atan(math.hypot(w, h) / 2 / f) + math.radians(0.5))
    front = np.flatnonzero(star_vec @ dcm[2] > math.cos(math.radians(6.0)))
    seen = rng.permutation(front[front < 15000])[:30]
    b = star_vec[seen] @ dcm.T + rng.normal(scale=1e-5, size=(len(seen), 3))
    b = np.vstack([b, rng.normal(size=(3, 3)) * [0.05, 0.05, 0.0] + [0.0, 0.0, 1.0]])      # false stars
    b = np.ascontiguousarray(b / np.linalg.norm(b, axis=1)[:, None])
    img = np.array([0, 1, 2, 3], dtype=np.int64)
    cat = np.array(seen[:4], dtype=np.int64)
    if seed % 2:
        cat[3] = seen[5]                       # a wrong candidate: its screen finds little
    n_rows = 15000 + 1000 * seed
    radius = 2.0 / f
    cone_radius = math.acos(cos_fov) + math.radians(1.0)
    rows = np.empty(n_rows, dtype=np.int64)
    no_sky = (np.zeros(0, dtype=np.int64), np.zeros(0))
    hits, k, axis = screen_in_cone(b, 20, star_vec, n_rows, img, cat, cos_fov, radius, math.cos(cone_radius), rows,
                                   *no_sky)
    want_hits, want_axis = _screen_reference(b, 20, star_vec, n_rows, img, cat, cos_fov, radius)
    assert hits == want_hits
    np.testing.assert_allclose(axis, want_axis, rtol=0, atol=1e-14)
    np.testing.assert_array_equal(rows[:k], np.flatnonzero(star_vec[:n_rows] @ axis > math.cos(cone_radius)))
    # Through a sky index of every row (the prefix's stars among the cone's): the same count, rows and axis.
    from startrack.skyindex import SkyIndex

    sky = SkyIndex(star_vec, n_bands=[8, 100, 141, 400][seed])
    rows_sky = np.full(n_rows, -7, dtype=np.int64)
    got = screen_in_cone(b, 20, star_vec, n_rows, img, cat, cos_fov, radius, math.cos(cone_radius), rows_sky,
                         sky.cells, sky.ra)
    assert got[:2] == (hits, k) and got[2].tobytes() == axis.tobytes()
    np.testing.assert_array_equal(rows_sky[:k], rows[:k])
    rows = rows[:k]
    assert np.all(np.isin(cat, rows)) and k < n_rows / 50
    sub = np.ascontiguousarray(star_vec[rows])
    pos = np.searchsorted(rows, cat)
    geometry = (f, w / 2 - 0.5, h / 2 - 0.5, w, h, 0.0, 0.0, 0.0, 0.0, 0, radius, 2)
    match, q, n_pred = refine(b, np.ascontiguousarray(star_vec[:n_rows]), img, cat, cos_fov, *geometry)
    reach = math.cos(cone_radius - math.acos(cos_fov) - 1e-9)
    ok, m2, q2, n2 = refine_in_cone(b, sub, img, pos, cos_fov, *geometry, axis, reach)
    assert ok
    np.testing.assert_array_equal(np.where(m2 >= 0, rows[np.maximum(m2, 0)], -1), match)
    assert np.array_equal(q2, q) and n2 == n_pred
    assert (np.count_nonzero(match >= 0) >= 25) == (seed % 2 == 0), np.count_nonzero(match >= 0)
    # The search's one call: the refinement, its matrix and the confidence on the cone's rows, the same numbers.
    from startrack._kernels.attitude import quat_to_dcm
    from startrack._kernels.verify import blind_confidence, verify_in_cone

    ok3, m3, q3, n3, dcm3, *confidence = verify_in_cone(b, sub, img, pos, cos_fov, *geometry, axis, reach, n_rows, 3e-5)
    assert ok3 and np.array_equal(m3, m2) and np.array_equal(q3, q2) and n3 == n2
    assert dcm3.tobytes() == quat_to_dcm(q2).tobytes()
    assert tuple(confidence) == blind_confidence(b, img, pos, sub, dcm3, cos_fov, radius, n_rows, 3e-5)
    # A cone whose axis lies 2 degrees off: the refined attitude's field leaves it.
    tilted = axis + np.cross(axis, [0.0, 0.0, 1.0]) / np.linalg.norm(np.cross(axis, [0.0, 0.0, 1.0])) * 0.035
    ok, *_ = refine_in_cone(b, sub, img, pos, cos_fov, *geometry, tilted / np.linalg.norm(tilted), reach)
    assert not ok
    ok, *_ = verify_in_cone(b, sub, img, pos, cos_fov, *geometry, tilted / np.linalg.norm(tilted), reach, n_rows, 3e-5)
    assert not ok


def test_a_candidate_refused_at_refinement_leaves_the_probe_for_the_next():
    """One probe (an image pattern, one level) finds two catalog patterns under its key: first a decoy, the image
    pattern's own shape at a focal length below ``f_lo`` (it passes the comparison at the probe's guess, and its
    refined focal length is refused), then the right one (the image stars, with centroid noise, at 7844 px).  The
    right one is found as it is found alone: the refused decoy must not leave the image edges at its focal length."""
    from startrack._kernels.patterns import _edges, _key, pattern_shapes, prefix_table, query_patterns

    xy = np.array([[872.3209341278791, 106.69952956431172], [720.676627729201, 630.6071718870826],
                   [1005.3922026207168, 648.0311518991821], [434.28504109466917, 752.4009281354162]])
    right = np.array([[0.045932674753842294, -0.0354435345537074, 0.9983155539448927],
                      [0.026273790092604166, 0.031886163060575734, 0.9991461157205406],
                      [0.06293475896353075, 0.033530776161429396, 0.9974542110614473],
                      [-0.009896247184174676, 0.04682377821859706, 0.9988541425478523]])
    f_decoy, f_lo = 5656.895823948685, 6661.243241490282
    decoy = np.column_stack([(xy - [511.5, 383.5]) / f_decoy, np.ones(4)])
    decoy /= np.linalg.norm(decoy, axis=1)[:, None]
    edges = [np.empty(6), np.empty(6)]
    for v, e in zip((decoy, right), edges):
        _edges(v[0], v[1], v[2], v[3], e)
    keys = np.array([_key(np.sort(e)) for e in edges], dtype=np.int64)
    assert keys[0] <= keys[1]                                   # the decoy is compared first
    rho = float(np.max(edges[0]))
    vec = np.vstack([decoy, right])
    pats = np.arange(8, dtype=np.int64).reshape(2, 4)

    def look_up(allowed):
        return query_patterns(xy, 511.5, 383.5, np.array([[0, 1, 2, 3]]), np.array([rho]), math.sqrt(2.0),
                              np.array([0]), prefix_table(keys)[None, :], keys, pats, pattern_shapes(vec, pats), vec,
                              np.array(allowed, dtype=np.uint8), 1.0, 0.05, f_lo, 20000.0, 100)

    alone_i, alone_f = look_up([0] * 4 + [1] * 4)
    assert len(alone_i) == 1 and sorted(alone_i[0, 2:6]) == [4, 5, 6, 7]
    assert abs(alone_f[0, 0] / 7843.906429114131 - 1.0) < 0.01
    assert len(look_up([1] * 4 + [0] * 4)[0]) == 0              # the decoy alone: refused
    both_i, both_f = look_up([1] * 8)
    np.testing.assert_array_equal(both_i, alone_i)
    np.testing.assert_array_equal(both_f, alone_f)


def test_an_index_files_sky_index_is_kept_in_the_cache(index, tmp_path, monkeypatch):
    """_file_sky: an index opened from a file has its stars' sky index built once and kept in the cache; a later
    process (a fresh screen state) reads it from there, the same arrays, without building one; a damaged copy is not
    read (built and written again); an index held in memory has none (its screens build one after SKY_SCREEN_AFTER)."""
    import startrack.patterns as patterns
    import startrack.skyindex as skyindex
    from startrack.formats.flatcopy import copy_path, read_copy

    built, opened = index
    monkeypatch.setenv("STARTRACK_CACHE", str(tmp_path))
    want = skyindex.SkyIndex(np.array(opened.star_vec))
    assert patterns._file_sky(built) is None
    path = copy_path(opened.path, patterns._SKY_COPY)
    assert not os.path.exists(path)
    first = patterns._file_sky(opened)
    assert os.path.exists(path)

    def same(sky):
        return np.array_equal(sky.cells, want.cells) and np.array_equal(sky.ra, want.ra)

    assert same(first)
    init = skyindex.SkyIndex.__init__

    def no_build(*_args, **_kwargs):
        raise AssertionError("the sky index was built again")

    monkeypatch.setattr(skyindex.SkyIndex, "__init__", no_build)
    assert same(patterns._file_sky(opened))
    # The screens read it from their first look (a process's first screen state).
    monkeypatch.setattr(patterns, "_SKY_SCREEN", {})
    cells, ra = patterns._screen_sky(opened, len(opened.star_id), 0.1)
    assert np.array_equal(cells, want.cells) and np.array_equal(ra, want.ra)
    # One byte of the copy changed: not read; built and written again.
    data = bytearray(open(path, "rb").read())
    data[len(data) // 2] ^= 0x5A
    with open(path, "wb") as fh:
        fh.write(data)
    assert read_copy(path) is None
    with pytest.raises(AssertionError, match="built again"):
        patterns._file_sky(opened)
    monkeypatch.setattr(skyindex.SkyIndex, "__init__", init)
    assert same(patterns._file_sky(opened))
    assert read_copy(path) is not None
    # A cache that cannot take a copy: none is built (each process would build it again for nothing).
    os.remove(path)
    monkeypatch.setattr(skyindex.SkyIndex, "__init__", no_build)
    monkeypatch.setattr(os, "access", lambda *_: False)
    assert patterns._file_sky(opened) is None


def test_combos_are_the_brightest_first_order():
    """`_combos(n)`: every 4-combination of n stars once, by the faintest star, then the next (tetra3's order,
    a prefix per n), as the nested loops that defined it built them."""
    from startrack.patterns import _combos

    for n in range(31):
        want = [(a, b, c, d) for d in range(3, n) for c in range(2, d) for b in range(1, c) for a in range(b)]
        got = _combos.__wrapped__(n)
        assert got.dtype == np.int64 and got.flags.c_contiguous and got.shape == (len(want), 4)
        assert got.tolist() == [list(w) for w in want], n


def _level_patterns_reference(vec, rho_max, rho_min, min_ratio, max_per_anchor, brightest_first):
    """Plain-Python :func:`startrack._kernels.patterns.level_patterns`: per anchor (each star, brightest first), its
    fainter neighbours within ``rho_max`` in brightness order (or nearest first), their 3-combinations by the
    faintest (farthest) one, then the next, each kept when its largest edge is in (rho_min, rho_max] and its smallest
    at least ``min_ratio`` of it, until ``max_per_anchor``."""
    import itertools

    def ang(a, b):
        return math.atan2(np.linalg.norm(np.cross(vec[a], vec[b])), float(vec[a] @ vec[b]))

    out = []
    for a in range(len(vec)):
        nb = [j for j in range(a + 1, len(vec)) if float(vec[a] @ vec[j]) >= math.cos(rho_max)]
        if not brightest_first:
            nb = sorted(nb, key=lambda j: -float(vec[a] @ vec[j]))
        made = 0
        for ib in range(len(nb)):
            for ic in range(ib):
                for idd in range(ic):
                    if made >= max_per_anchor:
                        break
                    quad = (a, nb[ib], nb[ic], nb[idd])
                    e = sorted(ang(p, q) for p, q in itertools.combinations(quad, 2))
                    if e[5] > rho_max or e[5] <= rho_min or e[0] < min_ratio * e[5]:
                        continue
                    out.append(quad)
                    made += 1
    return out


@pytest.mark.parametrize("brightest_first", [True, False])
@pytest.mark.parametrize("cap", [3, 12, 10**6])
def test_level_patterns_is_its_reference(brightest_first, cap):
    """The kernel makes the reference's patterns (the same stars, the same order of anchors): a cap of 3 keeps
    an anchor's first three, which differ between the two orders; with no cap both orders make every pattern."""
    from startrack._kernels.patterns import level_patterns

    rng = np.random.default_rng(cap)
    # 30 stars in a 10-degree cap around +z, brightest first by construction (the row order)
    v = np.column_stack([rng.normal(0, 0.05, (30, 2)), np.ones(30)])
    v /= np.linalg.norm(v, axis=1)[:, None]
    rho = math.radians(8.0)
    got, keys, _ = level_patterns(np.ascontiguousarray(v), rho, rho / math.sqrt(2), 0.05, cap, brightest_first)
    want = _level_patterns_reference(v, rho, rho / math.sqrt(2), 0.05, cap, brightest_first)
    assert [tuple(r) for r in got.tolist()] == want
    assert len(want) > 50 and len(keys) == len(want)
    if cap == 10**6:
        other, _, _ = level_patterns(np.ascontiguousarray(v), rho, rho / math.sqrt(2), 0.05, cap, not brightest_first)
        assert sorted(map(sorted, other.tolist())) == sorted(map(sorted, got.tolist()))


def test_build_index_refuses_an_unknown_neighbour_order(catalog):
    from startrack.errors import ParameterError

    with pytest.raises(ParameterError, match="neighbours"):
        build_index(catalog.filter_magnitude(None, 3.0), params={"neighbours": "random"})


@pytest.fixture(scope="module")
def sparse_indexes(catalog):
    """The small test index built with each neighbour order (stars to Hp 6, patterns of 4-23 degrees)."""
    cat = catalog.filter_magnitude(None, 6.0)
    return {order: build_index(cat, params={**PARAMS, "neighbours": order}) for order in ("nearest", "brightest")}


def test_sparse_fields_brightest_stars_are_patterns_of_the_index(sparse_indexes, catalog):
    """A sparse field (its 6 brightest stars detected, 20 x 15 degrees): the index holds a pattern of four of them
    in most fields, more often with the brightest neighbours first than with the nearest (same index size; 170 and
    162 of 200 fields when written)."""
    import itertools

    cat = catalog.filter_magnitude(None, 6.0)
    cam = Camera.from_fov(20.0, 1024, 768)
    rng = np.random.default_rng(38)
    sets = {}
    for order, idx in sparse_indexes.items():
        sets[order] = set(map(frozenset, np.asarray(idx.patterns).tolist()))
        assert len(idx.keys) == len(sparse_indexes["nearest"].keys)      # the same budget per anchor
    row_of = {int(i): r for r, i in enumerate(sparse_indexes["brightest"].star_id)}
    held = {"nearest": 0, "brightest": 0}
    fields = 0
    for q in random_quaternions(200, rng):
        stars, truth = star_list(cat, cam, quaternion_to_dcm(q), Sensor(), Scene(mag_limit=6.0), rng, sigma_px=0.0,
                                 max_stars=6)
        if len(stars) < 6:
            continue
        fields += 1
        rows = [row_of[i] for i in truth["star_ids"][:6]]
        for order, s in sets.items():
            held[order] += any(frozenset(c) in s for c in itertools.combinations(rows, 4))
    assert fields >= 100
    assert held["brightest"] >= 0.8 * fields and held["brightest"] > held["nearest"], (held, fields)


def test_sparse_fields_are_identified_or_refused_never_wrong(sparse_indexes, catalog):
    """Blind search on sparse fields: every answer is the truth, every failure has a reason; of fields whose 6-8
    brightest stars are detected about half are identified (23 of 40 when written: the verification wants four
    stars beyond the pattern), and fields of 5-7 detections with a false one are never answered wrongly."""
    idx = sparse_indexes["brightest"]
    cat = catalog.filter_magnitude(None, 6.0)
    cam = Camera.from_fov(20.0, 1024, 768)
    rows, vec = cat.rows_by_id(), cat.vectors()
    for lo, false_stars, seed in ((6, 0, 39), (5, 1, 40)):
        rng = np.random.default_rng(seed)
        solved = tried = 0
        for q in random_quaternions(40, rng):
            dcm = quaternion_to_dcm(q)
            stars, truth = star_list(cat, cam, dcm, Sensor(), Scene(mag_limit=6.0, false_stars=false_stars), rng,
                                     sigma_px=0.3, max_stars=int(rng.integers(lo, lo + 3)))
            if len(stars) < lo:
                continue
            tried += 1
            _, res, _ = solve_blind(stars, 1024, 768, idx, BlindOptions(timeout_s=2.0))
            if res.status != "ok":
                assert res.reason
                continue
            solved += 1
            ids = truth["star_ids"]
            for m in res.matches:     # the true star, or its unresolved neighbour (within 2 px) in a blend
                assert ids[m.star] is not None
                if ids[m.star] != m.id:
                    a, b = vec[rows[m.id]], vec[rows[ids[m.star]]]
                    assert math.acos(min(1.0, float(a @ b))) * cam.focal_length_px < 2.0
            _, cross, _ = _attitude_error_rad(quaternion_to_dcm(res.quaternion_estimate), dcm)
            assert math.degrees(cross) < 0.05
        assert tried >= 30, tried
        if false_stars == 0:
            assert solved >= 0.45 * tried, (solved, tried)


def _pinhole_rounds_reference(xy, img, cat_rows, trials, b, cam, star_vec, star_id, eps, sigma, params, cone, f_lo,
                              f_hi):
    """The fit-and-verify rounds of an undistorted pinhole as the blind search made them with a camera per round
    (_fit_camera, Camera.pixels_to_vectors, tolerance_rad, _verify_blind looking the cone's rows up each time)."""
    from startrack.identify.params import tolerance_rad
    from startrack.patterns import _F_CONVERGED, _fit_camera, _verify_blind

    matches, dcm, p_false, _ = _verify_blind(img, cat_rows, trials, b, cam, star_vec, star_id, eps, sigma, params,
                                             cone)
    if matches is None:
        return None
    previous = None
    for _ in range(3):
        idx, _, rows = matches
        f_before = cam.focal_length_px
        cam = _fit_camera(cam, dcm, xy[idx], star_vec[rows], False)
        if cam is None or not f_lo <= cam.focal_length_px <= f_hi * 1.1:
            return None
        pairs = (idx.tolist(), rows.tolist())
        if pairs == previous and abs(cam.focal_length_px / f_before - 1.0) < _F_CONVERGED:
            break
        previous = pairs
        b = cam.pixels_to_vectors(xy[:, 0], xy[:, 1])
        eps = tolerance_rad(cam, sigma, params)
        m2, dcm2, p2, _ = _verify_blind(idx, rows, trials, b, cam, star_vec, star_id, eps, sigma, params, cone)
        if m2 is None:
            break
        matches, dcm, p_false = m2, dcm2, p2
    return cam, matches, dcm, p_false


def test_pinhole_rounds_are_the_camera_rounds(index, catalog, monkeypatch):
    """_verify_pinhole (the focal length alone, the cone positions carried from round to round) gives the rounds
    made with a camera per round, to the bit, on every candidate the search verifies, right or wrong."""
    import startrack.patterns as patterns

    _, idx = index
    cat = catalog.filter_magnitude(None, 6.0)
    calls = []
    real = patterns._verify_pinhole

    def spy(*args):
        got = real(*args)
        calls.append((args, got))
        return got

    monkeypatch.setattr(patterns, "_verify_pinhole", spy)
    rng = np.random.default_rng(38)
    for fov in (8.0, 12.0, 18.0):
        cam = Camera.from_fov(fov, 1024, 768)
        for q in random_quaternions(4, rng):
            stars, _ = star_list(cat, cam, quaternion_to_dcm(q), Sensor(), Scene(mag_limit=6.0), rng, sigma_px=0.4,
                                 max_stars=40)
            solve_blind(stars, 1024, 768, idx, BlindOptions(timeout_s=5.0))
    assert sum(got is not None for _, got in calls) >= 6 and len(calls) >= 8, len(calls)
    for args, got in calls:
        want = _pinhole_rounds_reference(*args)
        assert (got is None) == (want is None)
        if got is None:
            continue
        assert got[0] == want[0] and got[0].focal_length_px == want[0].focal_length_px
        for a, b in zip(got[1], want[1], strict=True):
            assert a.dtype == b.dtype and np.array_equal(a, b)
        assert got[2].tobytes() == want[2].tobytes() and got[3] == want[3]


@pytest.mark.parametrize("fov, k1", [(50.0, -0.15), (70.0, -0.1)])
def test_wide_distorted_fields_are_identified_within_one_searchs_share(index, catalog, fov, k1):
    """Wide fields of strong barrel distortion with the smallest false-match limit the CLI gives one search of a blind
    solve (1e-6 split twelve ways: parities, detection depths, all-sky, the deep index): identified, every match right, the
    focal length and k1 measured.  A wide candidate's first verification (a pinhole's with a padded match radius) is
    a screen; the answer passed the limit at the strict radius on its fitted camera.  (This small index's patterns
    reach 23 deg: wider fields than these have none of their brightest stars' patterns in it.)"""
    _, idx = index
    cat = catalog.filter_magnitude(None, 6.0)
    rows, vec = cat.rows_by_id(), cat.vectors()
    cam = Camera.from_fov(fov, 1280, 960).replace(k1=k1)
    rng = np.random.default_rng(int(fov))
    for q in random_quaternions(3, rng):
        dcm = quaternion_to_dcm(q)
        stars, truth = star_list(cat, cam, dcm, Sensor(), Scene(mag_limit=6.0), rng, sigma_px=0.1, max_stars=60)
        for s in stars:
            s["sigma_px"] = 0.1
        fitted, res, _ = solve_blind(stars, 1280, 960, idx, BlindOptions(max_false_probability=1e-6 / 12,
                                                                         timeout_s=5.0))
        assert res.status == "ok", res.reason
        assert res.false_match_probability <= 1e-6 / 12 and len(res.matches) >= 20
        ids = truth["star_ids"]
        for m in res.matches:
            if ids[m.star] != m.id:         # a blend's neighbour, within 2 px
                a, b = vec[rows[m.id]], vec[rows[ids[m.star]]]
                assert math.acos(min(1.0, float(a @ b))) * cam.focal_length_px < 2.0
        assert fitted.k1 == pytest.approx(k1, abs=0.01)
        assert fitted.focal_length_px == pytest.approx(cam.focal_length_px, rel=3e-3)
        _, cross, roll = _attitude_error_rad(quaternion_to_dcm(res.quaternion_estimate), dcm)
        assert math.degrees(cross) * 3600 < 60 and abs(math.degrees(roll)) * 3600 < 300


def test_blind_bench_70_degree_frame_end_to_end(tmp_path, cli, solve_cache):
    """The blind bench's rendered 70 deg frame (k1 -0.1; benchmarks/blind_bench.py RENDERS) through the real CLI: it
    timed out after ~2,300 hypotheses once the false-match limit was shared among the searches (1e-6 / 12), its
    true candidates refused at their first, pinhole verification.  Identified at once, the camera measured."""
    proc = cli("render", "--fov-deg", "70", "--size", "1280x960", "--ra", "280", "--dec", "-30", "--roll", "200",
               "--k1", "-0.1", "--exposure-ms", "100", "--no-aberration", "--seed", "4", "-o", tmp_path / "f70.png",
               "-q", check=True)
    truth = json.loads(proc.stdout)
    solved = cli("solve", tmp_path / "f70.png", "--no-aberration", "-q", env=solve_cache, timeout=600)
    assert solved.returncode == 0, solved.stderr
    doc = json.loads(solved.stdout)
    assert doc["solve"]["status"] == "ok" and doc["solve"]["hypotheses"] <= 10
    cam = Camera.from_dict(doc["camera"])
    assert cam.focal_length_px == pytest.approx(truth["camera"]["focal_length_px"], rel=2e-3)
    assert cam.k1 == pytest.approx(-0.1, abs=0.005)
    _, cross, roll = _attitude_error_rad(quaternion_to_dcm(doc["attitude"]["quaternion"]),
                                         quaternion_to_dcm(truth["truth"]["quaternion"]))
    assert math.degrees(cross) * 3600 < 30 and abs(math.degrees(roll)) * 3600 < 60


@pytest.mark.parametrize("writeable", [False, True])
def test_a_cone_is_as_writable_as_its_catalog(writeable):
    """numba compiles a read-only array's kernels apart: the cone's rows (verify_in_cone) as writable as the
    catalog refine and blind_confidence read (a memory-mapped index's is read-only), so that the three share
    one compiled refine_from, blind_confidence and project_stars (a writable cone of a read-only index compiled
    them twice, ~3 s of a first solve)."""
    from startrack.patterns import _CatalogCone

    rng = np.random.default_rng(3)
    vec = rng.normal(size=(40, 3))
    vec /= np.linalg.norm(vec, axis=1)[:, None]
    vec.flags.writeable = writeable
    rows = np.array([2, 5, 7, 30])
    cone = _CatalogCone(rows, vec, np.arange(40) + 100, vec[5], 0.3)
    assert cone.vec.flags.writeable == writeable and cone.vec.flags.c_contiguous
    np.testing.assert_array_equal(cone.vec, vec[rows])
    np.testing.assert_array_equal(cone.ids, rows + 100)


def test_an_index_without_pattern_shapes_is_refused_naming_them(index, tmp_path, monkeypatch):
    """A file of layout 2 (before the pattern shapes) is refused with the array named, not read as damaged; an index
    whose shapes do not match its patterns is refused before any kernel reads them."""
    from dataclasses import replace

    import startrack.patterns as sp
    from startrack.errors import BadInputError

    built, _ = index
    path = str(tmp_path / "old.idx")
    with monkeypatch.context() as m:
        m.setattr(sp, "_ARRAYS", tuple(a for a in sp._ARRAYS if a != "shapes"))
        sp.save_index(built, path)
    with pytest.raises(BadInputError) as info:
        sp.open_index(path)
    assert info.value.field == "shapes" and "build it again" in str(info.value)
    with pytest.raises(BadInputError, match="shapes"):
        sp.check_index(replace(built, shapes=built.shapes[:-1]), "forged")
    with pytest.raises(BadInputError, match="shapes"):
        sp.check_index(replace(built, shapes=built.shapes.astype(np.int32)), "forged")


def test_the_built_shapes_are_those_of_the_stored_patterns(index):
    """build_index takes each pattern's shape from level_patterns' sorted edges; they are pattern_shapes' of the
    stored star rows (the edges the look-up computes), row for row."""
    from startrack._kernels.patterns import pattern_shapes

    built, opened = index
    want = pattern_shapes(np.ascontiguousarray(built.star_vec), np.ascontiguousarray(built.patterns))
    assert len(want) > 10000
    np.testing.assert_array_equal(built.shapes, want)
    np.testing.assert_array_equal(opened.shapes, want)


def test_a_wrong_wide_candidate_stuck_at_its_radius_is_not_verified_again(monkeypatch):
    """A wrong 85 deg candidate of the 11 deg ESA image Alt40_Azi45 (its four brightest detections but the third as
    Gamma Cyg, Vega, Polaris and a 6th-magnitude star, f 553 px; the first candidate its search verifies): its
    padded match radius (26 px) holds 10 chance stars at a chance of coincidence under the wide screen's
    1e-2, and the lens fitted on them misfits them by more than that radius, round after round, on the same matches.
    A round that repeats the last one's matches at the same radius is not verified again (_WIDE_STUCK): two
    verifications, where the rounds ran out after six (the rule off).  Its screen, which hits fewer of the image's
    brightest stars than chance would, now refuses it before any of them (_chance_hits)."""
    import os

    import startrack.patterns as patterns
    from startrack.centroid import CentroidOptions, find_stars
    from startrack.identify.params import IdentifyParams
    from startrack.imageio import read_image
    from startrack.solve import SolveOptions

    path = os.path.join(os.path.dirname(__file__), "data", "real", "2019-07-29T204726_Alt40_Azi45_Try1.tiff")
    image, meta = read_image(path)
    found = find_stars(image, CentroidOptions(max_stars=SolveOptions().max_stars), saturation=meta["saturation"]).stars
    stars = sorted(found, key=lambda s_: (-s_["peak"], -s_["flux"]))[:60]       # solve_blind's order and verify_stars
    xy = np.array([[s_["x"], s_["y"]] for s_ in stars])
    index = patterns.default_index()
    rows = {int(i): r for r, i in enumerate(np.asarray(index.star_id).tolist())}
    opts = patterns.BlindOptions()
    h, w = image.shape
    f_lo = (w / 2.0) / math.tan(math.radians(opts.fov_max_deg) / 2.0)
    f_hi = (w / 2.0) / math.tan(math.radians(opts.fov_min_deg) / 2.0)
    params = IdentifyParams(max_false_probability=1e-6)
    sigma = patterns._centroid_sigma_px(stars, params)
    calls = []
    verify = patterns._verify_blind

    def recording(*args, **kwargs):
        out = verify(*args, **kwargs)
        calls.append(None if out[0] is None else len(out[0][0]))
        return out

    monkeypatch.setattr(patterns, "_verify_blind", recording)

    def candidate():
        calls.clear()
        return patterns._verify_candidate(stars, xy, [0, 1, 2, 4], [rows[i] for i in (100453, 91262, 11767, 80331)],
                                          553.3589328282759, w, h, index, params, sigma, 1, f_lo, f_hi, opts)

    # Its screen puts 2 of the 16 other screened stars on catalog stars, fewer than chance would (_chance_hits): it
    # is refused before any verification.
    assert candidate() is None
    assert calls == []
    # Past the screen (chance taken as no hit at all), the rounds:
    monkeypatch.setattr(patterns, "_chance_hits", lambda *_: -1.0)
    assert candidate() is None
    assert calls == [10, 10]            # the padded radius's chance stars, twice: then stuck
    monkeypatch.setattr(patterns, "_WIDE_STUCK", -1.0)
    assert candidate() is None
    assert calls == [10] * 6            # every round alike until they ran out


def test_a_position_hints_star_mask_is_kept_for_the_next_frame(index):
    """The mask of the stars a position hint lets the look-up compare is made once per index, hint and reach (a batch
    of frames with one --ra/--dec/--radius), and is the stars within the reach of the hint."""
    import startrack.patterns as patterns

    built, opened = index
    hint = np.array([0.6, 0.0, 0.8])
    first = patterns._hint_rows(opened, hint, 0.3)
    assert patterns._hint_rows(opened, hint.copy(), 0.3) is first
    assert np.array_equal(first, (np.asarray(opened.star_vec) @ hint >= math.cos(0.3)).astype(np.uint8))
    assert 0 < first.sum() < len(first)
    wider = patterns._hint_rows(opened, hint, 0.4)
    assert wider is not first and wider.sum() > first.sum()
    other = patterns._hint_rows(built, hint, 0.3)       # another index (the same stars): its own mask
    assert other is not first and np.array_equal(other, first)


def test_chance_hits_is_what_wrong_candidates_hit():
    """_chance_hits: the screen's hits of wrong candidates (random catalog rows for the pattern, on a catalog spread
    evenly over the sky) average what it says, at a wide field's padded radius (2-7 chance hits) and a pinhole's
    (well under one); right candidates hit far more.  The oracle is the kernel's own count."""
    from startrack._kernels.verify import screen_in_cone
    from startrack.patterns import _chance_hits

    rng = np.random.default_rng(7)
    star_vec = rng.normal(size=(20000, 3))
    star_vec = np.ascontiguousarray(star_vec / np.linalg.norm(star_vec, axis=1)[:, None])
    no_sky = (np.zeros(0, dtype=np.int64), np.zeros(0))
    img = np.array([0, 1, 2, 3], dtype=np.int64)
    for f, radius_px, n_rows in ((700.0, 25.0, 3000), (700.0, 12.0, 3000), (3000.0, 2.0, 15000)):
        half_diag = math.atan(math.hypot(1024.0, 768.0) / 2.0 / f)
        cos_fov = math.cos(half_diag + math.radians(0.5))
        cone_radius = math.acos(cos_fov) + math.radians(1.0)
        rows = np.empty(n_rows, dtype=np.int64)
        got, want, right = [], [], []
        for _ in range(150):
            dcm = quaternion_to_dcm(random_quaternions(1, rng)[0])
            front = np.flatnonzero(star_vec[:n_rows] @ dcm[2] > math.cos(half_diag * 0.8))
            seen = rng.permutation(front)[:24]
            b = star_vec[seen] @ dcm.T
            b = np.ascontiguousarray(b / np.linalg.norm(b, axis=1)[:, None])
            for is_right, cat in ((True, seen[:4]), (False, rng.choice(n_rows, 4, replace=False))):
                hits, k, _ = screen_in_cone(b, 20, star_vec, n_rows, img, np.asarray(cat, dtype=np.int64), cos_fov,
                                            radius_px / f, math.cos(cone_radius), rows, *no_sky)
                if is_right:
                    right.append(hits - _chance_hits(k, cone_radius, radius_px / f, 20, img))
                else:
                    got.append(hits)
                    want.append(_chance_hits(k, cone_radius, radius_px / f, 20, img))
        assert np.mean(got) == pytest.approx(np.mean(want), rel=0.15, abs=0.05), (f, radius_px)
        assert min(right) > 5.0
