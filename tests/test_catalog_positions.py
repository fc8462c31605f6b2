"""A frame's matched stars at the frame's time, without moving the whole catalog (Catalog.rows_of, positions_of):
the same numbers, bit for bit, as the whole catalog propagated, and a solve with a time propagates its matches only."""
import glob
import os
from dataclasses import replace

import numpy as np
import pytest

from startrack.catalog import Catalog

REAL = sorted(glob.glob(os.path.join(os.path.dirname(__file__), "data", "real", "*.tiff")))
assert len(REAL) == 8, "tests/data/real holds the 8 ESA images"


@pytest.fixture()
def moved(monkeypatch):
    """The number of stars of each Catalog.propagate call made while the test runs."""
    sizes = []
    real = Catalog.propagate

    def spy(self, epoch):
        sizes.append(len(self.id))
        return real(self, epoch)

    monkeypatch.setattr(Catalog, "propagate", spy)
    return sizes


@pytest.mark.parametrize("epoch", [None, 1991.25, 2016.0, 2019.57, 2100.0])
def test_positions_of_are_the_whole_catalogs_propagated_rows(catalog, epoch):
    whole = catalog if epoch is None else catalog.propagate(epoch)
    by_id, vec = whole.rows_by_id(), whole.vectors()
    rng = np.random.default_rng(11)
    for size in (1, 3, 58, 400):
        ids = rng.choice(catalog.id, size=size, replace=False).tolist()
        rows, got, cat_rows = catalog.positions_of(ids + [10**9, -7], epoch)
        assert sorted(rows) == sorted(ids) and sorted(rows.values()) == list(range(size))
        for i in ids:
            assert got[rows[i]].tobytes() == vec[by_id[i]].tobytes()
            assert cat_rows[rows[i]] == catalog.rows_by_id()[i]


def _big_id_catalog(catalog, n=500):
    """Stars of ``catalog`` renamed with 64-bit ids (as Gaia's): the sorted table, not the dense one."""
    part = catalog.subset(np.arange(n))
    return replace(part, id=np.asarray(part.id, dtype=np.int64) * 10**12 + 4_000_000_000_123)


def test_rows_of_answers_as_rows_by_id_for_either_table(catalog):
    big = _big_id_catalog(catalog)
    for cat in (catalog, big):
        by_id = cat.rows_by_id()
        ids = cat.id[::7].tolist()
        assert cat.rows_of(ids).tolist() == [by_id[i] for i in ids]
        assert cat.rows_of([-1, 0, int(max(cat.id)) + 1, 2**62]).tolist() == [-1, -1, -1, -1]
    assert catalog._derived("id_table", catalog._id_table)[0] == "dense"
    assert big._derived("id_table", big._id_table)[0] == "sorted"


def test_rows_of_a_repeated_id_is_its_last_row_as_rows_by_id(catalog):
    part = catalog.subset(np.arange(20))
    ids = np.asarray(part.id).copy()
    ids[15] = ids[3]
    twice = replace(part, id=ids)
    assert twice.rows_of([int(ids[3])]).tolist() == [twice.rows_by_id()[int(ids[3])]] == [15]
    big = replace(_big_id_catalog(catalog, 20), id=np.where(np.arange(20) == 15, ids[3] * 10**12, ids * 10**12))
    assert big.rows_of([int(ids[3]) * 10**12]).tolist() == [big.rows_by_id()[int(ids[3]) * 10**12]] == [15]


def test_a_solve_with_a_time_moves_its_matches_alone(moved):
    """A frame's time moves the matched stars, not the catalog's 118,000 (90 ms a frame before); the answer is
    the one the whole catalog moved to that time gives."""
    from startrack.solve import SolveOptions, solve_image

    res = solve_image(REAL[0], SolveOptions(epoch=2019.57))
    assert res.status == "ok"
    assert moved and max(moved) <= len(res.identification.matches)
    # The attitude's stars at 2019.57, from the whole catalog moved there (as before).
    from startrack.catalog import load_catalog

    whole = load_catalog().propagate(2019.57)       # (after the count above)
    ids = [int(m[1]) for m in res.identification.matches]
    by_id = whole.rows_by_id()
    want = whole.vectors()[[by_id[i] for i in ids]]
    ra = np.degrees(np.arctan2(want[:, 1], want[:, 0])) % 360.0
    assert np.array_equal(res.matched_catalog["ra"], ra)


