"""Paper 000's triangle database and modified pyramid: kernels against naive twins, exact look-ups, identification."""
import itertools
import math

import numpy as np
import pytest

from startrack._kernels.triangles import internal_angles, triangle_candidates


def _naive_angles(p):
    out = []
    for v in range(3):
        a, b, c = p[v], p[(v + 1) % 3], p[(v + 2) % 3]
        u, w = b - a, c - a
        out.append(math.acos(np.clip(u @ w / (np.linalg.norm(u) * np.linalg.norm(w)), -1, 1)))
    return np.array(out)


def _random_rotation(rng):
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    return q if np.linalg.det(q) > 0 else -q


def test_internal_angles_match_naive_sum_to_pi_and_ignore_rotation():
    rng = np.random.default_rng(5)
    for _ in range(200):
        centre = rng.normal(size=3)
        centre /= np.linalg.norm(centre)
        p = centre + 0.05 * rng.normal(size=(3, 3))
        p /= np.linalg.norm(p, axis=1)[:, None]
        got = internal_angles(p[0], p[1], p[2])
        np.testing.assert_allclose(got, _naive_angles(p), atol=1e-9)
        assert abs(got.sum() - math.pi) < 1e-9          # a plane (chord) triangle: Table 4's rows sum to 180
        rot = _random_rotation(rng)
        q = p @ rot.T
        np.testing.assert_allclose(internal_angles(q[0], q[1], q[2]), got, atol=1e-9)


@pytest.fixture(scope="module")
def small_db(catalog):
    from startrack.triangles import build_triangles

    return build_triangles(catalog.filter_magnitude(None, 4.0), 10.0)


def test_every_triangle_is_stored_once_with_its_angles(small_db):
    db = small_db
    vec = db.star_vector
    cos_max = math.cos(math.radians(10.0))
    close = vec @ vec.T >= cos_max
    naive = sum(1 for i, j, k in itertools.combinations(range(len(vec)), 3) if close[i, j] and close[i, k] and
                close[j, k]) if len(vec) < 700 else None
    if naive is not None:
        assert db.n_triangles == naive
    assert np.all(np.diff(db.tri_key) >= 0)
    rng = np.random.default_rng(1)
    for t in rng.integers(0, db.n_triangles, 300):
        s = db.tri_stars[t]
        assert len(set(s.tolist())) == 3
        ang = _naive_angles(vec[s])
        np.testing.assert_allclose(ang, db.tri_angles[t], atol=1e-6)
        assert ang[0] <= ang[1] + 1e-6 <= ang[2] + 2e-6
        assert np.sign(np.linalg.det(vec[s])) == db.tri_hand[t]


def test_quadratic_and_kvector_ranges_contain_every_match(small_db):
    """Eqs. 10-12 (quadratic) and Mortari's line give intervals that contain every triangle of the window."""
    from startrack.triangles import search_intervals

    db = small_db
    rng = np.random.default_rng(2)
    thetas = db.tri_key[rng.integers(0, db.n_triangles, 200)]
    tol = math.radians(30 / 3600)
    out = search_intervals(db, thetas, tol)
    assert out["quadratic"] >= out["exact"] and out["linear"] >= out["exact"]
    from startrack._kernels.triangles import _quad_inverse

    n = db.n_triangles
    for th in thetas:
        kb = min(max(int(math.floor(_quad_inverse(*db.quad, th - tol, n))), 0), n)
        kt = min(max(int(math.ceil(_quad_inverse(*db.quad, th + tol, n))), 0), n)
        inside = np.nonzero((db.tri_key >= th - tol) & (db.tri_key <= th + tol))[0]
        assert inside.min() >= db.kquad[kb] and inside.max() < db.kquad[kt]


def test_a_measured_triangle_finds_its_catalog_triangle(small_db):
    db = small_db
    rng = np.random.default_rng(3)
    found = 0
    for t in rng.integers(0, db.n_triangles, 50):
        s = db.tri_stars[t]
        rot = _random_rotation(rng)
        b = db.star_vector[s] @ rot.T
        perm = rng.permutation(3)
        b = np.ascontiguousarray(b[perm])
        cands, interval = triangle_candidates(b, 0, 1, 2, db.tri_key, db.tri_stars, db.tri_angles, db.tri_hand,
                                              db.kquad, *db.quad, math.radians(5 / 3600), db.star_vector, 1000,
                                              db.kvector, *db.line)
        assert interval >= len(cands)
        found += any(list(c) == list(s[perm]) for c in cands)
    assert found == 50


def test_mirror_image_is_not_matched(small_db):
    db = small_db
    t = db.n_triangles // 2
    s = db.tri_stars[t]
    b = db.star_vector[s].copy()
    b[:, 0] = -b[:, 0]          # a reflection: same angles, opposite handedness
    cands, _ = triangle_candidates(np.ascontiguousarray(b), 0, 1, 2, db.tri_key, db.tri_stars, db.tri_angles,
                                   db.tri_hand, db.kquad, *db.quad, math.radians(5 / 3600), db.star_vector, 1000,
                                   db.kvector, *db.line)
    assert not any(list(c) == list(s) for c in cands)


