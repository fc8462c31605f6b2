"""What a real frame carries besides stars and sensor noise, as maps the renderer applies.

Each map is a pure function of its parameters and a numpy ``Generator``, so one seed gives one
frame.  The renderer (:func:`startrack.render.render_image`) combines them per pixel as

``expected e- = V (T (stars + sky G + nebulosity) + (1 - T) foreground) + dark + hot pixels + cosmic rays``

with ``V`` the optics' vignetting (a flat field: it dims stars and sky alike), ``G`` the sky's
gradient (light pollution: additive, it leaves the stars alone), ``T = 1 - M`` the transmission
of an opaque foreground body of mask ``M`` (stars behind it are hidden, its own surface shines
with its radiance).  The maps are sized in fractions of the frame, so they hold for any image
size, and none is tuned to one picture.
"""
from __future__ import annotations

import math

import numpy as np

from startrack.errors import ParameterError

FOREGROUNDS = ("disc", "edge", "branches")
MIRRORS = ("x", "y")

__all__ = ["FOREGROUNDS", "HORIZONS", "MIRRORS", "vignetting_map", "gradient_map", "nebulosity_map", "foreground_mask",
           "cosmic_rays", "fractal_noise", "horizon_profile", "horizon_altitude", "ground_mask", "below_skyline",
           "airmass"]


def _grid(height, width):
    yy, xx = np.mgrid[0:height, 0:width].astype(np.float64)
    return xx, yy


def vignetting_map(height, width, corner_response):
    """Relative response of the optics: 1 at the image centre, ``corner_response`` at its corners.

    The cos^4 law of a thin lens, ``cos^4(theta)`` with ``tan(theta) = r / r0``, ``r0`` chosen so the
    corners get ``corner_response``; a fixed pattern of the camera (the same every frame), which a
    flat frame measures and divides out.
    """
    if not 0 < corner_response <= 1:
        raise ParameterError("vignetting", f"the corner response must be in (0, 1], got {corner_response}")
    if corner_response == 1:
        return np.ones((height, width))
    xx, yy = _grid(height, width)
    cx, cy = (width - 1) / 2.0, (height - 1) / 2.0
    r2 = (xx - cx) ** 2 + (yy - cy) ** 2
    r02 = (cx * cx + cy * cy) / (corner_response ** -0.5 - 1.0)
    return 1.0 / (1.0 + r2 / r02) ** 2


def gradient_map(height, width, ratio, rng):
    """A linear sky gradient in a random direction: mean 1 over the frame, brightest / faintest = ``ratio``.

    ``1 + a d`` with ``d`` the distance along the direction scaled to [-1, 1] at the frame's corners
    and ``a = (ratio - 1) / (ratio + 1)``: a horizon's light pollution or twilight.
    """
    if not ratio >= 1:
        raise ParameterError("gradient", f"the brightest/faintest ratio must be >= 1, got {ratio}")
    angle = rng.uniform(0.0, 2.0 * math.pi)
    xx, yy = _grid(height, width)
    cx, cy = (width - 1) / 2.0, (height - 1) / 2.0
    d = (xx - cx) * math.cos(angle) + (yy - cy) * math.sin(angle)
    reach = abs(cx * math.cos(angle)) + abs(cy * math.sin(angle))
    d /= max(reach, 1e-12)
    return 1.0 + (ratio - 1.0) / (ratio + 1.0) * d


def fractal_noise(height, width, rng, slope=1.0, smallest_frac=0.0):
    """Random structure of amplitude spectrum ``1 / f^slope`` (f in cycles per frame), scaled to [0, 1].

    ``smallest_frac``: wavelengths shorter than this fraction of the frame's smaller side are cut
    (a smooth map).
    """
    white = rng.standard_normal((height, width))
    spec = np.fft.rfft2(white)
    fy = np.fft.fftfreq(height)[:, None] * height
    fx = np.fft.rfftfreq(width)[None, :] * width
    f = np.hypot(fx * min(height, width) / width, fy * min(height, width) / height)
    f[0, 0] = 1.0
    filt = f ** -slope
    filt[0, 0] = 0.0
    if smallest_frac > 0:
        filt[f > 1.0 / smallest_frac] = 0.0
    out = np.fft.irfft2(spec * filt, s=(height, width))
    lo, hi = out.min(), out.max()
    return (out - lo) / (hi - lo) if hi > lo else np.zeros((height, width))