@pytest.mark.parametrize("epoch", [None, 1900.0, 2019.57, 2100.0])
def test_photocentres_at_are_the_whole_catalogs_moved_then_searched(catalog, epoch):
    """Companions found among the stars that can reach a match by ``epoch`` alone: the same photocentres, bit for
    bit, as the whole catalog moved to ``epoch`` and searched (Catalog.photocentres)."""
    vec = catalog.vectors()
    rng = np.random.default_rng(5)
    sample = rng.choice(len(catalog.id), 3000, replace=False)
    radius = 30.0
    close = np.count_nonzero(vec[sample] @ vec.T >= np.cos(np.radians(radius / 3600)), axis=1) >= 2
    ids = [int(i) for i in catalog.id[sample[close][:15]]] + rng.choice(catalog.id, 40, replace=False).tolist()
    whole = catalog if epoch is None else catalog.propagate(epoch)
    by_id = whole.rows_by_id()
    want = whole.photocentres([by_id[i] for i in ids if i in by_id], radius)
    got = catalog.photocentres_at(ids + [10**9], radius, epoch)
    assert len(want) >= 10 and list(got) == list(want)
    assert all(got[k].tobytes() == want[k].tobytes() for k in want)


def test_attitude_moves_a_frames_matches_to_its_time(catalog, tmp_path):
    """`startrack attitude` moves a frame's matches to the frame's own time (Catalog.positions_of): its attitude is
    the one the whole catalog moved to that time gives (the catalog's own 1991.25 positions are 1.2" off here)."""
    import json
    import subprocess
    import sys

    from startrack.attitude import estimate_attitude
    from startrack.camera import Camera
    from startrack.timeutil import julian_year

    render = [sys.executable, "-m", "startrack", "render", "--stars-only", "--frames", "3", "--frame-interval-s",
              "20", "--fov-deg", "15", "--size", "1024x1024", "--sigma-px", "0.3", "--seed", "8", "--mag-max", "5.5",
              "--time", "2026-09-22T12:00:00Z", "--no-aberration"]
    frames = subprocess.run(render, capture_output=True, text=True, check=True).stdout
    docs = [json.loads(line) for line in frames.splitlines()]
    for d in docs:      # the rendered truth as the identification (ids of the rendered stars)
        d["identification"] = {"status": "ok", "algorithm": "truth", "matches": [
            {"star": k, "id": int(i)} for k, i in enumerate(d["truth"]["star_ids"]) if i is not None]}
    src = tmp_path / "ids.jsonl"
    src.write_text("".join(json.dumps(d) + "\n" for d in docs))
    out = subprocess.run([sys.executable, "-m", "startrack", "attitude", str(src), "--no-aberration",
                          "--merge-px", "0"], capture_output=True, text=True, check=True).stdout
    got = [json.loads(line)["attitude"] for line in out.splitlines()]
    from startrack.timeutil import parse_time

    for d, att in zip(docs, got, strict=True):
        ep = julian_year(parse_time(d["image"]["time"], "time"))
        assert att["epoch"] == pytest.approx(ep, abs=1e-12)
        whole = catalog.propagate(ep)
        by_id, vec = whole.rows_by_id(), whole.vectors()
        cam = Camera.from_dict(d["camera"])
        m = d["identification"]["matches"]
        body = np.array([cam.pixels_to_vectors(d["stars"][x["star"]]["x"], d["stars"][x["star"]]["y"]) for x in m])
        ref = vec[[by_id[x["id"]] for x in m]]
        want = estimate_attitude(body.reshape(-1, 3), ref, np.full(len(m), 0.3 / cam.focal_length_px))
        q = np.asarray(want.section()["quaternion"], dtype=np.float64)
        ang = 2 * np.degrees(np.arccos(min(1.0, abs(float(np.dot(q, att["quaternion"])))))) * 3600
        assert ang < 0.05, ang


