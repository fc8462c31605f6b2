"""The fast paths decide exactly as the general ones: the one-kernel verification (``verify._verify_fused``,
with the database's sky index) as the step-by-step Python path scanning every database star, and the
voting clusters grown in a kernel as the Python loops.

Both paths run on the same frames (centroid noise, false stars, magnitude noise, a focal-length
error so that every scale branch is taken); every result -- status, reason, trials, matched ids,
focal scale, false-match probability, attitude -- must be the same.
"""
import numpy as np
import pytest
from conftest import kvector_sensor

from startrack.camera import Camera
from startrack.evaluate import Condition, make_frames
from startrack.identify import IdentifyParams, driver, identify_stars, verify


@pytest.fixture(scope="module")
def sensor(catalog):
    """A 14 deg 1200x900 sensor; database Hp <= 5.8 merged for it."""
    return kvector_sensor(catalog, 14, 1200, 900, 5.8, 5.4)


def _result(res):
    """Everything but the false-match probability, which :func:`_same_probability` compares."""
    return (res.status, res.reason, str(res.reason_code), res.trials, [(m.star, m.id) for m in res.matches],
            res.focal_scale)


def _exact(res):
    """:func:`_result` and the false-match probability to the last bit (both sides the same kernels)."""
    return _result(res) + (res.false_match_probability,)


def _same_probability(a, b):
    """The same false-match probability up to rounding: the kernel's product, compiled, and the Python
    path's can differ in the last bit (seen: 4.921765112194026e-09 against 4.9217651121940275e-09, the
    kernel's own Python function giving the latter)."""
    pa, pb = a.false_match_probability, b.false_match_probability
    assert (pa is None) == (pb is None)
    if pa is not None:
        assert pa == pytest.approx(pb, rel=1e-12, abs=0)


CONDITIONS = [Condition(sigma_px=0.3, min_catalog_stars=4),
              Condition(sigma_px=1.0, false_stars=3, min_catalog_stars=4),
              Condition(sigma_px=0.3, false_stars=10, mag_noise=0.2, min_catalog_stars=4),
              Condition(sigma_px=0.5, focal_error_pct=2.0, false_stars=1, min_catalog_stars=4)]


@pytest.mark.parametrize("algorithm", ["pyramid", "brightness"])
def test_fused_and_python_verification_decide_alike(sensor, algorithm, monkeypatch):
    from startrack._kernels import verify as kernels

    cam, db, stars = sensor
    calls = []
    fused = kernels.verify_focal

    def counted(*args):
        calls.append(1)
        return fused(*args)

    monkeypatch.setattr(kernels, "verify_focal", counted)
    monkeypatch.setattr(driver, "FUSED_SEARCH", False)     # each proposal verified from Python (compared below)
    index = verify._sky_index
    outcomes = {"ok": 0, "failed": 0, "scaled": 0, "retried": 0}
    for k, cond in enumerate(CONDITIONS):
        params = IdentifyParams(sigma_px=max(cond.sigma_px, 0.3))
        for frame, _, _ in make_frames(stars, cam, cond, 25, 40 + k, mag_limit=5.4):
            monkeypatch.setattr(driver, "FUSED_VERIFY", True)
            monkeypatch.setattr(verify, "_sky_index", index)
            before = len(calls)
            a = identify_stars(frame, cam, db, algorithm, params)
            assert len(calls) - before == a.trials       # every proposal went through the kernel
            # The reference: the Python path, every database star scanned (no sky index).
            monkeypatch.setattr(driver, "FUSED_VERIFY", False)
            monkeypatch.setattr(verify, "_sky_index", lambda _db: verify._NO_INDEX)
            b = identify_stars(frame, cam, db, algorithm, params)
            assert len(calls) - before == a.trials       # ... and none of the Python path's
            assert _result(a) == _result(b)
            _same_probability(a, b)
            assert a.details.get("residual_arcsec_rms") == pytest.approx(b.details.get("residual_arcsec_rms"), abs=1e-3)
            if a.quaternion_estimate is not None:
                np.testing.assert_allclose(a.quaternion_estimate, b.quaternion_estimate, rtol=0, atol=1e-12)
            outcomes["ok" if a.status == "ok" else "failed"] += 1
            outcomes["scaled"] += a.focal_scale is not None
            outcomes["retried"] += a.trials > 1
    # The comparison covered accepted and refused frames, fitted scales and rejected proposals.
    assert outcomes["ok"] >= 60 and outcomes["scaled"] >= 10 and outcomes["retried"] >= 3, outcomes