def test_modified_pyramid_identifies_star_lists(catalog):
    """Paper 000's sensor reading 8 x 8 deg, stars 2.5 to 5.5 (kept small for the suite): no wrong answer."""
    from startrack.camera import Camera
    from startrack.evaluate import Condition, make_frames, score
    from startrack.identify import IdentifyParams
    from startrack.identify.driver import run
    from startrack.identify.modified_pyramid import propose_modified_pyramid
    from startrack.triangles import build_triangles

    cat = catalog.filter_magnitude(2.5, 5.5)
    db = build_triangles(cat, 8.0)
    cam = Camera.from_fov(8.0, 1024, 1024)
    frames = make_frames(cat, cam, Condition(sigma_px=0.3, min_stars=5), 60, seed=11)
    outcome = [score(run("modified-pyramid", propose_modified_pyramid, s, cam, db, IdentifyParams(sigma_px=0.3)), t)
               for s, t, _ in frames]
    assert outcome.count("bad") == 0
    assert outcome.count("success") >= 54, outcome.count("success")


def test_build_triangles_cli_and_refusals(cli, tmp_path):
    from conftest import assert_refused

    out = tmp_path / "tri.h5"
    proc = cli("build-triangles", "--fov-deg", "10", "--size", "800x800", "--mag-max", "4", "-o", out)
    assert proc.returncode == 0, proc.stderr
    from startrack.triangles import load_triangles

    db = load_triangles(str(out))
    assert db.n_triangles > 1000 and db.max_separation_deg == pytest.approx(10.0)
    assert_refused(cli("build-triangles", "--fov-deg", "10", "--size", "800x800", "--max-separation-deg", "-1",
                       "-o", tmp_path / "x.h5"), "--max-separation-deg")
    assert not (tmp_path / "x.h5").exists()


def test_quadruples_are_every_set_brightest_first():
    from startrack.identify.modified_pyramid import _quadruples

    for n in (4, 5, 9, 20):
        assert list(_quadruples(n)) == sorted(itertools.combinations(range(n), 4), key=lambda q: q[::-1])


def test_modified_pyramid_keeps_looking_through_false_stars(catalog):
    """Ten false stars among the detections: the first four-star set of true stars can be far down the list;
    the search goes through every set (its old stop at 200 sets failed most such frames), never wrong."""
    from startrack.camera import Camera
    from startrack.evaluate import Condition, make_frames, score
    from startrack.identify import IdentifyParams, identify_stars, make_config
    from startrack.triangles import build_triangles

    cat = catalog.filter_magnitude(2.5, 5.5)
    db = build_triangles(cat, 8.0)
    cam = Camera.from_fov(8.0, 1024, 1024)
    frames = make_frames(cat, cam, Condition(sigma_px=0.3, false_stars=10, min_catalog_stars=4), 12, 5,
                         mag_limit=5.5)
    params = IdentifyParams(sigma_px=0.3)
    every = [score(identify_stars(s, cam, db, "modified-pyramid", params), t) for s, t, _ in frames]
    first = [score(identify_stars(s, cam, db, "modified-pyramid", params,
                                  make_config("modified-pyramid", {"max_quadruples": 200})), t) for s, t, _ in frames]
    assert every.count("bad") == 0 and first.count("bad") == 0
    assert every.count("success") >= 10, every
    assert every.count("success") > first.count("success"), (every, first)


def test_build_triangles_merges_unresolved_doubles(cli, tmp_path):
    """HIP 103569 and 103571 (10" apart, 0.24 px on a 15 deg 1280 px sensor) image as one star: one entry,
    the brighter id; --merge-px 0 keeps both."""
    from startrack.triangles import load_triangles

    args = ["build-triangles", "--fov-deg", "15", "--size", "1280x960", "--mag-max", "6", "-q"]
    assert cli(*args, "-o", tmp_path / "m.h5").returncode == 0
    assert cli(*args, "--merge-px", "0", "-o", tmp_path / "u.h5").returncode == 0
    merged, unmerged = load_triangles(str(tmp_path / "m.h5")), load_triangles(str(tmp_path / "u.h5"))
    assert {103569, 103571} <= set(unmerged.star_id.tolist())
    assert len({103569, 103571} & set(merged.star_id.tolist())) == 1
    assert merged.n_stars < unmerged.n_stars


def test_a_false_star_in_the_core_on_an_undetected_catalog_star_is_not_named(catalog):
    """Found on a sensor no example uses (10.5 deg 1600x1200, database Hp <= 6.8, stars to 6.3, 5 false
    stars): the modified pyramid's four stars held a false star lying on HIP 48895 (Hp 6.56, fainter than
    the frame shows), 1.2 mag brighter than that star can be; the core was exempt from the magnitude
    check and the false star was named.  Now a core detection brighter than its catalog star allows is
    left unnamed (saturation only makes true stars look fainter), and the rest still identify the frame."""
    from startrack.camera import Camera
    from startrack.catalog import merge_radius_arcsec
    from startrack.evaluate import Condition, make_frames, score
    from startrack.identify import IdentifyParams, identify_stars
    from startrack.triangles import build_triangles

    cam = Camera.from_fov(10.5, 1600, 1200)
    db = build_triangles(catalog.filter_magnitude(None, 6.8).merge_close(merge_radius_arcsec(cam)), min(cam.fov_deg))
    (s, t, _), = make_frames(catalog.filter_magnitude(None, 6.3), cam,
                             Condition(sigma_px=0.5, false_stars=5, min_catalog_stars=4), 1, 77, mag_limit=6.3,
                             start=156)
    r = identify_stars(s, cam, db, "modified-pyramid", IdentifyParams(sigma_px=0.5))
    assert score(r, t) == "success"
    assert all(t["star_ids"][m.star] == m.id for m in r.matches)
    assert len(r.matches) >= 8
