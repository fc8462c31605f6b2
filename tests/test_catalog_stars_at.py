"""CatalogStarsAt (the final match's catalog at a frame's time, its stars moved where the frame reads them) gives what
CatalogStars of the whole catalog moved to that time gave: the same cones, vectors, motion and identifications, bit
for bit; and `identify` on timed frames writes the same documents."""
import json
import math
import os
import subprocess
import sys

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from startrack.camera import Camera
from startrack.identify.catalog_match import CatalogStars, CatalogStarsAt
from startrack.render import Scene, Sensor, star_list
from startrack.rotations import quaternion_to_dcm, radec_roll_to_dcm, random_quaternions

EPOCHS = [(2026.72, None), (1900.0, None), (2100.0, 2016.0), (1991.25, 2000.0), (2026.72, 2026.72)]


def _whole(catalog, epoch, since_epoch):
    """What `identify` built before: the whole catalog moved, its motion since the database's epoch."""
    since = catalog if since_epoch is None else catalog.propagate(since_epoch)
    return CatalogStars.from_catalog(catalog.propagate(epoch), since)


def _axes():
    fixed = [(0.0, 90.0, 0.0), (269.45, 4.69, 0.0), (180.0, -89.9, 10.0), (0.01, 0.0, 0.0), (359.9, -30.0, 70.0)]
    return [radec_roll_to_dcm(*a)[2] for a in fixed] + [quaternion_to_dcm(q)[2] for q in
                                                        random_quaternions(8, np.random.default_rng(12))]


@pytest.mark.parametrize("epoch, since_epoch", EPOCHS)
def test_cones_vectors_and_motion_are_the_whole_catalogs(catalog, epoch, since_epoch):
    here = CatalogStars.from_catalog(catalog)
    lazy = CatalogStarsAt(here, catalog, epoch, since_epoch)
    whole = _whole(catalog, epoch, since_epoch)
    for axis in _axes():
        # (269.45, 4.69): Barnard's star, the fastest, near the cone's edge at some radius
        for radius_deg in (0.5, 4.0, 11.0, 60.0, 179.5):
            for limit in (None, 6.0, 8.0):
                cos_r = math.cos(math.radians(radius_deg))
                want = whole.in_cone(axis, cos_r, limit)
                got = lazy.in_cone(axis, cos_r, limit)
                assert np.array_equal(got, want), (epoch, radius_deg, limit)
                assert np.array_equal(lazy.vectors_of(got), whole.vectors_of(want))
                assert np.array_equal(lazy.vectors_of(got[::-1].copy()), whole.vectors[want[::-1]])
    ids = catalog.id[np.r_[0:40, np.argsort(-np.hypot(np.nan_to_num(catalog.pm_ra), np.nan_to_num(catalog.pm_dec)))[:20]]]
    ids = np.concatenate([ids, [10**9]])           # an id the catalog lacks: unchanged
    vectors = np.random.default_rng(1).normal(size=(len(ids), 3))
    vectors /= np.linalg.norm(vectors, axis=1, keepdims=True)
    assert np.array_equal(lazy.moved(ids, vectors), whole.moved(ids, vectors))
    assert np.array_equal(lazy.parallax_of(ids), whole.parallax_of(ids))
    if epoch != (since_epoch or catalog.epoch):
        # The fastest stars did move: the comparison above is not of two unmoved catalogs.
        assert np.max(np.abs(lazy.moved(ids, vectors) - vectors)) > 1e-5


