"""The searches keep looking past false stars (issue 14): groups and candidates beyond the first ones."""
import pytest

from startrack.camera import Camera
from startrack.evaluate import Condition, make_frames, score
from startrack.identify import IdentifyParams, identify_stars, make_config


@pytest.fixture(scope="module")
def sensor16(catalog):
    """A 16 deg 1024x1024 sensor the other tests do not use; database Hp <= 5.8 merged for it."""
    from startrack.catalog import merge_radius_arcsec

    cam = Camera.from_fov(16, 1024, 1024)
    cat = catalog.filter_magnitude(None, 5.8).merge_close(merge_radius_arcsec(cam))
    return cam, cat, catalog.filter_magnitude(None, 5.4)


def test_min_catalog_stars_counts_catalog_stars_only(sensor16):
    cam, _, stars = sensor16
    frames = make_frames(stars, cam, Condition(sigma_px=0.3, false_stars=10, min_catalog_stars=6), 30, 4,
                         mag_limit=5.4)
    assert all(sum(1 for i in t["star_ids"] if i is not None) >= 6 for _, t, _ in frames)
    # min_stars counts every detection, false stars too.
    frames = make_frames(stars, cam, Condition(sigma_px=0.3, false_stars=10, min_stars=6), 30, 4, mag_limit=5.4)
    assert all(len(s) >= 6 for s, _, _ in frames)
    assert any(sum(1 for i in t["star_ids"] if i is not None) < 6 for _, t, _ in frames)


def test_labelling_goes_past_the_brightest_groups(sensor16):
    """Ten false stars among the detections: the groups of the 8 brightest rarely hold four true stars; the
    search continues with groups adding fainter stars (paper 004 stops at the 8 brightest)."""
    from startrack.labels import build_labels

    cam, cat, stars = sensor16
    db = build_labels(cat, max(cam.fov_deg))
    frames = make_frames(stars, cam, Condition(sigma_px=0.3, false_stars=10, min_catalog_stars=5), 60, 9,
                         mag_limit=5.4)
    params = IdentifyParams(sigma_px=0.3)
    wide = [score(identify_stars(s, cam, db, "labelling", params), t) for s, t, _ in frames]
    first8 = [score(identify_stars(s, cam, db, "labelling", params, make_config("labelling", {"group_stars": 8})), t)
              for s, t, _ in frames]
    assert wide.count("bad") == 0 and first8.count("bad") == 0
    assert wide.count("success") >= 0.9 * len(frames)
    assert wide.count("success") > first8.count("success") + 10


def test_brightness_search_covers_every_group_of_the_search_stars(sensor16):
    """Ten false stars: the four-star loops must reach the groups whose brightest star is true (the
    first 2000 loops hold only those of the two brightest detections)."""
    cam, cat, stars = sensor16
    from startrack.kvector import build_kvector, max_separation_deg

    db = build_kvector(cat, max_separation_deg(camera=cam))
    frames = make_frames(stars, cam, Condition(sigma_px=0.3, false_stars=10, min_catalog_stars=5), 40, 12,
                         mag_limit=5.4)
    params = IdentifyParams(sigma_px=0.3)
    full = [score(identify_stars(s, cam, db, "brightness", params), t) for s, t, _ in frames]
    short = [score(identify_stars(s, cam, db, "brightness", params, make_config("brightness", {"max_loops": 2000})), t)
             for s, t, _ in frames]
    assert full.count("bad") == 0 and short.count("bad") == 0
    assert full.count("success") >= 0.85 * len(frames)
    assert full.count("success") > short.count("success")


def test_voting_keeps_voting_when_its_clusters_fail(sensor16):
    """Ten false stars and few catalog stars: the true identities rank far below chance ones in the first
    vote (the paper's single winner, or each star's eight most voted, miss them); the clusters of every
    candidate, by triangle votes, find them."""
    cam, cat, stars = sensor16
    from startrack.kvector import build_kvector, max_separation_deg

    db = build_kvector(cat, max_separation_deg(camera=cam))
    frames = make_frames(stars, cam, Condition(sigma_px=0.3, false_stars=10, min_catalog_stars=4), 40, 13,
                         mag_limit=5.4)
    params = IdentifyParams(sigma_px=0.3)
    more = [score(identify_stars(s, cam, db, "voting", params), t) for s, t, _ in frames]
    once = [score(identify_stars(s, cam, db, "voting", params, make_config("voting", {"every_candidate": False})), t)
            for s, t, _ in frames]
    assert more.count("bad") == 0 and once.count("bad") == 0
    assert more.count("success") >= 0.9 * len(frames)
    assert more.count("success") >= once.count("success") + 8


