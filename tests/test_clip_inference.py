"""Clipped stars recognised from the pixels when no saturation level is given (or the level given is above every
pixel): a flat plateau at the frame's largest value is a clip, a lone largest pixel is not.  The Python API handed
pixels without ``saturation`` and the CLI reading the file (its type's largest DN) give the same stars and the
same answer."""
import csv
import json
import math
import os

import numpy as np
import pytest
from conftest import DATA, run_cli, star_field

import startrack
from startrack.centroid import CentroidOptions, find_stars
from startrack.imageio import read_image

REAL_EXTRA = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", "shared", "data", "real-extra")
ESA_CAMERA = os.path.join(DATA, "real", "camera.json")


def _field(seed, clip=None, shape=(240, 320), n_stars=40, sigma=1.3):
    """Gaussian stars on a sloped, noisy background (float32); ``clip``: every pixel above it set to it."""
    return star_field(shape, n_stars, seed, sigma, margin=5, log_flux=(2.5, 4.7), clip=clip).astype(np.float32)


def _stars(res):
    return [(s["x"], s["y"], s["flux"], s["saturated"]) for s in res.stars]


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_a_lone_largest_pixel_is_no_clip(seed):
    """Without a level, the frame's largest value held by one pixel (a noisy true peak) is no saturation: the
    stars are those of a level above every pixel, none saturated (the largest value taken as the level called
    the brightest star saturated and spared it the star-likeness tests)."""
    img = _field(seed)
    assert np.count_nonzero(img == img.max()) == 1
    got = find_stars(img)
    assert len(got.stars) >= 10
    assert not any(s["saturated"] for s in got.stars)
    assert _stars(got) == _stars(find_stars(img, saturation=float(img.max()) + 1.0))
    assert got.rejected == find_stars(img, saturation=float(img.max()) + 1.0).rejected


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_a_flat_plateau_at_the_largest_value_is_a_clip(seed):
    """Stars clipped flat below the level given (a 12-bit camera in 16-bit words) or without a level: the
    clipped stars are saturated, the same stars as with the clip level itself given, and the stars whose
    peak reached the clip are among them."""
    clip = 3000.0
    free = _field(seed)
    img = _field(seed, clip)
    assert np.count_nonzero(img == clip) >= 3
    at_level = find_stars(img, saturation=clip)
    assert sum(s["saturated"] for s in at_level.stars) >= 2
    for given in (None, 65535.0, 1e9):
        assert _stars(find_stars(img, saturation=given)) == _stars(at_level), given
    # Every plateau the clip made (the unclipped frame above it) is a saturated detection's.
    import cv2

    n, _, _, centres = cv2.connectedComponentsWithStats((free > clip).astype(np.uint8), connectivity=8)
    flagged = [(s["x"], s["y"]) for s in at_level.stars if s["saturated"]]
    assert n - 1 >= 2
    for cx, cy in centres[1:]:
        assert min(math.hypot(cx - x, cy - y) for x, y in flagged) < 2.0
    # Whole DN: a uint16 array's default is its type's largest DN, and the plateau below it is a clip the same.
    whole = np.rint(img).astype(np.uint16)
    assert _stars(find_stars(whole)) == _stars(find_stars(whole, saturation=65535.0)) == \
        _stars(find_stars(whole, saturation=clip))


@pytest.mark.parametrize("ties,clipped", [(1, False), (2, False), (3, True), (5, True)])
def test_plateau_size(ties, clipped):
    """The rule itself: the largest value held by 1 or 2 pixels of a star is its peak (a whole-DN tie); by 3 or
    more, a flat top, a clip.  Only the star holding them is saturated."""
    img = np.rint(_field(4)).astype(np.float32)
    y, x = np.unravel_index(int(np.argmax(img)), img.shape)
    top = float(img[y, x]) + 50.0
    for dy, dx in [(0, 0), (0, 1), (1, 0), (1, 1), (-1, 0)][:ties]:
        img[y + dy, x + dx] = top
    res = find_stars(img, CentroidOptions())
    flagged = [s for s in res.stars if s["saturated"]]
    if clipped:
        assert len(flagged) == 1 and math.hypot(flagged[0]["x"] - x, flagged[0]["y"] - y) < 2.0
    else:
        assert flagged == []


def _pairs(matches):
    return [(int(m["star"]), int(m["id"])) if isinstance(m, dict) else (int(m.star), int(m.id)) for m in matches]


