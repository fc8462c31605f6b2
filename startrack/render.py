"""Synthetic star images and star lists whose truth is known.

The renderer is the project's test oracle, so it is physically honest:

* **Photometry** (paper 003 Eqs. 7-9): a star of magnitude ``m`` delivers
  ``N_e = Z t 10^(-0.4 m)`` photo-electrons, a factor 2.512 per magnitude, with
  ``Z`` the zero point (photo-electrons per second from a magnitude-0 star,
  with aperture, optics transmission and quantum efficiency folded in) and ``t``
  the exposure time.
* **PSF**: a Gaussian of standard deviation ``psf_sigma_px`` integrated over
  each pixel's area with the error function (paper 003 Eqs. 4-5).
* **Motion**: with an angular rate the star is integrated along its trail
  (sub-samples no more than a quarter pixel apart); the truth position is the
  star's position at mid-exposure.
* **Sensor**: sky background and dark current (Poisson), photon shot noise,
  optional pixel response non-uniformity (PRNU, a fixed pattern of the sensor:
  the same map every frame of a given size), hot pixels (fixed alike), full-well
  saturation, read noise, gain (e-/DN), bias and quantisation to 8, 12 or 16 bits;
  optionally cosmic-ray hits and dark-subtracted output (bias and dark removed, clipped at 0).
* **Nuisances of real frames** (:mod:`startrack.nuisance`): vignetting, a sky gradient,
  nebulosity, an opaque foreground body (a disc, an edge, branches) that hides the stars behind
  it, and mirrored output (the written image flipped, as a FITS file stored bottom-up or a
  camera behind a diagonal mirror).
* **Errors for robustness studies**: magnitude noise, false stars, a
  focal-length error (the image is rendered with ``f (1 + e/100)`` while the
  camera section keeps the nominal ``f``; paper 004 Fig. 7).
"""
from __future__ import annotations

import functools
import math
from dataclasses import asdict, dataclass, field

import numpy as np

from startrack.camera import Camera
from startrack.errors import ParameterError
from startrack.rotations import (
    _propagate_attitude_rad,
    _rotation_vector_rad,
    dcm_to_quaternion,
    dcm_to_radec_roll,
    quaternion_to_dcm,
)

__all__ = [
    "Sensor",
    "Scene",
    "electrons_from_magnitude",
    "project_stars",
    "render_image",
    "star_list",
    "background_dn_cdf",
]


@dataclass
class Sensor:
    """Photometric and electronic model of a star camera (all documented units).

    Defaults describe a generic small-satellite star tracker: a magnitude-6 star
    gives about 800 photo-electrons in 100 ms.
    """

    zero_point_e_per_s: float = 2.0e6
    exposure_ms: float = 100.0
    psf_sigma_px: float = 1.0
    full_well_e: float = 20000.0
    bit_depth: int = 16
    gain_e_per_dn: float | None = None
    bias_dn: float | None = None
    read_noise_e: float = 5.0
    dark_current_e_per_s: float = 20.0
    background_e_per_s: float = 50.0
    prnu: float = 0.0
    hot_pixels: int = 0
    noise: bool = True
    dark_subtracted: bool = False
    cosmic_rays: int = 0
    vignetting: float = 1.0

    def __post_init__(self):
        checks = {
            "zero_point_e_per_s": self.zero_point_e_per_s > 0,
            "exposure_ms": self.exposure_ms > 0,
            "psf_sigma_px": self.psf_sigma_px > 0,
            "full_well_e": self.full_well_e > 0,
            "read_noise_e": self.read_noise_e >= 0,
            "dark_current_e_per_s": self.dark_current_e_per_s >= 0,
            "background_e_per_s": self.background_e_per_s >= 0,
            "prnu": 0 <= self.prnu < 1,
            "hot_pixels": self.hot_pixels >= 0,
            "cosmic_rays": self.cosmic_rays >= 0,
            "vignetting": 0 < self.vignetting <= 1,
        }
        for name, ok in checks.items():
            value = getattr(self, name)
            if not ok or not math.isfinite(float(value)):
                raise ParameterError(name, f"invalid value {value!r}")
        if self.bit_depth not in (8, 12, 16):
            raise ParameterError("bit_depth", f"must be 8, 12 or 16, got {self.bit_depth}")
        if self.gain_e_per_dn is not None and not self.gain_e_per_dn > 0:
            raise ParameterError("gain_e_per_dn", f"must be positive, got {self.gain_e_per_dn}")

    @property
    def max_dn(self) -> int:
        return 2 ** self.bit_depth - 1

    @property
    def gain(self) -> float:
        """Electrons per DN; by default the full well fills the ADC range."""
        return self.gain_e_per_dn if self.gain_e_per_dn is not None else self.full_well_e / self.max_dn

    @property
    def bias(self) -> float:
        """Bias (offset) in DN; by default 2% of the range, so noise is not clipped at 0."""
        return self.bias_dn if self.bias_dn is not None else round(0.02 * self.max_dn)

    @property
    def offset_dn(self) -> float:
        """The DN of zero electrons in the written image: the bias; dark-subtracted, minus the expected
        dark current too (a master bias + dark removed, as a calibrated frame is; the sky stays)."""
        if self.dark_subtracted:
            return -self.dark_current_e_per_s * self.exposure_s / self.gain
        return self.bias

    @property
    def exposure_s(self) -> float:
        return self.exposure_ms / 1000.0

    @property
    def background_e(self) -> float:
        """Expected sky + dark electrons per pixel in one exposure."""
        return (self.background_e_per_s + self.dark_current_e_per_s) * self.exposure_s

    def detection_limit_mag(self, snr: float = 5.0) -> float:
        """Magnitude of a star seen at signal-to-noise ``snr`` in one exposure.

        Its ``S`` photo-electrons (paper 003 Eq. 9) over an aperture of
        ``4 pi sigma^2`` pixels, each with variance ``background + dark + read^2``:
        ``S / sqrt(S + n var) = snr``, so ``S = (snr^2 + sqrt(snr^4 + 4 snr^2 n var)) / 2``.
        Fainter catalog stars add nothing a centroider could find.
        """
        n_var = 4.0 * math.pi * self.psf_sigma_px ** 2 * (self.background_e + self.read_noise_e ** 2)
        signal = 0.5 * (snr * snr + math.sqrt(snr ** 4 + 4.0 * snr * snr * n_var))
        return -2.5 * math.log10(signal / (self.zero_point_e_per_s * self.exposure_s))

    def to_dict(self) -> dict:
        d = asdict(self)
        d.update(gain_e_per_dn=self.gain, bias_dn=self.bias)
        return d


