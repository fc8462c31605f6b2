"""startrack.Solver, the public API: typed records from images, star lists and sequences."""
import ast
import json
import math
import pathlib
import subprocess
import sys

import numpy as np
import pytest

import startrack
from startrack.camera import Camera
from startrack.errors import BadInputError, ParameterError
from startrack.kvector import build_kvector, max_separation_deg
from startrack.records import Match
from startrack.render import RenderRun, Scene, Sensor
from startrack.rotations import _attitude_error_rad, quaternion_to_dcm, radec_roll_to_dcm

ROOT = pathlib.Path(__file__).resolve().parents[1]


def test_import_is_light_and_all_public_names_resolve():
    code = ("import sys, startrack; heavy = [m for m in ('numpy', 'numba', 'cv2', 'astropy', 'h5py', 'click') "
            "if m in sys.modules]; print(heavy); print(startrack.__all__)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.splitlines()
    assert out[0] == "[]"
    names = ast.literal_eval(out[1])
    assert "Solver" in names and "SolveResult" in names and "Status" in names
    for name in names:
        assert getattr(startrack, name) is not None
    with pytest.raises(AttributeError):
        startrack.NoSuchThing  # noqa: B018 - the attribute access is the test


@pytest.fixture(scope="module")
def world(catalog):
    cam = Camera.from_fov(12, 1024, 768)
    db = build_kvector(catalog.filter_magnitude(None, 6.0), max_separation_deg(camera=cam))
    return catalog, cam, db


def _frames(catalog, cam, n, seed, rate=(0.0, 0.0, 0.0)):
    a0 = radec_roll_to_dcm(100.0, 20.0, 10.0)
    run = RenderRun(catalog.filter_magnitude(None, 7.0), cam, Sensor(), Scene(rate_deg_s=rate), seed, a0, 1, n, 0.1)
    return list(run.frames_iter())


def _error_arcsec(attitude, truth_quaternion):
    _, cross, roll = _attitude_error_rad(attitude.dcm, quaternion_to_dcm(truth_quaternion))
    return math.degrees(cross) * 3600, abs(math.degrees(roll)) * 3600


def test_solve_identify_attitude_return_typed_records(world, tmp_path):
    from startrack.imageio import write_image

    catalog, cam, db = world
    doc, image, _ = _frames(catalog, cam, 1, 5)[0]
    solver = startrack.Solver(catalog, cam, db)
    # An array ...
    result = solver.solve(image, saturation=65535)
    assert isinstance(result, startrack.SolveResult)
    assert result.status == startrack.Status.OK and result.reason is None
    # One identification type for solve and identify (issue 42): Identification of Match(star, id).
    assert type(result.identification) is startrack.Identification
    assert result.identification.matches and all(type(m) is Match for m in result.identification.matches)
    cross, roll = _error_arcsec(result.attitude, doc["truth"]["quaternion"])
    assert cross < 5 and roll < 60
    # ... and a path give the same answer.
    path = tmp_path / "frame.png"
    write_image(str(path), image)
    from_path = solver.solve(path)
    np.testing.assert_allclose(from_path.attitude.quaternion, result.attitude.quaternion, atol=1e-9)
    # The image centre of a centred principal point is the boresight.
    assert result.center_ra == pytest.approx(result.attitude.ra, abs=1e-6)
    assert result.center_dec == pytest.approx(result.attitude.dec, abs=1e-6)
    # identify and attitude on the star table alone.
    ident = solver.identify(result.stars)
    assert isinstance(ident, startrack.Identification) and ident.status == "ok"
    # Each match is the rendered star nearest its detection, within 1 px (rounding both positions to whole
    # pixels called a detection 0.5 px from its star wrong whenever they rounded to neighbouring pixels).
    tx, ty = (np.array([s[k] for s in doc["truth"]["stars"]]) for k in ("x", "y"))
    tid = [s["id"] for s in doc["truth"]["stars"]]

    def truth_of(star):
        d = np.hypot(tx - result.stars.x[star], ty - result.stars.y[star])
        return tid[int(np.argmin(d))] if d.min() < 1.0 else None

    right = sum(truth_of(m.star) == m.id for m in ident.matches)
    assert right >= 0.9 * len(ident.matches) >= 4
    # Every detection the catalog holds is matched, as `startrack identify` matches them (its --match-all):
    # more than the database's own stars.
    assert len(ident.matches) > len(solver.identify(result.stars, match_all=False).matches)
    att = solver.attitude(result.stars, ident)
    assert isinstance(att, startrack.Attitude)
    assert _error_arcsec(att, doc["truth"]["quaternion"])[0] < 5
    # The frame sections are what the CLI writes: plain JSON.
    frame = json.loads(json.dumps(startrack.to_frame(result)))
    assert frame["solve"]["status"] == "ok" and frame["attitude"]["quaternion"] == pytest.approx(
        list(result.attitude.quaternion))
    assert len(frame["stars"]) == len(result.stars)


def test_failures_are_records_with_reason_codes(world):
    catalog, cam, db = world
    solver = startrack.Solver(catalog, cam, db)
    dark = np.full((768, 1024), 100, dtype=np.uint16)
    result = solver.solve(dark)
    assert result.status == "failed" and result.reason_code == startrack.ReasonCode.NO_STARS
    assert startrack.to_frame(result)["solve"]["reason_code"] == "no_stars"
    ident = solver.identify([{"x": 10.0, "y": 10.0}, {"x": 500.0, "y": 300.0}])
    assert ident.status == "failed" and ident.reason
    att = solver.attitude([], ident)
    assert att.status == "failed" and att.reason_code == startrack.ReasonCode.NOT_IDENTIFIED


def test_track_yields_track_states(world):
    catalog, cam, db = world
    frames = _frames(catalog, cam, 6, 9, rate=(0.2, 0.1, 0.0))
    solver = startrack.Solver(catalog, cam, db)
    states = list(solver.track([img for _, img, _ in frames], dt_s=0.1))
    assert [type(s).__name__ for s in states] == ["TrackState"] * 6
    assert states[0].mode == "lost-in-space" and states[-1].mode == "tracking"
    for (doc, _, _), state in zip(frames, states):
        assert state.attitude.status == "ok"
        assert _error_arcsec(state.attitude, doc["truth"]["quaternion"])[0] < 10


def test_solver_refuses_a_bad_argument_by_its_parameter_name(world):
    catalog, cam, db = world
    with pytest.raises(ParameterError) as info:
        startrack.Solver(catalog, cam, db).solve(np.zeros((10, 10)), fov_deg=-3)
    assert info.value.field == "fov_deg"
    with pytest.raises(BadInputError) as info:
        startrack.Solver(catalog).identify([{"x": 1.0, "y": 2.0}])
    assert info.value.field == "camera"


def test_library_errors_name_parameters_not_flags():
    with pytest.raises(ParameterError) as info:
        Camera.from_fov(-1, 100, 100)
    assert info.value.field == "fov_deg" and "--" not in str(info.value)
    # No library module raises an error whose text names a command-line flag.
    offenders = []
    for path in sorted((ROOT / "startrack").rglob("*.py")):
        if "cli" in path.relative_to(ROOT / "startrack").parts:
            continue
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Raise) and node.exc is not None:
                for sub in ast.walk(node.exc):
                    if isinstance(sub, ast.Constant) and isinstance(sub.value, str) and "--" in sub.value:
                        offenders.append(f"{path.name}:{node.lineno}: {sub.value!r}")
    assert offenders == []