def test_fused_pyramid_search_decides_as_the_python_loop(sensor, monkeypatch):
    """The pyramid's search and verification in one kernel (``Algorithm.fused``) as the driver's Python loop
    over the search's proposals, each verified by the fused verification: the same result, trials and
    details, the same attitude to the bit; with a budget of a few proposals, the same refusal."""
    from startrack._kernels import pyramid as kernels

    cam, db, stars = sensor
    calls = []
    fused = kernels.pyramid_identify

    def counted(*args):
        calls.append(1)
        return fused(*args)

    monkeypatch.setattr(kernels, "pyramid_identify", counted)
    # The pattern-star tier is built once per database and camera, by the first frame either path sees
    # (``prepare_ms`` in its details): built here, so the comparison does not depend on the tests before.
    identify_stars(make_frames(stars, cam, CONDITIONS[0], 1, 39, mag_limit=5.4)[0][0], cam, db, "pyramid")
    outcomes = {"ok": 0, "failed": 0, "scaled": 0, "retried": 0, "budget": 0}
    for k, cond in enumerate(CONDITIONS):
        for budget in (200, 2):
            params = IdentifyParams(sigma_px=max(cond.sigma_px, 0.3), max_proposals=budget)
            for frame, _, _ in make_frames(stars, cam, cond, 25, 40 + k, mag_limit=5.4):
                monkeypatch.setattr(driver, "FUSED_SEARCH", True)
                before = len(calls)
                a = identify_stars(frame, cam, db, "pyramid", params)
                assert len(calls) > before
                monkeypatch.setattr(driver, "FUSED_SEARCH", False)
                b = identify_stars(frame, cam, db, "pyramid", params)
                assert _exact(a) == _exact(b)
                assert a.details == b.details and a.tolerance_arcsec == b.tolerance_arcsec
                if a.quaternion_estimate is not None:
                    assert np.array_equal(a.quaternion_estimate, b.quaternion_estimate)
                outcomes["ok" if a.status == "ok" else "failed"] += 1
                outcomes["scaled"] += a.focal_scale is not None
                outcomes["retried"] += a.trials > 1
                outcomes["budget"] += "budget" in (a.reason or "")
    assert outcomes["ok"] >= 120 and outcomes["scaled"] >= 20 and outcomes["retried"] >= 6 and \
        outcomes["budget"] >= 1 and outcomes["failed"] >= 2, outcomes


def test_fused_verification_is_used_for_pinhole_cameras_only(sensor, monkeypatch):
    """A distorted camera takes the Python path (the kernels project through a pinhole)."""
    from startrack._kernels import pyramid as pyramid_kernels
    from startrack._kernels import verify as kernels

    cam, db, stars = sensor
    frame = make_frames(stars, cam, Condition(sigma_px=0.3, min_catalog_stars=5), 1, 3, mag_limit=5.4)[0][0]

    def refuse(*_args):
        raise AssertionError("the fused kernel was called")

    monkeypatch.setattr(kernels, "verify_focal", refuse)
    monkeypatch.setattr(pyramid_kernels, "pyramid_identify", refuse)
    distorted = Camera(cam.width, cam.height, cam.focal_length_px, cam.cx, cam.cy, 1e-9, 0.0)
    assert identify_stars(frame, distorted, db, "pyramid", IdentifyParams(sigma_px=0.3)).status == "ok"
    with pytest.raises(AssertionError, match="fused kernel"):
        identify_stars(frame, cam, db, "pyramid", IdentifyParams(sigma_px=0.3))