def test_voting_four_star_frames_at_one_pixel(sensor16):
    """Four stars at 1 px: ~700 catalog stars share the true identity's maximal 3 votes; every candidate's
    clusters hold the true one, the eight most voted rarely do."""
    cam, cat, stars = sensor16
    from startrack.kvector import build_kvector, max_separation_deg

    db = build_kvector(cat, max_separation_deg(camera=cam))
    frames = make_frames(stars, cam, Condition(sigma_px=1.0, max_stars=4, min_catalog_stars=4), 40, 21,
                         mag_limit=5.4)
    params = IdentifyParams(sigma_px=1.0)
    every = [score(identify_stars(s, cam, db, "voting", params), t) for s, t, _ in frames]
    top8 = [score(identify_stars(s, cam, db, "voting", params, make_config("voting", {"every_candidate": False})), t)
            for s, t, _ in frames]
    assert every.count("bad") == 0 and top8.count("bad") == 0
    assert every.count("success") >= 0.6 * len(frames)
    assert every.count("success") >= top8.count("success") + 0.4 * len(frames)


def test_grid_tries_further_orientations(sensor16):
    """A false star nearer a reference than its true nearest neighbour turns the grid pattern; the search
    goes on with patterns oriented by the next neighbours."""
    cam, cat, stars = sensor16
    from startrack.kvector import build_kvector, max_separation_deg

    db = build_kvector(cat, max_separation_deg(camera=cam))
    # Ten false stars: with the pattern radius at the field's diagonal, five no longer turned a pattern
    # the orientations of the other references could not make up for (60 of 60 either way).  Without the
    # single-reference proposals, which also make up for it (60 of 60 with one orientation).
    frames = make_frames(stars, cam, Condition(sigma_px=0.3, false_stars=10, min_catalog_stars=6), 60, 17,
                         mag_limit=5.4)
    params = IdentifyParams(sigma_px=0.3)
    more = [score(identify_stars(s, cam, db, "grid", params, make_config("grid", {"single_references": False})), t)
            for s, t, _ in frames]
    once = [score(identify_stars(s, cam, db, "grid", params,
                                 make_config("grid", {"orientations": 1, "single_references": False})), t)
            for s, t, _ in frames]
    assert more.count("bad") == 0 and once.count("bad") == 0
    assert more.count("success") > once.count("success")


def test_brightness_counts_magnitude_agreement_in_its_confidence(sensor16):
    """Four-star frames at 1 px: the geometric pattern chance alone (~1e-5) is above the 1e-6 limit; the
    brightness order only filtered geometric candidates, so the magnitude agreement is evidence of its own.
    Leaving it out (``uses_brightness``) refused every one of these frames."""
    import dataclasses

    from startrack.identify.brightness import BRIGHTNESS
    from startrack.identify.driver import run
    from startrack.kvector import build_kvector, max_separation_deg

    cam, cat, stars = sensor16
    db = build_kvector(cat, max_separation_deg(camera=cam))
    frames = make_frames(stars, cam, Condition(sigma_px=1.0, max_stars=4, min_catalog_stars=4), 60, 21,
                         mag_limit=5.4)
    params = IdentifyParams(sigma_px=1.0)
    old = dataclasses.replace(BRIGHTNESS, uses_brightness=True)
    now = [score(run(BRIGHTNESS, BRIGHTNESS.config(), s, cam, db, params), t) for s, t, _ in frames]
    before = [score(run(old, old.config(), s, cam, db, params), t) for s, t, _ in frames]
    assert now.count("bad") == 0 and before.count("bad") == 0
    assert now.count("success") >= 0.6 * len(frames)
    assert now.count("success") >= before.count("success") + 0.5 * len(frames)