@pytest.mark.parametrize("epoch", [2026.72, 1920.0])
def test_identifications_are_the_whole_catalogs(catalog, epoch):
    """identify_stars' final match (rendered 15 deg frames of the catalog at ``epoch``): the same matches, attitude
    and details with the frame's catalog moved star by star as with the whole catalog moved."""
    from startrack.identify import IdentifyParams, identify_stars
    from startrack.kvector import build_kvector, max_separation_deg

    cam = Camera.from_fov(15.0, 1024, 1024)
    db = build_kvector(catalog.filter_magnitude(None, 5.0), max_separation_deg(camera=cam))
    here = CatalogStars.from_catalog(catalog)
    lazy = CatalogStarsAt(here, catalog, epoch)
    whole = _whole(catalog, epoch, None)
    moved = catalog.propagate(epoch)
    vec = moved.vectors()
    rng = np.random.default_rng(int(epoch))
    params = IdentifyParams(sigma_px=0.3)
    identified = 0
    for q in random_quaternions(12, rng):
        stars, _ = star_list(moved, cam, quaternion_to_dcm(q), Sensor(), Scene(mag_limit=7.0), rng, sigma_px=0.3,
                             vectors=vec)
        if len(stars) < 6:
            continue
        a = identify_stars(stars, cam, db, "pyramid", params, catalog=lazy)
        b = identify_stars(stars, cam, db, "pyramid", params, catalog=whole)
        assert a.status == b.status and a.matches == b.matches
        if a.status == "ok":
            identified += 1
            assert np.array_equal(a.quaternion_estimate, b.quaternion_estimate)
            timing = ("prepare_ms",)       # (the database's first use for this sensor: set-up, not the answer)
            assert ({k: v for k, v in a.details.items() if k not in timing} ==
                    {k: v for k, v in b.details.items() if k not in timing})
            assert len(a.matches) > 10          # the final match added the catalog's fainter stars
    assert identified >= 8


def test_identify_on_frames_days_apart_writes_the_same_documents(tmp_path):
    """`startrack identify` on star lists a day apart: the documents the whole catalog's move gave (stored by the
    test's own reference run below, the old way, in the same process as the CLI's code)."""
    env = {k: v for k, v in os.environ.items()}
    st = [sys.executable, "-m", "startrack"]
    db = str(tmp_path / "db.h5")
    subprocess.run(st + ["build-kvector", "--fov-deg", "15", "--mag-max", "5.0", "-o", db], check=True, env=env,
                   capture_output=True)
    frames = subprocess.run(st + ["render", "--stars-only", "--frames", "4", "--frame-interval-s", "86400",
                                  "--rate-deg-s", "0.001,0.0005,0", "--fov-deg", "15", "--size", "1024x1024",
                                  "--sigma-px", "0.3", "--seed", "8", "--time", "2026-03-01T20:00:00Z"],
                            check=True, env=env, capture_output=True).stdout
    code = ("import sys\nimport startrack.identify.catalog_match as m\n"
            "if sys.argv[1] == 'whole':\n"
            "    m.CatalogStarsAt = lambda stars, catalog, ep, since: m.CatalogStars.from_catalog(\n"
            "        catalog.propagate(ep), catalog if since is None else catalog.propagate(since))\n"
            "from startrack.cli.main import main\nmain(['identify', '-d', sys.argv[2], '-q'])")
    out = {}
    for way in ("whole", "lazy"):
        proc = subprocess.run([sys.executable, "-c", code, way, db], input=frames, capture_output=True, env=env)
        assert proc.returncode in (0, 1), proc.stderr.decode()[-2000:]       # (1: a frame not identified)
        docs = [json.loads(line) for line in proc.stdout.decode().splitlines()]
        for d in docs:
            d["identification"].pop("time_ms")
            d["identification"].pop("prepare_ms", None)        # (set-up times)
        out[way] = docs
    assert len(out["lazy"]) == 4
    for a, b in zip(out["lazy"], out["whole"]):
        for key in set(a) | set(b):
            assert a.get(key) == b.get(key), key
    ok = [d for d in out["lazy"] if d["identification"]["status"] == "ok"]
    assert len(ok) >= 3 and all(d["identification"]["apparent"] for d in ok)


@settings(max_examples=200, deadline=None)
@given(st.lists(st.integers(-3, 60), min_size=1, max_size=40), st.lists(st.integers(-5, 70), max_size=30))
def test_catalog_rows_of_ids_are_the_sorted_searchs(ids, want):
    """CatalogStars' id look-up (a table by id for small distinct ids, else a sorted search) finds every id's first
    row and nothing else, as the stable argsort's search does."""
    from startrack.identify.catalog_match import CatalogStars

    cat_ids = np.array(ids, dtype=np.int64)
    stars = CatalogStars(np.zeros((len(ids), 3)), cat_ids, np.zeros(len(ids)))
    rows, found = stars._rows(want)
    for w, r, f in zip(want, rows.tolist(), found.tolist(), strict=True):
        assert f == (w in ids)
        assert 0 <= r < len(ids)
        if f:
            assert r == ids.index(w)