def test_calibrate_moves_each_frames_matches_alone(tmp_path, moved):
    """`startrack calibrate` of frames solved at their own times moves their matches to those times, not the
    whole catalog for each (100 ms and a kept copy of 15.6 MB a frame before)."""
    import json

    from startrack.cli.main import main
    from startrack.formats.frame import FRAME_FORMAT
    from startrack.formats.sections import to_frame
    from startrack.solve import SolveOptions, solve_image

    with open(tmp_path / "solved.jsonl", "w") as fh:
        for k, path in enumerate(REAL[:3]):
            doc = {"format": FRAME_FORMAT, **to_frame(solve_image(path, SolveOptions(epoch=2019.57 + 0.01 * k)))}
            assert doc["solve"]["status"] == "ok"
            fh.write(json.dumps(doc) + "\n")
    solves = len(moved)         # (the solves' own moves above)
    with pytest.raises(SystemExit) as done:
        main(["calibrate", str(tmp_path / "solved.jsonl"), "-o", str(tmp_path / "cal.json"), "-q"])
    assert done.value.code in (0, None)
    by_calibrate = moved[solves:]
    assert len(by_calibrate) == 3 and max(by_calibrate) <= 200
    assert json.loads((tmp_path / "cal.json").read_text())["calibration"]["frames"] == 3


def _old_matched_catalog(doc, catalog):
    """solve_result_from_frame's matched catalog before it moved the matches alone: the whole catalog moved."""
    epoch = doc.get("attitude", {}).get("epoch")
    cat = catalog.propagate(epoch) if epoch is not None and epoch != catalog.epoch else catalog
    rows = cat.rows_by_id()
    got = [rows.get(int(m["id"])) for m in doc["identification"]["matches"]]
    return {name: np.array([getattr(cat, name)[r] if r is not None else np.nan for r in got], dtype=np.float64)
            for name in ("ra", "dec", "mag")}


def test_a_documents_matched_catalog_moves_its_matches_alone(catalog, monkeypatch):
    """solve_result_from_frame(doc, catalog): the matches' catalog positions at the attitude's epoch are the whole
    catalog's moved there, bit for bit, at any epoch and with ids the catalog lacks (NaN), and nothing moves the
    whole catalog."""
    import copy
    import os

    from startrack import Solver
    from startrack.formats.sections import solve_result_from_frame
    from startrack.records import solve_result_to_frame

    path = os.path.join(os.path.dirname(__file__), "data", "real", "2019-07-29T204726_Alt40_Azi135_Try1.tiff")
    base = solve_result_to_frame(Solver().solve(path))
    assert base["solve"]["status"] == "ok"
    ids = [m["id"] for m in base["identification"]["matches"]]
    lacking = catalog.subset(~np.isin(catalog.id, ids[:3]))
    for cat in (catalog, lacking):
        for epoch in (None, float(catalog.epoch), 2019.58, 1900.0, 2100.0):
            doc = copy.deepcopy(base)
            if epoch is None:
                doc["attitude"].pop("epoch", None)
            else:
                doc["attitude"]["epoch"] = epoch
            want = _old_matched_catalog(doc, cat)
            whole = []
            real = type(cat).propagate

            def spy(self, ep, whole=whole, real=real):
                whole.append(len(self))
                return real(self, ep)

            monkeypatch.setattr(type(cat), "propagate", spy)
            got = solve_result_from_frame(doc, catalog=cat).matched_catalog
            monkeypatch.undo()
            assert all(n <= len(ids) for n in whole)
            for name in ("ra", "dec", "mag"):
                np.testing.assert_array_equal(got[name], want[name])
            assert np.isnan(got["ra"]).sum() == (3 if cat is lacking else 0)
