"""Issue 41 (reliability v3): no silent wrong table, no destroyed input, every cache checked, errors named.

Each test's docstring says what main did before the fix.
"""

import pytest

from tests.conftest import assert_refused, run_cli


@pytest.fixture(scope="module")
def db20(tmp_path_factory):
    """A small k-vector database (20 deg field, Hp <= 4)."""
    path = tmp_path_factory.mktemp("rel-db") / "db.h5"
    run_cli("build-kvector", "--fov-deg", "20", "--mag-max", "4", "-o", path, "-q", check=True)
    return path


# -- item 1: a wrong table, silently -----------------------------------------------------------------------------

def test_make_frames_never_returns_a_frame_below_min_stars(catalog):
    """main: after 1000 attitudes make_frames kept the last frame whatever its star count (mean 3.3 stars under a
    ">= 1000 stars" condition).  Now: every frame returned meets the condition, and an unmet one is an error."""
    from startrack.camera import Camera
    from startrack.errors import ParameterError
    from startrack.evaluate import Condition, make_frames

    cam = Camera.from_fov(20, 512, 512)
    cat = catalog.filter_magnitude(None, 4.0)
    frames = make_frames(cat, cam, Condition(min_stars=6), 20, 3, mag_limit=4.0)
    assert all(len(stars) >= 6 for stars, _, _ in frames)
    with pytest.raises(ParameterError) as info:
        make_frames(cat, cam, Condition(min_stars=1000), 1, 3, mag_limit=4.0)
    assert info.value.parameter == "min_stars" and "1000" in info.value.problem
    with pytest.raises(ParameterError) as info:
        make_frames(cat, cam, Condition(false_stars=50, min_stars=3, min_catalog_stars=500), 1, 3, mag_limit=4.0)
    assert info.value.parameter == "min_catalog_stars"


def test_evaluate_refuses_an_unmet_min_stars(db20):
    """main: `evaluate --min-stars 1000` exit 0 with a table row ">= 1000 stars" over frames of ~3 stars."""
    proc = run_cli("evaluate", "-d", db20, "--fov-deg", "20", "--size", "512x512", "-a", "pyramid", "-n", "2",
                   "--seed", "1", "--min-stars", "1000", "-q")
    assert_refused(proc, "--min-stars", "no frame with at least 1000 stars")
