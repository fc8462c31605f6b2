"""Star detection and sub-pixel centroiding.

The pipeline (paper 000 Sec. 3.1, paper 003 Sec. 3):

1. **Background**: a global sigma-clipped level and noise, and a local mesh
   (tiles of ``mesh_px``, sigma-clipped median, 3 x 3 median-filtered, bilinear
   interpolation) that follows gradients, moonlight and light pollution.
2. **Detection**: pixels above ``threshold_sigma`` times the local noise (or a
   fixed ``threshold_dn`` above the background; paper 000 uses 60 DN),
   optionally after a matched (Gaussian) filter for faint stars;
   connected-component labelling (paper 000 Fig. 6) with OpenCV's
   ``connectedComponentsWithStats``.
3. **Rejection**: blobs smaller than ``min_pixels`` or larger than
   ``max_pixels``; hot pixels and cosmic rays (almost all the flux in one
   pixel); elongated trails and extended objects (flagged, not centroided).
   Two touching stars are split at their saddle (deblending).
4. **Centroid** by ``method``: ``com`` (centre of mass of the blob, paper 000
   Eq. 1; paper 003 Eqs. 1-3), ``iwc`` (iterative intensity-weighted centroid
   with a Gaussian window), ``quine`` (Gaussian interpolation, paper 003
   Eqs. 4-6, Quine et al. 2007), ``gauss`` (2-D pixel-integrated Gaussian least
   squares).
5. **Adaptive selection** (paper 000 Fig. 9): the ``max_stars`` brightest.

Positions follow the project convention: ``x`` column, ``y`` row, ``(0, 0)`` the
centre of the top-left pixel.
"""
from __future__ import annotations

import functools
import math
import operator
import struct
import threading
import time
from dataclasses import asdict, dataclass, field

import numpy as np

from startrack.errors import BadInputError, ParameterError

__all__ = ["CentroidOptions", "CentroidResult", "estimate_background", "find_stars", "centroid_windows", "METHODS"]

METHODS = ("com", "iwc", "quine", "gauss")


@dataclass
class CentroidOptions:
    """Detection and centroiding settings (pixels and DN)."""

    method: str = "gauss"
    threshold_sigma: float = 5.0
    threshold_dn: float | None = None
    background: str = "mesh"
    mesh_px: int = 64
    matched_filter: bool = False
    filter_sigma_px: float = 1.0
    min_pixels: int = 3
    max_pixels: int = 5000
    max_elongation: float = 2.5
    hot_pixel_ratio: float = 0.7
    deblend: bool = True
    max_stars: int | None = None
    psf_sigma_px: float | None = None
    gain_e_per_dn: float | None = None
    saturation_dn: float | None = None
    tophat_px: float | None = None
    max_fwhm_ratio: float | None = None
    misfit_p: float = 1e-3
    star_likeness: bool = True

    def __post_init__(self):
        if self.method not in METHODS:
            raise ParameterError("method", f"unknown method {self.method!r}; choose from {', '.join(METHODS)}")
        if self.background not in ("mesh", "global", "tophat"):
            raise ParameterError("background", "must be 'mesh', 'global' or 'tophat'")
        if self.tophat_px is not None and not self.tophat_px >= 1:
            raise ParameterError("tophat_px", f"must be at least 1, got {self.tophat_px}")
        if not self.threshold_sigma > 0:
            raise ParameterError("threshold_sigma", f"must be positive, got {self.threshold_sigma}")
        if self.threshold_dn is not None and not self.threshold_dn > 0:
            raise ParameterError("threshold_dn", f"must be positive, got {self.threshold_dn}")
        if self.mesh_px < 8:
            raise ParameterError("mesh_px", f"must be at least 8, got {self.mesh_px}")
        if self.min_pixels < 1 or self.max_pixels < self.min_pixels:
            raise ParameterError("min_pixels", f"must be from 1 to the largest blob size ({self.max_pixels}), got {self.min_pixels}")
        if not 0 <= self.misfit_p < 1:
            raise ParameterError("misfit_p", f"must be in [0, 1), got {self.misfit_p}")
        if self.max_stars is not None and self.max_stars < 1:
            raise ParameterError("max_stars", f"must be at least 1, got {self.max_stars}")


@dataclass
class CentroidResult:
    """Stars found in one image, brightest first, and what was set aside."""

    stars: list
    rejected: list
    background_level: float
    background_sigma: float
    time_ms: float
    reason: str | None = None
    params: dict = field(default_factory=dict)

    def section(self) -> dict:
        """The frame document's ``centroid`` section (the stars go to ``stars``)."""
        out = {"method": self.params.get("method"), "n_stars": len(self.stars), "n_rejected": len(self.rejected),
               "background_dn": self.background_level, "noise_dn": self.background_sigma,
               "time_ms": self.time_ms, "rejected": self.rejected, "params": self.params}
        if self.reason:
            out["reason"] = self.reason
        return out


