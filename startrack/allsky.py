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
4. **The verdict.**  The frame is identified again, from nothing, with that camera by the k-vector
   pyramid and its verification (:func:`startrack.identify.identify_stars`): the false-match probability
   of an ordinary identification decides.  The verification also refuses a frame where most bright
   catalog stars predicted on the sensor are not detected; on the ground and beyond a fisheye's image
   circle (a 180 deg frame's corners look 110-180 deg off-axis, below the horizon) none ever is, so where
   the image shows ground (:func:`find_sky`) the detections of the sky's window about the principal point
   (:func:`sky_window`) are identified first, as a frame of that size, then the whole frame.  When the
   camera is refused, the next centre square's is tried (:func:`propose_cameras`).  Steps 1-3 only
   propose a camera; they never accept a frame.
"""
from __future__ import annotations

import logging
import math

import numpy as np

from startrack.timeutil import search_clock

__all__ = ["AllSkyOptions", "propose_camera", "propose_cameras", "CROP_FRACTIONS", "SkyRegion", "find_sky", "sky_window"]

log = logging.getLogger(__name__)

#: Half-sides of the central squares searched as pinhole frames, in fractions of the image's shorter side.
CROP_FRACTIONS = (0.12, 0.08, 0.17)
RING_DEG = 15.0                 # the growth step off-axis
#: The extinction assumed where stars are predicted (magnitudes per air mass) by default: none.  0.2 (V band at a
#: clear site) is what the must-show frames carry, but predicting through it cost more than it gained there:
#: a star dropped from the prediction is dropped as a competitor in the match's uniqueness test too, and a
#: detected star fainter than the limit then matched its neighbour (orthographic 180 deg, 200 frames: 195 right
#: and the projection right on 148 with 0.2; 197 and 187 with 0; benchmarks/results/results-allsky-2026-12-05.md).
EXTINCTION_K = 0.0


class AllSkyOptions:
    """Settings of :func:`propose_camera`.

    ``mag_max``: faintest catalog stars predicted while growing, after the extinction
    ``extinction_k * (X - 1)`` at air mass ``X`` (:func:`startrack.nuisance.airmass`, the zenith taken at the
    boresight: an all-sky camera looks up; ``EXTINCTION_K``, none, by default: see its comment); ``match_px``: the smallest match radius (pixels; the radius is also at least four of a star's
    ``sigma_px``); ``timeout_s``: the pinhole search's time per square."""

    def __init__(self, mag_max: float = 6.0, match_px: float = 2.5, timeout_s: float = 2.0,
                 max_false_probability: float = 1e-6, sigma_px: float | None = None,
                 extinction_k: float | None = None):
        self.mag_max = mag_max
        self.extinction_k = EXTINCTION_K if extinction_k is None else float(extinction_k)
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


def _centre_solves(stars, width, height, index, options, deadline):
    """Step 1, each square of :data:`CROP_FRACTIONS` in turn while time is left: yields ``(focal length px, k1,
    dcm, matches [(star index, catalog id)], fraction)`` for every square the pinhole search identifies."""
    from startrack.attitude import svd_solve
    from startrack.patterns import BlindOptions, solve_blind

    cx, cy = (width - 1) / 2.0, (height - 1) / 2.0
    for frac in CROP_FRACTIONS:
        if search_clock() > deadline:
            return
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
        yield cam.focal_length_px, cam.k1, svd_solve(b, ref), matches, frac


def _match(xs, ys, radius, px, py):
    """Each detection's one predicted star within its ``radius`` (none when a second is within 1.5 times it);
    a predicted star taken twice goes to neither.  Returns ``(detections, predicted)`` index arrays."""
    xs, ys, px, py = (np.asarray(a, dtype=np.float64) for a in (xs, ys, px, py))
    radius = np.broadcast_to(np.asarray(radius, dtype=np.float64), xs.shape)
    if len(px) == 0 or len(xs) == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    near, idx, second = _two_nearest(xs, ys, px, py, 1.5 * radius)
    take = (near <= radius) & (second > 1.5 * radius) & np.isfinite(radius)
    det = np.flatnonzero(take)
    cat = idx[det]
    uniq, counts = np.unique(cat, return_counts=True)
    once = np.isin(cat, uniq[counts == 1])
    return det[once], cat[once]


def _two_nearest(xs, ys, px, py, reach):
    """For each point ``(xs, ys)`` the nearest of ``(px, py)`` (distance, index) and the second's distance,
    exact within ``reach`` (per point) and ``inf`` beyond it: the predicted points are binned in square cells
    of the largest finite reach, and each point looks in its cell's 3 x 3 neighbourhood only (linear time)."""
    n = len(xs)
    best = np.full(n, np.inf)
    second = np.full(n, np.inf)
    idx = np.full(n, -1, dtype=np.int64)
    finite = np.isfinite(reach)
    if not finite.any():
        return best, idx, second
    cell = float(np.max(reach[finite])) * (1 + 1e-9) + 1e-9
    ok = np.isfinite(px) & np.isfinite(py)
    pid = np.flatnonzero(ok)
    if len(pid) == 0:
        return best, idx, second
    span = 1 << 31
    pkey = np.floor(px[pid] / cell).astype(np.int64) * span + np.floor(py[pid] / cell).astype(np.int64)
    order = np.argsort(pkey, kind="stable")
    skey, pid = pkey[order], pid[order]
    cx = np.floor(xs / cell).astype(np.int64)
    cy = np.floor(ys / cell).astype(np.int64)
    for ox in (-1, 0, 1):
        for oy in (-1, 0, 1):
            q = (cx + ox) * span + (cy + oy)
            lo = np.searchsorted(skey, q, "left")
            cnt = np.searchsorted(skey, q, "right") - lo
            for j in range(int(cnt.max(initial=0))):
                sel = np.flatnonzero(cnt > j)
                p = pid[lo[sel] + j]
                d = np.hypot(xs[sel] - px[p], ys[sel] - py[p])
                b = best[sel]
                better = d < b
                second[sel] = np.where(better, b, np.minimum(second[sel], d))
                best[sel] = np.where(better, d, b)
                idx[sel] = np.where(better, p, idx[sel])
    return best, idx, second


def extincted_mag(mag, theta, k):
    """Catalog magnitudes ``mag`` as seen ``theta`` (radians) from the zenith: ``mag + k (X(theta) - 1)``,
    ``X`` Kasten and Young's air mass (1 at the zenith, 38 at the horizon and below it)."""
    from startrack.nuisance import airmass

    return np.asarray(mag, dtype=np.float64) + k * (airmass(theta) - 1.0)


def _grow(stars, width, height, f0, dcm, catalog_vec, options, sigma_px, theta0, projection, catalog_mag=None):
    """Step 2: the detections matched to catalog rows over the whole frame, ring by ring from ``theta0`` (rad):
    ``(camera, dcm, detection indices, catalog rows)``.

    A ring's new stars are predicted by extrapolating the model fitted inside it, so their match radius
    is widened by 2 % of their radius from the principal point (a projection the model has not yet seen
    bends away by about that much over one ring); a match is still the only predicted star within its
    radius and none other within 1.5 times it.  With ``catalog_mag`` only the stars brighter than
    ``options.mag_max`` after the extinction (:func:`extincted_mag`, the zenith at the boresight) are
    predicted: near the horizon the atmosphere dims them below the detections' limit, and predicting them
    would only crowd the matches."""
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
            seen = theta <= min(limit, cam.max_theta)
            if catalog_mag is not None:
                seen &= extincted_mag(catalog_mag, theta, options.extinction_k) <= options.mag_max
            near = np.flatnonzero(seen)
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
        The first of :func:`propose_cameras`.
    """
    last = "the image centre gave no star pattern as a pinhole frame"
    for cam, info in propose_cameras(stars, width, height, index, catalog, options, deadline, projections):
        if cam is not None:
            return cam, info
        last = info
    return None, last


def propose_cameras(stars, width: int, height: int, index, catalog, options: AllSkyOptions | None = None,
                    deadline: float | None = None, projections=None):
    """:func:`propose_camera` from each centre square of :data:`CROP_FRACTIONS` that the pinhole search
    identifies, in turn, while time is left: yields ``(Camera, dict)``, or ``(None, reason)`` for a square
    whose growth or fit proposed nothing.  The caller verifies each (step 4) and takes the next only when it
    is refused: a square's pinhole solve can be right yet measure its focal length a few percent off (few
    stars, the fisheye's curvature taken by the focal length), which no ring growth recovers, and another
    square's need not."""
    opts = options or AllSkyOptions()
    if deadline is None:
        deadline = search_clock() + 3 * opts.timeout_s
    cat = vec = None
    for centre in _centre_solves(stars, width, height, index, opts, deadline):
        if cat is None:
            cat = catalog.filter_magnitude(None, opts.mag_max)
            vec = cat.vectors()
        yield _proposed(stars, width, height, centre, cat, vec, opts, projections)


def _proposed(stars, width, height, centre, cat, vec, opts, projections):
    """Steps 2 and 3 from one centre solve (:func:`_centre_solves`): ``(Camera, dict)`` or ``(None, reason)``."""
    from startrack.calibrate import calibrate_projection
    from startrack.camera import PROJECTIONS
    from startrack.errors import StartrackError

    f0, _, dcm, _, frac = centre
    sig = np.array([s.get("sigma_px", opts.sigma_px or 0.5) or 0.5 for s in stars], dtype=np.float64)
    sigma_px = float(np.median(sig)) if opts.sigma_px is None else float(opts.sigma_px)
    theta0 = math.atan(frac * min(width, height) * math.sqrt(2.0) / f0)     # the centre square's corners
    # Grown through each projection in turn (their radial terms absorb what is left): the one that matches
    # the most stars holds the frame's matches, on which every projection is then fitted.
    grown = None
    for projection in (projections or [p for p in PROJECTIONS if p != "pinhole"]):
        got = _grow(stars, width, height, f0, dcm, vec, opts, sigma_px, theta0, projection, cat.mag)
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
                                          "projections": res.projections,
                                          "extinction": {"k_mag_per_airmass": opts.extinction_k,
                                                         "source": "default" if opts.extinction_k == EXTINCTION_K
                                                         else "given", "zenith": "boresight"}}