@dataclass
class Scene:
    """What is rendered besides the catalog: errors and motion for robustness studies."""

    mag_limit: float | None = None
    mag_noise: float = 0.0
    false_stars: int = 0
    focal_error_pct: float = 0.0
    rate_deg_s: tuple = (0.0, 0.0, 0.0)
    extra: dict = field(default_factory=dict)
    foreground: str | None = None
    foreground_fraction: float = 0.3
    foreground_e_per_s: float | None = None
    nebulosity_e_per_s: float = 0.0
    gradient: float = 1.0
    mirror: str | None = None
    horizon: str | None = None
    extinction_mag: float = 0.0
    ground_lights: int = 0

    def __post_init__(self):
        from startrack.nuisance import FOREGROUNDS, HORIZONS, MIRRORS

        if self.horizon is not None and self.horizon not in HORIZONS:
            raise ParameterError("horizon", f"must be one of {', '.join(HORIZONS)}, got {self.horizon!r}")
        if not 0 <= int(self.ground_lights) == self.ground_lights:
            raise ParameterError("ground_lights", f"must be a count >= 0, got {self.ground_lights}")
        if not (self.extinction_mag >= 0 and math.isfinite(self.extinction_mag)):
            raise ParameterError("extinction_mag", f"must be >= 0 (magnitudes per air mass), got {self.extinction_mag}")

        if self.foreground is not None and self.foreground not in FOREGROUNDS:
            raise ParameterError("foreground", f"must be one of {', '.join(FOREGROUNDS)}, got {self.foreground!r}")
        if not 0 < self.foreground_fraction < 1:
            raise ParameterError("foreground_fraction", f"must be in (0, 1), got {self.foreground_fraction}")
        if self.foreground_e_per_s is not None and not (self.foreground_e_per_s >= 0
                                                         and math.isfinite(self.foreground_e_per_s)):
            raise ParameterError("foreground_e_per_s", f"must be >= 0, got {self.foreground_e_per_s}")
        if not (self.nebulosity_e_per_s >= 0 and math.isfinite(self.nebulosity_e_per_s)):
            raise ParameterError("nebulosity_e_per_s", f"must be >= 0, got {self.nebulosity_e_per_s}")
        if not (self.gradient >= 1 and math.isfinite(self.gradient)):
            raise ParameterError("gradient", f"the brightest/faintest sky ratio must be >= 1, got {self.gradient}")
        if self.mirror is not None and self.mirror not in MIRRORS:
            raise ParameterError("mirror", f"must be one of {', '.join(MIRRORS)}, got {self.mirror!r}")
        if not self.mag_noise >= 0:
            raise ParameterError("mag_noise", f"must be >= 0, got {self.mag_noise}")
        if self.false_stars < 0:
            raise ParameterError("false_stars", f"must be >= 0, got {self.false_stars}")
        if not -50 < self.focal_error_pct < 50:
            raise ParameterError("focal_error_pct", f"must be within +-50, got {self.focal_error_pct}")
        if len(self.rate_deg_s) != 3 or not all(math.isfinite(v) for v in self.rate_deg_s):
            raise ParameterError("rate_deg_s", "must be three finite numbers wx,wy,wz")


def electrons_from_magnitude(mag, sensor: Sensor):
    """Photo-electrons of a star of magnitude ``mag`` in one exposure (paper 003 Eq. 9).

    ``In_m = In_0 * 2.512^(0 - m)`` with ``In_0 = Z t`` the signal of a magnitude-0
    star; 2.512 is ``100^(1/5)`` exactly here.
    """
    return sensor.zero_point_e_per_s * sensor.exposure_s * 10.0 ** (-0.4 * np.asarray(mag, dtype=np.float64))