def test_grid_catalog_patterns_for_a_database_deeper_than_the_frame(sensor16):
    """The six brightest stars of each frame against a database to Hp 5.8: a catalog star's nearest
    neighbour is often one the frame does not hold, which turns the paper's pattern; the catalog patterns
    oriented by the 2nd and 3rd nearest neighbours too match it."""
    cam, cat, stars = sensor16
    from startrack.kvector import build_kvector, max_separation_deg

    db = build_kvector(cat, max_separation_deg(camera=cam))
    frames = make_frames(stars, cam, Condition(sigma_px=0.3, max_stars=6, min_catalog_stars=4), 60, 23,
                         mag_limit=5.4)
    params = IdentifyParams(sigma_px=0.3)
    three = [score(identify_stars(s, cam, db, "grid", params), t) for s, t, _ in frames]
    one = [score(identify_stars(s, cam, db, "grid", params, make_config("grid", {"catalog_orientations": 1})), t)
           for s, t, _ in frames]
    assert three.count("bad") == 0 and one.count("bad") == 0
    assert three.count("success") >= 0.65 * len(frames)
    assert three.count("success") >= one.count("success") + 0.3 * len(frames)


def test_grid_single_references_in_four_star_fields(sensor16):
    """The four brightest stars of a frame: often only one reference has its true pattern among the best,
    and no second reference confirms it; each reference match is then proposed alone with its orientation
    star and the neighbours their angles name, and the shared verification decides (no wrong answer)."""
    cam, cat, stars = sensor16
    from startrack.kvector import build_kvector, max_separation_deg

    db = build_kvector(cat, max_separation_deg(camera=cam))
    frames = make_frames(stars, cam, Condition(sigma_px=0.3, max_stars=4, min_catalog_stars=4), 60, 31,
                         mag_limit=5.4)
    params = IdentifyParams(sigma_px=0.3)
    single = [score(identify_stars(s, cam, db, "grid", params), t) for s, t, _ in frames]
    paired = [score(identify_stars(s, cam, db, "grid", params, make_config("grid", {"single_references": False})), t)
              for s, t, _ in frames]
    assert single.count("bad") == 0 and paired.count("bad") == 0
    assert single.count("success") >= paired.count("success") + 0.1 * len(frames)


def test_grid_confirmed_references_bring_their_neighbours(sensor16):
    """Two confirmed references: the other stars whose angles to both name exactly one catalog star join
    the proposal (a pattern of four or more, not a pair); none of them named wrongly, false stars left out."""
    import math
    import types

    import numpy as np

    from startrack.identify.grid import _with_neighbours
    from startrack.kvector import build_kvector, max_separation_deg

    cam, cat, stars = sensor16
    db = build_kvector(cat, max_separation_deg(camera=cam))
    index = {int(i): k for k, i in enumerate(db.star_id)}
    frames = make_frames(stars, cam, Condition(sigma_px=0.3, false_stars=3, min_catalog_stars=6), 30, 29,
                         mag_limit=5.4)
    added = wrong = 0
    for s, t, _ in frames:
        b = cam.pixels_to_vectors(np.array([v["x"] for v in s]), np.array([v["y"] for v in s]))
        true = [(i, index[int(v)]) for i, v in enumerate(t["star_ids"]) if v is not None and int(v) in index]
        ctx = types.SimpleNamespace(tol=np.full(len(s), 4 * 0.3 / cam.focal_length_px),
                                    margin=math.radians(2 / 3600))
        img, got = _with_neighbours(ctx, b, db, [true[0][0], true[1][0]], [true[0][1], true[1][1]])
        truth = dict(true)
        for i, c in zip(img[2:], got[2:]):
            added += 1
            wrong += truth.get(i) != c
    assert wrong == 0
    assert added >= 2 * len(frames)


def test_grid_builds_its_catalog_patterns_outside_the_frames_time(sensor16):
    """The first frame of a sensor builds the grid's catalog patterns: reported as prepare_ms, not in time_ms;
    frames whose tolerance differs a little share them (the buffer radius is rounded up)."""
    from startrack.identify.grid import GridConfig, grid_geometry
    from startrack.kvector import build_kvector, max_separation_deg

    cam, cat, stars = sensor16
    db = build_kvector(cat, max_separation_deg(camera=cam))
    frames = make_frames(stars, cam, Condition(sigma_px=0.3, min_catalog_stars=4), 2, 5, mag_limit=5.4)
    first = identify_stars(frames[0][0], cam, db, "grid", IdentifyParams(sigma_px=0.3))
    again = identify_stars(frames[1][0], cam, db, "grid", IdentifyParams(sigma_px=0.3))
    assert first.details.get("prepare_ms", 0) > 0 and "prepare_ms" not in again.details
    # The build is reported apart: the first frame's time is that of an ordinary frame, not the build's.
    assert first.time_ms < first.details["prepare_ms"]
    # Tolerances 10 % apart give one buffer radius (above the configured buffer: rounded up in sqrt(2) steps).
    cfg = GridConfig()
    eps = 3.0 * cfg.buffer_px / cam.focal_length_px
    b1 = grid_geometry(cam, db, cfg, eps)[1]
    assert b1 == grid_geometry(cam, db, cfg, 1.1 * eps)[1] and b1 >= 3 * 1.1 * eps
    assert grid_geometry(cam, db, cfg, 0.1 * eps)[1] == pytest.approx(cfg.buffer_px / cam.focal_length_px)


