"""Adding an identification algorithm = one module + one registry line, through the driver and the real CLI."""
import json
import math
import sys
import textwrap

import pytest
from conftest import assert_refused, run_cli

from startrack.camera import Camera
from startrack.evaluate import Condition, make_frames, score
from startrack.identify import IdentifyParams, algorithm_names, config_fields, identify_stars, make_config, register
from startrack.identify.driver import search_levels
from startrack.kvector import build_kvector, max_separation_deg

# A toy algorithm: every catalog pair at the angle of the two brightest stars, both ways round.
# Two stars fix an attitude; the shared verification matches the rest and decides.
TOY = textwrap.dedent('''
    import math
    from dataclasses import dataclass, field

    from startrack.identify import Algorithm, Proposal


    @dataclass(frozen=True)
    class ToyConfig:
        max_pairs: int = field(default=4000, metadata={"help": "Catalog pairs tried."})


    def search(ctx, config):
        th = math.acos(min(1.0, float(ctx.b[0] @ ctx.b[1])))
        eps = ctx.pair_eps(0, 1)
        for n, t in enumerate(ctx.db.pairs_between(th - eps, th + eps)[: config.max_pairs], start=1):
            i, j = int(ctx.db.pair_i[t]), int(ctx.db.pair_j[t])
            yield Proposal([0, 1], [i, j], n)
            yield Proposal([0, 1], [j, i], n)


    TOY = Algorithm("toy-pair", search, ToyConfig, "kvector", "Brightest pair, every catalog candidate.")
''')


@pytest.fixture(scope="module")
def toy_module(tmp_path_factory):
    """The toy as a module on disk with an entry point (the one registry line outside startrack)."""
    root = tmp_path_factory.mktemp("plugin")
    (root / "toy_identify.py").write_text(TOY)
    dist = root / "toy_identify-0.1.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: toy-identify\nVersion: 0.1\n")
    (dist / "entry_points.txt").write_text("[startrack.identify]\ntoy-pair = toy_identify:TOY\n")
    sys.path.insert(0, str(root))
    yield root
    sys.path.remove(str(root))


@pytest.fixture(scope="module")
def setup20(catalog):
    cat = catalog.filter_magnitude(None, 5.0)
    return cat, build_kvector(cat, max_separation_deg(20.0)), Camera.from_fov(20, 1024, 1024)


@pytest.mark.usefixtures("toy_module")
def test_registered_toy_runs_through_the_driver(setup20):
    import toy_identify

    register(toy_identify.TOY)
    assert "toy-pair" in algorithm_names()
    assert any(f["name"] == "max_pairs" and f["algorithms"] == ["toy-pair"] for f in config_fields())
    cat, db, cam = setup20
    frames = make_frames(cat, cam, Condition(sigma_px=0.2, min_stars=10), 20, 3, mag_limit=5.0)
    params = IdentifyParams(sigma_px=0.2, max_proposals=10000)
    results = [identify_stars(s, cam, db, "toy-pair", params) for s, _, _ in frames]
    outcomes = [score(r, t) for r, (_, t, _) in zip(results, frames)]
    assert outcomes.count("bad") == 0 and outcomes.count("success") >= 18
    # The driver kept looking: most frames needed many proposals, and says so.
    assert max(r.trials for r in results) > 10
    # A proposal budget is honoured and reported: one search verifies at most max_proposals; after a
    # spent budget the search of more stars (max_search_stars) has a budget of its own.
    one = identify_stars(frames[0][0], cam, db, "toy-pair",
                         IdentifyParams(sigma_px=0.2, max_proposals=1, max_search_stars=20),
                         make_config("toy-pair", {"max_pairs": 10}))
    assert one.trials == 1 and "search_stars" not in one.details
    tight = identify_stars(frames[0][0], cam, db, "toy-pair", IdentifyParams(sigma_px=0.2, max_proposals=1),
                           make_config("toy-pair", {"max_pairs": 10}))
    searches = search_levels(len(frames[0][0]), IdentifyParams())
    assert len(searches) > 1 and tight.trials <= len(searches)
    if one.status == "failed":
        assert one.reason.startswith("search budget of 1 proposals spent")
        # (this frame's first proposal is rejected: the deeper search had its own)
        assert tight.trials == 2 and tight.details["search_stars"] == searches[-1]
    if tight.status == "failed":
        assert tight.reason_code is not None


