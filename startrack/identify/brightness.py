"""Brightness-referenced identification (Zhang, Zhao, Liu & Liu 2014; paper 003 Sec. 4).

The star-pair catalog keeps each pair's brighter star first (Sec. 4.2.1), so
the measured brightness order of two image stars halves the candidates when
their intensities differ by more than ``gamma`` (in magnitudes).  When the
brightest image star is brighter than ``M_t`` (magnitude 3), the reference
(three-star) mode searches only pairs whose brighter star is brighter than
magnitude 3 (165 stars in the Hipparcos catalog, Table 2); otherwise the
four-star mode runs.  The loop orders follow Fig. 5 (kernel
:func:`startrack._kernels.identify.brightness_search`).

The intensity-magnitude relation (Eq. 9, ``In_m = In_k 2.512^(k - m)``) is
estimated from the frame itself: the database's faintest magnitude is the
detection limit, so the faintest quarter of the frame's stars sits near it;
``In_k`` is their median intensity with ``k`` the median magnitude of the
faintest quarter of the catalog stars expected in such a field.  ``M_t`` is then
``In_k 2.512^(k - 3)``.  A wrong estimate only costs speed: the reference mode
finds nothing and the four-star mode runs.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from startrack.identify.base import Algorithm, Proposal


@dataclass(frozen=True)
class BrightnessConfig:
    """Settings of the brightness-referenced search (paper 003 Sec. 4.3)."""

    gamma_mag: float = field(default=0.6, metadata={
        "help": "Brightness difference (mag) beyond which a pair's order must match the catalog's."})
    reference_mag: float = field(default=3.0, metadata={
        "help": "M_t: reference-star mode for stars brighter than this magnitude."})
    max_loops: int = field(default=2000, metadata={"help": "Loops of the Fig. 5 search before giving up."})


def calibrate_zero_point(fluxes, db_mag_max: float):
    """Eq. 9 from the frame: ``(In_k, k)`` of the faintest quarter of the detected stars."""
    f = np.sort(np.asarray(fluxes, dtype=np.float64))
    f = f[f > 0]
    if len(f) == 0:
        return None
    quarter = f[: max(1, len(f) // 4)]
    # Stars of a magnitude-limited sample pile up towards the limit (about 3x more per
    # magnitude); the faintest quarter lies within ~0.3 mag of it.
    k = db_mag_max - 0.3
    return float(np.median(quarter)), k


def search_brightness(ctx, config: BrightnessConfig):
    """Paper 003's Fig. 5 loop: each unique match in turn, continuing after one the verification rejects."""
    from startrack._kernels.identify import brightness_search

    b, db, eps, stars = ctx.b, ctx.db, ctx.eps, ctx.stars

    flux = np.array([max(float(s.get("flux", 0.0)), 1e-12) for s in stars])
    if not np.all(np.diff(flux) <= 1e-9 * max(flux.max(), 1.0)) and len(flux) > 1:
        order = np.argsort(-flux, kind="stable")
    else:
        order = np.arange(len(flux))
    gamma = float(config.gamma_mag)
    ref_mag = float(config.reference_mag)
    cal = calibrate_zero_point(flux, float(db.star_mag.max()))
    inst = -2.5 * np.log10(flux[order])
    if cal is not None:
        in_k, k = cal
        m_t = in_k * 2.512 ** (k - ref_mag)
        ref_ok = flux[order] >= m_t
    else:
        ref_ok = np.zeros(len(order), dtype=bool)
    names = {1: "reference-star", 2: "four-star", 3: "triangle"}
    bo = np.ascontiguousarray(b[order])
    loops = 0
    while True:
        mode, idx, cat, loops = brightness_search(
            bo, inst, db.star_vector, db.star_mag, db.pair_i, db.pair_j, db.pair_cos, db.kvector,
            np.asarray(db.line, dtype=np.float64), eps, gamma, ref_ok, ref_mag, int(config.max_loops), int(loops))
        if mode == 0:
            return
        keep = [t for t in range(4) if idx[t] >= 0]
        yield Proposal([int(order[idx[t]]) for t in keep], [int(cat[t]) for t in keep], int(loops),
                       {"mode": names[int(mode)]})


BRIGHTNESS = Algorithm("brightness", search_brightness, BrightnessConfig, "kvector",
                       "Paper 003's brightness-referenced search on the k-vector pair database.",
                       uses_brightness=True)