def test_grid_warm_up_with_the_frames_camera_builds_their_patterns(sensor16):
    """warm_up given the frames' camera (identify --camera) prepares the grid for it: the first frame builds
    nothing (without the camera it warmed up on a 10 deg camera of its own, and the first frame built)."""
    from startrack.identify import warm_up
    from startrack.kvector import build_kvector, max_separation_deg

    cam, cat, stars = sensor16
    frames = make_frames(stars, cam, Condition(sigma_px=0.5, min_catalog_stars=4), 1, 9, mag_limit=5.4)
    for camera, built in ((cam, False), (None, True)):
        db = build_kvector(cat, max_separation_deg(camera=cam))
        warm_up("grid", db, IdentifyParams(), camera)
        first = identify_stars(frames[0][0], cam, db, "grid", IdentifyParams())
        assert ("prepare_ms" in first.details) is built



def _frame15(sensor15, sigma, false_stars, focal_pct, index):
    cam, _, stars = sensor15
    cond = Condition(sigma_px=sigma, false_stars=false_stars, focal_error_pct=focal_pct, min_catalog_stars=4)
    return make_frames(stars, cam, cond, index + 1, 14, mag_limit=5.5)[index][:2]


@pytest.mark.parametrize("fused", [True, False])
def test_pyramid_gate_counts_every_fourth_star_it_tried(sensor15, fused, monkeypatch):
    """A triad's pyramid is completed by whichever other search star matches, so each triad puts n - 3
    four-star patterns to the test and the gate's look-elsewhere factor counts them all.  Counting the
    triads alone, these two frames (the focal length 2 % and 1 % off, so the true pattern is not there
    at the nominal focal length) were accepted at 1.9e-7 and 5.0e-7 with a false star or a wrong star in
    the pyramid, both below the 1e-6 gate; now the nominal pass refuses them and the search goes on to
    the right answer."""
    import startrack.identify.driver as driver

    monkeypatch.setattr(driver, "FUSED_SEARCH", fused)
    cam, db, _ = sensor15
    for sigma, false_stars, focal_pct, index in ((0.3, 10, 2.0, 78), (1.0, 3, 1.0, 57)):
        frame, truth = _frame15(sensor15, sigma, false_stars, focal_pct, index)
        res = identify_stars(frame, cam, db, "pyramid", IdentifyParams(sigma_px=sigma))
        assert score(res, truth) == "success", (index, res.matches, res.reason)
        # The patterns compared: every triad tried, times the n - 3 fourth stars of each.
        assert res.details["patterns"] % (min(len(frame), 20) - 3) == 0


@pytest.mark.parametrize("fused", [True, False])
def test_pyramid_second_pass_keeps_triads_with_triangles_at_many_scales(sensor15, fused, monkeypatch):
    """With the focal length free, a triad's windows hold its triangles at every scale it tells apart
    (free_focal_patterns: 16-24 here), so the nominal limit of 64 triangles skipped every triad of this
    1 px frame (263-971 triangles each, the true pyramid among them) and it failed; the second pass's
    limit is that many times larger."""
    import startrack.identify.driver as driver
    from startrack.identify.pyramid import PyramidConfig

    monkeypatch.setattr(driver, "FUSED_SEARCH", fused)
    cam, db, _ = sensor15
    frame, truth = _frame15(sensor15, 1.0, 3, 1.0, 14)
    assert PyramidConfig().max_triangles == 64
    res = identify_stars(frame, cam, db, "pyramid", IdentifyParams(sigma_px=1.0))
    assert score(res, truth) == "success", res.reason
    assert res.focal_scale == pytest.approx(1 / 1.01, abs=0.003)


