"""Brightness-referenced identification (Zhang, Zhao, Liu & Liu 2014; paper 003 Sec. 4).

The star-pair catalog keeps each pair's brighter star first (Sec. 4.2.1, Eq. 10), so the
measured brightness order of two image stars halves the candidates when their intensities
differ by more than ``gamma`` (in magnitudes).  Here the catalog is held oriented and
banded by magnitude, each segment with its own k-vector (Eqs. 11-12;
:func:`pair_bands`), so that a look-up (Eqs. 13-14) searches only the segments the
brightness allows: the scope narrowing that is the method's claim
(:mod:`startrack._kernels.brightness`).

Eq. 9, ``In_m = In_k 2.512^(k - m)``, with ``In_k`` the intensity of a star of catalog
magnitude ``k``, calibrates intensity to magnitude.  The paper obtains ``In_k`` "by
averaging the intensity values of an identified bright star in different images": here
the calibration is given (``brightness_calibration = "k:In_k"``, e.g. from
:func:`intensity_calibration` over identified frames).  With it, ``M_t = In_k 2.512^(k -
3)`` is the intensity of a magnitude-3 star and the reference-star (three-star) mode runs
while the frame's brightest remaining star is above it (Sec. 4.3.1, Fig. 5); otherwise,
and always without a calibration (``M_t`` is then unknown), the four-star mode runs
(Sec. 4.3.2).  Every proposal reports the calibration its brightest identified star
implies (``details["calibration"]``), so identified frames calibrate the next ones.

Confidence: the shared verification's false-match probability counts the magnitude
agreement of the proposal's stars here as for every algorithm.  The brightness order only
filters geometric candidates; the pattern chance it multiplies is the geometric one
(every catalog pattern of that shape, whatever its brightness), so the magnitude factor
is the chance that a geometric coincidence also agrees in brightness, not a second count
of the same evidence.  (Leaving it out refused true four-star frames at 1 px noise and
with false stars: "false-match probability 2.5e-05 above the limit".)
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field

import numpy as np

from startrack.identify.algorithm import Algorithm, Proposal

BAND_WIDTH_MAG = 0.5    # magnitude bands of the oriented pair catalog fainter than the reference stars


@dataclass(frozen=True)
class BrightnessConfig:
    """Settings of the brightness-referenced search (paper 003 Sec. 4.3)."""

    gamma_mag: float = field(default=0.6, metadata={
        "help": "Brightness difference (mag) beyond which a pair's order must match the catalog's."})
    reference_mag: float = field(default=3.0, metadata={
        "help": "Reference-star mode for stars brighter than this magnitude (M_t of Eq. 9)."})
    brightness_calibration: str = field(default="", metadata={
        "help": "Eq. 9 calibration 'K:IN_K': the intensity IN_K (flux units) of a star of catalog magnitude K; "
                "without it only the four-star mode runs."})
    mag_window: float = field(default=0.0, metadata={
        "help": "Four-star mode: limit the brightest star's candidates to its calibrated magnitude +- this "
                "(0: the paper's brightness order only)."})
    max_loops: int = field(default=10000, metadata={
        "help": "Loops of the Fig. 5-6 search before giving up (10000 covers every four-star group of 20 stars; "
                "the driver's budget still applies)."})


def parse_calibration(text: str):
    """``"k:In_k"`` -> ``(k, In_k)`` (None for an empty string); ``BadInputError`` naming the setting."""
    if not text:
        return None
    from startrack.errors import BadInputError

    try:
        k, in_k = (float(v) for v in str(text).split(":"))
    except ValueError:
        raise BadInputError("brightness_calibration", None,
                            f"expected 'K:IN_K' (magnitude:intensity), got {text!r}") from None
    if not (math.isfinite(k) and math.isfinite(in_k) and in_k > 0):
        raise BadInputError("brightness_calibration", None, f"needs a finite magnitude and a positive intensity, "
                                                            f"got {text!r}")
    return k, in_k


def magnitudes(flux, calibration):
    """Eq. 9 inverted: catalog magnitudes ``k - log_2.512(In / In_k)`` of intensities ``flux``."""
    k, in_k = calibration
    return k - np.log(np.asarray(flux, dtype=np.float64) / in_k) / math.log(2.512)


def intensity_calibration(samples, k: float = 3.0):
    """Eq. 9's ``(k, In_k)`` from identified stars: the mean of ``In 2.512^(m - k)``.

    ``samples`` are ``(catalog magnitude, intensity)`` of identified stars, one per frame
    (the paper averages "an identified bright star in different images").  ``k`` is
    where the calibration is stated (the reference magnitude by default).
    """
    s = np.asarray(samples, dtype=np.float64).reshape(-1, 2)
    s = s[np.isfinite(s).all(axis=1) & (s[:, 1] > 0)]
    if len(s) == 0:
        return None
    return float(k), float(np.mean(s[:, 1] * 2.512 ** (s[:, 0] - k)))


@dataclass
class PairBands:
    """The oriented, magnitude-banded star-pair catalog of :mod:`startrack._kernels.brightness`."""

    ent_x: np.ndarray
    ent_y: np.ndarray
    ent_cos: np.ndarray
    seg_ptr: np.ndarray
    kv_ptr: np.ndarray
    kv_all: np.ndarray
    seg_line: np.ndarray
    band_lo: np.ndarray
    band_hi: np.ndarray

    def kernel_args(self):
        return (self.ent_x, self.ent_y, self.ent_cos, self.seg_ptr, self.kv_ptr, self.kv_all, self.seg_line,
                self.band_lo, self.band_hi)


def pair_bands(db, ref_mag: float = 3.0, band_w: float = BAND_WIDTH_MAG) -> PairBands:
    """Eq. 10's star-pair catalog of ``db`` oriented and banded (built once per database, cached on it).

    Each pair ``(I, J)`` (``I`` the brighter) gives the entry ``(I, J)`` on side 0 and
    ``(J, I)`` on side 1; entries are grouped by (side, magnitude band of their first
    star), sorted by cosine within a group, and each group gets Mortari's k-vector
    (Eqs. 11-12).  The first band holds every star brighter than ``ref_mag``: side 0 of
    it is the reference stars' pair sub-catalog of Sec. 4.3.1 (``B_I`` < 3); the others
    are ``band_w`` wide from ``ref_mag`` on (for the magnitude window).  Few, full
    segments keep the k-vector's overshoot (an entry or two per segment searched) small.
    """
    cache = db.__dict__.setdefault("_brightness_bands", {})
    key = (float(ref_mag), float(band_w))
    if key in cache:
        return cache[key]
    from startrack.kvector import _kvector_line

    mag = np.asarray(db.star_mag, dtype=np.float64)
    a, b, c = np.asarray(db.pair_i), np.asarray(db.pair_j), np.asarray(db.pair_cos, dtype=np.float64)
    a_bright = mag[a] <= mag[b]
    big = np.where(a_bright, a, b)          # I of Eq. 10
    small = np.where(a_bright, b, a)        # J
    x = np.concatenate([big, small])
    y = np.concatenate([small, big])
    side = np.concatenate([np.zeros(len(c), np.int64), np.ones(len(c), np.int64)])
    cos = np.concatenate([c, c])
    top = float(mag.max()) if len(mag) else ref_mag
    nb = 1 + max(0, int(math.ceil((top - ref_mag) / band_w)))
    band_lo = np.concatenate([[-np.inf], ref_mag + band_w * np.arange(nb - 1, dtype=np.float64)])
    band_hi = np.concatenate([band_lo[1:], [np.inf]])
    band = np.clip(np.searchsorted(band_lo, mag[x], side="right") - 1, 0, nb - 1).astype(np.int64)
    seg = side * nb + band
    order = np.lexsort((cos, seg))
    x, y, cos, seg = x[order], y[order], cos[order], seg[order]
    seg_ptr = np.searchsorted(seg, np.arange(2 * nb + 1)).astype(np.int64)
    kvs, lines = [], np.zeros((2 * nb, 2))
    for g in range(2 * nb):
        vals = cos[seg_ptr[g]:seg_ptr[g + 1]]
        if len(vals):
            kv, line = _kvector_line(vals)
        else:
            kv, line = np.zeros(1, np.int64), (1.0, 0.0)
        kvs.append(np.asarray(kv, dtype=np.int64))
        lines[g] = line
    kv_ptr = np.concatenate([[0], np.cumsum([len(k) for k in kvs])]).astype(np.int64)
    out = PairBands(np.ascontiguousarray(x, np.int64), np.ascontiguousarray(y, np.int64), np.ascontiguousarray(cos),
                    seg_ptr, kv_ptr, np.concatenate(kvs).astype(np.int64), lines, band_lo, band_hi)
    cache[key] = out
    return out


@functools.lru_cache(maxsize=64)
def _calibration(text: str):
    return parse_calibration(text)


def search_brightness(ctx, config: BrightnessConfig):
    """Paper 003's Fig. 5-6 loops: each unique match in turn, continuing after one the verification rejects.

    Each proposal's ``details``: ``mode``, ``scope`` (oriented pair entries examined so
    far, Eqs. 13-14 on the narrowed ranges), ``scope_unnarrowed`` (the entries the whole
    catalog's k-vector ranges of the same look-ups hold), ``calibration`` (``k:In_k`` of
    its brightest star, Eq. 9).
    """
    from startrack._kernels.brightness import brightness_search

    db = ctx.db
    fo = np.array(ctx.flux if ctx.flux is not None else np.zeros(len(ctx.b)), dtype=np.float64)
    fo[~(fo > 1e-12)] = 1e-12                       # missing (NaN) or non-positive: the faintest
    if np.all(fo[:-1] >= fo[1:]):
        order = np.arange(len(fo))                  # brightest first already (as centroid writes them)
    else:
        order = np.argsort(-fo, kind="stable")
        fo = fo[order]
    inst = -2.5 * np.log10(fo)
    ref_mag = float(config.reference_mag)
    cal = _calibration(config.brightness_calibration)
    if cal is not None:
        k, in_k = cal
        m_t = in_k * 2.512 ** (k - ref_mag)       # Eq. 9: the intensity of a magnitude-M_t star
        ref_ok = fo > m_t
        est = magnitudes(fo, cal)
    else:
        ref_ok = np.zeros(len(fo), dtype=np.bool_)
        est = np.full(len(fo), np.nan)
    bands = pair_bands(db, ref_mag)
    bo = np.ascontiguousarray(ctx.b[order])
    scope = np.zeros(2, dtype=np.int64)
    loops = 0
    line = db.__dict__.get("_line_array")
    if line is None:
        line = db.__dict__["_line_array"] = np.asarray(db.line, dtype=np.float64)
    args = (db.star_vector, db.star_mag, *bands.kernel_args(), db.kvector, line, float(ctx.eps),
            float(config.gamma_mag), ref_mag, float(config.mag_window), int(config.max_loops))
    while True:
        mode, idx, cat, loops = brightness_search(bo, inst, est, ref_ok, *args, int(loops), scope)
        if mode == 0:
            return
        keep = [t for t in range(4) if idx[t] >= 0]
        first = min(keep, key=lambda t: idx[t])     # the brightest star of the proposal
        in_ref = float(fo[idx[first]]) * 2.512 ** (float(db.star_mag[cat[first]]) - ref_mag)
        yield Proposal([int(order[idx[t]]) for t in keep], [int(cat[t]) for t in keep], int(loops),
                       {"mode": _MODES[int(mode)], "scope": int(scope[0]), "scope_unnarrowed": int(scope[1]),
                        "calibration": f"{ref_mag:g}:{in_ref:.6g}"})


_MODES = {1: "reference-star", 2: "four-star", 3: "triangle"}


BRIGHTNESS = Algorithm("brightness", search_brightness, BrightnessConfig, "kvector",
                       "Paper 003's brightness-referenced search on the k-vector pair database.",
                       focal_sweep=True)