def project_stars(vectors, dcm, camera: Camera, margin_px: float = 0.0):
    """Image positions of catalog stars seen at attitude ``dcm``.

    Returns
    -------
    index : ndarray of int
        Catalog rows that land on the image (within ``margin_px`` outside its edge).
    x, y : ndarray
        Their positions in pixels.
    """
    cam_vec = vectors @ np.asarray(dcm).T
    # A fisheye sees to its image circle, but what lies beyond 90 deg from the boresight is below the horizon.
    cos_limit = math.cos(math.radians(min(89.0, camera.max_off_axis_deg + 1.0))) if camera.is_pinhole else 0.0
    front = np.flatnonzero(cam_vec[:, 2] > cos_limit)
    x, y = camera.vectors_to_pixels(cam_vec[front])
    inside = camera.in_image(x, y, margin=-margin_px) & np.isfinite(x)
    return front[inside], x[inside], y[inside]


def background_dn_cdf(sensor: Sensor):
    """Distribution of a star-free pixel's DN, as a cumulative table.

    ``DN = round((Poisson(B) + N(0, r)) / g + bias)`` with ``B`` the sky + dark
    electrons, ``r`` the read noise and ``g`` the gain.  Returns ``(cdf, lo)``:
    ``cdf[i] = P(DN <= lo + i)``.

    The Poisson counts are kept where they carry probability (``B +- 12 sqrt(B) + 12``)
    and each DN's sum runs over the counts within 9 read-noise sigmas of its edge (the
    counts below it add their whole probability, those above none), so the work and the
    memory grow with the background's spread, not its size: a daylight background of
    1e6 electrons is a table of ~12,000 DN built in a few milliseconds.
    """
    from startrack._kernels.render import background_cdf

    lam = float(sensor.background_e)
    g, bias, rn = sensor.gain, sensor.bias, sensor.read_noise_e
    kmin = max(0, int(math.floor(lam - 12.0 * math.sqrt(lam) - 12.0)))
    kmax = int(lam + 12.0 * math.sqrt(lam) + 12.0)
    k = np.arange(kmin, kmax + 1, dtype=np.float64)
    if lam > 0:
        pk = np.exp(-lam + k * math.log(lam) - np.array([math.lgamma(v + 1.0) for v in k]))
    else:
        pk = np.r_[1.0, np.zeros(kmax)]
    lo = int(math.floor((kmin - 9.0 * rn) / g + bias)) - 1
    hi = int(math.ceil((kmax + 9.0 * rn) / g + bias)) + 1
    d = np.arange(lo, hi + 1, dtype=np.float64)
    # DN = d  <=>  g (d - bias - 0.5) <= k + n < g (d + 0.5 - bias)
    upper = g * (d + 0.5 - bias)
    cdf = background_cdf(np.ascontiguousarray(upper), np.ascontiguousarray(pk), float(kmin), float(rn))
    cdf = np.clip(cdf / cdf[-1], 0.0, 1.0)
    cdf[-1] = 1.0
    return np.ascontiguousarray(cdf), lo


def _guide_table(cdf, size=4096):
    """``guide[b]`` = first index with ``cdf >= b / size`` (indexed search)."""
    return np.searchsorted(cdf, np.arange(size) / size, side="left").astype(np.int64)


@functools.lru_cache(maxsize=1)
def _prnu_map(height, width, prnu):
    """The sensor's fixed-pattern gain map: the same sensor every frame (seeded by its size).

    Memoised by value (a pure function of its arguments): a run renders every frame with one sensor.
    """
    rng = np.random.default_rng([height, width, 0x5052_4E55])
    out = np.ascontiguousarray(1.0 + prnu * rng.standard_normal((height, width)))
    return out


@functools.lru_cache(maxsize=4)
def _hot_pixel_map(height, width, count, full_well_e):
    """The sensor's hot pixels ``(rows, cols, electrons)``: fixed like its PRNU (seeded by the frame size and the
    count), so a dark frame rendered with the same options holds them too.

    Single pixels of log-uniform dark charge, 1 % to 200 % of the full well: most mildly hot, about one in
    eight saturated, as a sensor's dark-current outliers are.
    """
    rng = np.random.default_rng([height, width, count, 0x484F_5450])
    cols = rng.integers(0, width, count)
    rows = rng.integers(0, height, count)
    level = full_well_e * 0.01 * 200.0 ** rng.uniform(0.0, 1.0, count)
    return rows, cols, level


def _background_table(sensor: Sensor):
    return _background_table_of(sensor.background_e, sensor.gain, sensor.offset_dn, sensor.read_noise_e)


@functools.lru_cache(maxsize=1)
def _background_table_of(background_e, gain, bias, read_noise_e):
    """Memoised by value: the background table of the sensor's four noise parameters."""
    from types import SimpleNamespace

    cdf, lo = background_dn_cdf(SimpleNamespace(background_e=background_e, gain=gain, bias=bias,
                                                read_noise_e=read_noise_e))
    return cdf, _guide_table(cdf), lo


def _trail_positions(vectors, dcm, camera, rate_rad_s, exposure_s, sigma):
    """Per-star positions along the exposure: shape (n, n_sub), mid-exposure centred."""
    rate = np.asarray(rate_rad_s, dtype=np.float64)
    if not np.any(rate):
        x, y = camera.vectors_to_pixels(vectors @ dcm.T)
        return x[:, None], y[:, None]
    # Trail length bound: |w| t f (plus roll sweep at the image corner).
    length = float(np.linalg.norm(rate)) * exposure_s * camera.focal_length_px * 1.5
    n_sub = int(min(2000, max(2, math.ceil(length / min(0.25, sigma / 2.0)) + 1)))
    times = (np.arange(n_sub) + 0.5) / n_sub - 0.5
    xs = np.empty((len(vectors), n_sub))
    ys = np.empty((len(vectors), n_sub))
    for t_index, t in enumerate(times * exposure_s):
        a = _propagate_attitude_rad(dcm, rate, t)
        xs[:, t_index], ys[:, t_index] = camera.vectors_to_pixels(vectors @ a.T)
    return xs, ys


