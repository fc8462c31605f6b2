"""Blind solving of all-sky and fisheye frames (fields of about 100 to 200 degrees).

No tangent plane holds such a frame, and no single scale: the pinhole searches of :mod:`startrack.solve`
find nothing in it.  But near the principal point every projection of :mod:`startrack.camera` is a
pinhole of the same focal length (each ``g(theta)`` has ``g'(0) = 1``, ``g(theta) = theta (1 + O(theta^2))``),
so the search goes in four steps:

1. **The centre as a pinhole.**  The detections in a square about the image centre (a tenth of the
   image's side each way, 12-27 deg of sky for 120-180 deg fields: well above any horizon, clear of
   the extinction and crowding of low altitudes) are a narrow frame for the scale-invariant pattern
   search (:func:`startrack.patterns.solve_blind`), which measures its focal length (and a k1 for the
   fisheye's departure from a tangent plane) and its attitude.  Larger and smaller squares follow
   when it finds nothing.
2. **Growing outward.**  From that attitude and focal length the catalog is predicted ring after ring
   (every 15 deg off-axis, to the frame's edge) through each fisheye projection in turn, each detection
   matched to the one predicted star within its radius (none when two are), and the focal length (then
   k1, k2 as the rings reach 45 and 70 deg) and the attitude refitted (:func:`startrack.calibrate.calibrate`)
   on the matches so far; the projection that matches the most stars keeps its matches.
3. **The projection.**  Every projection is fitted to the matched stars with its significant distortion
   terms; the least BIC wins (:func:`startrack.calibrate.calibrate_projection`).
4. **The verdict.**  The whole frame is identified again, from nothing, with that camera by the
   k-vector pyramid and its verification (:func:`startrack.identify.identify_stars`): the false-match
   probability of an ordinary identification, over the whole field, decides.  Steps 1-3 only propose a
   camera; they never accept a frame.
"""
from __future__ import annotations

import logging
import math

import numpy as np

from startrack.timeutil import search_clock

__all__ = ["AllSkyOptions", "propose_camera", "CROP_FRACTIONS"]

log = logging.getLogger(__name__)

#: Half-sides of the central squares searched as pinhole frames, in fractions of the image's shorter side.
CROP_FRACTIONS = (0.12, 0.08, 0.17)
RING_DEG = 15.0                 # the growth step off-axis


class AllSkyOptions:
    """Settings of :func:`propose_camera`.

    ``mag_max``: faintest catalog stars predicted while growing; ``match_px``: the smallest match radius
    (pixels; the radius is also at least four of a star's ``sigma_px``); ``timeout_s``: the pinhole
    search's time per square."""

    def __init__(self, mag_max: float = 6.0, match_px: float = 2.5, timeout_s: float = 2.0,
                 max_false_probability: float = 1e-6, sigma_px: float | None = None):
        self.mag_max = mag_max
        self.match_px = match_px
        self.timeout_s = timeout_s
        self.max_false_probability = max_false_probability
        self.sigma_px = sigma_px


def _crop(stars, cx, cy, half):
    """The detections within ``half`` pixels of ``(cx, cy)`` in x and y, as a frame of ``2 half`` pixels whose
    centre is ``(cx, cy)``: ``(crop stars, their indices)``."""
    out, rows = [], []
    for i, s in enumerate(stars):
        dx, dy = s["x"] - cx, s["y"] - cy
        if abs(dx) < half and abs(dy) < half:
            out.append(dict(s, x=dx + half - 0.5, y=dy + half - 0.5))
            rows.append(i)
    return out, rows