def test_toy_runs_through_the_real_cli(toy_module, tmp_path):
    db = tmp_path / "db.h5"
    run_cli("build-kvector", "--fov-deg", "20", "--mag-max", "5.0", "-o", db, check=True)
    env = {"PYTHONPATH": f"{toy_module}:{':'.join(p for p in sys.path if p)}"}
    frames = run_cli("render", "--stars-only", "--count", "8", "--fov-deg", "20", "--size", "1024x1024",
                     "--mag-limit", "5", "--sigma-px", "0.2", "--seed", "4", check=True, env=env).stdout
    help_text = run_cli("identify", "--help", env=env, check=True).stdout
    assert "toy-pair" in help_text and "--max-pairs" in help_text
    proc = run_cli("identify", "-d", db, "-a", "toy-pair", "--max-pairs", "3000", "--max-proposals", "10000",
                   "--sigma-px", "0.2", input=frames, env=env)
    docs = [json.loads(line) for line in proc.stdout.splitlines()]
    assert len(docs) == 8
    ok = [d for d in docs if d["identification"]["status"] == "ok"]
    assert len(ok) >= 6, [d["identification"].get("reason") for d in docs]
    for d in ok:
        assert d["identification"]["algorithm"] == "toy-pair" and d["identification"]["trials"] >= 1
        for m in d["identification"]["matches"]:
            assert d["truth"]["star_ids"][m["star"]] == m["id"]
    # An option of another algorithm is refused, naming it.
    assert_refused(run_cli("identify", "-d", db, "-a", "toy-pair", "--gamma-mag", "0.3", input=frames, env=env),
                   "--gamma-mag", "brightness")


def test_unknown_setting_names_the_field():
    from startrack.errors import BadInputError

    with pytest.raises(BadInputError, match="max_pairs"):
        make_config("pyramid", {"max_pairs": 3})
    with pytest.raises(BadInputError, match="unknown algorithm"):
        identify_stars([{"x": 1.0, "y": 2.0}] * 3, Camera.from_fov(10, 100, 100), None, "no-such")


def test_sparse_four_star_frames_are_identified(catalog):
    """A sensor the other tests do not use (12 deg, 800x600, stars to 5.2, database 5.7): four-star frames."""
    cat = catalog.filter_magnitude(None, 5.7)
    cam = Camera.from_fov(12, 800, 600)
    db = build_kvector(cat, max_separation_deg(camera=cam))
    frames = make_frames(catalog.filter_magnitude(None, 5.2), cam, Condition(sigma_px=0.25, max_stars=4, min_stars=4),
                         60, 21, mag_limit=5.2)
    results = [identify_stars(s, cam, db, "pyramid", IdentifyParams(sigma_px=0.25)) for s, _, _ in frames]
    outcomes = [score(r, t) for r, (_, t, _) in zip(results, frames)]
    assert outcomes.count("bad") == 0
    assert outcomes.count("success") >= 0.9 * len(frames), [r.reason for r in results if r.status != "ok"]
    assert all(r.false_match_probability <= 1e-6 for r in results if r.status == "ok")
    assert not math.isnan(sum(r.time_ms for r in results))