def render_image(catalog, camera: Camera, dcm, sensor: Sensor, scene: Scene, rng: np.random.Generator,
                 seed: int | None = None, vectors=None):
    """Render one frame.

    Parameters
    ----------
    catalog : startrack.catalog.Catalog
        Stars (already propagated to the frame's epoch).
    camera : Camera
        The nominal camera; the image is rendered with the focal length
        perturbed by ``scene.focal_error_pct``.
    dcm : ndarray (3, 3)
        Attitude at mid-exposure.
    sensor, scene :
        The models above.
    rng : numpy Generator
        Drives every random choice (magnitude noise, false stars, the pixel
        noise seed, then the nuisances: gradient, nebulosity, foreground,
        cosmic rays), so one seed gives one image; a frame without nuisances
        draws exactly what it drew before they existed.  PRNU and hot pixels
        are the sensor's, the same every frame of a size.
    vectors : ndarray (n, 3), optional
        ``catalog.vectors()``, when the caller already has them.

    Returns
    -------
    image : ndarray (height, width) of uint8 or uint16
        As written: flipped when ``scene.mirror`` is set.
    truth : dict
        The frame document's ``truth`` section (positions in pixels of the
        written image, degrees; the attitude is the un-mirrored camera's).
    """
    from startrack._kernels.render import add_stars, expose

    dcm = np.asarray(dcm, dtype=np.float64)
    vectors = catalog.vectors() if vectors is None else vectors
    true_cam = camera.with_focal_length(camera.focal_length_px * (1.0 + scene.focal_error_pct / 100.0))
    margin = 5.0 * sensor.psf_sigma_px + 2.0 + float(np.linalg.norm(scene.rate_deg_s)) * math.pi / 180 \
        * sensor.exposure_s * camera.focal_length_px
    index, x_mid, y_mid = project_stars(vectors, dcm, true_cam, margin)
    mags = catalog.mag[index]
    if scene.mag_limit is not None:
        keep = mags <= scene.mag_limit
        index, x_mid, y_mid, mags = index[keep], x_mid[keep], y_mid[keep], mags[keep]
    ground, horizon_truth = None, None
    if scene.horizon is not None or not true_cam.is_pinhole:
        # The camera looks at the zenith: the ground (below the skyline, and outside a fisheye's image
        # circle) is dark and hides the stars behind it.
        from startrack import nuisance

        profile = nuisance.horizon_profile(scene.horizon or "flat", rng)
        cam_vec = vectors[index] @ dcm.T
        keep = ~nuisance.below_skyline(cam_vec, profile)
        horizon_truth = {"kind": scene.horizon or "flat",
                         "hidden_star_ids": sorted(int(i) for i in catalog.id[index[~keep]]),
                         "max_altitude_deg": float(np.degrees(profile.max()))}
        index, x_mid, y_mid, mags = index[keep], x_mid[keep], y_mid[keep], mags[keep]
        ground = nuisance.ground_mask(true_cam, profile, soft_px=max(1.0, sensor.psf_sigma_px))
        horizon_truth["ground_fraction"] = float(ground.mean())
    rendered_mag = mags + (rng.normal(0.0, scene.mag_noise, len(mags)) if scene.mag_noise > 0 else 0.0)
    if scene.extinction_mag > 0:
        # The atmosphere's extinction, the boresight at the zenith: mag_rendered holds it, mag is the catalog's.
        from startrack.nuisance import airmass

        zenith = np.arccos(np.clip((vectors[index] @ dcm.T)[:, 2], -1.0, 1.0))
        rendered_mag = rendered_mag + scene.extinction_mag * airmass(zenith)
    electrons = electrons_from_magnitude(rendered_mag, sensor)
    xs, ys = _trail_positions(vectors[index], dcm, true_cam, np.radians(scene.rate_deg_s),
                              sensor.exposure_s, sensor.psf_sigma_px)
    # False stars: random position and brightness inside the image.
    n_false = int(scene.false_stars)
    faint = scene.mag_limit if scene.mag_limit is not None else (float(np.max(catalog.mag)) if len(catalog) else 6.0)
    false_x = rng.uniform(-0.5, camera.width - 0.5, n_false)
    false_y = rng.uniform(-0.5, camera.height - 0.5, n_false)
    false_mag = rng.uniform(min(faint, max(0.0, faint - 5.0)), faint, n_false)   # a limit below 0: all at it
    height, width = camera.height, camera.width
    signal = np.zeros((height, width), dtype=np.float64)
    if n_false:
        xs = np.vstack([xs, np.repeat(false_x[:, None], xs.shape[1], axis=1)])
        ys = np.vstack([ys, np.repeat(false_y[:, None], ys.shape[1], axis=1)])
        electrons = np.concatenate([electrons, electrons_from_magnitude(false_mag, sensor)])
    add_stars(signal, np.ascontiguousarray(xs), np.ascontiguousarray(ys), np.ascontiguousarray(electrons),
              float(sensor.psf_sigma_px))
    hot = []
    if sensor.hot_pixels:
        hot_levels = _hot_pixel_map(height, width, int(sensor.hot_pixels), float(sensor.full_well_e))
        hot = [{"x": int(a), "y": int(b), "electrons": float(c)} for b, a, c in zip(*hot_levels)]
    pixel_seed = int(rng.integers(0, 2**63 - 1)) if seed is None else int(seed)
    extra_truth = _apply_nuisances(signal, sensor, scene, rng, x_mid, y_mid, ground)
    if horizon_truth is not None:
        if scene.ground_lights:
            horizon_truth["lights"] = _ground_lights(signal, ground, true_cam, sensor, int(scene.ground_lights), rng)
        extra_truth["horizon"] = horizon_truth
    if sensor.hot_pixels:
        np.add.at(signal, hot_levels[:2], hot_levels[2])
    if sensor.cosmic_rays:
        from startrack.nuisance import cosmic_rays

        extra_truth["cosmic_rays"] = cosmic_rays(signal, int(sensor.cosmic_rays), rng, sensor.full_well_e)
    prnu = _prnu_map(height, width, sensor.prnu) if sensor.prnu > 0 else np.empty((0, 0))
    cdf, guide, lo = _background_table(sensor)
    image = np.empty((height, width), dtype=np.uint8 if sensor.bit_depth == 8 else np.uint16)
    expose(signal, image, cdf, guide, lo, float(sensor.background_e), prnu, float(sensor.full_well_e),
           float(sensor.read_noise_e), float(sensor.gain), float(sensor.offset_dn), float(sensor.max_dn),
           pixel_seed, bool(sensor.noise))
    ra, dec, roll = dcm_to_radec_roll(dcm)
    peak_e = electrons[: len(index)] * _peak_fraction(sensor.psf_sigma_px)
    hidden = extra_truth.get("foreground", {}).get("hidden", np.zeros(len(index), dtype=bool))
    truth = {
        "quaternion": dcm_to_quaternion(dcm).tolist(),
        "ra": float(ra), "dec": float(dec), "roll": float(roll),
        "stars": [
            {"id": int(catalog.id[i]), "x": float(x), "y": float(y), "mag": float(m),
             "mag_rendered": float(mr), "electrons": float(e), "saturated": bool(p + sensor.background_e >= sensor.full_well_e)}
            for i, x, y, m, mr, e, p, h in zip(index, x_mid, y_mid, mags, rendered_mag, electrons, peak_e, hidden)
            if not h
        ],
        "false_stars": [{"x": float(a), "y": float(b), "mag": float(m)} for a, b, m in zip(false_x, false_y, false_mag)],
        "hot_pixels": hot,
        "epoch": float(catalog.epoch),
        "focal_length_px": float(true_cam.focal_length_px),
        "rate_deg_s": [float(v) for v in scene.rate_deg_s],
    }
    if "foreground" in extra_truth:
        fg = extra_truth.pop("foreground")
        fg["hidden_star_ids"] = sorted(int(catalog.id[i]) for i, h in zip(index, hidden) if h)
        del fg["hidden"]
        truth["foreground"] = fg
    truth.update(extra_truth)
    truth["stars"].sort(key=lambda s: s["mag"])
    if scene.mirror is not None:
        image = np.ascontiguousarray(image[:, ::-1] if scene.mirror == "x" else image[::-1, :])
        _mirror_truth(truth, scene.mirror, width, height)
    return image, truth