# --- The sky in the image -------------------------------------------------------------------------------------

#: The side (pixels) of the tiles whose median background tells the sky from the ground.
SKY_TILE_PX = 16
#: The sky's and the ground's levels differ significantly when this many tile-median errors apart.
SKY_CONTRAST_SIGMA = 8.0


class SkyRegion:
    """Where an image shows the sky, from its background (:func:`find_sky`).

    ``ground`` (tiles ``tile_px`` on a side, row-major from the top-left pixel) is True where the background
    is darker than the midpoint of the sky's and the ground's levels, in a region that reaches the frame's
    border: the ground under a skyline, a roof, the outside of a lens's image circle.  ``circle``
    ``(cx, cy, radius_px)`` is the lens's image circle when its edge is seen (else None)."""

    def __init__(self, ground, tile_px, width, height, sky_level, ground_level, circle):
        self.ground = np.asarray(ground, dtype=bool)
        self.tile_px = int(tile_px)
        self.width, self.height = int(width), int(height)
        self.sky_level, self.ground_level = float(sky_level), float(ground_level)
        self.circle = circle

    def _tile(self, xs, ys):
        ny, nx = self.ground.shape
        col = np.clip(np.floor((np.asarray(xs, dtype=np.float64) + 0.5) / self.tile_px), 0, nx - 1).astype(np.int64)
        row = np.clip(np.floor((np.asarray(ys, dtype=np.float64) + 0.5) / self.tile_px), 0, ny - 1).astype(np.int64)
        return row, col

    def in_sky(self, xs, ys, margin: int = 0):
        """True for the pixels ``(xs, ys)`` (0-based, x the column) that see the sky, and are ``margin`` blocks
        or more from the ground (a light just below the skyline shares its block with the sky)."""
        row, col = self._tile(xs, ys)
        ground = self.ground
        for _ in range(margin):
            ground = _dilate(ground)
        return ~ground[row, col]

    def pixel_mask(self):
        """The ground as a (height, width) boolean image."""
        yy, xx = np.mgrid[0:self.height, 0:self.width]
        return ~self.in_sky(xx, yy)

    @property
    def masked_fraction(self) -> float:
        """The fraction of the image's pixels on the ground: each ground block weighted by the pixels it holds
        (:meth:`_tile`'s rows and columns), without building the whole-frame mask."""
        row, _ = self._tile(np.zeros(self.height), np.arange(self.height))
        _, col = self._tile(np.arange(self.width), np.zeros(self.width))
        ny, nx = self.ground.shape
        pixels = np.outer(np.bincount(row, minlength=ny), np.bincount(col, minlength=nx))
        return float(pixels[self.ground].sum()) / (self.width * self.height)

    def record(self) -> dict:
        """The ``solve.allsky.sky`` record (docs/formats.md)."""
        out = {"masked_fraction": round(self.masked_fraction, 5), "tile_px": self.tile_px,
               "sky_level_dn": round(self.sky_level, 2), "ground_level_dn": round(self.ground_level, 2),
               "image_circle": None}
        if self.circle is not None:
            cx, cy, r = self.circle
            out["image_circle"] = {"cx": round(float(cx), 2), "cy": round(float(cy), 2), "radius_px": round(float(r), 2)}
        return out