def _centre_solve(stars, width, height, index, options, deadline):
    """Step 1: ``(focal length px, k1, dcm, matches [(star index, catalog id)], fraction)`` or None."""
    from startrack.attitude import svd_solve
    from startrack.patterns import BlindOptions, solve_blind

    cx, cy = (width - 1) / 2.0, (height - 1) / 2.0
    for frac in CROP_FRACTIONS:
        if search_clock() > deadline:
            return None
        half = frac * min(width, height)
        crop, rows = _crop(stars, cx, cy, half)
        if len(crop) < 8:
            log.info("all-sky: %d stars within %.0f px of the centre: too few", len(crop), half)
            continue
        size = int(round(2 * half))
        bo = BlindOptions(sigma_px=options.sigma_px, max_false_probability=options.max_false_probability,
                          timeout_s=min(options.timeout_s, max(0.0, deadline - search_clock())))
        cam, res, info = solve_blind(crop, size, size, index, bo)
        if cam is None:
            log.info("all-sky: the centre (%d px square, %d stars) as a pinhole: nothing (%d candidates)", size,
                     len(crop), info["verified"])
            continue
        row_of = dict(zip((m.id for m in res.matches), info["rows"]))
        xs = np.array([crop[m.star]["x"] for m in res.matches])
        ys = np.array([crop[m.star]["y"] for m in res.matches])
        b = cam.pixels_to_vectors(xs, ys)
        ref = np.asarray(index.star_vec)[[row_of[m.id] for m in res.matches]]
        matches = [(rows[m.star], int(m.id)) for m in res.matches]
        log.info("all-sky: the centre (%d px square, %d stars) as a pinhole: f %.1f px, k1 %.3f, %d stars", size,
                 len(crop), cam.focal_length_px, cam.k1, len(matches))
        return cam.focal_length_px, cam.k1, svd_solve(b, ref), matches, frac
    return None


def _match(xs, ys, radius, px, py):
    """Each detection's one predicted star within its ``radius`` (none when a second is within 1.5 times it);
    a predicted star taken twice goes to neither.  Returns ``(detections, predicted)`` index arrays."""
    if len(px) == 0 or len(xs) == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    d = np.hypot(xs[:, None] - px[None, :], ys[:, None] - py[None, :])
    order = np.argsort(d, axis=1)
    rows = np.arange(len(xs))
    near = d[rows, order[:, 0]]
    second = d[rows, order[:, 1]] if d.shape[1] > 1 else np.full(len(xs), np.inf)
    take = (near <= radius) & (second > 1.5 * radius) & np.isfinite(radius)
    det = np.flatnonzero(take)
    cat = order[det, 0]
    uniq, counts = np.unique(cat, return_counts=True)
    once = np.isin(cat, uniq[counts == 1])
    return det[once], cat[once]


def _grow(stars, width, height, f0, dcm, catalog_vec, options, sigma_px, theta0, projection):
    """Step 2: the detections matched to catalog rows over the whole frame, ring by ring from ``theta0`` (rad):
    ``(camera, dcm, detection indices, catalog rows)``.

    A ring's new stars are predicted by extrapolating the model fitted inside it, so their match radius
    is widened by 2 % of their radius from the principal point (a projection the model has not yet seen
    bends away by about that much over one ring); a match is still the only predicted star within its
    radius and none other within 1.5 times it."""
    from startrack.calibrate import calibrate
    from startrack.camera import Camera
    from startrack.errors import StartrackError

    xs = np.array([s["x"] for s in stars], dtype=np.float64)
    ys = np.array([s["y"] for s in stars], dtype=np.float64)
    cam = Camera(width, height, f0, (width - 1) / 2.0, (height - 1) / 2.0, projection=projection)
    limit = theta0
    det = cat = np.zeros(0, dtype=np.int64)
    while True:
        # The farthest the frame reaches at this model: its corners (or where the model ends).
        edge = math.radians(cam.max_off_axis_deg)
        limit = min(limit + math.radians(RING_DEG), edge)
        for _ in range(2):
            v = catalog_vec @ dcm.T
            theta = np.arccos(np.clip(v[:, 2], -1.0, 1.0))
            near = np.flatnonzero(theta <= min(limit, cam.max_theta))
            px, py = cam.vectors_to_pixels(v[near])
            ok = np.isfinite(px) & cam.in_image(px, py)
            near, px, py = near[ok], px[ok], py[ok]
            radius = np.full(len(xs), max(options.match_px, 4.0 * sigma_px))
            rho = np.hypot(xs - cam.cx, ys - cam.cy)
            outer = cam.pixels_to_theta(xs, ys) > limit - math.radians(RING_DEG)
            radius = np.where(outer | ~np.isfinite(rho), np.maximum(radius, 0.02 * rho), radius)
            d_idx, p_idx = _match(xs, ys, radius, px, py)
            if len(d_idx) < 6:
                break
            det, cat = d_idx, near[p_idx]
            fit = ["focal_length_px"]
            for name, above, least in (("k1", 45.0, 25), ("k2", 70.0, 60)):
                if limit > math.radians(above) and len(det) >= least:
                    fit.append(name)
            try:
                res = calibrate([(dcm, np.column_stack([xs[det], ys[det]]), catalog_vec[cat])], cam, fit, iterations=15)
            except StartrackError:
                break
            cam = res.camera
            dcm = _corrected(dcm, cam, xs[det], ys[det], catalog_vec[cat])
        if limit >= edge - 1e-9:
            break
    return cam, dcm, det, cat