def _apply_nuisances(signal, sensor: Sensor, scene: Scene, rng, star_x, star_y, ground=None):
    """Turn ``signal`` (star electrons) into the expected electrons above the flat ``background_e``.

    The combination of :mod:`startrack.nuisance`: ``V (T (stars + sky G + nebulosity) + M foreground)``
    plus dark, minus the flat sky + dark the exposure kernel adds (so a pixel may be below it: the
    sky behind a dark body, a vignetted corner).  Without nuisances ``signal`` is left alone and no
    random number is drawn.  ``ground``: 1 where the ground (a dark skyline, the outside of a fisheye's
    image circle) hides the sky (:func:`startrack.nuisance.ground_mask`).  Returns the truth of what was added.
    """
    from startrack import nuisance

    height, width = signal.shape
    truth = {}
    spatial = (scene.gradient > 1 or scene.nebulosity_e_per_s > 0 or scene.foreground is not None
               or sensor.vignetting < 1 or ground is not None)
    if not spatial:
        return truth
    t = sensor.exposure_s
    sky_e = sensor.background_e_per_s * t
    sky = np.full((height, width), sky_e)
    if scene.gradient > 1:
        sky *= nuisance.gradient_map(height, width, scene.gradient, rng)
        truth["gradient"] = float(scene.gradient)
    if scene.nebulosity_e_per_s > 0:
        sky += scene.nebulosity_e_per_s * t * nuisance.nebulosity_map(height, width, rng, sensor.psf_sigma_px)
        truth["nebulosity_e_per_s"] = float(scene.nebulosity_e_per_s)
    light = signal + sky
    if scene.foreground is not None:
        mask, texture = nuisance.foreground_mask(height, width, scene.foreground, scene.foreground_fraction, rng,
                                                 soft_px=max(1.0, sensor.psf_sigma_px))
        radiance = scene.foreground_e_per_s
        if radiance is None:
            # A moon in a star exposure saturates; a roof or a tree at night is dark.
            radiance = 2.0 * sensor.full_well_e / t if scene.foreground == "disc" else 0.0
        light = light * (1.0 - mask) + radiance * t * texture * mask
        col = np.clip(np.rint(star_x), 0, width - 1).astype(np.int64)
        row = np.clip(np.rint(star_y), 0, height - 1).astype(np.int64)
        truth["foreground"] = {"kind": scene.foreground, "fraction": float(mask.mean()),
                               "e_per_s": float(radiance), "hidden": mask[row, col] >= 0.5}
    if ground is not None:
        light = light * (1.0 - ground)
    if sensor.vignetting < 1:
        light *= nuisance.vignetting_map(height, width, sensor.vignetting)
    signal[:] = light - sky_e
    return truth


