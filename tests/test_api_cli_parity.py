"""The Python API and the CLI give the same answer (issue 38): Solver.solve beside `startrack solve`,
Solver.identify beside `startrack identify` (its defaults: every detection matched against the catalog),
on a real ESA image and on a rendered one."""
import glob
import json
import os

import pytest
from conftest import DATA, run_cli

import startrack
from startrack.camera import Camera

ESA_IMAGE = sorted(glob.glob(os.path.join(DATA, "real", "*.tiff")))[0]
ESA_CAMERA = os.path.join(DATA, "real", "camera.json")


@pytest.fixture(scope="module")
def esa_db(tmp_path_factory):
    out = tmp_path_factory.mktemp("db") / "esa.h5"
    run_cli("build-kvector", "--camera", ESA_CAMERA, "--mag-max", "6.5", "-o", out, check=True)
    return out


@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    out = tmp_path_factory.mktemp("img") / "sky.png"
    run_cli("render", "--camera", ESA_CAMERA, "--mag-max", "8", "--seed", "38", "-o", out, "-q", check=True)
    return out


def _pairs(matches):
    return [(int(m["star"]), int(m["id"])) if isinstance(m, dict) else (int(m.star), int(m.id)) for m in matches]


@pytest.mark.parametrize("which", ["esa", "rendered"])
def test_solver_and_cli_give_the_same_answer(which, rendered, esa_db, solve_cache, monkeypatch):
    image = ESA_IMAGE if which == "esa" else str(rendered)
    monkeypatch.setenv("STARTRACK_CACHE", solve_cache["STARTRACK_CACHE"])
    # solve, blind.
    cli_doc = json.loads(run_cli("solve", image, "-q", env=solve_cache, check=True).stdout)
    # The Python API's first search without a sky index (a process's screens read every row of their catalog
    # prefix until they have read SKY_SCREEN_AFTER times the index's stars, when the cache holds none); the CLI's
    # read the sky index that the cache holds (patterns._file_sky).
    import startrack.patterns as patterns

    file_sky = patterns._file_sky
    monkeypatch.setattr(patterns, "_file_sky", lambda _index: None)
    monkeypatch.setattr(patterns, "SKY_SCREEN_AFTER", float("inf"))
    monkeypatch.setattr(patterns, "_SKY_SCREEN", {})
    result = startrack.Solver().solve(image)
    assert all(state[2] is None for state in patterns._SKY_SCREEN.values())
    assert result.status == "ok" and cli_doc["solve"]["status"] == "ok"
    assert _pairs(result.identification.matches) == _pairs(cli_doc["identification"]["matches"])
    assert len(result.identification.matches) >= 10
    assert result.attitude.ra == pytest.approx(cli_doc["attitude"]["ra"], abs=1e-9)
    assert result.attitude.dec == pytest.approx(cli_doc["attitude"]["dec"], abs=1e-9)
    # Through the pattern index's sky index (patterns._screen_sky, the cache's copy): the same answer, to the bit.
    monkeypatch.setattr(patterns, "_file_sky", file_sky)
    monkeypatch.setattr(patterns, "_SKY_SCREEN", {})
    sky = startrack.Solver().solve(image)
    assert any(state[2] is not None for state in patterns._SKY_SCREEN.values())
    assert _pairs(sky.identification.matches) == _pairs(result.identification.matches)
    assert sky.attitude.quaternion.tobytes() == result.attitude.quaternion.tobytes()
    assert sky.identification.false_match_probability == result.identification.false_match_probability
    assert sky.camera == result.camera
    # identify with its defaults on the same detections and camera.
    cent = run_cli("centroid", image, "--camera", ESA_CAMERA, check=True).stdout
    cli_id = json.loads(run_cli("identify", "-d", esa_db, input=cent, check=True).stdout)["identification"]
    frame = json.loads(cent)
    solver = startrack.Solver(camera=Camera.from_dict(frame["camera"]), database=esa_db)
    ident = solver.identify(frame["stars"])
    assert ident.status == "ok" and cli_id["status"] == "ok"
    assert _pairs(ident.matches) == _pairs(cli_id["matches"])
    # The final match is what made them differ: the database's stars alone are fewer.
    database_only = solver.identify(frame["stars"], match_all=False)
    cli_only = json.loads(run_cli("identify", "-d", esa_db, "--database-only", input=cent,
                                  check=True).stdout)["identification"]
    assert _pairs(database_only.matches) == _pairs(cli_only["matches"])
    assert len(ident.matches) > len(database_only.matches)
