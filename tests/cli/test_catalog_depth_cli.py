"""Deep catalog, chosen database depth and unresolved doubles through the real CLI (issue 14)."""
import json

import numpy as np
import pytest
from conftest import assert_refused, run_cli

# Pairs 20-35" apart that a 15 deg 1280 px sensor (42"/px) images as one star: (brighter, fainter).
DOUBLES = ((86614, 86620), (63003, 63005), (5131, 5132))
SENSOR = ("--fov-deg", "15", "--size", "1280x960")


@pytest.fixture(scope="module")
def db15(tmp_path_factory):
    out = tmp_path_factory.mktemp("db") / "s15.h5"
    proc = run_cli("build-kvector", *SENSOR, "--mag-max", "6", "-o", out, check=True)
    assert "unresolved groups merged" in proc.stderr
    return out


def test_database_lists_merged_doubles(db15):
    from startrack.kvector import load_kvector

    db = load_kvector(str(db15))
    assert db.params["merge_arcsec"] == pytest.approx(2 * 15 * 3600 / 1280, rel=1e-2)   # 2 px at the centre
    held = dict(zip(db.merged_id.tolist(), db.merged_into.tolist(), strict=True))
    for bright, faint in DOUBLES:
        assert bright in db.star_id and faint not in db.star_id
        assert held[faint] == bright


def test_frames_centred_on_doubles_name_the_brighter_star(db15, catalog):
    frames = []
    for n, (bright, _faint) in enumerate(DOUBLES):
        k = int(np.flatnonzero(catalog.id == bright)[0])
        for j, roll in enumerate((0.0, 100.0, 230.0)):
            # The pair near the centre, then off-centre, under different rolls and noise.
            ra = catalog.ra[k] + 2.0 * j / max(np.cos(np.radians(catalog.dec[k])), 0.2)
            frames.append(run_cli("render", "--stars-only", *SENSOR, "--ra", ra, "--dec", catalog.dec[k],
                                  "--roll", roll, "--mag-max", "6", "--sigma-px", "0.3",
                                  "--seed", 10 * n + j, check=True).stdout)
    proc = run_cli("identify", "-d", db15, input="".join(frames))
    docs = [json.loads(line) for line in proc.stdout.splitlines()]
    assert len(docs) == 9
    for doc, (bright, faint) in zip(docs, [d for d in DOUBLES for _ in range(3)], strict=True):
        truth = doc["truth"]
        blend = next(s for s in truth["stars"] if s["id"] == bright)
        assert faint in blend.get("blended", [])          # render sees one star, named after the brighter
        ident = doc["identification"]
        assert ident["status"] == "ok", ident
        named = {m["id"]: truth["star_ids"][m["star"]] for m in ident["matches"]}
        assert all(named_id == true_id for named_id, true_id in named.items())   # 0 wrong, strictly
        assert faint not in named


def test_build_kvector_chooses_the_depth(tmp_path):
    out = tmp_path / "auto.h5"
    proc = run_cli("build-kvector", "--fov-deg", "20", "--size", "1280x960", "-o", out, check=True)
    assert "depth chosen" in proc.stderr
    from startrack.kvector import load_kvector

    db = load_kvector(str(out))
    p = db.params
    assert p["depth"] == "chosen" and p["stars_per_field"] == 20
    assert db.star_mag.max() <= p["depth_mag_max"] + 1e-6
    # The recorded Monte Carlo of database stars per field: 95 % of the sky holds 15 or more.
    assert p["field_stars_p5"] >= 15 and p["field_stars_median"] <= 30
    assert db.n_pairs <= p["max_pairs"] * 1.2


def test_build_kvector_depth_options_are_checked(tmp_path):
    out = tmp_path / "x.h5"
    assert_refused(run_cli("build-kvector", "--fov-deg", "20", "--mag-max", "5", "--stars-per-field", "20",
                           "-o", out), "--stars-per-field")
    assert_refused(run_cli("build-kvector", "--fov-deg", "20", "--merge-px", "2", "--mag-max", "5", "-o", out),
                   "--merge-px", "--size")
    assert_refused(run_cli("build-kvector", *SENSOR, "--merge-px", "-1", "--mag-max", "5", "-o", out), "--merge-px")


def test_render_default_depth_is_the_sensor_detection_limit():
    # The catalog goes to Hp 14.6; render stops where the sensor's 5-sigma detection stops.
    def render(*extra):
        doc = json.loads(run_cli("render", "--stars-only", "--fov-deg", "20", "--size", "1024x1024", "--ra", "83.8",
                                 "--dec", "-1.2", "--seed", "1", *extra, check=True).stdout)
        return doc["render"]["params"]["scene"]["mag_limit"], [s["mag"] for s in doc["truth"]["stars"]]

    limit, mags = render()
    assert limit == pytest.approx(8.11, abs=0.01)          # default sensor: ~114 e- at SNR 5
    assert max(mags) <= limit and max(mags) > limit - 0.1
    deeper, mags = render("--exposure-ms", "1000")
    assert deeper > limit + 1.0 and max(mags) <= deeper


def test_identify_searches_fainter_detections_when_the_brightest_are_false(db15):
    """Thirty false stars as bright as the stars: the 20 brightest detections hold a few catalog stars,
    and the search of their patterns spends its proposals on chance ones; the search of the 40 brightest
    (--max-search-stars, default 80) finds every frame, none wrong.  With --max-search-stars 20 (one
    search) every frame fails, exit status 1."""
    frames = run_cli("render", "--stars-only", *SENSOR, "--mag-max", "5.5", "--sigma-px", "0.3", "--false-stars", "30",
                     "--count", "4", "--seed", "3", check=True).stdout
    deep = run_cli("identify", "-d", db15, input=frames)
    assert deep.returncode == 0, deep.stderr
    for line in deep.stdout.splitlines():
        doc = json.loads(line)
        ident, ids = doc["identification"], doc["truth"]["star_ids"]
        assert ident["status"] == "ok"
        assert 20 < ident["search_stars"] <= len(doc["stars"])
        assert len(ident["matches"]) >= 5
        assert all(ids[m["star"]] == m["id"] for m in ident["matches"])
    one = run_cli("identify", "-d", db15, "--max-search-stars", "20", input=frames)
    assert one.returncode == 1
    docs = [json.loads(line)["identification"] for line in one.stdout.splitlines()]
    assert [d["status"] for d in docs] == ["failed"] * 4
    assert all("search_stars" not in d for d in docs)
