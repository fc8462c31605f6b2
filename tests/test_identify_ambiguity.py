"""Close pairs and wrong core stars: verification names a star only when the frame tells it apart."""
import math

import numpy as np
import pytest

from startrack.camera import Camera
from startrack.identify import IdentifyParams, identify_stars
from startrack.identify.algorithm import Algorithm, NoConfig, Proposal
from startrack.identify.driver import run
from startrack.kvector import build_kvector, max_separation_deg
from startrack.rotations import radec_roll_to_dcm, vector_to_radec

SIGMA = 1.0


@pytest.fixture(scope="module")
def sensor(catalog):
    """A 12 deg 1024x768 sensor (not used by other tests), database to Hp 6 without merging."""
    cam = Camera.from_fov(12, 1024, 768)
    cat = catalog.filter_magnitude(None, 6.0)
    return cam, cat, build_kvector(cat, max_separation_deg(camera=cam))


def _close_pairs(cat, cam, lo_px, hi_px, min_dmag):
    """Pairs of stars to Hp 5.5 between ``lo_px`` and ``hi_px`` apart, magnitudes differing by ``min_dmag``+."""
    v = cat.vectors()
    bright = np.flatnonzero(cat.mag <= 5.5)
    vb = v[bright]
    cos_hi = math.cos(hi_px / cam.focal_length_px)
    out = []
    for a in range(len(bright)):
        d = vb[a + 1:] @ vb[a]
        for o in np.flatnonzero(d >= cos_hi):
            i, j = bright[a], bright[a + 1 + o]
            sep = math.acos(min(1.0, float(v[i] @ v[j]))) * cam.focal_length_px
            if sep >= lo_px and abs(cat.mag[i] - cat.mag[j]) >= min_dmag:
                out.append((sep, int(i), int(j)))
    return sorted(out)


def _frame(cat, cam, centre_vec, with_flux=True):
    """Noise-free stars (Hp <= 5.5) of the field around ``centre_vec``, brightest first, with their ids."""
    ra, dec = vector_to_radec(centre_vec)
    # the pair off the centre, stars around it (degrees, as every public function of startrack.rotations)
    dcm = radec_roll_to_dcm(ra, dec - 2.0, math.degrees(0.4))
    keep = np.flatnonzero(cat.mag <= 5.5)
    body = cat.vectors()[keep] @ dcm.T
    front = body[:, 2] > 0.5
    x, y = cam.vectors_to_pixels(body[front])
    inside = cam.in_image(x, y)
    idx = keep[front][inside]
    stars = [{"x": float(a), "y": float(b), "id": int(cat.id[k]), "mag": float(cat.mag[k])}
             for a, b, k in zip(x[inside], y[inside], idx)]
    for s in stars:
        if with_flux:
            s["flux"] = 1.0e5 * 10 ** (-0.4 * s["mag"])
    stars.sort(key=lambda s: s["mag"])
    return stars


def _swap_towards(stars, id_a, id_b, frac=0.35):
    """Move each detection of the pair to ``frac`` of the way from the *other* star's position."""
    a = next(s for s in stars if s["id"] == id_a)
    b = next(s for s in stars if s["id"] == id_b)
    ax, ay, bx, by = a["x"], a["y"], b["x"], b["y"]
    a["x"], a["y"] = bx + frac * (ax - bx), by + frac * (ay - by)
    b["x"], b["y"] = ax + frac * (bx - ax), ay + frac * (by - ay)


def _wrong(res, stars):
    return [(m.star, m.id, stars[m.star]["id"]) for m in res.matches if stars[m.star]["id"] != m.id]


@pytest.mark.parametrize("with_flux", [True, False])
def test_close_pair_is_named_by_magnitude_or_refused(sensor, with_flux):
    """Two resolved stars 1.5-4.5 px apart at 1 px noise, each detection nearer the *other* star's prediction.

    With fluxes the magnitudes tell them apart (both named right); without, the
    pair is refused -- never reported swapped.
    """
    cam, cat, db = sensor
    pairs = _close_pairs(cat, cam, 1.5, 4.5, 0.4)
    assert pairs, "the catalog holds such pairs"
    checked = 0
    for _, i, j in pairs[:4]:
        stars = _frame(cat, cam, cat.vectors()[i], with_flux)
        ids = [s["id"] for s in stars]
        if len(stars) < 6 or cat.id[i] not in ids or cat.id[j] not in ids:
            continue
        _swap_towards(stars, int(cat.id[i]), int(cat.id[j]))
        res = identify_stars([{k: s[k] for k in ("x", "y", "flux") if k in s} for s in stars], cam, db, "pyramid",
                             IdentifyParams(sigma_px=SIGMA))
        assert res.status == "ok", res.reason
        assert _wrong(res, stars) == []
        named = {m.id for m in res.matches}
        pair = {int(cat.id[i]), int(cat.id[j])}
        if with_flux:
            assert pair <= named
        else:
            assert not pair & named
        checked += 1
    assert checked >= 1


@pytest.mark.parametrize("real_star_detected", [False, True])
def test_a_wrong_star_in_the_proposal_is_not_bent_into_place(sensor, real_star_detected):
    """A proposal whose first star is a false detection 15 sigma from a catalog star (beside the real
    detection, or instead of it) must not be accepted naming it, though the fit of four stars and a
    focal length can bring it within its match radius."""
    cam, cat, db = sensor
    v = cat.vectors()
    dbi = {int(h): k for k, h in enumerate(db.star_id)}
    sigma = 0.3
    rng = np.random.default_rng(5)
    tried = 0
    for _ in range(60):
        stars = _frame(cat, cam, v[rng.integers(len(v))])
        if len(stars) < 10:
            continue
        fake = dict(stars[0])
        ang = rng.uniform(0, 2 * math.pi)
        fake["x"] += 15 * sigma * math.cos(ang)
        fake["y"] += 15 * sigma * math.sin(ang)
        frame = [fake] + (stars if real_star_detected else stars[1:])
        core = [0, 2, 3, 4] if real_star_detected else [0, 1, 2, 3]
        proposal = Proposal(core, [dbi[frame[k]["id"]] for k in core])

        def search(_ctx, _config, proposal=proposal):
            yield proposal

        res = run(Algorithm("toy", search), NoConfig(), [{k: s[k] for k in ("x", "y", "flux")} for s in frame], cam,
                  db, IdentifyParams(sigma_px=sigma))
        assert res.status != "ok" or all(m.star != 0 for m in res.matches), res.matches
        tried += 1
    assert tried >= 20