def nebulosity_map(height, width, rng, psf_sigma_px=1.0):
    """Smooth structured emission, peak 1: a few Gaussian clouds, filaments and 1/f structure.

    Clouds of 3-15 % of the frame's smaller side, 1-3 filaments (curved random paths of 30-80 % of
    the side, 0.5-2 % wide) and the 1/f^1.4 field above its median (patchy, zero elsewhere); sizes in
    fractions of the frame, so any image size gets the same look.
    """
    from startrack._kernels.render import add_stars

    side = float(min(height, width))
    neb = np.zeros((height, width))
    xx, yy = _grid(height, width)
    for _ in range(int(rng.integers(3, 7))):
        x0, y0 = rng.uniform(0, width), rng.uniform(0, height)
        s = rng.uniform(0.03, 0.15) * side
        neb += rng.uniform(0.3, 1.0) * np.exp(-0.5 * ((xx - x0) ** 2 + (yy - y0) ** 2) / (s * s))
    for _ in range(int(rng.integers(1, 4))):
        width_px = max(psf_sigma_px, rng.uniform(0.005, 0.02) * side)
        length = rng.uniform(0.3, 0.8) * side
        n = max(2, int(length / (0.5 * width_px)))
        step = length / n
        heading = rng.uniform(0, 2 * math.pi)
        turn = rng.normal(0.0, 2.0 / n, n).cumsum()        # a gently curving path
        px = rng.uniform(0, width) + np.cumsum(step * np.cos(heading + turn))
        py = rng.uniform(0, height) + np.cumsum(step * np.sin(heading + turn))
        signal = np.zeros((height, width))
        # Gaussians of the filament's width every `step` px along the path: a ridge of line density
        # e / step, whose cross-section peaks at e / (step sqrt(2 pi) width): peak 0.3-1.
        e = np.full(n, rng.uniform(0.3, 1.0) * step * math.sqrt(2.0 * math.pi) * width_px)
        add_stars(signal, np.ascontiguousarray(px[:, None]), np.ascontiguousarray(py[:, None]), e, float(width_px))
        neb += signal
    patchy = fractal_noise(height, width, rng, slope=1.4, smallest_frac=0.01)   # the ISM: power ~ f^-2.8
    neb += 0.5 * np.clip(patchy - np.median(patchy), 0.0, None) / max(1e-12, 1.0 - np.median(patchy))
    peak = neb.max()
    return neb / peak if peak > 0 else neb


def _soften(binary, soft_px):
    import cv2

    m = binary.astype(np.float64)
    if soft_px > 0:
        k = 2 * int(math.ceil(3 * soft_px)) + 1
        m = cv2.GaussianBlur(m, (k, k), soft_px, borderType=cv2.BORDER_REPLICATE)
    # Fully opaque inside and fully clear outside, whatever the blur's rounding.
    m[m > 1.0 - 1e-9] = 1.0
    m[m < 1e-9] = 0.0
    return m


def _branches_field(height, width, rng):
    """``min over branches (distance to the branch / its thickness)`` of a random tree entering at an edge."""
    import cv2

    factor = max(1, int(math.ceil(max(height, width) / 256)))
    h, w = int(math.ceil(height / factor)), int(math.ceil(width / factor))
    side = float(min(h, w))
    edge = int(rng.integers(4))                 # the trunk enters from this side, pointing inwards
    t = rng.uniform(0.2, 0.8)
    start, heading = [((t * w, h), -math.pi / 2), ((t * w, 0.0), math.pi / 2),
                      ((0.0, t * h), 0.0), ((w, t * h), math.pi)][edge]
    segments = []

    def grow(x, y, angle, length, thick, depth):
        x2, y2 = x + length * math.cos(angle), y + length * math.sin(angle)
        segments.append((x, y, x2, y2, thick))
        if depth == 0:
            return
        for side_sign in (-1.0, 1.0):
            grow(x2, y2, angle + side_sign * rng.uniform(0.25, 0.7) + rng.normal(0, 0.1),
                 length * rng.uniform(0.6, 0.8), thick * 0.65, depth - 1)

    grow(start[0], start[1], heading + rng.normal(0, 0.15), side * rng.uniform(0.3, 0.45), 1.0, 6)
    xx, yy = _grid(h, w)
    field = np.full((h, w), np.inf)
    for x1, y1, x2, y2, thick in segments:
        dx, dy = x2 - x1, y2 - y1
        length2 = max(dx * dx + dy * dy, 1e-12)
        u = np.clip(((xx - x1) * dx + (yy - y1) * dy) / length2, 0.0, 1.0)
        d = np.hypot(xx - (x1 + u * dx), yy - (y1 + u * dy)) / thick
        np.minimum(field, d, out=field)
    if factor == 1:
        return field
    return cv2.resize(field.astype(np.float32), (width, height), interpolation=cv2.INTER_LINEAR).astype(np.float64)