def _tile_medians(image, tile):
    """Median and robust scatter (1.4826 MAD) of each ``tile`` x ``tile`` block, ``(h // tile, w // tile)`` of
    them from the top-left pixel (the last partial row and column of blocks belong to the whole ones before)."""
    h, w = image.shape
    ny, nx = max(1, h // tile), max(1, w // tile)
    ty, tx = min(tile, h), min(tile, w)
    a = np.asarray(image[:ny * ty, :nx * tx], dtype=np.float32).reshape(ny, ty, nx, tx).transpose(0, 2, 1, 3)
    a = a.reshape(ny, nx, ty * tx)
    med = np.median(a, axis=2)
    mad = 1.4826 * np.median(np.abs(a - med[..., None]), axis=2)
    return med, mad


def _grow_from_border(candidate):
    """The tiles of ``candidate`` connected (4-neighbours) to the grid's border."""
    reach = np.zeros_like(candidate)
    reach[0, :], reach[-1, :], reach[:, 0], reach[:, -1] = (candidate[0, :], candidate[-1, :], candidate[:, 0],
                                                            candidate[:, -1])
    while True:
        grown = reach.copy()
        grown[1:] |= reach[:-1]
        grown[:-1] |= reach[1:]
        grown[:, 1:] |= reach[:, :-1]
        grown[:, :-1] |= reach[:, 1:]
        grown &= candidate
        if np.array_equal(grown, reach):
            return reach
        reach = grown


def _fit_circle(x, y):
    """Least-squares circle (Kasa): ``(cx, cy, r)``."""
    a = np.column_stack([2 * x, 2 * y, np.ones_like(x)])
    (cx, cy, c), *_ = np.linalg.lstsq(a, x * x + y * y, rcond=None)
    return float(cx), float(cy), float(math.sqrt(max(c + cx * cx + cy * cy, 0.0)))


def _image_circle(ground, tile, width, height, sectors=72, tolerance_px=None):
    """The lens's image circle from the sky's outer edge, or None when too little of it is seen.

    In each of ``sectors`` directions about the image centre the outermost sky tile marks the sky's edge,
    unless it lies on the frame's border (the circle is outside the frame there).  A circle is fitted to
    these edges; an obstruction (a roof, a tree) only pulls an edge inward, so edges well inside the circle
    are dropped and it is fitted again.  The circle stands when at least a quarter of the directions lie on
    it within ``tolerance_px`` (default two tiles)."""
    ny, nx = ground.shape
    rows, cols = np.nonzero(~ground)
    if len(rows) == 0:
        return None
    px = (cols + 0.5) * tile - 0.5
    py = (rows + 0.5) * tile - 0.5
    cx0, cy0 = (width - 1) / 2.0, (height - 1) / 2.0
    ang = np.arctan2(py - cy0, px - cx0)
    rad = np.hypot(px - cx0, py - cy0)
    sector = np.floor((ang + math.pi) / (2 * math.pi) * sectors).astype(np.int64) % sectors
    ex, ey = [], []
    for k in range(sectors):
        sel = np.flatnonzero(sector == k)
        if len(sel) == 0:
            continue
        i = sel[np.argmax(rad[sel])]
        if rows[i] in (0, ny - 1) or cols[i] in (0, nx - 1):
            continue
        # the edge half a tile beyond the outermost sky tile's centre
        u = np.array([px[i] - cx0, py[i] - cy0]) / max(rad[i], 1e-9)
        ex.append(px[i] + 0.5 * tile * u[0])
        ey.append(py[i] + 0.5 * tile * u[1])
    ex, ey = np.array(ex), np.array(ey)
    tol = 2.0 * tile if tolerance_px is None else float(tolerance_px)
    if len(ex) < sectors // 4:
        return None
    keep = np.ones(len(ex), dtype=bool)
    for _ in range(4):
        cx, cy, r = _fit_circle(ex[keep], ey[keep])
        res = np.hypot(ex - cx, ey - cy) - r
        new = res > -tol
        if np.array_equal(new, keep) or np.count_nonzero(new) < 3:
            break
        keep = new
    on = np.count_nonzero(np.abs(res) <= tol)
    if on < sectors // 4 or not (0 <= cx < width and 0 <= cy < height):
        return None
    return cx, cy, r


def find_sky(image, tile_px: int = SKY_TILE_PX):
    """The sky and the ground of an all-sky frame, from its background level: a :class:`SkyRegion`, or None
    when no region darker than the sky reaches the frame's border.

    The background is the median of each block (stars barely move it), of half, one or two ``tile_px`` on a
    side: the smallest whose medians tell the two levels apart (below); the sky's level is the
    median of the blocks within a quarter of the image's shorter side of its centre (an all-sky camera
    looks up), the ground's the median of the blocks below the midpoint (iterated from the darkest block).  They must differ by ``SKY_CONTRAST_SIGMA`` times a block
    median's error (``1.25 sigma / tile_px``, ``sigma`` the pixels' robust scatter) or nothing is found:
    a flat frame stays all sky.  Ground is every block below their midpoint that is connected to the
    frame's border; its dark-sky-free (un-lit) ground is what this finds, not a ground brighter than the sky.
    """
    img = np.asarray(image)
    h, w = img.shape
    # The smallest blocks (the finest skyline) whose medians still tell the two levels apart.
    for tile in (tile_px // 2, tile_px, 2 * tile_px):
        if tile < 2 or tile > min(h, w) // 4:
            continue
        med, mad = _tile_medians(img, tile)
        ny, nx = med.shape
        yc = (np.arange(ny) + 0.5) * tile - 0.5
        xc = (np.arange(nx) + 0.5) * tile - 0.5
        r = np.hypot(xc[None, :] - (w - 1) / 2.0, yc[:, None] - (h - 1) / 2.0)
        central = r <= 0.25 * min(w, h)
        if not central.any():
            continue
        sky = float(np.median(med[central]))
        sigma = float(np.median(mad[central]))
        err = 1.2533 * max(sigma, 0.5) / tile
        # The ground's level: from the darkest block, then (as Ridler and Calvard's iteration) the median of the
        # blocks below the midpoint, a few times: the darkest block alone is the ground's level minus its noise.
        dark = float(med.min())
        for _ in range(3):
            below = med < 0.5 * (sky + dark)
            if not below.any():
                break
            dark = float(np.median(med[below]))
        if sky - dark >= SKY_CONTRAST_SIGMA * err:
            break
    else:
        return None
    threshold = 0.5 * (sky + dark)
    ground = _grow_from_border(med < threshold)
    if not ground.any():
        return None
    level = float(np.median(med[ground]))
    # The skyline to half a block: blocks of half the side where the ground meets the sky, the coarse blocks
    # elsewhere.  A half-side block's median has twice the error, so the levels are at least SKY_CONTRAST_SIGMA / 4
    # of its errors from the midpoint: enough to place an edge already found, not to find one.
    fine = tile // 2
    if fine >= 4:
        fmed, _ = _tile_medians(img, fine)
        grid = np.kron(ground, np.ones((2, 2), dtype=bool))
        zone = np.kron(_dilate(ground) & _dilate(~ground), np.ones((2, 2), dtype=bool))
        fy, fx = min(fmed.shape[0], grid.shape[0]), min(fmed.shape[1], grid.shape[1])
        refined = np.zeros(fmed.shape, dtype=bool)
        refined[:fy, :fx] = np.where(zone[:fy, :fx], fmed[:fy, :fx] < threshold, grid[:fy, :fx])
        # the remainder of a side that the coarse blocks folded into their last one
        refined[fy:, :] = refined[fy - 1:fy, :]
        refined[:, fx:] = refined[:, fx - 1:fx]
        ground, tile = _grow_from_border(refined), fine
    circle = _image_circle(ground, tile, w, h, tolerance_px=4.0 * tile)
    return SkyRegion(ground, tile, w, h, sky, level, circle)


def sky_window(region: SkyRegion, cx: float, cy: float, margin: int = 1):
    """The largest rectangle of whole sky blocks about the principal point ``(cx, cy)`` found by growing its four
    sides in turn, a block at a time, while the new row or column is all sky and ``margin`` blocks or more from
    the ground (:meth:`SkyRegion.in_sky`): ``(x0, y0, x1, y1)``, the pixels ``x0 <= x < x1``, ``y0 <= y < y1``; or
    None when the principal point's own block is not sky.

    The verification of an identification (:mod:`startrack.identify.verify`) counts every bright catalog star
    predicted on the sensor that is not detected against it; on the ground, and outside a fisheye's image
    circle, no star is ever detected.  Within this window every predicted star should be."""
    ground = region.ground
    for _ in range(margin):
        ground = _dilate(ground)
    sky = ~ground
    ny, nx = sky.shape
    row, col = region._tile(cx, cy)
    r0 = r1 = int(row)
    c0 = c1 = int(col)
    if not sky[r0, c0]:
        return None
    grew = True
    while grew:
        grew = False
        if r0 > 0 and sky[r0 - 1, c0:c1 + 1].all():
            r0, grew = r0 - 1, True
        if r1 < ny - 1 and sky[r1 + 1, c0:c1 + 1].all():
            r1, grew = r1 + 1, True
        if c0 > 0 and sky[r0:r1 + 1, c0 - 1].all():
            c0, grew = c0 - 1, True
        if c1 < nx - 1 and sky[r0:r1 + 1, c1 + 1].all():
            c1, grew = c1 + 1, True
    t = region.tile_px
    # The last block of a row or column also holds the pixels its whole blocks leave over (SkyRegion._tile).
    x1 = region.width if c1 == nx - 1 else (c1 + 1) * t
    y1 = region.height if r1 == ny - 1 else (r1 + 1) * t
    return c0 * t, r0 * t, x1, y1


def _dilate(mask):
    """``mask`` grown by one block (8-neighbours)."""
    out = mask.copy()
    out[1:] |= mask[:-1]
    out[:-1] |= mask[1:]
    grown = out.copy()
    grown[:, 1:] |= out[:, :-1]
    grown[:, :-1] |= out[:, 1:]
    return grown
