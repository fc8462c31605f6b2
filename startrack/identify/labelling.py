"""Labelling identification (Kim & Cho 2019; paper 004).

For groups of ``group_size`` of the brightest image stars (the 4 brightest
first, then the other groups of the ``stars_per_field`` brightest in order),
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

import itertools
import math
from dataclasses import dataclass, field

import numpy as np

from startrack.identify.base import Algorithm, Proposal


@dataclass(frozen=True)
class LabellingConfig:
    """Settings of the labelling search (paper 004)."""

    label_boundary: float = field(default=0.2, metadata={
        "help": "Sub-labels this close to a rounding boundary are looked up both ways."})
    max_focal_error: float = field(default=0.05, metadata={
        "help": "Largest relative focal-length error a label match may imply."})
    max_entries: int = field(default=64, metadata={"help": "Database entries examined per label."})
    group_stars: int | None = field(default=None, metadata={
        "help": "Brightest detections whose groups are tried (default: the database's stars per field, "
                "paper 004's 8); more find groups past bright false stars, slowly."})


def _pair_angles(vecs):
    n = len(vecs)
    return np.array([math.acos(min(1.0, max(-1.0, float(vecs[a] @ vecs[b]))))
                     for a in range(n) for b in range(a + 1, n)])


def _labels_with_variants(angles, digits, boundary, max_variants=8):
    d = np.sort(angles)[::-1]
    scale = 10 ** digits
    x = scale * d[1:] / d[0]
    base = np.floor(x + 0.5).astype(np.int64)
    frac = x - np.floor(x)
    uncertain = [i for i in range(len(x)) if abs(frac[i] - 0.5) < boundary]
    uncertain = sorted(uncertain, key=lambda i: abs(frac[i] - 0.5))[: int(math.log2(max_variants))]
    out = []
    for flips in itertools.product((0, 1), repeat=len(uncertain)):
        sub = base.copy()
        for i, f in zip(uncertain, flips):
            if f:
                sub[i] = int(math.floor(x[i])) if base[i] > x[i] else int(math.floor(x[i])) + 1
        label = 0
        for v in sub:
            label = label * scale + int(v)
        out.append(label)
    return out


def search_labelling(ctx, config: LabellingConfig):
    """Groups of the brightest stars in paper 004's order; each group's label matches, best Eq. 5 error first.

    The paper stops at the first group that matches; here the matches of a
    group the verification rejects are followed by the next group's.
    """
    b, db, eps = ctx.b, ctx.db, ctx.eps
    group = db.group_size
    # The paper's groups come from the stars_per_field brightest; false stars among them push
    # true ones further down: group_stars widens the set (groups brightest first).
    n_use = min(len(b), db.stars_per_field if config.group_stars is None else int(config.group_stars))
    if n_use < group:
        return
    boundary = float(config.label_boundary)
    max_scale = float(config.max_focal_error)
    perms = list(itertools.permutations(range(group)))
    pair_index = [(a, c) for a in range(group) for c in range(a + 1, group)]
    tried = 0
    for combo in itertools.combinations(range(n_use), group):
        tried += 1
        vecs = b[list(combo)]
        mea = _pair_angles(vecs)
        found = {}
        for label in _labels_with_variants(mea, db.scale_digits, boundary):
            start, end = db.lookup(label)
            for entry in range(start, min(end, start + config.max_entries)):
                members = db.members[entry]
                cvec = db.star_vector[members]
                best = None
                for perm in perms:
                    cat_angles = np.array([math.acos(min(1.0, max(-1.0, float(cvec[perm[a]] @ cvec[perm[c]]))))
                                           for a, c in pair_index])
                    s = float(cat_angles @ mea / (mea @ mea))
                    if abs(s - 1.0) > max_scale:
                        continue
                    err = float(np.sum(np.abs(s * mea - cat_angles)))     # Eq. 5 after the scale
                    if best is None or err < best[0]:
                        best = (err, tuple(int(members[perm[a]]) for a in range(group)), s)
                if best is None:
                    continue
                # Accept when the residual is what centroid noise explains (eps per angle) plus, when the
                # focal length is far off, the departure of the gnomonic angles from one common scale.
                allowance = len(mea) * (eps + 0.5 * abs(best[2] - 1.0) * float(np.max(mea)) ** 3)
                if best[0] <= allowance and (best[1] not in found or best[0] < found[best[1]][0]):
                    found[best[1]] = best
        for err, cat, s in sorted(found.values()):
            yield Proposal(list(combo), list(cat), tried, {"label_error_arcsec": round(math.degrees(err) * 3600, 3),
                                                          "label_focal_scale": round(s, 6)})


LABELLING = Algorithm("labelling", search_labelling, LabellingConfig, "labels",
                      "Kim & Cho's labelling on a label database (build-labels).")