def _clusters_python(ctx, b, keep, identity, votes2, top):
    """Geometric voting's clusters as the Python loops grew them before the kernel (the reference)."""
    n = len(b)
    best = int(votes2.max(initial=0))
    if best < 2:
        return []
    flat = [(int(votes2[i, a]), i, int(identity[i, a])) for i in range(n) for a in range(top)
            if identity[i, a] >= 0 and votes2[i, a] >= 1]
    flat.sort(key=lambda t: (-t[0], t[1]))
    sv = ctx.db.star_vector
    out, seen = [], set()
    for v0, i0, c0 in flat:
        if v0 < 2:
            break
        cluster = [(i0, c0)]
        for _, i, c in flat:
            if any(i == m for m, _ in cluster) or any(c == k for _, k in cluster):
                continue
            if all(abs(float(np.arccos(min(1.0, float(b[i] @ b[m])))) - float(np.arccos(min(1.0, float(sv[c] @ sv[k]))))
                       ) <= ctx.pair_eps(int(keep[i]), int(keep[m])) for m, k in cluster):
                cluster.append((i, c))
        key = frozenset((int(keep[i]), c) for i, c in cluster)
        if len(cluster) >= 3 and key not in seen:
            seen.add(key)
            out.append(([int(keep[i]) for i, _ in cluster], [c for _, c in cluster]))
    return out


def test_voting_clusters_kernel_grows_the_python_clusters(sensor, monkeypatch):
    """Every vote of frames with false stars: the kernel's clusters are the Python loops' clusters, in the
    same order."""
    from startrack.identify import voting

    cam, db, stars = sensor
    rounds = []
    original = voting._clusters

    def spy(ctx, config, b, keep, identity, votes2, top, seen, patterns):
        rounds.append((ctx, config, b.copy(), keep.copy(), identity.copy(), votes2.copy(), top))
        yield from original(ctx, config, b, keep, identity, votes2, top, seen, patterns)

    monkeypatch.setattr(voting, "_clusters", spy)
    for k, cond in enumerate([Condition(sigma_px=0.3, false_stars=10, min_catalog_stars=4),
                              Condition(sigma_px=1.0, false_stars=3, min_catalog_stars=4)]):
        params = IdentifyParams(sigma_px=cond.sigma_px)
        for frame, _, _ in make_frames(stars, cam, cond, 20, 70 + k, mag_limit=5.4):
            identify_stars(frame, cam, db, "voting", params)
    proposals = 0
    for ctx, config, b, keep, identity, votes2, top in rounds:
        ctx.deadline = float("inf")         # replayed after the frame's time budget
        got = [(p.image, p.catalog) for p in original(ctx, config, b, keep, identity, votes2, top, set(), 1)]
        assert got == _clusters_python(ctx, b, keep, identity, votes2, top)
        proposals += len(got)
    assert len(rounds) >= 30 and proposals >= 20, (len(rounds), proposals)


def test_sky_index_cones_hold_the_stars_of_a_full_scan(catalog):
    """cone_stars with the sky index (bands of z, right ascension within a band) returns exactly the stars,
    in the same order, of the test of every star: random cones of 0.5 to 40 deg, some around a pole,
    some straddling right ascension 0, for several band counts."""
    import math

    from startrack._kernels.sky_index import cone_stars, sky_index

    sv = np.ascontiguousarray(catalog.filter_magnitude(None, 6.5).vectors())
    rng = np.random.default_rng(5)
    none = (np.zeros(0, dtype=np.int64), np.zeros(0))
    held = 0
    for nb in (8, int(math.sqrt(len(sv))), 1024):
        cells, ra = sky_index(sv, nb)
        for t in range(300):
            v = rng.normal(size=3)
            if t % 3 == 1:
                v = np.array([0.05 * rng.normal(), 0.05 * rng.normal(), rng.choice([-1.0, 1.0])])
            elif t % 3 == 2:
                v = np.array([1.0, 0.01 * rng.normal(), rng.normal()])
            v /= np.linalg.norm(v)
            cos_r = math.cos(math.radians(rng.uniform(0.5, 40.0)))
            full, fast = np.empty(len(sv), dtype=np.int64), np.empty(len(sv), dtype=np.int64)
            k1 = cone_stars(v[0], v[1], v[2], cos_r, sv, *none, full)
            k2 = cone_stars(v[0], v[1], v[2], cos_r, sv, cells, ra, fast)
            assert k1 == k2 and np.array_equal(full[:k1], fast[:k2])
            held += k1
    assert held > 10000


