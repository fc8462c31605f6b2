"""The pyramid's first search tier: the pairs of the database's pattern stars (startrack.identify.pyramid)."""
import math

import numpy as np
import pytest
from conftest import kvector_sensor

from startrack.evaluate import Condition, make_frames, score
from startrack.identify import IdentifyParams, driver, identify_stars
from startrack.identify import pyramid as P


@pytest.fixture(scope="module")
def wide(catalog):
    """A 20 deg 1280x960 sensor, database Hp <= 6 merged for it, stars to 5.5: a field with about 33
    database stars, where the pattern stars hold a fraction of the pairs."""
    return kvector_sensor(catalog, 20, 1280, 960, 6.0, 5.5)


def test_pattern_stars_have_few_brighter_neighbours(wide):
    """The first tier's pairs are exactly the database's pairs of two stars each with fewer than PATTERN_STARS
    brighter database stars within half the short side of the field (counted here over every star, not
    from the pairs), its k-vector finds them, and it shares the database's stars."""
    cam, db, _ = wide
    first = P.pattern_database(db, cam)
    assert first is not None
    v = np.asarray(db.star_vector)
    r = math.radians(min(cam.fov_deg)) / 2
    mag = np.asarray(db.star_mag)
    close = (v @ v.T) >= math.cos(r)
    brighter = (close & (mag[None, :] < mag[:, None])).sum(axis=1)
    pattern = brighter < P.PATTERN_STARS
    assert 0.2 < pattern.mean() < 0.9
    keep = pattern[db.pair_i] & pattern[db.pair_j]
    assert np.array_equal(first.pair_i, db.pair_i[keep]) and np.array_equal(first.pair_j, db.pair_j[keep])
    assert np.array_equal(first.pair_cos, db.pair_cos[keep])
    assert first.star_vector is db.star_vector and first.star_id is db.star_id
    assert first.n_pairs <= P.PATTERN_PAIRS_MAX * db.n_pairs
    rng = np.random.default_rng(3)
    for lo in rng.uniform(first.pair_cos[0], first.pair_cos[-1], 50):
        hi = lo + 2e-5
        idx = first.pairs_between(math.acos(hi), math.acos(lo))
        want = np.flatnonzero((first.pair_cos >= lo) & (first.pair_cos <= hi))
        assert np.array_equal(idx, want)
    # Cached per camera model, and dropped with the arrays it was made from.
    assert P.pattern_database(db, cam) is first
    db.pair_cos = db.pair_cos
    assert P.pattern_database(db, cam) is not first


def test_no_first_tier_where_it_would_keep_most_pairs(catalog):
    """A 14 deg field of a Hp 5.8 database holds about ten database stars: nearly every star is a pattern
    star, and the search has one tier."""
    cam, db, _ = kvector_sensor(catalog, 14, 1200, 900, 5.8, 5.4)
    assert P.pattern_database(db, cam) is None
    assert P.pattern_budget(200) == 50 and P.pattern_budget(3) == 1 and P.pattern_budget(0) == 1


def _tiers_run(db, monkeypatch):
    """The list to which each kernel search of the fused pyramid appends whether it searched ``db``'s own pairs
    (True: the second tier, or the only one) or the first tier's."""
    drive = P._drive
    tiers = []

    def counted(plan, args, frame):
        tiers.append(plan[1][1] is db.pair_i)
        return drive(plan, args, frame)

    monkeypatch.setattr(P, "_drive", counted)
    return tiers