def foreground_mask(height, width, kind, fraction, rng, soft_px=1.0):
    """An opaque foreground body covering ``fraction`` of the frame: ``(mask, texture)``.

    ``mask`` is 1 on the body, 0 off it, with a soft edge (a Gaussian of ``soft_px``: the body is out
    of focus at the stars' focus); ``texture`` its relative surface brightness (mean about 1).

    * ``disc``: a filled disc (a moon) centred anywhere in the frame, its radius set so that it covers
      ``fraction``; mottled (maria) by a smooth random map.
    * ``edge``: a horizon or roof line across the frame at a random angle, its profile roughened by
      1/f noise of a few % of the frame; the side beyond it covered.
    * ``branches``: a tree-like silhouette, a trunk entering at an edge branching six times, every
      branch thickened alike until the covered fraction is reached.

    The covered area is set by a quantile of the shape's distance field, so ``fraction`` holds
    exactly before the edge is softened.
    """
    if kind not in FOREGROUNDS:
        raise ParameterError("foreground", f"must be one of {', '.join(FOREGROUNDS)}, got {kind!r}")
    if not 0 < fraction < 1:
        raise ParameterError("foreground_fraction", f"must be in (0, 1), got {fraction}")
    xx, yy = _grid(height, width)
    side = float(min(height, width))
    texture = np.ones((height, width))
    if kind == "disc":
        x0, y0 = rng.uniform(0, width), rng.uniform(0, height)
        field = np.hypot(xx - x0, yy - y0)
        texture = 1.0 - 0.35 * fractal_noise(height, width, rng, slope=1.5, smallest_frac=0.02)
    elif kind == "edge":
        angle = rng.uniform(0, 2 * math.pi)
        c, s = math.cos(angle), math.sin(angle)
        along = (xx - (width - 1) / 2.0) * -s + (yy - (height - 1) / 2.0) * c
        across = (xx - (width - 1) / 2.0) * c + (yy - (height - 1) / 2.0) * s
        # A 1-D 1/f profile of a few % of the frame (trees, buildings on the horizon).
        n = int(2 * math.hypot(width, height)) + 2
        spec = np.fft.rfft(rng.standard_normal(n))
        f = np.arange(len(spec), dtype=np.float64)
        f[0] = 1.0
        profile = np.fft.irfft(spec / f, n)
        profile *= rng.uniform(0.01, 0.05) * side / max(1e-12, np.std(profile))
        index = np.clip(np.rint(along + n / 2).astype(np.int64), 0, n - 1)
        field = across + profile[index]
        texture = 0.7 + 0.6 * fractal_noise(height, width, rng, slope=1.0, smallest_frac=0.01)
    else:
        field = _branches_field(height, width, rng)
        texture = 0.7 + 0.6 * fractal_noise(height, width, rng, slope=1.0, smallest_frac=0.01)
    threshold = np.quantile(field, fraction)
    return _soften(field <= threshold, soft_px), texture


def cosmic_rays(signal, count, rng, full_well_e):
    """Add ``count`` cosmic-ray hits to ``signal`` (electrons); returns their truth.

    A hit is a sharp straight track (not blurred by the optics): most are one or two pixels, some
    longer (lengths 1 + an exponential of mean 3 px, at most 30 px), depositing 2-50 % of the full
    well per pixel crossed.
    """
    height, width = signal.shape
    hits = []
    for _ in range(count):
        x0, y0 = rng.uniform(-0.5, width - 0.5), rng.uniform(-0.5, height - 0.5)
        length = min(30.0, 1.0 + rng.exponential(3.0)) - 1.0
        angle = rng.uniform(0, 2 * math.pi)
        per_px = rng.uniform(0.02, 0.5) * full_well_e
        n = max(1, int(math.ceil(4 * length)))
        ts = np.linspace(0.0, length, n) if length > 0 else np.zeros(1)
        cols = np.rint(x0 + ts * math.cos(angle)).astype(np.int64)
        rows = np.rint(y0 + ts * math.sin(angle)).astype(np.int64)
        ok = (cols >= 0) & (cols < width) & (rows >= 0) & (rows < height)
        pixels = sorted(set(zip(rows[ok].tolist(), cols[ok].tolist())))
        for r, c in pixels:
            signal[r, c] += per_px
        hits.append({"x": float(x0), "y": float(y0), "length_px": float(length), "angle_deg": math.degrees(angle),
                     "electrons": float(per_px * len(pixels))})
    return hits


HORIZONS = ("flat", "random")