def _ground_lights(signal, ground, camera, sensor: Sensor, count, rng):
    """Add ``count`` point lights (street lamps, lit windows) on the ground below the skyline, inside the lens's
    image circle, as bright as magnitude 0-4 stars, to ``signal``: their truth ``[{x, y, mag}]``."""
    from startrack._kernels.render import add_stars

    rows, cols = np.nonzero(ground >= 0.999)
    if len(rows):
        vec = camera.pixels_to_vectors(cols.astype(np.float64), rows.astype(np.float64))
        seen = np.all(np.isfinite(vec), axis=-1)
        rows, cols = rows[seen], cols[seen]
    if len(rows) == 0:
        return []
    pick = rng.choice(len(rows), size=min(count, len(rows)), replace=False)
    x = cols[pick] + rng.uniform(-0.5, 0.5, len(pick))
    y = rows[pick] + rng.uniform(-0.5, 0.5, len(pick))
    mag = rng.uniform(0.0, 4.0, len(pick))
    add_stars(signal, np.ascontiguousarray(x[:, None]), np.ascontiguousarray(y[:, None]),
              np.ascontiguousarray(electrons_from_magnitude(mag, sensor)), float(sensor.psf_sigma_px))
    return [{"x": float(a), "y": float(b), "mag": float(m)} for a, b, m in zip(x, y, mag)]


def _mirror_truth(truth, axis, width, height):
    """Flip the truth's pixel positions as the written image was flipped (x -> W-1-x or y -> H-1-y)."""
    key, size = ("x", width) if axis == "x" else ("y", height)
    for name in ("stars", "false_stars", "hot_pixels", "cosmic_rays"):
        for item in truth.get(name, []):
            item[key] = (size - 1) - item[key]
            if name == "cosmic_rays":
                a = math.radians(item["angle_deg"])
                item["angle_deg"] = math.degrees(math.atan2(math.sin(a), -math.cos(a)) if axis == "x"
                                                 else math.atan2(-math.sin(a), math.cos(a))) % 360.0
    for item in truth.get("horizon", {}).get("lights", []):
        item[key] = (size - 1) - item[key]
    truth["mirror"] = axis


def _peak_fraction(sigma):
    """Fraction of a centred pixel-integrated Gaussian in its brightest pixel."""
    return math.erf(0.5 / (math.sqrt(2.0) * sigma)) ** 2


def _merge_unresolved(x, y, mags, ids, resolve_px):
    """Blend stars closer than ``resolve_px``: one entry at the flux-weighted position with the
    summed flux, carrying the brighter star's id (a centroider sees one blob)."""
    order = np.argsort(mags, kind="stable")
    kept = []
    for k in order:
        for g in kept:
            if math.hypot(x[k] - g["x"], y[k] - g["y"]) < resolve_px:
                f_g = 10 ** (-0.4 * g["mag"])
                f_k = 10 ** (-0.4 * mags[k])
                g["x"] = (g["x"] * f_g + x[k] * f_k) / (f_g + f_k)
                g["y"] = (g["y"] * f_g + y[k] * f_k) / (f_g + f_k)
                g["mag"] = -2.5 * math.log10(f_g + f_k)
                g["blended"].append(int(ids[k]))
                break
        else:
            kept.append({"x": float(x[k]), "y": float(y[k]), "mag": float(mags[k]), "id": int(ids[k]), "blended": []})
    return kept