def test_two_tiers_fused_decide_as_the_python_loop(wide, monkeypatch):
    """With two tiers the fused search (one kernel call a tier) and the driver's Python loop over
    search_pyramid's proposals give the same result, trials, patterns and attitude; some frames are
    identified in the first tier and some only in the second (a small budget leaves the first tier two
    proposals, and with pattern stars made rare the first tier often finds nothing)."""
    cam, db, stars = wide
    tiers = _tiers_run(db, monkeypatch)
    seen = {"first": 0, "second": 0, "ok": 0, "one tier": 0}
    conds = [Condition(sigma_px=0.3, min_catalog_stars=4), Condition(sigma_px=1.0, false_stars=6, min_catalog_stars=4),
             Condition(sigma_px=0.5, focal_error_pct=1.0, false_stars=3, min_catalog_stars=4)]
    for k, (cond, few) in enumerate([(c, few) for few in (False, True) for c in conds]):
        # (few: pattern stars made rare, so that the first tier fails often and the second identifies)
        monkeypatch.setattr(P, "PATTERN_STARS", 3 if few else 10)
        db.pair_cos = db.pair_cos          # drop the cached tiers
        for budget in (200, 8):
            params = IdentifyParams(sigma_px=cond.sigma_px, max_proposals=budget)
            for frame, truth, _ in make_frames(stars, cam, cond, 20, 70 + k, mag_limit=5.5):
                monkeypatch.setattr(driver, "FUSED_SEARCH", True)
                tiers.clear()
                a = identify_stars(frame, cam, db, "pyramid", params)
                ran = list(tiers)
                monkeypatch.setattr(driver, "FUSED_SEARCH", False)
                b = identify_stars(frame, cam, db, "pyramid", params)
                assert (a.status, a.reason, a.trials, [tuple(m) for m in a.matches], a.focal_scale) == \
                       (b.status, b.reason, b.trials, [tuple(m) for m in b.matches], b.focal_scale)
                # (the first frame after the tiers were dropped builds them: prepare_ms)
                assert {**a.details, "prepare_ms": 0} == {**b.details, "prepare_ms": 0}
                assert (a.false_match_probability is None) == (b.false_match_probability is None)
                if a.false_match_probability is not None:
                    assert a.false_match_probability == pytest.approx(b.false_match_probability, rel=1e-12)
                if a.quaternion_estimate is not None:
                    assert np.array_equal(a.quaternion_estimate, b.quaternion_estimate)
                # The first tier first, for a frame of more search stars than PATTERN_STARS; else one tier.
                use = min(len(frame), params.max_stars)
                assert ran[0] is (use <= P.PATTERN_STARS), (use, ran)
                seen["one tier"] += use <= P.PATTERN_STARS
                assert score(a, truth) != "wrong"
                seen["ok"] += a.ok
                seen["first"] += a.ok and ran == [False]
                seen["second"] += a.ok and ran[-1] is True
    monkeypatch.undo()
    db.pair_cos = db.pair_cos
    assert seen["first"] >= 60 and seen["second"] >= 10 and seen["ok"] >= 200, seen


def test_second_tier_identifies_what_the_first_cannot(wide, monkeypatch):
    """With pattern stars made rare (fewer than 2 brighter neighbours) the first tier holds few of a
    field's triangles: the second tier identifies every clean frame, with the patterns of both tiers
    counted (more than with one tier)."""
    cam, db, stars = wide
    params = IdentifyParams(sigma_px=0.3)
    frames = make_frames(stars, cam, Condition(sigma_px=0.3, min_catalog_stars=4), 30, 5, mag_limit=5.5)
    one = [identify_stars(f, cam, db, "pyramid", params) for f, _, _ in frames]
    monkeypatch.setattr(P, "PATTERN_STARS", 2)
    db.pair_cos = db.pair_cos          # drop the cached tiers
    assert P.pattern_database(db, cam) is not None
    two = [identify_stars(f, cam, db, "pyramid", params) for f, _, _ in frames]
    monkeypatch.undo()
    db.pair_cos = db.pair_cos
    for (_, truth, _), a, b in zip(frames, one, two):
        assert score(a, truth) == "success" and score(b, truth) == "success"
        assert b.details["patterns"] >= a.details["patterns"]
    assert sum(b.details["patterns"] > a.details["patterns"] for a, b in zip(one, two)) >= 5


def test_a_used_database_pickles_without_its_caches(wide):
    """A database that identified frames (its kernel plans hold compiled functions, its tiers other databases)
    pickles to a process pool or a cluster without them, and the copy identifies as the original."""
    import pickle

    cam, db, stars = wide
    params = IdentifyParams(sigma_px=0.3)
    frames = make_frames(stars, cam, Condition(sigma_px=0.3, min_catalog_stars=4), 3, 9, mag_limit=5.5)
    before = [identify_stars(f, cam, db, "pyramid", params) for f, _, _ in frames]
    assert any(k.startswith("_") for k in db.__dict__)
    copy = pickle.loads(pickle.dumps(db))
    assert not [k for k in copy.__dict__ if k.startswith("_")]
    assert np.array_equal(copy.pair_cos, db.pair_cos) and copy.max_angle_deg == db.max_angle_deg
    after = [identify_stars(f, cam, copy, "pyramid", params) for f, _, _ in frames]
    for a, b in zip(before, after):
        assert (a.status, [tuple(m) for m in a.matches], a.trials) == (b.status, [tuple(m) for m in b.matches], b.trials)


def test_a_frame_of_few_stars_has_one_tier(wide, monkeypatch):
    """A frame of at most PATTERN_STARS search stars is searched over every pair only: its few patterns would
    make the proposals a first tier verified in vain weigh on its gate."""
    cam, db, stars = wide
    plans = _tiers_run(db, monkeypatch)
    params = IdentifyParams(sigma_px=0.3)
    frames = make_frames(stars, cam, Condition(sigma_px=0.3, min_catalog_stars=12), 5, 12, mag_limit=5.5)
    for frame, truth, _ in frames:
        for keep in (P.PATTERN_STARS, P.PATTERN_STARS + 2):
            plans.clear()
            few = frame[:keep]
            r = identify_stars(few, cam, db, "pyramid", params)
            assert plans[0] is (keep <= P.PATTERN_STARS)
            assert score(r, truth) != "wrong" and r.ok