def test_fused_pyramid_settings_are_shared_and_left_unchanged(sensor, monkeypatch):
    """The fused pyramid's kernel settings (``fpar``, ``ipar``) are made once per camera, settings and
    tolerance and shared by the frames after: the kernel must leave them as made, and a setting changed
    in place on the same IdentifyParams must reach the kernel (the cache key is the values)."""
    from startrack.identify import pyramid

    cam, db, stars = sensor
    made = pyramid._inputs
    calls = []

    def spy(plan, config, frame, camera, params, n):
        got = made(plan, config, frame, camera, params, n)
        cached = dict(pyramid._SETTINGS)
        pyramid._SETTINGS.clear()
        calls.append((got[1], pyramid._settings(config, frame, camera, params)))     # made afresh
        pyramid._SETTINGS.clear()
        pyramid._SETTINGS.update(cached)
        return got

    monkeypatch.setattr(pyramid, "_inputs", spy)
    params = IdentifyParams(sigma_px=0.3)
    frames = [f for f, _, _ in make_frames(stars, cam, Condition(sigma_px=0.3, false_stars=3, min_catalog_stars=4),
                                           20, 11, mag_limit=5.4)]
    results = [identify_stars(f, cam, db, "pyramid", params) for f in frames]
    assert any(r.trials > 1 for r in results)        # kernel calls with rejected proposals
    # The kernel's arguments after the frame's arrays: triads, fpar, ipar, state, seen (budget rows), ...
    assert len({id(rest[1]) for rest, _ in calls}) < len(calls)      # shared
    for rest, (fpar, ipar, budget, triads) in calls:
        assert np.array_equal(rest[1], fpar) and np.array_equal(rest[2], ipar) and rest[4].shape[0] == budget
        assert np.array_equal(rest[0], triads)
    params.max_proposals = 1
    params.max_false_probability = 1e-30
    for f in frames[:5]:
        a = identify_stars(f, cam, db, "pyramid", params)
        b = identify_stars(f, cam, db, "pyramid", IdentifyParams(sigma_px=0.3, max_proposals=1,
                                                                  max_false_probability=1e-30))
        assert _exact(a) == _exact(b) and a.status == "failed" and a.trials == 1


def test_fused_pyramid_from_threads_decides_as_one_thread(sensor):
    """The kernel's in/out arrays are reused per thread (pyramid._buffers): frames identified from several
    threads at once, with the interpreter switching threads every microsecond, give the results of one thread."""
    import sys
    from concurrent.futures import ThreadPoolExecutor

    cam, db, stars = sensor
    params = IdentifyParams(sigma_px=1.0)
    frames = [f for f, _, _ in make_frames(stars, cam, Condition(sigma_px=1.0, false_stars=10, min_catalog_stars=4),
                                           40, 12, mag_limit=5.4)]
    alone = [_exact(identify_stars(f, cam, db, "pyramid", params)) for f in frames]
    interval = sys.getswitchinterval()
    sys.setswitchinterval(1e-6)
    try:
        with ThreadPoolExecutor(4) as pool:
            threaded = list(pool.map(lambda f: _exact(identify_stars(f, cam, db, "pyramid", params)), frames * 3))
    finally:
        sys.setswitchinterval(interval)
    assert threaded == alone * 3
    assert sum(r[0] == "ok" for r in alone) >= 30 and any(r[3] > 1 for r in alone)