def star_list(catalog, camera: Camera, dcm, sensor: Sensor, scene: Scene, rng: np.random.Generator,
              sigma_px: float = 0.0, max_stars: int | None = None, drop_fraction: float = 0.0, vectors=None,
              resolve_px: float | None = None):
    """A frame's ``stars`` straight from the truth, with centroid and magnitude noise.

    The fast path for identification studies (no image): catalog stars inside
    the (focal-error perturbed) image at or brighter than ``scene.mag_limit``
    (stars closer than ``resolve_px``, by default two PSF sigmas, blended into
    one as a centroider would see them), each moved by Gaussian noise of
    ``sigma_px`` per axis; ``flux`` is the
    photo-electrons of its noisy magnitude; a fraction ``drop_fraction`` of
    stars is dropped at random; ``scene.false_stars`` false stars of random
    position and brightness are added; the ``max_stars`` brightest are kept.

    Returns
    -------
    stars : list of dict
        ``x``, ``y``, ``flux``, brightest first.
    truth : dict
        ``quaternion``, ``ra``, ``dec``, ``roll``, ``stars`` (every visible
        catalog star) and ``star_ids``: for each entry of ``stars`` its catalog
        id, or ``None`` for a false star.
    """
    dcm = np.asarray(dcm, dtype=np.float64)
    vectors = catalog.vectors() if vectors is None else vectors
    true_cam = camera.with_focal_length(camera.focal_length_px * (1.0 + scene.focal_error_pct / 100.0))
    resolve = 2.0 * sensor.psf_sigma_px if resolve_px is None else resolve_px
    # Stars just outside the edge still blend with those just inside.
    index, x, y = project_stars(vectors, dcm, true_cam, margin_px=resolve)
    mags = catalog.mag[index]
    if scene.mag_limit is not None:
        keep = mags <= scene.mag_limit
        index, x, y, mags = index[keep], x[keep], y[keep], mags[keep]
    blobs = _merge_unresolved(x, y, mags, catalog.id[index], resolve)
    blobs = [bl for bl in blobs if true_cam.in_image(bl["x"], bl["y"])]
    x = np.array([b["x"] for b in blobs])
    y = np.array([b["y"] for b in blobs])
    mags = np.array([b["mag"] for b in blobs])
    blob_ids = [b["id"] for b in blobs]
    truth_stars = [{"id": b["id"], "x": b["x"], "y": b["y"], "mag": b["mag"],
                    **({"blended": b["blended"]} if b["blended"] else {})} for b in blobs]
    noisy_mag = mags + (rng.normal(0.0, scene.mag_noise, len(mags)) if scene.mag_noise > 0 else 0.0)
    mx = x + (rng.normal(0.0, sigma_px, len(x)) if sigma_px > 0 else 0.0)
    my = y + (rng.normal(0.0, sigma_px, len(y)) if sigma_px > 0 else 0.0)
    ids = list(blob_ids)
    if drop_fraction > 0:
        keep = rng.random(len(ids)) >= drop_fraction
        mx, my, noisy_mag = mx[keep], my[keep], noisy_mag[keep]
        ids = [i for i, k in zip(ids, keep) if k]
    n_false = int(scene.false_stars)
    faint = scene.mag_limit if scene.mag_limit is not None else (float(np.max(catalog.mag)) if len(catalog) else 6.0)
    fx = rng.uniform(-0.5, camera.width - 0.5, n_false)
    fy = rng.uniform(-0.5, camera.height - 0.5, n_false)
    fmag = rng.uniform(min(faint, max(0.0, faint - 5.0)), faint, n_false)
    all_x = np.concatenate([mx, fx])
    all_y = np.concatenate([my, fy])
    flux = electrons_from_magnitude(np.concatenate([noisy_mag, fmag]), sensor)
    all_ids = ids + [None] * n_false
    order = np.argsort(-flux, kind="stable")
    if max_stars is not None:
        order = order[:max_stars]
    stars = [{"x": float(all_x[k]), "y": float(all_y[k]), "flux": float(flux[k])} for k in order]
    if scene.mirror is not None:
        # The list as a mirrored camera measures it (x -> W-1-x or y -> H-1-y), truth alike.
        key, size = ("x", camera.width) if scene.mirror == "x" else ("y", camera.height)
        for star in stars + truth_stars:
            star[key] = (size - 1) - star[key]
    ra, dec, roll = dcm_to_radec_roll(dcm)
    truth = {
        "quaternion": dcm_to_quaternion(dcm).tolist(),
        "ra": float(ra), "dec": float(dec), "roll": float(roll),
        "stars": truth_stars,
        "star_ids": [all_ids[k] for k in order],
        "epoch": float(catalog.epoch),
        "focal_length_px": float(true_cam.focal_length_px),
    }
    if scene.mirror is not None:
        truth["mirror"] = scene.mirror
    return stars, truth


def attitude_rate_check(dcm_a, dcm_b, dt):
    """Body rate (rad/s) that turns ``dcm_a`` into ``dcm_b`` in ``dt`` seconds."""
    delta = np.asarray(dcm_b) @ np.asarray(dcm_a).T
    return _rotation_vector_rad(delta) / dt


def frame_seed(seed: int, index: int) -> int:
    """The seed of frame ``index`` of a run seeded ``seed`` (recorded in each document)."""
    return int(np.random.SeedSequence([int(seed), int(index)]).generate_state(1, dtype=np.uint64)[0] >> np.uint64(1))


MAX_FALSE_STARS = 100_000
"""Most false stars per frame render and evaluate accept (memory grows with the count)."""