def test_match_everything_against_a_deeper_catalog(catalog):
    """Detections fainter than the database are matched to the catalog with the attitude (0 wrong)."""
    from startrack.identify.catalog_match import CatalogStars

    cam = Camera.from_fov(14, 1000, 800)                     # a sensor the other tests do not use
    db = build_kvector(catalog.filter_magnitude(None, 5.5), max_separation_deg(camera=cam))
    deep = CatalogStars.from_catalog(catalog)
    frames = make_frames(catalog.filter_magnitude(None, 7.0), cam, Condition(sigma_px=0.2, false_stars=2), 15, 8,
                         mag_limit=7.0)
    beyond = ok = 0
    for stars, truth, seed in frames:
        res = identify_stars(stars, cam, db, "pyramid", IdentifyParams(sigma_px=0.2), catalog=deep)
        assert score(res, truth) != "bad", seed
        if res.status == "ok":
            ok += 1
            beyond += res.details.get("matched_beyond_database", 0)
            true_stars = sum(1 for i in truth["star_ids"] if i is not None)
            assert len(res.matches) >= 0.8 * true_stars, seed
    # A frame may hold fewer than four database stars (the database is shallow on purpose).
    assert ok >= 13 and beyond > 100


def test_retired_pyramid_quadratic_is_refused_with_its_reason(tmp_path):
    """pyramid-quadratic returned exactly pyramid's answers and was retired: the library and every command that takes
    an algorithm refuse it with the reason and what to use (exit 2), not as an unknown name; it is no choice."""
    from startrack.errors import BadInputError
    from startrack.identify import get_algorithm

    reason = "retired: it returned exactly pyramid's answers; use pyramid or modified-pyramid (paper 000)"
    assert "pyramid-quadratic" not in algorithm_names()
    with pytest.raises(BadInputError, match="use pyramid or modified-pyramid"):
        get_algorithm("pyramid-quadratic")
    db = tmp_path / "db.h5"
    db.write_bytes(b"")
    assert_refused(run_cli("identify", "-d", db, "-a", "pyramid-quadratic", input=""), reason)
    assert_refused(run_cli("track", "-d", db, "-a", "pyramid-quadratic", tmp_path / "x.jsonl"), reason)
    assert_refused(run_cli("evaluate", "-d", db, "-a", "pyramid,pyramid-quadratic"), reason)
    help_text = run_cli("identify", "--help").stdout
    assert "modified-pyramid" in help_text and "pyramid-quadratic" not in help_text


def test_entry_points_are_importlib_metadatas(toy_module, tmp_path, monkeypatch):
    """The registry's own reading of the installed distributions' entry points (without importing
    importlib.metadata) finds what importlib.metadata finds: the toy plugin's, every console script of this
    environment, and of a distribution on sys.path twice, the first copy only."""
    from importlib.metadata import entry_points

    from startrack.identify import ENTRY_POINT_GROUP, _entry_points

    shadow = tmp_path / "Toy_Identify-0.2.dist-info"     # the same distribution (normalised name), later on the path
    shadow.mkdir()
    (shadow / "METADATA").write_text("Metadata-Version: 2.1\nName: Toy_Identify\nVersion: 0.2\n")
    (shadow / "entry_points.txt").write_text("# a comment\n[startrack.identify]\n toy-pair =  other:TOY \n"
                                             "[console_scripts]\ntoy = other:main\n")
    other = tmp_path / "other_plugin-1.0.dist-info"
    other.mkdir()
    (other / "METADATA").write_text("Metadata-Version: 2.1\nName: other-plugin\nVersion: 1.0\n")
    (other / "entry_points.txt").write_text("[startrack.identify]\nsecond = toy_identify:TOY [extra]\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    monkeypatch.setattr(sys, "path", [p for p in sys.path if p != str(toy_module)])
    monkeypatch.setattr(sys, "path", [str(toy_module), *sys.path])       # the toy's own copy first
    for group in (ENTRY_POINT_GROUP, "console_scripts", "pytest11"):
        want = sorted((e.name, e.value) for e in entry_points(group=group))
        got = sorted((e.name, e.value) for e in _entry_points(group))
        assert got == want, group
    got = {e.name: e for e in _entry_points(ENTRY_POINT_GROUP)}
    assert got["toy-pair"].value == "toy_identify:TOY"          # the first copy's
    import toy_identify

    assert got["second"].load() is toy_identify.TOY and got["toy-pair"].load() is toy_identify.TOY
