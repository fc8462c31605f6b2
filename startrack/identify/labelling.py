"""Labelling identification (Kim & Cho 2019; paper 004).

For groups of ``group_size`` of the brightest image stars (the 4 brightest
first, then the other groups of the ``stars_per_field`` brightest in order,
then groups adding the next fainter star, and the next),
the integer label of the group's distance ratios (Eqs. 1-3) is looked up in the
sorted label database through its trend line (Fig. 3); every entry with an
equal label is a candidate, and the angle error of Eq. 5,
``theta_err = sum |theta_mea - theta_cat|``, chooses among them.  The stars of
the best group are identified at once; the shared verification then
identifies the rest.

Distances are angles between the stars' unit vectors computed with the
nominal focal length: a focal-length error scales them all alike, which the
ratios cancel (the method's claim, Fig. 7).  Two details the paper leaves open
are settled here and documented:

* a measured sub-label within ``boundary`` of a rounding boundary may round
  either way under noise, so both roundings are looked up (at most 8 labels);
* Eq. 5 is evaluated after the best common scale ``s`` of the measured angles
  (``s = sum theta_cat theta_mea / sum theta_mea^2``, the focal-length error),
  so that the check keeps the labels' scale invariance; ``|s - 1|`` must stay
  below ``max_focal_error`` (5%), and the star correspondence is the one of
  the 24 orders of the group with the smallest error (equal distance sums can
  swap the Sec. 2.3 order under noise).
"""
from __future__ import annotations

import functools
import itertools
import math
from dataclasses import dataclass, field

import numpy as np

from startrack.identify.algorithm import Algorithm, Proposal


@dataclass(frozen=True)
class LabellingConfig:
    """Settings of the labelling search (paper 004)."""

    label_boundary: float = field(default=0.2, metadata={
        "help": "Sub-labels this close to a rounding boundary are looked up both ways."})
    max_focal_error: float = field(default=0.05, metadata={
        "help": "Largest relative focal-length error a label match may imply."})
    max_entries: int = field(default=64, metadata={"help": "Database entries examined per label."})
    group_stars: int | None = field(default=None, metadata={
        "help": "Brightest detections whose groups are tried: those of the database's stars per field (paper "
                "004's 8) first, then groups adding each next star up to this (default: all search stars)."})


@functools.lru_cache(maxsize=64)
def _group_order(n_first: int, n: int, group: int) -> np.ndarray:
    """Image groups in search order: every group of the ``n_first`` brightest stars, then those
    adding star ``n_first`` (with ``group - 1`` brighter ones), then star ``n_first + 1``, ..."""
    rows = [c for c in itertools.combinations(range(n_first), group)]
    for new in range(n_first, n):
        rows += [c + (new,) for c in itertools.combinations(range(new), group - 1)]
    out = np.array(rows, dtype=np.int64).reshape(-1, group)
    out.setflags(write=False)
    return out


@functools.lru_cache(maxsize=8)
def _perm_tables(group: int):
    perms = np.array(list(itertools.permutations(range(group))), dtype=np.int64)
    pairs = [(a, c) for a in range(group) for c in range(a + 1, group)]
    return perms, np.array([a for a, _ in pairs], dtype=np.int64), np.array([c for _, c in pairs], dtype=np.int64)


def search_labelling(ctx, config: LabellingConfig):
    """Groups of the brightest stars in paper 004's order; each group's label matches, best Eq. 5 error first.

    The paper takes the groups of the ``stars_per_field`` brightest stars (8)
    and stops at the first that matches.  Here the matches of a group the
    verification rejects are followed by the next group's, and when the
    groups of the brightest stars are exhausted -- false stars among them
    hide the true ones -- the search goes on with groups that add the next
    star, and the next (``group_stars`` caps how far), within the driver's
    budget.  The scan itself is one kernel
    (:func:`startrack._kernels.labelling.labelling_scan`).
    """
    from startrack._kernels.labelling import labelling_scan

    b, db, eps = ctx.b, ctx.db, ctx.eps
    group = db.group_size
    n_first = min(len(b), db.stars_per_field)
    n_use = len(b) if config.group_stars is None else min(len(b), int(config.group_stars))
    if n_use < group:
        return
    combos = _group_order(min(n_first, n_use), n_use, group)
    perms, pa, pc = _perm_tables(group)
    boundary = float(config.label_boundary)
    max_flips = int(math.log2(8))
    t = 0
    scale = float(10 ** db.scale_digits)
    trend = np.ascontiguousarray(db.trend, dtype=np.float64)
    while t < len(combos):
        t, mem, err, sc, n = labelling_scan(
            b, combos, t, db.label, db.members, db.star_vector, trend, float(db.trend_scale), int(db.trend_radius),
            scale, boundary, max_flips, float(config.max_focal_error), float(eps), int(config.max_entries), perms, pa,
            pc, 64)
        if t < 0:
            return
        combo = combos[t].tolist()
        t += 1
        for k in range(n):
            yield Proposal(combo, mem[k].tolist(), t, {"label_error_arcsec": round(math.degrees(err[k]) * 3600, 3),
                                                        "label_focal_scale": round(float(sc[k]), 6)})


LABELLING = Algorithm("labelling", search_labelling, LabellingConfig, "labels",
                      "Kim & Cho's labelling on a label database (build-labels).")