@pytest.mark.parametrize("fused", [True, False])
def test_pyramid_nominal_pass_leaves_the_second_half_the_budget(sensor15, fused, monkeypatch):
    """A dense field (18 stars) seen through a focal length 2 % off at 1 px: the nominal pass found a chance
    pyramid in triad after triad and spent all 200 proposals on them, so the second pass, which has the
    true pyramid, never ran.  The nominal pass now has half the budget."""
    import startrack.identify.driver as driver

    monkeypatch.setattr(driver, "FUSED_SEARCH", fused)
    cam, db, _ = sensor15
    frame, truth = _frame15(sensor15, 1.0, 0, 2.0, 59)
    assert len(frame) == 18
    res = identify_stars(frame, cam, db, "pyramid", IdentifyParams(sigma_px=1.0))
    assert score(res, truth) == "success", res.reason
    assert 100 < res.trials <= 200


def test_search_levels():
    """The search stars of each search: max_stars, doubled while the one before found nothing, up to
    max_search_stars and the frame's count."""
    from startrack.identify.driver import search_levels

    p = IdentifyParams()
    assert (p.max_stars, p.max_search_stars) == (20, 80)
    assert search_levels(10, p) == [10]
    assert search_levels(20, p) == [20]
    assert search_levels(30, p) == [20, 30]
    assert search_levels(500, p) == [20, 40, 80]
    assert search_levels(500, IdentifyParams(max_search_stars=20)) == [20]
    assert search_levels(500, IdentifyParams(max_search_stars=10)) == [20]
    assert search_levels(500, IdentifyParams(max_stars=30, max_search_stars=100)) == [30, 60, 100]


@pytest.mark.parametrize("fused", [True, False])
def test_pyramid_searches_deeper_when_the_brightest_are_not_stars(sensor15, fused, monkeypatch):
    """Forty false stars as bright as the stars: the 20 brightest detections hold few catalog stars, and
    their pyramids are chance ones; the search of the 40 brightest (then 80) finds the field.  The gate
    counts the trials of every search: no wrong identity either way."""
    import startrack.identify.driver as driver

    monkeypatch.setattr(driver, "FUSED_SEARCH", fused)
    cam, db, stars = sensor15
    frames = make_frames(stars, cam, Condition(sigma_px=0.3, false_stars=40, min_catalog_stars=6), 24, 31,
                         mag_limit=5.5)
    deep = [identify_stars(s, cam, db, "pyramid", IdentifyParams(sigma_px=0.3)) for s, _, _ in frames]
    one = [identify_stars(s, cam, db, "pyramid", IdentifyParams(sigma_px=0.3, max_search_stars=20))
           for s, _, _ in frames]
    deep_scores = [score(r, t) for r, (_, t, _) in zip(deep, frames)]
    one_scores = [score(r, t) for r, (_, t, _) in zip(one, frames)]
    assert deep_scores.count("bad") == 0 and one_scores.count("bad") == 0
    assert deep_scores.count("success") >= one_scores.count("success") + 8, (deep_scores, one_scores)
    went = [(r, len(s)) for r, (s, _, _) in zip(deep, frames) if r.ok and "search_stars" in r.details]
    assert went and all(r.details["search_stars"] in (40, min(n, 80)) for r, n in went)
    # Each deeper search is counted; at the nominal focal length the nominal searches of 20, 40 and 80 stars
    # come first (search_plan): the frames are found there, without the free-focal-length passes.
    assert all(r.details["searches"] >= 2 for r, _ in went)
    assert sum(r.details["searches"] <= 3 for r, _ in went) >= 0.8 * len(went)
    assert all("search_stars" not in r.details and "searches" not in r.details for r in one)


def test_search_plan():
    """Every depth at the nominal focal length first, then the free focal length's passes, for a search that
    has them and a frame deeper than one search; both passes in each search otherwise."""
    from startrack.identify.driver import BOTH_PASSES as B
    from startrack.identify.driver import FREE_PASS as F
    from startrack.identify.driver import NOMINAL_PASS as N
    from startrack.identify.driver import search_plan

    p = IdentifyParams()
    assert search_plan(15, p, True) == [(15, B)]
    assert search_plan(30, p, True) == [(20, N), (30, N), (20, F), (30, F)]
    assert search_plan(500, p, True) == [(20, N), (40, N), (80, N), (20, F), (40, F), (80, F)]
    assert search_plan(500, p, False) == [(20, B), (40, B), (80, B)]
    assert search_plan(500, IdentifyParams(max_focal_error=0.0), True) == [(20, B), (40, B), (80, B)]
    assert search_plan(500, IdentifyParams(max_search_stars=20), True) == [(20, B)]