def horizon_profile(kind, rng, n_azimuth=720):
    """The altitude (radians) of the skyline every ``2 pi / n_azimuth`` of azimuth, from azimuth 0.

    ``"flat"``: the astronomical horizon, 0 everywhere.  ``"random"``: an observatory's
    skyline drawn from ``rng``: a low ridge (0-4 deg, smooth), a few buildings (flat
    tops 4-25 deg high, 4-35 deg wide) and tree lines (rounded crowns 3-20 deg high,
    1-6 deg wide each), the altitude the highest of them; at least two thirds of the
    azimuths stay below 15 deg, so the sky keeps most of its area.
    """
    if kind not in HORIZONS:
        raise ParameterError("horizon", f"must be one of {', '.join(HORIZONS)}, got {kind!r}")
    az = np.arange(n_azimuth) * (2.0 * math.pi / n_azimuth)
    alt = np.zeros(n_azimuth)
    if kind == "flat":
        return alt
    # A ridge: a few low harmonics, 0-4 deg.
    ridge = np.zeros(n_azimuth)
    for h in range(1, 5):
        ridge += rng.uniform(0, 1) / h * np.cos(h * az + rng.uniform(0, 2 * math.pi))
    ridge -= ridge.min()
    alt = np.maximum(alt, math.radians(rng.uniform(0.0, 4.0)) * ridge / max(float(ridge.max()), 1e-12))

    def wrapped(center):
        return np.angle(np.exp(1j * (az - center)))

    for _ in range(int(rng.integers(0, 4))):     # buildings
        width = math.radians(rng.uniform(4, 35))
        height = math.radians(rng.uniform(4, 25))
        alt = np.where(np.abs(wrapped(rng.uniform(0, 2 * math.pi))) <= width / 2, np.maximum(alt, height), alt)
    for _ in range(int(rng.integers(0, 4))):     # tree lines: rows of rounded crowns
        start = rng.uniform(0, 2 * math.pi)
        for _ in range(int(rng.integers(2, 12))):
            crown = math.radians(rng.uniform(1, 6))
            height = math.radians(rng.uniform(3, 20))
            d = wrapped(start) / crown
            alt = np.maximum(alt, np.where(np.abs(d) < 1, height * np.sqrt(np.clip(1 - d * d, 0, 1)), 0.0))
            start += crown * rng.uniform(0.8, 1.6)
    # Keep the sky: at most a third of the azimuths above 15 deg (lower the skyline if not).
    high = np.quantile(alt, 2.0 / 3.0)
    if high > math.radians(15.0):
        alt *= math.radians(15.0) / high
    return alt


def horizon_altitude(profile, azimuth):
    """The skyline ``profile``'s altitude (radians) at ``azimuth`` (radians), linearly interpolated."""
    n = len(profile)
    pos = np.mod(np.asarray(azimuth, dtype=np.float64), 2.0 * math.pi) * (n / (2.0 * math.pi))
    i0 = np.floor(pos).astype(np.int64) % n
    frac = pos - np.floor(pos)
    return profile[i0] * (1.0 - frac) + profile[(i0 + 1) % n] * frac


def ground_mask(camera, profile, soft_px=1.0):
    """Where the ground hides the sky in a zenith-pointing ``camera``'s image: 1 on the ground, 0 in the sky.

    A pixel sees the ground when its direction's altitude ``90 deg - theta`` (``theta`` its angle from
    the boresight) is below the skyline ``profile`` at its azimuth (the camera frame's, ``atan2(y, x)``),
    or when it lies outside the model's image circle.  The edge is softened over ``soft_px`` pixels at
    the local scale ``1 / f`` rad per pixel.
    """
    yy, xx = np.mgrid[0:camera.height, 0:camera.width].astype(np.float64)
    vec = camera.pixels_to_vectors(xx, yy)
    theta = np.arccos(np.clip(vec[..., 2], -1.0, 1.0))
    az = np.arctan2(vec[..., 1], vec[..., 0])
    depth = (theta - (math.pi / 2 - horizon_altitude(profile, az))) * camera.focal_length_px / max(soft_px, 1e-9)
    mask = np.clip(depth + 0.5, 0.0, 1.0)
    return np.where(np.isfinite(mask), mask, 1.0)


def below_skyline(camera_vectors, profile):
    """True for camera-frame directions under the skyline ``profile`` (:func:`ground_mask`'s rule)."""
    v = np.asarray(camera_vectors, dtype=np.float64)
    theta = np.arccos(np.clip(v[..., 2], -1.0, 1.0))
    az = np.arctan2(v[..., 1], v[..., 0])
    return theta > math.pi / 2 - horizon_altitude(profile, az)


def airmass(zenith_angle):
    """Kasten and Young's (1989) relative air mass at ``zenith_angle`` (radians; 38 at the horizon)."""
    z = np.degrees(np.asarray(zenith_angle, dtype=np.float64))
    alt = np.clip(90.0 - z, 0.0, 90.0)
    return 1.0 / (np.sin(np.radians(alt)) + 0.50572 * (alt + 6.07995) ** -1.6364)