@pytest.mark.parametrize("algorithm", ["pyramid", "labelling"])
def test_star_table_is_identified_as_its_star_list(sensor, algorithm, catalog):
    """A StarTable's columns (read as they are, no per-star dict) give the result of the same stars as
    dicts: with and without reported sigmas, on the fused path (pyramid) and the Python one (labelling)."""
    from startrack.labels import build_labels
    from startrack.records import StarTable

    cam, db, stars = sensor
    dbase = db if algorithm == "pyramid" else build_labels(catalog.filter_magnitude(None, 5.8), 14.0)
    cond = Condition(sigma_px=0.5, false_stars=2, min_catalog_stars=4)
    seen_ok = 0
    for k, (frame, _, _) in enumerate(make_frames(stars, cam, cond, 12, 77, mag_limit=5.4)):
        if k % 2:      # reported per-star sigmas, some missing (the frame's median stands in)
            frame = [dict(s, sigma_px=0.2 + 0.05 * i) if i % 3 else dict(s) for i, s in enumerate(frame)]
        for params in (IdentifyParams(sigma_px=0.5), IdentifyParams()):
            a = identify_stars(frame, cam, dbase, algorithm, params)
            table = StarTable([s["x"] for s in frame], [s["y"] for s in frame], [s.get("flux") for s in frame],
                              [s.get("sigma_px", np.nan) for s in frame])      # NaN: not reported
            b = identify_stars(table, cam, dbase, algorithm, params)
            assert _exact(a) == _exact(b)
            if a.quaternion_estimate is not None:
                np.testing.assert_array_equal(a.quaternion_estimate, b.quaternion_estimate)
            seen_ok += a.status == "ok"
    assert seen_ok >= 12


def test_matched_scale_is_focal_scale():
    """The loop's scale of the matches (matched_scale: the chords of every pair, then their least-squares
    sums) is focal_scale's value bit for bit, for any detections and stars (the fused and the Python
    verification take the one and the other before)."""
    from startrack._kernels.focal import focal_scale, matched_scale

    rng = np.random.default_rng(11)
    sv = rng.normal(size=(300, 3))
    sv /= np.linalg.norm(sv, axis=1)[:, None]
    b = rng.normal(size=(40, 3)) + np.array([0.0, 0.0, 8.0])
    b /= np.linalg.norm(b, axis=1)[:, None]
    xs, ys = rng.uniform(0, 1000, 40), rng.uniform(0, 800, 40)
    for trial in range(300):
        n = int(rng.integers(0, 25))
        mi = np.sort(rng.choice(40, n, replace=False)).astype(np.int64)
        mc = rng.choice(300, n, replace=False).astype(np.int64)
        want = focal_scale(b, mi, sv, mc)
        got, _ = matched_scale(b, xs, ys, np.full(40, 0.3), 3000.0, sv, mi, mc)
        assert (np.isnan(want) and np.isnan(got)) or want == got, (trial, want, got)