def _median(values) -> float:
    """``np.median`` of values, to the bit (the middle value, or the mean of the middle two; NaN when one is NaN),
    without its overhead (~15 us a call on the small arrays here) nor its import of ``numpy.ma`` (~4 ms of a
    process that calls it first)."""
    v = np.sort(np.asarray(values, dtype=np.float64), axis=None)
    n = v.shape[0]
    if n == 0 or math.isnan(v[-1]):      # NaN sorts last
        return math.nan
    return float(v[n // 2]) if n & 1 else float((v[n // 2 - 1] + v[n // 2]) / 2)


def _median3(a):
    """3 x 3 median filter of a small 2-D array (edges replicated)."""
    from startrack._kernels.background import median3

    return median3(np.ascontiguousarray(a, dtype=np.float64))


def estimate_background(image: np.ndarray, options: CentroidOptions, saturation: float | None = None):
    """Background level and noise on a coarse mesh, and their global values (DN).

    Returns ``(level_mesh, sigma_mesh, global_level, global_sigma)``; the mesh
    arrays have one value per ``mesh_px`` tile (a 1 x 1 mesh for ``global``).
    Each level and noise is the normal core of the tile's (or the frame's)
    sampled pixels (:func:`startrack._kernels.background.core_stats_of_sorted`):
    it holds on frames clipped at zero after a dark subtraction, on 8-bit
    frames of a few grey levels and under stars, where a median and MAD do not.
    The noise is the normal's sigma; on whole DN the caller adds the rounding's
    1/12 DN^2 where a pixel's noise is meant.  Pixels at or above ``saturation``
    are no data (they say nothing of the sky's level): a tile of a bright
    body's saturated face takes its neighbours' level, and a tile across its
    edge the level of its unsaturated part.
    """
    from startrack._kernels.background import background_mesh, core_stats_of_sorted, mesh_core_stats, mesh_samples

    h, w = image.shape

    def frame_stats():
        step = max(1, int(round(math.sqrt(h * w / 10000.0))))
        sample = np.ascontiguousarray(image[::step, ::step], dtype=np.float64).ravel()
        # ~10^4 values, sorted by numpy.  NaN and infinite pixels are no data.
        ordered = np.sort(sample)
        if ordered.size and not (np.isfinite(ordered[0]) and np.isfinite(ordered[-1])):
            ordered = ordered[np.isfinite(ordered)]
        return core_stats_of_sorted(ordered)

    if options.background == "global" or min(h, w) < 2 * options.mesh_px:
        glevel, gsigma = frame_stats()
        return np.full((1, 1), glevel), np.full((1, 1), gsigma), float(glevel), float(gsigma)
    cell = options.mesh_px
    mstep = max(1, cell // 10)    # ~100 samples per tile: the median to ~0.13 sigma
    ny, nx = -(-h // cell), -(-w // cell)
    # Strips of whole tile rows, each made float32 on its own (a float32 frame's are views): no float copy of a
    # large frame of whole DN (issue 41); the tiles are independent, so the values are the whole frame's.
    step = h if image.dtype == np.float32 and h * w < _BAND_MIN_PIXELS else cell * max(1, _BAND_BYTES // (4 * w * cell))
    fine = ny * nx * -(-min(cell, h) // mstep) * -(-min(cell, w) // mstep) > 4_000_000
    if not fine and image.dtype in (np.uint8, np.uint16) and image.flags.c_contiguous:
        # Whole DN are sampled as they are (float32 holds them exactly): no float copy of any strip.
        strips = [image]
    elif step >= h:
        strips = [np.ascontiguousarray(image, dtype=np.float32)]
    else:
        strips = (np.ascontiguousarray(image[r0:r0 + step], dtype=np.float32) for r0 in range(0, h, step))
    if not fine:
        # The tiles' samples sorted by numpy (vectorised; ~0.07 ms for 192 tiles of 121 samples against
        # ~0.4 ms of insertion sorts in background_mesh), then the same clipped statistics.  Saturated pixels are
        # left out as they are sampled (no copy of the frame).
        sat32 = math.inf if saturation is None else float(np.float32(saturation))
        parts = [mesh_samples(strip, cell, mstep, sat32) for strip in strips]
        if len(parts) == 1:
            samples, counts, sampled = parts[0]
        else:
            samples = np.full((ny * nx, max(p[0].shape[1] for p in parts)), np.inf, dtype=np.float32)
            t = 0
            for part, _, _ in parts:
                samples[t:t + part.shape[0], :part.shape[1]] = part
                t += part.shape[0]
            counts = np.concatenate([p[1] for p in parts])
            sampled = np.concatenate([p[2] for p in parts])
        level, sigma = mesh_core_stats(np.sort(samples, axis=1), counts, sampled, ny, nx)
    else:       # a fine mesh on a large frame: no copy of every sample
        parts = []
        for strip in strips:
            if saturation is not None:
                strip = np.where(strip >= saturation, np.float32(np.nan), strip)
            parts.append(background_mesh(strip, cell, mstep))
        level = np.concatenate([p[0] for p in parts])
        sigma = np.concatenate([p[1] for p in parts])
    # Tiles without data (NaN: mostly NaN pixels) take their neighbours' median, else the frame's level.
    level = _median3(level)
    sigma = _median3(sigma)
    have = np.isfinite(level) & np.isfinite(sigma)
    if have.any():
        # The frame's level and noise are its typical tile's: a foreground body, a dark horizon or a bright moon
        # over part of the frame makes the frame's histogram two-humped, and its core's width is not a noise.
        glevel, gsigma = _median(level[have]), _median(sigma[have])
    else:
        glevel, gsigma = frame_stats()
    level = np.where(np.isfinite(level), level, glevel)
    sigma = np.where(sigma > 0, sigma, gsigma)
    return level, sigma, float(glevel), float(gsigma)


def _tophat(img: np.ndarray, options: CentroidOptions) -> np.ndarray:
    """The image minus its grey opening by a disk: what is smaller than the disk (stars) stays.

    Nebulae, gradients, the Milky Way's glow, twilight and vignetting are
    broader than a star and are removed with the opening; a star is removed by
    it entirely when the disk is wider than the star.  The disk's radius is
    ``tophat_px``, else three times the lower-quartile FWHM of the stars a first,
    plain (mesh background) detection finds, within 3-25 px.
    """
    import cv2

    r = options.tophat_px
    if r is None:
        from dataclasses import replace

        first = find_stars(img, replace(options, background="mesh", max_stars=30, max_fwhm_ratio=None))
        fwhm = [s_["fwhm_px"] for s_ in first.stars if not s_["saturated"]]
        # The narrower stars set the scale: in a nebula the wide detections are knots, not stars.
        r = 3.0 * float(np.percentile(fwhm, 25)) if fwhm else 6.0
        r = min(25.0, max(3.0, r))
    k = 2 * int(round(r)) + 1
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))
    opened = cv2.morphologyEx(img, cv2.MORPH_OPEN, kernel)
    return np.ascontiguousarray(img - opened, dtype=np.float32)


_CLIP_KAPPA = 3.0
# Standard deviation of a unit normal truncated to +-3: clipped samples' std reads this much low.
_CLIP_STD = math.sqrt(1.0 - 2.0 * _CLIP_KAPPA * math.exp(-0.5 * _CLIP_KAPPA**2) / math.sqrt(2.0 * math.pi)
                      / math.erf(_CLIP_KAPPA / math.sqrt(2.0)))


def _pixel_noise_mesh(residual, sigma_mesh, cell):
    """Per-tile pixel noise (DN) for the fit's weights and its covariance: every pixel, clipped std.

    The detection mesh's sigma is 1.4826 MAD of ~100 samples a tile; on integer
    DN the MAD moves in half-DN steps, and its scatter makes ``1 / sigma^2``
    (what weights and covariances use) read high: on paper 000's sensor it
    gave ``E[1/s^2]^(-1/2)`` 1.6 % below the true noise, ~3 % on the NEES
    of background-limited stars (issue 21).  Here each tile's residual pixels
    (the background already subtracted) within 3 sigma of the mesh's sigma (the
    normal core's: one pass lands within 0.1 % of the converged value, median
    over the tiles of real and rendered frames) give a standard deviation, divided by that of a
    3-sigma-truncated normal; then the mesh's 3 x 3 median filter.  The
    detection thresholds keep the mesh's own sigma.
    """
    from startrack._kernels.background import tile_clipped_std

    h, w = residual.shape
    ny, nx = sigma_mesh.shape
    if cell * ny < h or cell * nx < w or (ny, nx) == (1, 1):
        return sigma_mesh
    sig = np.ascontiguousarray(sigma_mesh, dtype=np.float64)
    out = tile_clipped_std(residual, int(cell), sig, _CLIP_KAPPA, _CLIP_STD, 1, np.empty_like(sig))
    return _noise_floor(out, sigma_mesh)


def _noise_floor(tile_std, sigma_mesh):
    """:func:`_pixel_noise_mesh`'s last step: the tiles' clipped standard deviations 3 x 3 median-filtered, at
    least a quarter of the mesh's typical noise."""
    return np.maximum(_median3(tile_std), 0.25 * _median(sigma_mesh))


#: Pixels a thread of :func:`_subtract_background` gets at least (measured: on 2 cores a 1024 x 768 frame's pass
#: takes ~0.25 ms on one thread; a hand-off to a thread costs ~0.05 ms), and in one chunk.
_PIXELS_PER_THREAD = 200_000
_PIXELS_PER_CHUNK = 100_000


def _subtract_background(image, level_mesh, thresh_mesh, cell, residual, labels, foreground, row_counts, sigma_mesh,
                         noise: bool, keys: list | None = None):
    """``residual``, the mask in ``labels`` (:func:`startrack._kernels.centroid.subtract_background_rows`) and,
    when ``noise``, the pixel-noise mesh of :func:`_pixel_noise_mesh` from the same pass (else None); strips of whole tile rows
    on :func:`threads` threads (the same values whatever their number).  ``keys`` (a list; a C-contiguous float32
    ``image``): each strip's smallest and largest pixel order key
    (:func:`startrack._kernels.centroid.subtract_background_rows_keyed`) are appended to it."""
    from startrack._kernels.centroid import subtract_background_rows, subtract_background_rows_keyed

    h, w = image.shape
    ny, nx = level_mesh.shape
    noise = noise and (ny, nx) != (1, 1) and cell * ny >= h and cell * nx >= w
    sig = np.ascontiguousarray(sigma_mesh, dtype=np.float64)
    out = np.empty_like(sig) if noise else np.empty((0, 0))
    args = (image, np.ascontiguousarray(level_mesh, dtype=np.float64),
            np.ascontiguousarray(thresh_mesh, dtype=np.float64), float(cell), residual, labels, int(foreground),
            row_counts)
    if keys is None:
        kernel, extra = subtract_background_rows, ()
    else:
        kernel, extra = subtract_background_rows_keyed, (image.view(np.int32),)
    n_threads = min(threads(), h * w // _PIXELS_PER_THREAD)
    if n_threads <= 1 or (ny, nx) == (1, 1):
        got = kernel(*args, 0, h, sig, _CLIP_KAPPA, _CLIP_STD, out, 0, *extra)
        if keys is not None:
            keys.append(got)
    else:
        kernel = kernel.resolve((*args, 0, h, sig, _CLIP_KAPPA, _CLIP_STD, out, 0, *extra))
        # Chunks of whole tile rows, about _PIXELS_PER_CHUNK pixels each.
        step = max(1, _PIXELS_PER_CHUNK // (int(cell) * w))
        rows = [min(h, int(cell) * j) for j in range(0, ny, step)] + [h]
        got = [None] * (len(rows) - 1)

        def run(i):
            got[i] = kernel(*args, rows[i], rows[i + 1], sig, _CLIP_KAPPA, _CLIP_STD, out, 0, *extra)

        _run_chunks(run, len(rows) - 1, n_threads)
        if keys is not None:
            keys.extend(got)
    return _noise_floor(out, sigma_mesh) if noise else None


def _flag_misfits(stars, p_value, min_stars=5):
    """``misfit: true`` on the stars whose weighted fit's chi-square fails, beyond the frame's own PSF mismatch.

    A single pixel-integrated Gaussian star leaves ``chi2 ~ chi-square(dof)``.
    Real optics are not Gaussian: every star leaves an excess ``chi2 - dof``
    that grows as its ``SNR^2`` (the profile error, a fixed fraction of its
    signal, as in DAOPHOT's noise model).  The frame's typical fraction
    ``c = median((chi2 - dof) / SNR^2)`` over its fitted stars (when there are
    ``min_stars``; else 0) is taken as the PSF's own, and a star is a misfit when
    ``chi2 - c SNR^2`` still exceeds the ``1 - p_value`` point of chi-square:
    a neighbour in its window, a cosmic ray, a cut or distorted image.  On a
    rendered (Gaussian) frame ``c`` is ~0 and this is the plain chi-square test.
    """
    if not p_value > 0:
        return
    fitted = [s_ for s_ in stars if "fit_chi2" in s_ and s_.get("snr", 0) > 0 and math.isfinite(s_["snr"])]
    excess = [(s_["fit_chi2"] - s_["fit_dof"]) / s_["snr"] ** 2 for s_ in fitted]
    c = max(0.0, _median(excess)) if len(fitted) >= min_stars else 0.0
    for s_ in fitted:
        if _chi2_p_value(s_["fit_chi2"] - c * s_["snr"] ** 2, s_["fit_dof"]) < p_value:
            s_["misfit"] = True


def _chi2_p_value(chi2, dof):
    """Upper tail ``P(X >= chi2)`` of chi-square with ``dof`` degrees of freedom (Wilson-Hilferty)."""
    if dof <= 0 or not math.isfinite(chi2):
        return 1.0
    k = 2.0 / (9.0 * dof)
    z = ((max(chi2, 0.0) / dof) ** (1.0 / 3.0) - (1.0 - k)) / math.sqrt(k)
    return 0.5 * math.erfc(z / math.sqrt(2.0))


def _uncertainty(flux, sigma_psf, noise, gain):
    """1-sigma centroid uncertainty per axis, px (King 1983; Liebe 2002).

    ``sigma_x^2 = s^2 / N_e + 4 pi s^4 n^2 / F^2`` with ``s`` the PSF sigma,
    ``N_e`` the star's photo-electrons (only when the gain is known), ``n`` the
    background noise per pixel and ``F`` the flux, both in DN.
    """
    if flux <= 0:
        return float("nan")
    # Photon term sigma^2 / N_e (N_e = flux * gain electrons), in px^2.
    shot = sigma_psf**2 / (flux * gain) if gain else 0.0
    bg = 4.0 * math.pi * sigma_psf**4 * noise**2 / flux**2
    return math.sqrt(shot + bg + 1e-6)


#: Variance of rounding to whole DN (uniform over one DN): the floor of an integer image's pixel noise.
_QUANT_VAR = 1.0 / 12.0
_PHASES = (np.arange(6) + 0.5) / 6 - 0.5       # sub-pixel phases of the COM model, per axis


def _is_integer_image(img) -> bool:
    """True when the pixel values are whole numbers (8-, 12- or 16-bit data, whatever the array's dtype)."""
    if np.issubdtype(img.dtype, np.integer):
        return True
    probe = np.ascontiguousarray(img[:: max(1, img.shape[0] // 64), :: max(1, img.shape[1] // 64)])   # gathered once
    return bool(np.all(probe == np.round(probe)))


def _pixel_gaussian(flux, s, half):
    """A pixel-integrated Gaussian star of ``flux`` and sigma ``s`` at every phase of :data:`_PHASES`:
    ``(values (P, n, n), offsets (n,))``, phases in C order (y slow, x fast)."""
    off = np.arange(-half, half + 1, dtype=np.float64)
    edges = np.concatenate([off - 0.5, [off[-1] + 0.5]])
    z = ((edges[None, :] - _PHASES[:, None]) / (math.sqrt(2.0) * s)).ravel().tolist()
    c = 0.5 * (1.0 + np.array([math.erf(t) for t in z])).reshape(len(_PHASES), len(edges))
    g = np.diff(c, axis=1)                                      # (phases, n)
    vals = flux * g[:, None, :, None] * g[None, :, None, :]     # (py, px, y, x)
    return vals.reshape(len(_PHASES) ** 2, len(off), len(off)), off


@functools.lru_cache(maxsize=4096)
def _com_sigma_model(flux, s, thresh, var_bg, inv_gain, integer, clip, draws=6):
    """1-sigma per-axis error of the thresholded centre of mass of a Gaussian star, px (cached on rounded inputs).

    The ``com`` method is the residual-weighted mean over the pixels above the detection
    threshold.  Its error here is simulated, not assumed: a pixel-integrated Gaussian of
    ``flux`` (DN) and sigma ``s`` (px) at a grid of sub-pixel phases, ``draws`` noise
    realisations each (background variance ``var_bg`` less the rounding's, plus the shot
    noise ``m / gain`` when the gain is known), rounded to whole DN when the image is
    integer, clipped at ``clip`` (a saturated star), thresholded at ``thresh``; the RMS
    of the COM's offset from the true centre.  It holds the pixel-phase error of the
    truncation and of the rounding (systematic for one star, spread like noise over the
    stars of a field), the propagated noise and the noise in which pixels pass the
    threshold.  The draws come from a fixed seed: the same inputs, the same sigma.
    """
    half = int(max(2, math.ceil(4.0 * s)))
    vals, off = _pixel_gaussian(flux, s, half)
    v = np.repeat(np.repeat(_PHASES, len(_PHASES)), draws)      # y phase (slow)
    u = np.repeat(np.tile(_PHASES, len(_PHASES)), draws)        # x phase (fast)
    vals = np.repeat(vals, draws, axis=0)
    var_an = max(var_bg - (_QUANT_VAR if integer else 0.0), 0.0) + inv_gain * vals
    obs = vals + np.random.default_rng(20261202).standard_normal(vals.shape) * np.sqrt(var_an)
    if integer:
        obs = np.floor(obs + 0.5)
    obs = np.minimum(obs, clip)
    w = np.where(obs > thresh, obs, 0.0)
    fw = w.sum(axis=(1, 2))
    ok = fw > 0
    if not np.any(ok):
        return float("nan")
    w, fw, u, v = w[ok], fw[ok], u[ok], v[ok]
    cx = (w.sum(axis=1) * off).sum(axis=1) / fw
    cy = (w.sum(axis=2) * off).sum(axis=1) / fw
    return math.sqrt(0.5 * (np.mean((cx - u) ** 2) + np.mean((cy - v) ** 2)))


def _com_uncertainty(flux, peak, sig_est, psf_sigma, thresh, noise, gain, integer, saturated):
    """:func:`_com_sigma_model` for one detected star: its flux, the PSF sigma (given, else from the peak-to-flux
    ratio of an unsaturated star, else the blob's moments), the local threshold and noise, on rounded inputs."""
    if not (flux > 0 and math.isfinite(flux)):
        return float("nan")
    if psf_sigma:
        s = psf_sigma
    elif not saturated and peak > 0:
        # A pixel-integrated Gaussian's peak pixel holds ~F / (2 pi s^2 + 1/6 ...) of its flux: s from the ratio.
        s = math.sqrt(max(flux / (2.0 * math.pi * peak) - 1.0 / 12.0, 0.0))
    else:
        s = sig_est
    s = min(max(s, 0.3), 5.0)
    # Inputs on a grid (0.05 dex, 0.05 px) so that a field's stars share a few cached models: sigma moves by < 6 %.
    r2 = lambda x: float(10 ** (round(20 * math.log10(x)) / 20)) if x > 0 else 0.0     # noqa: E731
    clip = r2(float(peak)) if saturated else float("inf")
    return _com_sigma_model(r2(flux), round(20 * s) / 20, r2(thresh), r2(noise**2), r2(1.0 / gain) if gain else 0.0,
                            bool(integer), clip)


_WORKSPACE = threading.local()

#: Threads of :func:`find_stars` set by :func:`set_threads` (None: from the environment, see :func:`threads`).
_THREADS: int | None = None
_POOL = None            # (pid, size, ThreadPoolExecutor): a forked child's copy has no threads and is replaced


def set_threads(n: int | None) -> None:
    """The number of threads :func:`find_stars` may use in this process (``None``: back to :func:`threads`' default).

    The results are the same whatever the number: the threads split independent work (image strips, stars).
    """
    global _THREADS
    if n is not None and (not isinstance(n, int) or n < 1):
        raise ParameterError("threads", f"must be a whole number >= 1, got {n!r}")
    _THREADS = n


def threads() -> int:
    """Threads :func:`find_stars` uses: :func:`set_threads`'s number, else ``$STARTRACK_THREADS``, else
    ``$NUMBA_NUM_THREADS``, else 1 in a worker process of a pool (``solve -j N``, ``evaluate -j N``, Dask's
    workers: the pool already uses the cores), else the CPUs this process may run on (at most 4) less the
    cores other processes keep busy (the one-minute load average, rounded, less one for this process), at
    least 1.

    On a machine already busy a second thread is worse than none: a thread that has started a strip and is
    then descheduled holds the frame up for a scheduler time slice (measured on 2 cores at load 2.3: 7.3 ms a
    frame on two threads against 2.4 ms on one; tetra3rs's threads went from 3.7 to 6.9 ms likewise); at
    load 1.5 two threads took 2.20 ms a frame against 2.59 ms on one (the 8 ESA images, alternated).
    """
    import os
    import sys

    if _THREADS is not None:
        return _THREADS
    for var in ("STARTRACK_THREADS", "NUMBA_NUM_THREADS"):
        value = os.environ.get(var, "").strip()
        if value.isdigit() and int(value) >= 1:
            return int(value)
    # A pool's worker imported multiprocessing to start (spawn) or inherited it (fork); a process that never
    # imported it is no worker, and does not pay its import here.
    mp = sys.modules.get("multiprocessing")
    if mp is not None and mp.parent_process() is not None:
        return 1
    try:
        cpus = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        cpus = os.cpu_count() or 1
    try:
        # The load counts this process too when it is busy (a batch of frames): one of it is ours.
        busy = max(0, math.floor(os.getloadavg()[0] + 0.5) - 1)
    except (AttributeError, OSError):
        busy = 0
    return max(1, min(cpus - busy, 4))


def _run_chunks(run, n_chunks: int, n_threads: int) -> None:
    """``run(i)`` for every chunk ``i < n_chunks`` (independent work, kernels that release the GIL), on this
    thread and up to ``n_threads - 1`` of the pool's.

    The chunks are handed out one at a time to whichever thread is free, and this thread takes them too: on a
    busy machine, where a pool thread may not get a core for milliseconds, this thread does the work itself
    and returns without waiting for it (it waits only for chunks a pool thread has started).  Raises the first
    error of a chunk.
    """
    import os

    global _POOL
    if n_threads <= 1 or n_chunks <= 1:
        for i in range(n_chunks):
            run(i)
        return
    lock = threading.Condition()
    state = [0, 0, None]        # next chunk, chunks running, first error

    def work():
        while True:
            with lock:
                i = state[0]
                if i >= n_chunks or state[2] is not None:
                    return
                state[0] = i + 1
                state[1] += 1
            try:
                run(i)
            except BaseException as exc:  # noqa: BLE001 - raised again on the calling thread
                with lock:
                    state[2] = state[2] or exc
            finally:
                with lock:
                    state[1] -= 1
                    if state[1] == 0:
                        lock.notify_all()

    pid = os.getpid()
    helpers = min(n_threads, n_chunks) - 1
    if _POOL is None or _POOL[0] != pid or _POOL[1] < helpers:
        from concurrent.futures import ThreadPoolExecutor

        _POOL = (pid, helpers, ThreadPoolExecutor(helpers, thread_name_prefix="startrack-centroid"))
    for _ in range(helpers):
        _POOL[2].submit(work)
    work()
    with lock:
        while state[1] > 0:
            lock.wait()
    if state[2] is not None:
        raise state[2]


#: Frames of at least this many pixels are measured in bands of rows (:class:`_Bands`): no whole-frame residual
#: nor float copy of the frame, ~2 bytes a pixel (the labels) beyond the frame (issue 41).  Below it the whole
#: residual (4 bytes a pixel) is kept and reused across frames, which is faster.
_BAND_MIN_PIXELS = 16_000_000
#: Bytes of a band of float32 rows in the mask's and the background mesh's passes (at least one tile row).
_BAND_BYTES = 8_000_000


class _Bands:
    """The residual of a frame too large to hold whole, computed where a measurement needs it
    (:func:`startrack._kernels.centroid.residual_rows`, the same values to the bit as the whole residual's):
    windows around each candidate and star, bands of rows for the mask (:func:`_mask_in_bands`).

    A window starts on a multiple of the mesh tile (``cell``) on either axis, so the noise mesh's tiles from
    ``(y0 // cell, x0 // cell)`` on are the window's own.  Positions handed to a kernel on a window are
    ``x - x0, y - y0`` (exact: an integer taken from a coordinate at least as large), so its pixels' offsets
    from them are the same numbers; a fit's iterates, kept at a finer precision, differ in the last bits.
    """

    def __init__(self, image, level_mesh, cell):
        self.image = image
        self.level = np.ascontiguousarray(level_mesh, dtype=np.float64)
        self.cell = int(cell)
        self.shape = image.shape

    def rows(self, r0, r1, c0=0, c1=None):
        """The residual of rows ``r0:r1`` (and columns ``c0:c1``), float32."""
        from startrack._kernels.centroid import residual_rows

        c1 = self.shape[1] if c1 is None else c1
        return residual_rows(self.image, self.level, float(self.cell), int(r0), int(r1), int(c0), int(c1),
                             np.empty((r1 - r0, c1 - c0), dtype=np.float32))

    def window(self, x, y, reach):
        """``(y0, x0, tile)``: the residual of the rows and columns within ``reach`` of ``(x, y)`` (a position
        outside the frame is taken at its nearest pixel), from a multiple of the mesh tile on either axis."""
        h, w = self.shape
        cell = self.cell
        xc = min(max(x, 0.0), w - 1.0) if x == x else 0.0
        yc = min(max(y, 0.0), h - 1.0) if y == y else 0.0
        y0 = max(0, int(math.floor(yc)) - reach)
        x0 = max(0, int(math.floor(xc)) - reach)
        y0 -= y0 % cell
        x0 -= x0 % cell
        y1 = min(h, int(math.ceil(yc)) + reach + 2)
        x1 = min(w, int(math.ceil(xc)) + reach + 2)
        return y0, x0, self.rows(y0, y1, x0, x1)

    def measure(self, cand, psf_sigma, mesh, cell, out, fit):
        """:func:`_measure_gauss`'s fits ``fit(residual, cand, mesh, out)``, each candidate on a window of the
        residual that holds every pixel its fits read (and its aperture, else the aperture again on a window
        that holds it)."""
        from startrack._kernels.centroid import aperture_flux

        h, w = self.shape
        part = np.zeros((1, out.shape[1]))
        for k in range(len(cand)):
            sig = float(psf_sigma) if psf_sigma else max(0.5, min(float(cand[k, 2]), 5.0))
            half = int(max(2, math.ceil(3 * sig)))
            # The unweighted fit moves at most ``half`` from the candidate (else it is refused), its sigma at most
            # 4 half; the weighted fit's window is at most 3.5 times that: every fitted pixel within 15 half + 1.
            y0, x0, tile = self.window(cand[k, 0], cand[k, 1], 15 * half + 2)
            th, tw = tile.shape
            local = cand[k:k + 1].copy()
            local[0, 0] -= x0
            local[0, 1] -= y0
            part[:] = 0.0
            fit(tile, local, np.ascontiguousarray(mesh[y0 // cell:(y0 + th - 1) // cell + 1,
                                                       x0 // cell:(x0 + tw - 1) // cell + 1]), part)
            x, y = part[0, 0], part[0, 1]
            r = max(2.0, 3.0 * part[0, 2])
            if ((y0 > 0 and math.floor(y - r) < 0) or (y0 + th < h and math.ceil(y + r) + 1 > th)
                    or (x0 > 0 and math.floor(x - r) < 0) or (x0 + tw < w and math.ceil(x + r) + 1 > tw)):
                # The aperture (3 fitted sigmas) reached out of the window: sum it on a window that holds it.
                a, b, tile = self.window(x + x0, y + y0, int(math.ceil(r)) + 2)
                part[0, 9], part[0, 10] = aperture_flux(tile, x + x0 - b, y + y0 - a, r)
            part[0, 0] += x0
            part[0, 1] += y0
            out[k] = part[0]


#: The order keys (:func:`startrack._kernels.centroid.float32_key_range`) of ``+inf`` and ``-inf``: a key at or beyond
#: either is a pixel that is not finite.
_KEY_POS_INF = 0x7F800000
_KEY_NEG_INF = -0x7F800001


def _pixel_range(img):
    """``(smallest, largest)`` pixel of ``img`` as floats, both NaN when a pixel is NaN or infinite (as
    ``float(img.min()), float(img.max())``, whose NaN propagates, and an infinity is not finite either).  A
    C-contiguous float32 frame (every frame find_stars measures whole) in one pass of
    :func:`startrack._kernels.centroid.float32_key_range`; others by numpy."""
    if img.dtype != np.float32 or not img.flags.c_contiguous or img.size == 0:
        return float(img.min()), float(img.max())
    from startrack._kernels.centroid import float32_key_range

    lo, hi = float32_key_range(img.reshape(-1).view(np.int32))
    if hi >= _KEY_POS_INF or lo <= _KEY_NEG_INF:
        return math.nan, math.nan
    return _key_value(int(lo)), _key_value(int(hi))


def _key_value(key: int) -> float:
    """The float32 value (as a float) of an order key of :func:`startrack._kernels.centroid.float32_key_range`."""
    bits = key ^ ((key >> 31) & 0x7FFFFFFF)       # the flip undoes itself
    return _F32.unpack(_I32.pack(bits))[0]


#: find_stars takes a whole float32 frame's range from its background pass (False: from a pass of its own, as
#: other frames; the tests compare the two).
_FUSED_RANGE = True
_I32 = struct.Struct("<i")
_F32 = struct.Struct("<f")


def _banded(image, options) -> bool:
    """Whether :func:`find_stars` measures ``image`` in bands (:class:`_Bands`): a frame of at least
    :data:`_BAND_MIN_PIXELS` and a mesh background (at least 2 x 2 tiles)."""
    return (image.ndim == 2 and image.size >= _BAND_MIN_PIXELS and options.background == "mesh"
            and min(image.shape) >= 2 * options.mesh_px)


def warm_bands(image) -> None:
    """Run the band path (:class:`_Bands`) on ``image`` (a small frame suffices) as uint8, uint16 and float32,
    with and without the matched filter, so that its kernels are compiled in this process (before an
    ahead-of-time build of them: a large frame then needs no compiler)."""
    global _BAND_MIN_PIXELS
    saved, _BAND_MIN_PIXELS = _BAND_MIN_PIXELS, 0
    try:
        for dtype in (np.uint8, np.uint16, np.float32):
            frame = np.clip(image, 0, np.iinfo(dtype).max if dtype != np.float32 else None).astype(dtype)
            for deep in (False, True):
                find_stars(frame, CentroidOptions(matched_filter=deep))
    finally:
        _BAND_MIN_PIXELS = saved


def _mask_in_bands(image, level_mesh, thresh_mesh, cell, labels, foreground, row_counts, sigma_mesh, options):
    """:func:`_subtract_background` (and the matched filter's mask) band by band: the mask into ``labels``, the
    pixel-noise mesh (or None) returned, no residual kept.  The bands are whole tile rows, so the noise mesh is
    the whole pass's to the bit; the matched filter's band holds its kernel's half-width more rows on either
    side (the smoothed rows of the band's own are then the whole frame's)."""
    import cv2

    from startrack._kernels.centroid import residual_rows, subtract_background_rows

    h, w = labels.shape
    ny, nx = level_mesh.shape
    noise = options.method == "gauss" and cell * ny >= h and cell * nx >= w
    sig = np.ascontiguousarray(sigma_mesh, dtype=np.float64)
    out = np.empty_like(sig) if noise else np.empty((0, 0))
    level = np.ascontiguousarray(level_mesh, dtype=np.float64)
    thresh = np.ascontiguousarray(thresh_mesh, dtype=np.float64)
    pad = 0
    if options.matched_filter:
        k = max(3, int(2 * math.ceil(3 * options.filter_sigma_px) + 1))
        g1 = cv2.getGaussianKernel(k, options.filter_sigma_px)
        norm = float(np.sqrt(np.sum((g1 @ g1.T) ** 2))) if options.threshold_dn is None else 1.0
        pad = k // 2
        zeros, det_thresh = np.zeros(thresh.shape), np.ascontiguousarray(thresh * norm)
    step = cell * max(1, _BAND_BYTES // (4 * w * cell))
    # The band's buffers, made once (fresh pages for every band cost more than the pass).
    res_buf = np.empty((min(h, step + 2 * pad), w), dtype=np.float32)
    img_buf = None if image.dtype == np.float32 else np.empty_like(res_buf)
    det_buf = np.empty_like(res_buf) if options.matched_filter else None
    for r0 in range(0, h, step):
        r1 = min(h, r0 + step)
        a, b = max(0, r0 - pad), min(h, r1 + pad)
        if img_buf is None:
            band = image[a:b]
        else:
            band = img_buf[:b - a]
            band[...] = image[a:b]          # whole DN: the same values as float32
        res = res_buf[:b - a]
        subtract_background_rows(band, level, thresh, float(cell), res, labels, int(foreground), row_counts, r0, r1,
                                 sig, _CLIP_KAPPA, _CLIP_STD, out, a)
        if options.matched_filter:
            # The rows beyond the band's own, residual only (their mask is another band's).
            residual_rows(image, level, float(cell), a, r0, 0, w, res[:r0 - a])
            residual_rows(image, level, float(cell), r1, b, 0, w, res[r1 - a:])
            det = cv2.GaussianBlur(res, (k, k), options.filter_sigma_px, dst=det_buf[:b - a])
            band_thresh = det_thresh
            if options.threshold_dn is None:
                band_thresh = det_thresh * (_filtered_noise(res, det, norm) / norm)
            subtract_background_rows(det, zeros, band_thresh, float(cell), det, labels, int(foreground), row_counts,
                                     r0, r1, sig, _CLIP_KAPPA, _CLIP_STD, np.empty((0, 0)), a)
    return _noise_floor(out, sigma_mesh) if noise else None


#: The matched filter's measured noise counts (:func:`_filtered_noise`) when over this many times white noise's.
_WHITE_EXCESS = 1.2


def _filtered_noise(residual, smoothed, norm):
    """The matched filter's noise in units of a pixel's: the kernel's L2 norm ``norm`` when the residual's noise is
    white; measured (the smoothed residual's robust spread over the residual's) when that is larger.

    A background the mesh does not follow (daylight, cloud, a texture: structure a few pixels to a cell wide) is
    not white: the filter keeps it whole while the white-noise threshold drops by the norm (0.28 for a 1 px PSF),
    so that its bumps became hundreds of detections for the blind search to try (a daylight frame: 0 detections,
    then 51 through the filter, a 5 s search).  The spread is measured on ~8,000 pixels of each (a strided sample:
    a median's relative sampling error ~1.2 / sqrt(n), 1.3 % here against the 20 % excess that counts; 65,000 pixels
    cost ~3 ms a call, as much again as the rest of a 1024 x 768 frame's matched-filter detection).
    """
    step = max(1, int(math.sqrt(residual.size / 8192.0)))
    spread_a = _spread(residual[::step, ::step])
    if not spread_a > 0:        # a frame of one or two grey levels: no spread to compare with
        return norm
    spread_b = _spread(smoothed[::step, ::step])
    # White noise measures the norm within a few % (the spreads' sampling error on the ~8,000 pixels, or on a band's
    # few thousand): only a clear excess is structure, so that a white-noise frame's threshold, in bands or
    # whole, stays the norm's.
    measured = spread_b / spread_a
    return measured if measured > _WHITE_EXCESS * norm else norm


def _spread(sample) -> float:
    """The median absolute deviation from the median of ``sample`` (a copy is partitioned in place: ~5 times
    faster than ``np.median`` twice; the upper middle value of an even count, not the mean of the two)."""
    a = np.array(sample, dtype=np.float64).ravel()
    k = a.size // 2
    a.partition(k)
    np.subtract(a, a[k], out=a)
    np.abs(a, out=a)
    a.partition(k)
    return float(a[k])


def _workspace(shape, max_blobs, whole=True):
    """Per-thread buffers for one frame shape, reused across frames.

    A 1024 x 1024 frame needs ~8 MB of scratch (residual, labels, blob
    table, fill stack); allocating it afresh for every frame costs more
    in page faults than the labelling itself once the allocator has started
    returning large blocks to the system.  ``labels`` is all zero between calls.
    """
    ws = getattr(_WORKSPACE, "buffers", None)
    if ws is not None and whole != (ws["residual"] is not None):
        _WORKSPACE.buffers = ws = None      # let the other kind's buffers go before these are made
    if ws is None or ws["shape"] != shape or ws["table"].shape[0] < max_blobs + 1:
        h, w = shape
        # Labels in uint16 (max_blobs < 65535): 2 bytes a pixel, not 4, and they are the detection mask too
        # (``_FOREGROUND`` until labelled): 6 bytes a pixel with the residual (issue 41: an 8000 x 6000 frame's
        # scratch was 470 MB at 9 bytes a pixel).  The fill stack holds pixel indices: int32 below 2^31 pixels.
        ws = {"shape": shape, "residual": np.empty(shape, dtype=np.float32) if whole else None,
              "labels": np.zeros(shape, dtype=np.uint16 if max_blobs < 65535 else np.int32),
              "table": np.empty((max_blobs + 1, 16)), "row_counts": np.zeros(h, dtype=np.int64),
              "stack": np.empty(min(h * w, 4_000_000), dtype=np.int32 if h * w < 2**31 else np.int64)}
        _WORKSPACE.buffers = ws
    return ws


def find_stars(image: np.ndarray, options: CentroidOptions | None = None, saturation: float | None = None,
               source: str = "image") -> CentroidResult:
    """Detect and centroid the stars of one image.

    Parameters
    ----------
    image : ndarray (height, width)
        Pixel values in DN (any numeric dtype).
    options : CentroidOptions
    saturation : float, optional
        The DN at which a pixel is saturated (default: the largest DN a
        file of the image's type holds for uint8 and uint16 pixels, else
        none).  Below it, or without one, the frame's largest value is a
        clip when it makes a flat plateau (:data:`_CLIP_PLATEAU_PX` pixels
        at exactly that value in one blob); a lone largest pixel is not.
    source : str
        Name for messages.

    Returns
    -------
    CentroidResult
        ``stars``: list of dicts with ``x``, ``y``, ``flux``, ``peak``,
        ``npix``, ``snr``, ``noise_dn`` (background noise per pixel where the
        star lies), ``sigma_px`` (estimated 1-sigma uncertainty per
        axis), ``fwhm_px``, ``saturated``; brightest first.  With the
        ``gauss`` method, when the weighted fit converges: ``cov_px2`` (the
        fit's own 2 x 2 position covariance, the inverse of its information
        over the fitted pixels; ``sigma_px`` is then its per-axis RMS),
        ``fit_chi2`` and ``fit_dof`` (its weighted residual sum and degrees of
        freedom), and, when the gain is known, ``misfit: true`` when that
        chi-square's p-value is below ``options.misfit_p`` beyond the frame's
        own PSF mismatch (:func:`_flag_misfits`: a neighbour in the window, a
        cosmic ray, a distorted image; the position may be biased beyond
        ``cov_px2``).  An image where
        nothing can be found gives an empty list and a ``reason``.
    """
    from startrack._kernels.centroid import clear_labels, label_blobs_into

    options = options or CentroidOptions()
    t0 = time.perf_counter()
    image = np.asarray(image)
    banded = _banded(image, options)
    if image.dtype == np.float32 or (image.dtype in (np.uint8, np.uint16)
                                     and (banded or options.background != "tophat")):
        # A frame of whole DN stays as it is: no float copy.  The kernels read its pixels as float32 holds them
        # (exactly), so the residual, mask and background are the float copy's to the bit; the top-hat's
        # morphology alone needs the floats.
        img = np.ascontiguousarray(image)
    else:
        img = np.ascontiguousarray(image, dtype=np.float32)
    if img.ndim != 2 or img.size == 0:
        raise BadInputError(source, None, f"expected a 2-D image, got shape {img.shape}")
    params = dict(options.__dict__)     # every field is a scalar: a shallow copy is asdict's

    def result(stars, rejected, level, sigma, reason=None):
        return CentroidResult(stars, rejected, float(level), float(sigma), (time.perf_counter() - t0) * 1000.0,
                              reason, params)

    sat = options.saturation_dn if options.saturation_dn is not None else saturation
    if sat is None and image.dtype in (np.uint8, np.uint16):
        sat = float(np.iinfo(image.dtype).max)      # as an 8- or 16-bit file says (imageio.read_image): the CLI's
    # ~128 x 128 pixels of the frame, gathered once (each a cache line of its own): compared below with a level
    # or two, which on the strided view made numpy gather them again for each comparison.
    probe = np.ascontiguousarray(img[:: max(1, img.shape[0] // 128), :: max(1, img.shape[1] // 128)])
    given_sat = sat

    def levels(bottom, top, probe):
        """The frame's saturation level and what the range says before any search: ``(result or None, sat,
        inferred, frac_sat, span)``."""
        span = top - bottom
        if span <= 0 and (given_sat is None or top < given_sat):
            # One value everywhere (an array of zeros, a dark frame of one DN) carries no signal; it is saturated
            # only when that value reaches a saturation level given or read from the file.
            return result([], [], top, 0.0, "image is constant: no signal"), None, False, 0.0, span
        # Below the level given (or with none), the frame may still be clipped: a flat plateau at its largest value
        # (_clip_confirmed, after the labelling) is clipping on any sensor -- a 12-bit camera in 16-bit words, a
        # full well or an encoder below the type's range, pixels scaled or converted after the clip.  Until then the
        # largest value is the candidate level; every frame has a largest value, and a lone one is no clip.
        inferred = given_sat is None or top < given_sat
        level = top if inferred else given_sat
        # np.mean of the comparison: its count over the probe's size (the same division, without a float copy).
        frac_sat = (np.count_nonzero(probe >= level) / probe.size if probe.size else 0.0) if level > bottom else 1.0
        if frac_sat > 0.95:
            # Over 95 % saturated: daylight, a lens cap off in the sun.  A bright body over part of the frame (the
            # Moon, a lit building) leaves the rest to search.
            return (result([], [], float(np.median(probe)), 0.0, f"image is saturated ({100 * frac_sat:.0f}% of "
                           "pixels)"), level, inferred, frac_sat, span)
        return None, level, inferred, frac_sat, span

    integer = _is_integer_image(img)

    def background(det_img, bg_sat):
        """The background mesh (saturated pixels no data when ``bg_sat``), the detection threshold's and the mesh's
        tile size."""
        level_mesh, sigma_mesh, glevel, gsigma = estimate_background(det_img, options, bg_sat)
        sigma_mesh = np.maximum(sigma_mesh, max(gsigma, 1e-3) * 0.25)
        if options.threshold_dn is not None:
            thresh_mesh = np.full(level_mesh.shape, float(options.threshold_dn))
        else:
            # A pixel's noise: the background's normal sigma, and on whole DN the rounding's 1/12 DN^2 (the
            # whole noise of a frame whose pixels sit in one or two grey levels, where sigma is 0).
            thresh_mesh = options.threshold_sigma * np.sqrt(sigma_mesh**2 + (_QUANT_VAR if integer else 0.0))
        cell = options.mesh_px if level_mesh.shape != (1, 1) else max(img.shape)
        return level_mesh, sigma_mesh, glevel, gsigma, thresh_mesh, cell

    max_blobs = 20000
    ws = _workspace(img.shape, max_blobs, not banded)
    residual, labels, table = ws["residual"], ws["labels"], ws["table"]
    foreground = int(np.iinfo(labels.dtype).max)       # the mask: pixels to label (blob numbers <= max_blobs)
    counts = ws["row_counts"]
    # A whole float32 frame (no top-hat: the background pass reads the frame itself) has its range from that pass
    # (subtract_background_rows_keyed): one pass over the pixels fewer.  That pass needs the background first,
    # whose saturated pixels depend on the range: it is made with what the probe already tells (pixels at a
    # level given are saturated whatever the range), and made again in the one case the range changes that (no
    # level given or reached, and the probe holds the frame's largest value: saturated pixels at an inferred
    # level).  A frame with a pixel that is not finite takes the passes below instead.  The same numbers either way.
    fused = (_FUSED_RANGE and not banded and options.background != "tophat" and img.dtype == np.float32
             and img.flags.c_contiguous)
    if fused:
        guess = sat if sat is not None and probe.size and np.count_nonzero(probe >= sat) else None
        level_mesh, sigma_mesh, glevel, gsigma, thresh_mesh, cell = background(img, guess)
        keys = []
        noise_mesh = _subtract_background(img, level_mesh, thresh_mesh, cell, residual, labels, foreground, counts,
                                          sigma_mesh, options.method == "gauss", keys)
        lo, hi = min(k[0] for k in keys), max(k[1] for k in keys)
        if hi >= _KEY_POS_INF or lo <= _KEY_NEG_INF:
            fused = False           # NaN or infinite pixels: the passes below
            labels.fill(0)          # (which may return before writing the mask again)
        else:
            early, sat, inferred, frac_sat, span = levels(_key_value(int(lo)), _key_value(int(hi)), probe)
            if early is None:
                bg_sat = sat if frac_sat > 0 else None
                if bg_sat != guess:         # (a level or None; the range is finite here)
                    level_mesh, sigma_mesh, glevel, gsigma, thresh_mesh, cell = background(img, bg_sat)
                    if gsigma > 0 or span > 0:
                        noise_mesh = _subtract_background(img, level_mesh, thresh_mesh, cell, residual, labels,
                                                          foreground, counts, sigma_mesh, options.method == "gauss")
                if not gsigma > 0 and span <= 0:
                    early = result([], [], glevel, 0.0, "image is constant: no signal")
            if early is not None:
                labels.fill(0)          # the reused buffer is left as the next frame expects it
                return early
            det_img = img
    if not fused:
        # NaN (or infinite) pixels -- a dead region, a mosaic's gaps -- are no data: the levels of the rest.
        bottom, top = _pixel_range(img)      # NaN when a pixel is not finite
        if not (math.isfinite(bottom) and math.isfinite(top)):
            finite = img[np.isfinite(img)]
            if finite.size == 0:
                return result([], [], float("nan"), 0.0, "image is constant: no finite pixel value")
            bottom, top = float(finite.min()), float(finite.max())
            probe = probe[np.isfinite(probe)]
        early, sat, inferred, frac_sat, span = levels(bottom, top, probe)
        if early is not None:
            return early
        det_img = img
        if options.background == "tophat":
            det_img = _tophat(img, options)
        # Saturated pixels are no data for the background (only looked for when the probe saw some).
        level_mesh, sigma_mesh, glevel, gsigma, thresh_mesh, cell = background(
            det_img, sat if frac_sat > 0 and det_img is img else None)
        if not gsigma > 0 and span <= 0:
            return result([], [], glevel, 0.0, "image is constant: no signal")
    if banded:
        from startrack._kernels.centroid import label_blobs_lazy

        noise_mesh = _mask_in_bands(img, level_mesh, thresh_mesh, cell, labels, foreground, counts, sigma_mesh,
                                    options)
        residual = _Bands(img, level_mesh, cell)
        n_found = label_blobs_lazy(img, residual.level, float(cell), float(sat), max_blobs, labels, foreground,
                                   counts, table, ws["stack"])
        if inferred:
            _clip_confirmed(table, n_found, max_blobs)
        try:
            noise_mesh = sigma_mesh if noise_mesh is None else noise_mesh
            return _measure(img, residual, labels, table, n_found, max_blobs, options, noise_mesh, cell, glevel,
                            gsigma, result, thresh_mesh, integer)
        finally:
            if n_found > max_blobs:
                labels.fill(0)
            else:
                clear_labels(labels, table, n_found)
    if not fused:
        noise_mesh = _subtract_background(det_img, level_mesh, thresh_mesh, cell, residual, labels, foreground,
                                          counts, sigma_mesh, options.method == "gauss")
    if options.matched_filter:
        # (OpenCV only here: a frame measured without the matched filter never imports it, ~17 ms)
        import cv2

        # Detect on the residual smoothed by the PSF-sized Gaussian; the noise of
        # the filtered image is the pixel noise times the kernel's L2 norm.
        k = max(3, int(2 * math.ceil(3 * options.filter_sigma_px) + 1))
        det = cv2.GaussianBlur(residual, (k, k), options.filter_sigma_px)
        g1 = cv2.getGaussianKernel(k, options.filter_sigma_px)
        norm = float(np.sqrt(np.sum((g1 @ g1.T) ** 2))) if options.threshold_dn is None else 1.0
        if options.threshold_dn is None:
            norm = _filtered_noise(residual, det, norm)
        # The smoothed residual's level is 0 everywhere; its threshold follows the frame's own noise mesh.
        # The mask of the smoothed residual (its own level, 0, subtracted in place: the same values).
        _subtract_background(det, np.zeros(thresh_mesh.shape), thresh_mesh * norm, cell, det, labels, foreground,
                             counts, sigma_mesh, False)
    n_found = label_blobs_into(residual, img, float(sat), max_blobs, labels, foreground, counts, table, ws["stack"])
    if inferred:
        _clip_confirmed(table, n_found, max_blobs)
    try:
        noise_mesh = sigma_mesh if noise_mesh is None else noise_mesh
        return _measure(img, residual, labels, table, n_found, max_blobs, options, noise_mesh, cell, glevel, gsigma,
                        result, thresh_mesh, integer)
    finally:
        # Leave the reused label buffer zeroed for the next frame.
        if n_found > max_blobs:
            labels.fill(0)
        else:
            clear_labels(labels, table, n_found)


#: Pixels at exactly the frame's largest value, in one blob, that make a plateau: clipping (:func:`_clip_confirmed`).
#: One is every frame's brightest pixel; two are a whole-DN tie of a peak's top pixels; three or more pixels at
#: one value, the largest of the frame, are a flat top that no point-spread function has.
_CLIP_PLATEAU_PX = 3


def _clip_confirmed(table, n_found: int, max_blobs: int) -> None:
    """Keep the frame's largest value, the candidate saturation level of :func:`find_stars` when none is
    given (or the level given is above every pixel), only if it is a clip: a blob holds :data:`_CLIP_PLATEAU_PX`
    or more pixels at it (column 10 of the labelling's ``table``).  When not, the blobs' counts of saturated
    pixels are set to 0: no star is saturated (a noisy true peak is not clipped; calling it so kept a 33 deg
    photograph's Dubhe, its blob 3 times the point sources' width, as a star the CLI set apart).  Reads only
    the blob table: no pass over the pixels."""
    n = min(n_found, max_blobs)
    if n > 0 and float(table[1:n + 1, 10].max()) < _CLIP_PLATEAU_PX:
        table[1:n + 1, 10] = 0.0


#: A candidate's flux (its last entry, always > 0): candidates are sorted on it brightest first with
#: ``reverse=True``, which keeps equal ones in their order (as sorting on ``-flux`` does).
_CANDIDATE_FLUX = operator.itemgetter(7)


def _blob_budget(max_stars: int) -> int:
    """Blobs examined (classified, deblended) for ``max_stars`` stars: room for blends, duplicates and rejections."""
    return 4 * max_stars + 40


def _measure(img, residual, labels, table, n_found, max_blobs, options, sigma_mesh, cell, glevel, gsigma, result,
             thresh_mesh=None, integer=False):
    """Classify the labelled blobs, centroid the stars and build the result (:func:`find_stars`'s second half).

    ``integer``: the image holds whole DN, so every pixel's noise includes the rounding's
    1/12 DN^2 (on an 8-bit frame whose analogue noise is below a DN, the measured
    background noise is ~0 and the rounding is all the noise there is).
    """
    from startrack._kernels.centroid import aperture_flux, quine_offset, split_blob, windowed_centroid

    quant = _QUANT_VAR if integer else 0.0

    def sigma_at(x, y):
        x, y = min(max(x, 0), img.shape[1] - 1), min(max(y, 0), img.shape[0] - 1)
        n = float(sigma_mesh[min(int(y) // cell, sigma_mesh.shape[0] - 1), min(int(x) // cell, sigma_mesh.shape[1] - 1)])
        return math.sqrt(n * n + quant)

    def thresh_at(x, y):
        if thresh_mesh is None:
            return 0.0
        x, y = min(max(x, 0), img.shape[1] - 1), min(max(y, 0), img.shape[0] - 1)
        return float(thresh_mesh[min(int(y) // cell, thresh_mesh.shape[0] - 1),
                                 min(int(x) // cell, thresh_mesh.shape[1] - 1)])
    if n_found == 0:
        return result([], [], glevel, gsigma, "no pixel above the detection threshold")
    if n_found > max_blobs:
        return result([], [], glevel, gsigma,
                      f"over {max_blobs} detections: not a star field (noise or texture), or the threshold is too low")
    candidates = []
    rejected = []
    # One conversion of the blob table to Python floats (arithmetic on numpy scalars costs ~10x more).
    labs = np.arange(1, n_found + 1)
    if options.max_stars is not None and n_found > _blob_budget(options.max_stars):
        # Only the brightest blobs can give the max_stars brightest stars (a blend's pieces share its flux):
        # classify and deblend those, in label order, and leave the faint majority (noise peaks, a photo's
        # texture) unexamined.
        flux = table[1:n_found + 1, 0]
        keep = np.argpartition(-flux, _blob_budget(options.max_stars))[:_blob_budget(options.max_stars)]
        labs = np.sort(keep) + 1
    # The blobs' shape, and what each is, for all of them at once (numpy); the Python loop below visits only the
    # blobs that are not plain candidates (set aside, or tried for deblending).
    arr = table[labs, :16]
    flux, cx, cy, peak, npix, mxx, myy, mxy, nsat, ratio = (arr[:, k] for k in (0, 1, 2, 3, 6, 7, 8, 9, 10, 11))
    tr = mxx + myy
    disc = np.sqrt(np.maximum(tr * tr / 4 - (mxx * myy - mxy * mxy), 0.0))
    l2 = np.maximum(tr / 2 - disc, 1e-6)
    elong = np.sqrt((tr / 2 + disc) / l2)
    minor = np.sqrt(np.maximum(l2, 0.25))
    hot = (ratio >= options.hot_pixel_ratio) & (nsat == 0)
    plain = ((flux > 0) & (npix >= options.min_pixels) & (npix <= options.max_pixels) & ~hot
             & ~((elong > options.max_elongation) & (npix >= 8)))
    if options.deblend:
        plain &= ~((npix >= 6) & (elong > 1.35))
    # Most blobs of a frame are noise peaks below min_pixels that the loop below would drop without a record (all
    # but the hot pixels it reports): left out here, at once.  The plain candidates before each blob the loop
    # visits go in first, in label order, as before.
    silent = (flux <= 0) | ((npix < options.min_pixels) & ~((ratio >= options.hot_pixel_ratio) & (npix <= 2)
                                                            & (nsat == 0) & (peak > 0)))
    plain_at = np.flatnonzero(plain)
    visit = np.flatnonzero(~plain & ~silent)

    def rows_of(at):
        """The candidate tuples of the blobs ``at`` (indices into ``labs``)."""
        return list(zip(cx[at].tolist(), cy[at].tolist(), peak[at].tolist(), npix[at].tolist(), nsat[at].tolist(),
                        minor[at].tolist(), [False] * len(at), flux[at].tolist()))

    plain_only = rows_of(plain_at)
    visit_rows = rows_of(visit)
    peak_buf = np.empty((64, 2), dtype=np.int64)
    done = 0
    for k, before, own in zip(visit.tolist(), np.searchsorted(plain_at, visit).tolist(), visit_rows, strict=True):
        candidates.extend(plain_only[done:before])
        done = before
        row = arr[k].tolist()
        f, x, y, pk, px, py, n, _, _, _, ns, rt = row[:12]
        area = int(n)
        px, py = int(px), int(py)
        if f <= 0:
            continue
        if area < options.min_pixels:
            if rt >= options.hot_pixel_ratio and area <= 2 and ns == 0 and pk > 0:
                rejected.append({"x": float(px), "y": float(py), "flux": float(f), "reason": "hot pixel"})
            continue
        if area > options.max_pixels:
            rejected.append({"x": float(x), "y": float(y), "flux": float(f), "npix": area, "reason": "too large"})
            continue
        if rt >= options.hot_pixel_ratio and ns == 0:
            rejected.append({"x": float(px), "y": float(py), "flux": float(f), "reason": "hot pixel or cosmic ray"})
            continue
        e = float(elong[k])
        if options.deblend and area >= 6 and e > 1.35:
            left, top, bw, bh = int(row[12]), int(row[13]), int(row[14] - row[12] + 1), int(row[15] - row[13] + 1)
            if isinstance(residual, _Bands):
                # The blob's bounding box alone (split_blob reads nothing outside it): the same peaks.
                tile = residual.rows(top, top + bh, left, left + bw)
                n_peaks = split_blob(tile, np.ascontiguousarray(labels[top:top + bh, left:left + bw]), int(labs[k]),
                                     0, 0, bw, bh, 2.5, 0.7, peak_buf)
                peak_buf[:n_peaks] += (left, top)
                src, oy, ox = tile, top, left
            else:
                n_peaks = split_blob(residual, labels, int(labs[k]), left, top, bw, bh, 2.5, 0.7, peak_buf)
                src, oy, ox = residual, 0, 0
            if n_peaks >= 2:
                peaks = peak_buf[:n_peaks].tolist()
                for (qx, qy) in peaks:
                    candidates.append((float(qx), float(qy), float(src[qy - oy, qx - ox]), area / len(peaks), ns,
                                       own[5], True, f / len(peaks)))
                continue
        if e > options.max_elongation and area >= 8:
            rejected.append({"x": float(x), "y": float(y), "flux": float(f), "npix": area,
                             "elongation": e, "reason": "elongated (trail or extended object)"})
            continue
        candidates.append(own)
    candidates.extend(plain_only[done:])
    if options.max_stars is not None and len(candidates) > 3 * options.max_stars + 20:
        # Only the brightest blobs can be among the max_stars brightest stars: centroid those
        # (with room for duplicates and shape rejections) and skip the faint majority.
        candidates.sort(key=_CANDIDATE_FLUX, reverse=True)
        candidates = candidates[:3 * options.max_stars + 20]
    if options.star_likeness:
        candidates, wide = _extended_blobs(candidates)
        rejected.extend(wide)
    stars = []
    memo: dict = {}
    method = options.method
    if method == "gauss":
        stars = _measure_brightest(residual, candidates, options, sigma_mesh, cell, quant, memo)
        candidates = []
    h_img, w_img = img.shape
    # The other methods (com, iwc, quine) and the deblended peaks of a non-gauss frame, star by star.
    for (cx, cy, peak, npix, nsat, sig_est, deblended, _) in candidates:
        if not (math.isfinite(cx) and math.isfinite(cy) and math.isfinite(sig_est)):
            continue        # a blob of infinite pixels: no position, no star (as measure_candidates)
        sigma_psf = options.psf_sigma_px or max(0.5, min(sig_est, 5.0))
        half = int(max(2, math.ceil(3 * sigma_psf)))
        if isinstance(residual, _Bands):
            # A window of the residual holding every pixel read below (the windowed centroid moves at most
            # ``half``, its window ``half`` more, the aperture within ``half``); positions in it less its corner.
            oy, ox, res = residual.window(cx, cy, 3 * half + 4)
        else:
            oy, ox, res = 0, 0, residual
        x, y, ok = cx, cy, True
        xi, yi = int(round(cx)), int(round(cy))
        if deblended or method == "iwc":
            x, y, ok = windowed_centroid(res, cx - ox, cy - oy, sigma_psf, half, 30)
            x, y = x + ox, y + oy
        elif method == "quine":
            if 1 <= xi < w_img - 1 and 1 <= yi < h_img - 1:
                # peak pixel of the blob, then 3-pixel sums across the other axis
                win = res[yi - oy - 1:yi - oy + 2, xi - ox - 1:xi - ox + 2]
                colsum = win.sum(axis=0)
                rowsum = win.sum(axis=1)
                x = xi + quine_offset(colsum[0], colsum[1], colsum[2], sigma_psf)
                y = yi + quine_offset(rowsum[0], rowsum[1], rowsum[2], sigma_psf)
        if not ok:
            x, y = cx, cy
        # Aperture flux: the blob, or for deblended stars a 3-sigma aperture.
        r = max(2.0, 3.0 * sigma_psf)
        flux, n_ap = aperture_flux(res, x - ox, y - oy, r)
        noise = sigma_at(x, y)
        if flux <= 0:
            continue
        var = n_ap * noise**2 + (flux / options.gain_e_per_dn if options.gain_e_per_dn else 0.0)
        snr = flux / math.sqrt(var) if var > 0 else float("inf")
        star = {
            "x": float(x), "y": float(y), "flux": flux, "peak": float(peak), "npix": int(npix),
            "snr": float(snr), "sigma_px": _uncertainty(flux, sigma_psf, noise, options.gain_e_per_dn),
            "fwhm_px": 2.3548 * sigma_psf, "noise_dn": float(noise), "saturated": bool(nsat > 0),
            "_nsat": int(nsat), **({"deblended": True} if deblended else {}),
        }
        if method == "com" and not deblended:
            # The thresholded COM's own error model: pixel phase (truncation, rounding) and propagated noise.
            star["sigma_px"] = _com_uncertainty(flux, peak, sig_est, options.psf_sigma_px, thresh_at(x, y), noise,
                                                options.gain_e_per_dn, integer, nsat > 0)
        stars.append(star)
    if options.gain_e_per_dn:
        # Without the gain the weights lack the stars' shot noise and chi-square cannot test the model.
        _flag_misfits(stars, options.misfit_p)
    stars.sort(key=lambda s: -s["flux"])
    # The last probe of _measure_brightest saw these very stars in this order: its results stand (the misfit
    # flags set since are not read by either).
    same = memo.get("ids") == [id(s_) for s_ in stars]
    stars = memo["unique"] if same else _unique(stars)
    if options.star_likeness:
        stars, unlike = memo["likeness"] if same else _star_likeness(stars, residual)
        rejected.extend(unlike)
    for s_ in stars:
        del s_["_nsat"]
    if options.max_fwhm_ratio is not None:
        stars, wide = _by_shape(stars, options.max_fwhm_ratio)
        rejected.extend(wide)
    if options.max_stars is not None:
        stars = stars[: options.max_stars]
    reason = None if stars else "no star-like detection (all rejected)"
    return result(stars, rejected, glevel, gsigma, reason)


def _extended_blobs(candidates: list):
    """Set apart, before any fit, the blobs that two independent widths both call extended: ``(candidates,
    rejected)``.

    For a point source of PSF sigma ``s`` the peak pixel holds ``~F / (2 pi s^2)`` of
    the flux, so ``sqrt(F / (2 pi peak))`` reads ``s`` (less for a faint blob, whose
    thresholded flux is short); the second moments of its thresholded pixels
    read at most ``s`` across their minor axis.  The frame's point-source sigma
    ``s0`` is the centre of the shortest half of the first width over the 30
    brightest unsaturated, unblended blobs (:func:`_shorth_centre`: stars, even
    when half of them are not).  A blob whose first width exceeds ``3 s0`` and
    whose minor-axis moment exceeds ``2 s0`` (and a blend's pieces, when the
    blend's minor-axis moment exceeds ``3 s0``) is an extended object, nebula or
    a foreground body's piece: its fit, whose window grows with it, would cost
    ten times a star's and :func:`_star_likeness` would set it apart after.
    Saturated blobs are left to :func:`_star_likeness`.
    """
    widths = [math.sqrt(c[7] / (2.0 * math.pi * c[2])) for c in sorted(candidates, key=_CANDIDATE_FLUX, reverse=True)
              if not c[6] and c[4] == 0 and c[2] > 0][:30]
    if len(widths) < 5:
        return candidates, []
    s0 = math.exp(_shorth_centre(np.log(widths)))
    keep, out = [], []
    for c in candidates:
        cx, cy, peak, _, nsat, minor, deblended, flux = c
        if nsat == 0 and ((deblended and minor > 3.0 * s0) or (not deblended and peak > 0 and minor > 2.0 * s0
                                                                 and flux > 9.0 * 2.0 * math.pi * peak * s0 * s0)):
            out.append({"x": cx, "y": cy, "flux": flux, "reason": f"wider than the point-spread function (blob "
                        f"sigma {minor:.1f} px, the point sources' {s0:.1f} px)"})
        else:
            keep.append(c)
    return keep, out


def _measure_brightest(residual, candidates, options, noise_mesh, cell, quant_var, memo=None):
    """:func:`_measure_gauss` of the candidates, brightest blob first: ``max_stars + 10`` of them, then
    batches of half as many until ``max_stars`` distinct star-like detections are in hand (all of them
    without ``max_stars``).

    The fit is most of find_stars' time; a frame of many blobs (a photograph's texture, noise) is fitted
    only as deep as its brightest stars need.  ``memo`` (a dict) receives the last probe: the identities of
    the stars it sorted, and what :func:`_unique` and :func:`_star_likeness` made of them, which the caller
    reuses when it is given the same stars in the same order (no batch fitted after the probe).
    """
    if options.max_stars is None:
        return _measure_gauss(residual, candidates, options, noise_mesh, cell, quant_var)
    candidates = sorted(candidates, key=_CANDIDATE_FLUX, reverse=True)
    first = options.max_stars + 10
    stars = _measure_gauss(residual, candidates[:first], options, noise_mesh, cell, quant_var)
    batch = first // 2
    for i in range(first, len(candidates), batch):
        ordered = sorted(stars, key=lambda s_: -s_["flux"])
        probe = _unique(ordered)
        liked = _star_likeness(probe, residual) if options.star_likeness else None
        if memo is not None:
            memo.update(ids=[id(s_) for s_ in ordered], unique=probe, likeness=liked)
        if len(probe if liked is None else liked[0]) >= options.max_stars:
            break
        stars += _measure_gauss(residual, candidates[i:i + batch], options, noise_mesh, cell, quant_var)
    return stars


#: Candidates a thread of :func:`_measure_gauss` gets at least (a fit takes ~10 us; handing work to a thread ~50),
#: and in one chunk.
_FITS_PER_THREAD = 16
_FITS_PER_CHUNK = 8


def _measure_gauss(residual, candidates, options, noise_mesh, cell, quant_var):
    """The stars of ``candidates`` with the ``gauss`` method: every fit in one kernel call
    (:func:`startrack._kernels.psf_fit.measure_candidates`), then the records."""
    from startrack._kernels.psf_fit import measure_candidates

    if not candidates:
        return []
    cand = np.array([(c[0], c[1], c[5], 1.0 if c[6] else 0.0) for c in candidates], dtype=np.float64)
    out = np.zeros((len(candidates), 12))
    inv_g = 1.0 / options.gain_e_per_dn if options.gain_e_per_dn else 0.0
    mesh = np.ascontiguousarray(noise_mesh, dtype=np.float64)

    def fit(res, cand, mesh, out):
        args = (float(options.psf_sigma_px or 0.0), mesh, int(cell), float(quant_var), inv_g)
        n_threads = min(threads(), len(cand) // _FITS_PER_THREAD)
        if n_threads > 1:
            # Each fit is independent: chunks of _FITS_PER_CHUNK candidates, to whichever thread is free.
            kernel = measure_candidates.resolve((res, cand, *args, out))
            cuts = list(range(0, len(cand), _FITS_PER_CHUNK)) + [len(cand)]
            _run_chunks(lambda i: kernel(res, cand[cuts[i]:cuts[i + 1]], *args, out[cuts[i]:cuts[i + 1]]),
                        len(cuts) - 1, n_threads)
        else:
            measure_candidates(res, cand, *args, out)

    if not isinstance(residual, _Bands):
        fit(residual, cand, mesh, out)
    else:
        residual.measure(cand, options.psf_sigma_px, mesh, cell, out, fit)
    gain = options.gain_e_per_dn
    stars = []
    for (_, _, peak, npix, nsat, _, deblended, _), row in zip(candidates, out.tolist(), strict=True):
        x, y, sigma_psf, fitted, cxx, cxy, cyy, chi2, n_pix, flux, n_ap, noise = row
        if flux <= 0:
            continue
        var = n_ap * noise**2 + (flux / gain if gain else 0.0)
        snr = flux / math.sqrt(var) if var > 0 else float("inf")
        star = {
            "x": x, "y": y, "flux": flux, "peak": float(peak), "npix": int(npix),
            "snr": float(snr), "sigma_px": math.sqrt(0.5 * (cxx + cyy)) if fitted else _uncertainty(flux, sigma_psf,
                                                                                                  noise, gain),
            "fwhm_px": 2.3548 * sigma_psf, "noise_dn": noise, "saturated": bool(nsat > 0), "_nsat": int(nsat),
        }
        if deblended:
            star["deblended"] = True
        if fitted:
            # The weighted fit's own covariance is the estimate's sigma (issue 21); its chi-square tests the model.
            star["cov_px2"] = [[cxx, cxy], [cxy, cyy]]
            star["fit_chi2"] = chi2
            star["fit_dof"] = int(n_pix - 5)
        stars.append(star)
    return stars


def _unique(stars: list) -> list:
    """Drop a detection within 1.5 px (or half its FWHM) of a brighter one: two peaks of one blob that converged."""
    from startrack._kernels.centroid import unique_positions

    if not stars:
        return []
    xs = np.array([s_["x"] for s_ in stars], dtype=np.float64)
    ys = np.array([s_["y"] for s_ in stars], dtype=np.float64)
    radii = np.array([max(1.5, 0.5 * s_.get("fwhm_px", 0.0)) for s_ in stars], dtype=np.float64)
    keep = unique_positions(xs, ys, radii, np.empty(len(stars), dtype=np.bool_))
    return [s_ for s_, k in zip(stars, keep.tolist()) if k]


#: The point-spread function's width is taken from at most this many of the frame's best stars.
_PSF_STARS = 60
#: Fits that ended at the Gaussian fit's smallest sigma (0.2 px) measured no width: not in the PSF's sample.
_FWHM_FLOOR = 2.3548 * 0.2 * 1.05


def _shorth_centre(values) -> float:
    """The middle of the shortest interval holding half of ``values``: a location that up to half of them,
    on either side, cannot move (foreground blobs, hot pixels)."""
    v = np.sort(np.asarray(values, dtype=np.float64))
    h = (len(v) + 1) // 2
    widths = v[h - 1:] - v[:len(v) - h + 1]
    i = int(np.argmin(widths))
    return _median(v[i:i + h])


def frame_psf(stars: list):
    """The frame's point-spread function from its best stars: ``(fwhm_px, relative spread)``, or ``None``.

    The best stars are the unsaturated, fitted detections of SNR >= 10 whose fit
    did not end at its smallest width (at most
    :data:`_PSF_STARS`, highest SNR first); at least 5 are needed.  The width is
    the centre of the shortest half of their log FWHMs (:func:`_shorth_centre`):
    a frame whose brightest detections are half foreground blobs still reads
    its stars' width; the spread is 1.4826 MAD of the log widths about it (the
    PSF's own variation over the field and the fits' noise).
    """
    best = sorted((s_ for s_ in stars if not s_["saturated"] and "cov_px2" in s_ and s_["snr"] >= 10
                   and s_["fwhm_px"] > _FWHM_FLOOR), key=lambda s_: -s_["snr"])[:_PSF_STARS]
    if len(best) < 5:
        return None
    logs = np.log([s_["fwhm_px"] for s_ in best])
    centre = _shorth_centre(logs)
    spread = 1.4826 * _median(np.abs(logs - centre))
    return math.exp(centre), spread


def _star_likeness(stars: list, residual):
    """Set apart the detections that are not point sources of the frame's own PSF: ``(stars, rejected)``.

    Each detection is held against :func:`frame_psf` (when the frame has five
    good stars to measure it from):

    - **wider** than the PSF by more than ``max(2, exp(5 spread))`` times (an
      extended blob, a piece of a foreground body, a galaxy, a defocused
      reflection: a star is never twice as wide as the frame's other stars
      unless the PSF varies that much over the field, which the spread measures);
    - **sharper** than half the PSF's width, when the PSF is resolved (FWHM >= 2
      px) and the detection is unsaturated with SNR >= 10 (a hot pixel, a cosmic
      ray: light that did not come through the optics);
    - **saturated over more than a disc of 3 FWHM radius** (a flat-topped
      foreground body or bloom: a Gaussian star would need a peak e^25 times the
      saturation level);
    - **centred outside the image** (a fit that ran off the edge).  A star cut by
      the border is kept: the fit models the pixels that are there and its
      sigma says what the cut costs (setting such stars apart lost 1 % of the
      catalog stars of paper 000's 752 x 480 frames, and 4 of 300 frames'
      identifications);
    - **on an extended structure**: the median residual in the annulus from 2
      to 4 FWHM around it (at least 3 to 6 px) is above half its own peak and
      twice the pixel noise: a point source stands out of its surroundings by
      more than they stand out of the background (a star on a nebula's glow is
      fitted with its local level); a bump on a lit edge, a nebula's knot or a
      body's limb does not.

    The set-aside detections keep ``x``, ``y``, ``flux``, ``fwhm_px`` and the
    ``reason``.
    """
    from startrack._kernels.centroid import annulus_medians

    psf = frame_psf(stars)
    if psf is None or not stars:
        return stars, []
    fwhm, spread = psf
    h, w = residual.shape
    wide = fwhm * max(2.0, math.exp(5.0 * spread))
    r_in = max(3.0, 2.0 * fwhm)
    r_out = max(r_in + 3.0, 4.0 * fwhm)
    xs = np.array([s_["x"] for s_ in stars])
    ys = np.array([s_["y"] for s_ in stars])
    around = np.empty(len(stars))
    if isinstance(residual, _Bands):
        one = np.empty(1)
        for k in range(len(stars)):
            y0, x0, tile = residual.window(xs[k], ys[k], int(math.ceil(r_out)) + 1)
            around[k] = annulus_medians(tile, xs[k:k + 1] - x0, ys[k:k + 1] - y0, r_in, r_out, one)[0]
    else:
        annulus_medians(residual, xs, ys, r_in, r_out, around)
    around = around.tolist()
    sat_area = math.pi * (3.0 * fwhm) ** 2
    keep, out = [], []
    for s_, ring in zip(stars, around):
        x, y, f = s_["x"], s_["y"], s_["fwhm_px"]
        reason = None
        if s_["_nsat"] > sat_area:
            reason = f"saturated over {s_['_nsat']} px, wider than any star (a foreground body or bloom)"
        elif not s_["saturated"] and f > wide:
            reason = f"wider than the point-spread function (FWHM {f:.1f} px, the stars' {fwhm:.1f} px)"
        elif not s_["saturated"] and fwhm >= 2.0 and s_["snr"] >= 10 and f < 0.5 * fwhm:
            reason = f"sharper than the point-spread function (FWHM {f:.1f} px, the stars' {fwhm:.1f} px): " \
                     "a hot pixel or cosmic ray"
        elif min(x + 0.5, y + 0.5, w - 0.5 - x, h - 0.5 - y) < 0.0:
            reason = "centred outside the image"
        elif ring == ring and ring > 0.5 * s_["peak"] and ring > 2.0 * s_["noise_dn"]:
            reason = f"on an extended structure (its surroundings at {ring / s_['peak']:.0%} of its peak)"
        if reason is None:
            keep.append(s_)
        else:
            out.append({"x": x, "y": y, "flux": s_["flux"], "fwhm_px": f, "reason": reason})
    return keep, out


def _by_shape(stars: list, max_ratio: float):
    """Keep point sources: FWHM within ``max_ratio`` of the median FWHM of the unsaturated stars.

    Nebula knots, galaxies, comets' comae and out-of-focus blobs are wider than
    the stars of the same image; saturated stars are wider too but kept (their
    width says nothing about their nature).
    """
    widths = [s_["fwhm_px"] for s_ in stars[:60] if not s_["saturated"]]
    if len(widths) < 5:
        return stars, []
    med = _median(widths)
    keep, out = [], []
    for s_ in stars:
        if s_["saturated"] or s_["fwhm_px"] <= max_ratio * med:
            keep.append(s_)
        else:
            out.append({"x": s_["x"], "y": s_["y"], "flux": s_["flux"], "fwhm_px": s_["fwhm_px"],
                        "reason": f"wider than a star (FWHM {s_['fwhm_px']:.1f} px, median {med:.1f} px)"})
    return keep, out


def centroid_windows(image: np.ndarray, centres, half_size: int, options: CentroidOptions | None = None,
                     saturation: float | None = None):
    """Centroid only inside square windows around predicted positions (tracking mode).

    Parameters
    ----------
    image : ndarray (height, width)
    centres : array_like (n, 2)
        Predicted ``(x, y)`` in pixels.
    half_size : int
        Window half-width in pixels (the window is ``2 half + 1`` wide).

    Returns
    -------
    list of dict or None
        For each window, the brightest star-like blob inside it (same fields
        as :func:`find_stars`, plus ``window``) or ``None`` when nothing was
        found.  The background is the normal core of the window's border.
    """
    from startrack._kernels.background import core_stats_of_sorted

    options = options or CentroidOptions()
    img = np.asarray(image, dtype=np.float32)
    h, w = img.shape
    out = []
    for px, py in np.asarray(centres, dtype=np.float64).reshape(-1, 2):
        if not (np.isfinite(px) and np.isfinite(py)):
            out.append(None)
            continue
        xi, yi = int(round(px)), int(round(py))
        x0, x1 = max(0, xi - half_size), min(w, xi + half_size + 1)
        y0, y1 = max(0, yi - half_size), min(h, yi + half_size + 1)
        if x1 - x0 < 5 or y1 - y0 < 5:
            out.append(None)
            continue
        sub = img[y0:y1, x0:x1]
        border = np.concatenate([sub[0], sub[-1], sub[1:-1, 0], sub[1:-1, -1]]).astype(np.float64)
        border = np.sort(border[np.isfinite(border)])
        level, sigma = core_stats_of_sorted(border) if border.size else (0.0, 0.0)
        opts = CentroidOptions(**{**asdict(options), "background": "global", "max_stars": None})
        res = find_stars(sub - level + 0.0, opts, saturation=(saturation - level) if saturation else None)
        if not res.stars:
            out.append(None)
            continue
        best = dict(res.stars[0])
        best["x"] += x0
        best["y"] += y0
        best["window"] = [x0, y0, x1 - 1, y1 - 1]
        out.append(best)
    return out