@pytest.mark.parametrize("fused", [True, False])
def test_focal_length_off_is_found_after_the_nominal_searches(sensor15, fused, monkeypatch):
    """A focal length 1.5 % off and 15 false stars: more than 20 detections, so the nominal searches of 20 and
    more stars come first (search_plan) and find nothing; the free focal length's pass then finds the field,
    measures the scale, and names no wrong star although every search's trials count."""
    import startrack.identify.driver as driver

    monkeypatch.setattr(driver, "FUSED_SEARCH", fused)
    cam, db, stars = sensor15
    frames = make_frames(stars, cam, Condition(sigma_px=0.3, false_stars=15, min_catalog_stars=6,
                                               focal_error_pct=1.5), 12, 8, mag_limit=5.5)
    assert all(len(s) > 20 for s, _, _ in frames)
    got = [identify_stars(s, cam, db, "pyramid", IdentifyParams(sigma_px=0.3)) for s, _, _ in frames]
    scores = [score(r, t) for r, (_, t, _) in zip(got, frames)]
    assert scores.count("bad") == 0 and scores.count("success") >= 9, scores
    free = [r for r, (s, _, _) in zip(got, frames)
            if r.ok and r.details.get("searches", 1) > len(driver.search_levels(len(s), IdentifyParams()))]
    assert len(free) >= 8
    assert all(r.focal_scale is not None and abs(r.focal_scale - 1.0) > 0.01 for r in free)


def test_focal_scales():
    """Scales 2 eps / theta apart (theta the widest angle of the search stars), nearest first, within the error."""
    import math

    import numpy as np

    from startrack.identify.driver import focal_scales

    theta = math.radians(10.0)
    b = np.array([[0.0, 0.0, 1.0], [math.sin(theta), 0.0, math.cos(theta)], [0.0, math.sin(0.1), math.cos(0.1)]])
    theta = math.acos(float(b[1] @ b[2]))      # the widest angle of the three
    eps = 1e-4
    got = focal_scales(b, eps, 0.05)
    d = 2 * eps / theta
    assert got[:4] == pytest.approx([1 + d, 1 - d, 1 + 2 * d, 1 - 2 * d], rel=1e-9)
    assert len(got) == 2 * int(0.05 / d) and max(abs(s - 1) for s in got) <= 0.05
    assert focal_scales(b, eps, 0.0) == [] and focal_scales(b[:1], eps, 0.05) == []


@pytest.mark.parametrize("algorithm", ["brightness", "voting"])
def test_focal_length_off_is_swept_for_nominal_searches(sensor15, algorithm):
    """Brightness and voting compare angles at the focal length they are given: 1.5 % off, their searches
    find nothing, and the driver searches again at the scales the tolerance tells apart (focal_scales).  The
    frames are found, the scale measured, no star named wrong; with no focal error allowed, not found."""
    cam, db, stars = sensor15
    frames = make_frames(stars, cam, Condition(sigma_px=0.3, min_catalog_stars=6, focal_error_pct=1.5), 12, 5,
                         mag_limit=5.5)
    swept = [identify_stars(s, cam, db, algorithm, IdentifyParams(sigma_px=0.3)) for s, _, _ in frames]
    scores = [score(r, t) for r, (_, t, _) in zip(swept, frames)]
    assert scores.count("bad") == 0 and scores.count("success") >= 10, scores
    went = [r for r in swept if r.ok and r.details.get("searches", 1) >= 2]
    assert len(went) >= 8, [(r.status, r.details.get("searches"), r.focal_scale) for r in swept]
    assert all(abs(r.focal_scale - 0.985) < 0.003 for r in went), [r.focal_scale for r in went]
    fixed = [identify_stars(s, cam, db, algorithm, IdentifyParams(sigma_px=0.3, max_focal_error=0.0))
             for s, _, _ in frames]
    assert sum(r.ok for r in fixed) <= 3