def test_api_without_saturation_agrees_with_the_cli_on_a_clipped_frame(tmp_path, solve_cache, monkeypatch):
    """A rendered 12-bit frame (16-bit file) whose three brightest stars are clipped flat at 4095: the CLI reads
    the file's level (65535), the Python API gets the pixels alone.  Both solve, with the same stars (the
    clipped ones saturated in both), the same matches and the same attitude."""
    path = tmp_path / "clipped.png"
    doc = json.loads(run_cli("render", "--camera", ESA_CAMERA, "--bit-depth", "12", "--exposure-ms", "1000",
                             "--ra", "83.8", "--dec", "-1.2", "--seed", "7", "-o", path, "-q", check=True).stdout)
    clipped_truth = [s for s in doc["truth"]["stars"] if s["saturated"]]
    pixels, meta = read_image(str(path))
    assert meta["saturation"] == 65535.0 and pixels.max() == 4095.0 and len(clipped_truth) >= 2
    monkeypatch.setenv("STARTRACK_CACHE", solve_cache["STARTRACK_CACHE"])
    cli_doc = json.loads(run_cli("solve", path, "-q", env=solve_cache, check=True).stdout)
    result = startrack.Solver().solve(pixels)
    assert result.status == "ok" and cli_doc["solve"]["status"] == "ok"
    api_stars = [(s["x"], s["y"], bool(s["saturated"])) for s in result.stars.to_list()]
    cli_stars = [(s["x"], s["y"], s["saturated"]) for s in cli_doc["stars"]]
    assert [s[2] for s in api_stars] == [s[2] for s in cli_stars]
    assert np.allclose([s[:2] for s in api_stars], [s[:2] for s in cli_stars], rtol=0, atol=1e-9)
    assert _pairs(result.identification.matches) == _pairs(cli_doc["identification"]["matches"])
    assert result.attitude.ra == pytest.approx(cli_doc["attitude"]["ra"], abs=1e-9)
    assert result.attitude.dec == pytest.approx(cli_doc["attitude"]["dec"], abs=1e-9)
    # The clipped stars are recognised: each truly clipped star in the field is a saturated detection.
    flagged = [(x, y) for x, y, sat in cli_stars if sat]
    for s in clipped_truth:
        if 3 <= s["x"] <= pixels.shape[1] - 4 and 3 <= s["y"] <= pixels.shape[0] - 4:
            assert min(math.hypot(s["x"] - x, s["y"] - y) for x, y in flagged) < 1.0


@pytest.mark.skipif(not os.path.isdir(REAL_EXTRA), reason="../shared/data/real-extra is not beside the clone")
def test_apod4_solves_through_the_api_without_saturation(solve_cache, monkeypatch):
    """The 33 deg photograph (8-bit colour JPEG, read as float grey, largest value 252.6 in one pixel) solves
    through Solver.solve(pixels) without ``saturation`` as with the file's 255 and as from its path: its largest
    pixel (Dubhe's blob, 3 times the point sources' width) is no clip."""
    monkeypatch.setenv("STARTRACK_CACHE", solve_cache["STARTRACK_CACHE"])
    path = os.path.join(REAL_EXTRA, "apod4.jpg")
    ref = next(r for r in csv.DictReader(open(os.path.join(REAL_EXTRA, "solutions.csv"))) if r["file"] == "apod4.jpg")
    pixels, meta = read_image(path)
    solver = startrack.Solver()
    bare = solver.solve(pixels)
    assert bare.status == "ok", bare.reason
    for other in (solver.solve(pixels, saturation=meta["saturation"]), solver.solve(path)):
        assert other.status == "ok"
        assert _pairs(other.identification.matches) == _pairs(bare.identification.matches)
        assert other.attitude.quaternion.tobytes() == bare.attitude.quaternion.tobytes()
    ra, dec = math.radians(bare.center_ra), math.radians(bare.center_dec)
    ra0, dec0 = math.radians(float(ref["ra_deg"])), math.radians(float(ref["dec_deg"]))
    sep = math.acos(min(1.0, math.sin(dec) * math.sin(dec0) + math.cos(dec) * math.cos(dec0) * math.cos(ra - ra0)))
    assert math.degrees(sep) * 3600 < 0.5 * float(ref["arcsec_per_px"])   # within half a pixel of the reference