def _corrected(dcm, cam, xs, ys, ref):
    """The attitude of the matched stars through ``cam`` (Wahba by SVD), or ``dcm`` when they cannot give one."""
    from startrack.attitude import svd_solve

    b = cam.pixels_to_vectors(xs, ys)
    ok = np.all(np.isfinite(b), axis=1)
    if np.count_nonzero(ok) < 3:
        return dcm
    return svd_solve(b[ok], ref[ok])


def propose_camera(stars, width: int, height: int, index, catalog, options: AllSkyOptions | None = None,
                   deadline: float | None = None, projections=None):
    """Steps 1-3 of the module docstring: a camera for an all-sky frame, or ``(None, reason)``.

    Parameters
    ----------
    stars : list of dict
        Detections (``x``, ``y``, optionally ``sigma_px``), brightest first.
    width, height : int
        Image size; the principal point starts at the image centre.
    index : startrack.patterns.PatternIndex
        The blind search's pattern index.
    catalog : startrack.catalog.Catalog
        The catalog the frame is grown against (stars to ``options.mag_max``).
    projections : list of str, optional
        The projections to fit (default: each one the stars allow).

    Returns
    -------
    (Camera, dict) or (None, str)
        The camera fitted (projection, focal length, significant distortion, principal point) and what
        was measured (``centre_fraction``, ``matched``, ``projections``: each candidate's fit), or the
        reason none could be proposed.  Never an identification: see :func:`startrack.solve.solve_image`.
    """
    from startrack.calibrate import calibrate_projection
    from startrack.camera import PROJECTIONS
    from startrack.errors import StartrackError

    opts = options or AllSkyOptions()
    if deadline is None:
        deadline = search_clock() + 3 * opts.timeout_s
    centre = _centre_solve(stars, width, height, index, opts, deadline)
    if centre is None:
        return None, "the image centre gave no star pattern as a pinhole frame"
    f0, _, dcm, _, frac = centre
    sig = np.array([s.get("sigma_px", opts.sigma_px or 0.5) or 0.5 for s in stars], dtype=np.float64)
    sigma_px = float(np.median(sig)) if opts.sigma_px is None else float(opts.sigma_px)
    cat = catalog.filter_magnitude(None, opts.mag_max)
    vec = cat.vectors()
    theta0 = math.atan(frac * min(width, height) * math.sqrt(2.0) / f0)     # the centre square's corners
    # Grown through each projection in turn (their radial terms absorb what is left): the one that matches
    # the most stars holds the frame's matches, on which every projection is then fitted.
    grown = None
    for projection in (projections or [p for p in PROJECTIONS if p != "pinhole"]):
        got = _grow(stars, width, height, f0, dcm, vec, opts, sigma_px, theta0, projection)
        log.info("all-sky: grown as %s: %d stars matched", projection, len(got[2]))
        if grown is None or len(got[2]) > len(grown[2]):
            grown = got
    cam, dcm, det, rows = grown
    if len(det) < 10:
        return None, f"only {len(det)} stars matched growing out from the centre"
    xy = np.array([[stars[i]["x"], stars[i]["y"]] for i in det])
    try:
        res = calibrate_projection([(dcm, xy, vec[rows])], cam, projections)
    except StartrackError as exc:
        return None, f"no projection fitted: {exc}"
    log.info("all-sky: %d stars matched out to %.0f deg; %s, f %.2f px, RMS %.2f px", len(det),
             math.degrees(float(np.max(np.arccos(np.clip((vec[rows] @ dcm.T)[:, 2], -1, 1))))),
             res.camera.projection, res.camera.focal_length_px, res.rms_after_px)
    return res.camera.replace(extra={}), {"centre_fraction": frac, "matched": int(len(det)),
                                          "projections": res.projections}