def test_scale_interval_holds_the_chord_scale():
    """scale_interval's O(n) interval holds focal_scale's value as computed, for fields measured at a focal
    length off by up to 3 %, with noise, with wrong matches among the right ones and with matches that are
    all wrong, under the attitude that matched them or a poor one; and it is narrow where the residuals
    are small (exact positions, the true attitude: width < 1e-6), so that it decides the focal loop there.
    (Fails if a bound's sign or its n factor were wrong: the wrong-match and scaled fields put the scale
    at either edge.)"""
    from startrack._kernels.attitude import quat_to_dcm
    from startrack._kernels.common import pixels_to_unit
    from startrack._kernels.focal import focal_scale, scale_interval
    from startrack.rotations import quaternion_to_dcm, random_quaternions

    rng = np.random.default_rng(23)
    narrow = 0
    for trial, q in enumerate(random_quaternions(200, rng)):
        n = int(rng.integers(3, 60))
        f_true = float(rng.uniform(800, 6000))
        xs, ys = rng.uniform(0, 1280, n), rng.uniform(0, 960, n)
        scale = 1.0 + float(rng.uniform(-0.03, 0.03)) * (trial % 3 != 0)
        sv = pixels_to_unit(xs, ys, f_true, 639.5, 479.5) @ quaternion_to_dcm(q)   # the stars, ICRS
        noisy = trial % 2 == 0
        b = pixels_to_unit(xs + noisy * rng.normal(0, 0.5, n), ys + noisy * rng.normal(0, 0.5, n), f_true * scale,
                           639.5, 479.5)
        mi = np.arange(n, dtype=np.int64)
        mc = np.arange(n, dtype=np.int64)
        wrong = trial % 5
        if wrong == 1:
            mc[: n // 4] = rng.permutation(mc[: n // 4])       # some wrong matches
        elif wrong == 2:
            mc = rng.permutation(mc)                            # all wrong
        dcm = quaternion_to_dcm(q)
        if wrong == 3:                                          # an attitude a degree off
            dcm = quat_to_dcm(np.asarray(random_quaternions(1, rng)[0]) * 0.02 + np.asarray(q))   # (not unit)
        lo, hi = scale_interval(b, mi, sv, mc, np.ascontiguousarray(dcm))
        got = focal_scale(b, mi, sv, mc)
        assert lo <= got <= hi, (trial, lo, got, hi)
        if wrong in (0, 4) and not noisy and scale == 1.0:
            assert hi - lo < 1e-6, (trial, lo, hi)
            narrow += 1
    assert narrow >= 8


def test_focal_scale_of_chords_measures_a_known_focal_error():
    """A field measured with a focal length 1 % short of the true one (every measured angle about 1 %
    too large) gives the focal scale ``f_used / f_true`` (true f = f / scale) to within the tangent
    projection's departure from proportional angles, whichever attitude; 1 at the true focal length."""
    from startrack._kernels.common import pixels_to_unit
    from startrack._kernels.focal import focal_scale
    from startrack.rotations import quaternion_to_dcm, random_quaternions

    rng = np.random.default_rng(5)
    f_true, f_used = 3000.0, 3000.0 / 1.01
    xs = rng.uniform(0, 1280, 12)
    ys = rng.uniform(0, 960, 12)
    for q in random_quaternions(5, rng):
        b_true = pixels_to_unit(xs, ys, f_true, 639.5, 479.5)
        sv = b_true @ quaternion_to_dcm(q)          # the catalog's vectors of these detections
        b = pixels_to_unit(xs, ys, f_used, 639.5, 479.5)
        idx = np.arange(12, dtype=np.int64)
        s = focal_scale(b, idx, sv, idx)
        # Angles through a pinhole are not exactly proportional to 1/f (tan): within 1e-3.
        assert abs(s - f_used / f_true) < 1e-3, s
        assert abs(focal_scale(b_true, idx, sv, idx) - 1.0) < 1e-12


def test_database_caches_follow_its_arrays(sensor):
    """What identification caches on a k-vector database (the pyramid's plan, sorted magnitudes, the sky
    index) is dropped when one of its arrays is set: the pyramid's next plan holds the new array."""
    import copy

    from startrack.identify import pyramid

    cam, db, stars = sensor
    db = copy.copy(db)
    db.__dict__ = {k: v for k, v in db.__dict__.items() if not k.startswith("_")}
    frame = make_frames(stars, cam, Condition(sigma_px=0.3, min_catalog_stars=5), 1, 5, mag_limit=5.4)[0][0]
    params = IdentifyParams(sigma_px=0.3)
    assert identify_stars(frame, cam, db, "pyramid", params).status == "ok"
    plan = db.__dict__["_pyramid_plan"]
    assert pyramid._plan(db) is plan and "_mags_sorted" in db.__dict__
    db.star_mag = np.full(len(db.star_mag), 1.0)
    assert not [k for k in db.__dict__ if k.startswith("_")]
    assert pyramid._plan(db) is not plan
    assert pyramid._plan(db)[2][8] is db.star_mag