@dataclass
class RenderRun:
    """Everything one ``render`` invocation needs; :meth:`frames` yields the results.

    ``attitude`` is a DCM or ``None`` for random attitudes (one per frame with
    ``count``).  A sequence (``frames > 1``) starts at ``attitude`` (or a random
    one) and turns at ``scene.rate_deg_s`` (camera frame) every
    ``frame_interval_s``.  Every frame's ``image`` section carries its
    ``time`` (ISO-8601, mid-exposure: ``start_time``, or the catalog's epoch
    when none is given, plus ``k * frame_interval_s``) and ``exposure_ms``.
    """

    catalog: object
    camera: Camera
    sensor: Sensor
    scene: Scene
    seed: int
    attitude: np.ndarray | None = None
    count: int = 1
    frames: int = 1
    frame_interval_s: float = 0.1
    start_time: object = None
    stars_only: bool = False
    sigma_px: float = 0.0
    max_stars: int | None = None
    drop_fraction: float = 0.0
    image_path: object = None      # image_path(frame index) -> file name, or None (no image files)
    first_seed: int | None = None
    params: dict = field(default_factory=dict)
    blackout: tuple = ()
    first_index: int = 0           # index of the first frame (a chunk of a larger set: same seeds and names)
    aberration: bool = False       # the sky as a moving observer sees it (startrack.apparent)
    velocity_km_s: tuple | None = None    # the camera's GCRS velocity (km/s) at the first frame
    orbit_period_s: float | None = None   # the velocity turns about (v x z) with this period (a circular orbit)

    def observer_velocity(self, t_s: float):
        """The camera's GCRS velocity (km/s) ``t_s`` seconds after the first frame, or ``None``."""
        if self.velocity_km_s is None:
            return None
        v = np.asarray(self.velocity_km_s, dtype=np.float64)
        if not self.orbit_period_s:
            return v
        normal = np.cross(v, [0.0, 0.0, 1.0])
        if np.linalg.norm(normal) < 1e-9 * max(np.linalg.norm(v), 1e-300):
            normal = np.cross(v, [1.0, 0.0, 0.0])
        normal /= np.linalg.norm(normal)
        angle = 2.0 * math.pi * t_s / self.orbit_period_s
        # Rodrigues: v turned by angle about the orbit normal (normal is perpendicular to v).
        return v * math.cos(angle) + np.cross(normal, v) * math.sin(angle)

    def apparent_vectors(self, vectors, t, t_s: float, cache: dict):
        """The catalog's unit vectors at their apparent places at UTC ``t`` (parallax, solar deflection,
        aberration)."""
        velocity = self.observer_velocity(t_s)
        if not self.aberration:
            return vectors, velocity
        from startrack.apparent import aberrate, observer_state

        key = (t, None if velocity is None else tuple(velocity))
        if key not in cache:
            cache.clear()
            cache[key] = aberrate(vectors, observer_state(t, velocity), parallax_mas=self.catalog.plx)
        return cache[key], velocity

    @property
    def total(self) -> int:
        return self.count * self.frames

    def frames_iter(self):
        """Yield ``(document, image_or_None, image_path_or_None)`` for every frame."""
        import datetime as _dt

        from startrack._version import __version__
        from startrack.formats.frame import FRAME_FORMAT
        from startrack.timeutil import format_time

        vectors = self.catalog.vectors()
        apparent_cache = {}
        rate = np.radians(np.asarray(self.scene.rate_deg_s, dtype=np.float64))
        start = self.start_time if self.start_time is not None else epoch_time(self.catalog.epoch)
        index = self.first_index
        for _ in range(self.count):
            base = None
            for k in range(self.frames):
                seed_k = self.first_seed if (self.first_seed is not None and self.total == 1) else frame_seed(self.seed, index)
                rng = np.random.default_rng(seed_k)
                if base is None:
                    if self.attitude is not None:
                        base = np.asarray(self.attitude, dtype=np.float64)
                    else:
                        base = quaternion_to_dcm(random_quaternions_one(rng))
                dcm = _propagate_attitude_rad(base, rate, k * self.frame_interval_s) if k else base
                doc = {"format": FRAME_FORMAT}
                image_doc = {"width": self.camera.width, "height": self.camera.height}
                # Every frame carries its time (mid-exposure) and exposure, so `track` needs no option.
                t_frame = start + _dt.timedelta(seconds=k * self.frame_interval_s)
                image_doc["time"] = format_time(t_frame)
                seen, velocity = self.apparent_vectors(vectors, t_frame, k * self.frame_interval_s, apparent_cache)
                image_doc["exposure_ms"] = float(self.sensor.exposure_ms)
                image = None
                path = None
                if self.stars_only:
                    stars, truth = star_list(self.catalog, self.camera, dcm, self.sensor, self.scene, rng,
                                             self.sigma_px, self.max_stars, self.drop_fraction, seen)
                else:
                    catalog = self.catalog
                    if k in self.blackout:
                        # A covered or blinded frame: the sensor's noise and no star.
                        catalog = self.catalog.subset(np.zeros(len(self.catalog), dtype=bool))
                    image, truth = render_image(catalog, self.camera, dcm, self.sensor, self.scene, rng,
                                                vectors=None if k in self.blackout else seen)
                    if k in self.blackout:
                        truth["blackout"] = True
                    path = self.image_path(index) if self.image_path else None
                    if path:
                        image_doc["path"] = path
                    image_doc["bit_depth"] = self.sensor.bit_depth
                doc["image"] = image_doc
                doc["camera"] = self.camera.to_dict()
                if velocity is not None:
                    doc["observer"] = {"velocity_km_s": [float(v) for v in velocity]}
                doc["truth"] = truth
                if self.stars_only:
                    doc["stars"] = stars
                doc["render"] = {
                    "startrack_version": __version__,
                    "frame_index": index,
                    "sequence": {"index": k, "frames": self.frames} if self.frames > 1 else None,
                    "frame_seed": seed_k,
                    "seed": self.seed,
                    "params": self.params,
                }
                yield doc, image, path
                index += 1


def epoch_time(epoch: float):
    """The UTC time of a decimal Julian year (the catalog's epoch when no --time is given: the sky as rendered)."""
    import datetime as _dt

    from startrack.timeutil import _J2000

    return _J2000 + _dt.timedelta(days=(float(epoch) - 2000.0) * 365.25)


def random_quaternions_one(rng):
    from startrack.rotations import random_quaternions

    return random_quaternions(1, rng)[0]
