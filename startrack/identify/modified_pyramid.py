"""Paper 000's modified pyramid: four stars, four triangles, the triangle database searched by its smallest angle.

Hashemi et al. (2019) Sec. 3.2: the measured stars give triangles whose internal
angles (Eq. 2) are looked up in the triangle database
(:mod:`startrack.triangles`) by the smallest angle, through the quadratic fit
of Eqs. 7-12 (or, to compare, Mortari's k-vector line: Table 5).  A catalog
triangle that matches three of the stars is confirmed by the fourth star: the
triangle of two of its stars and the fourth must be in the database with the
same two catalog stars, and the fourth star's angle to the third must agree
(Mortari's "confirming fourth star").  Each confirmed four-star pattern is a
proposal for the shared verification; the paper takes the four brightest
stars, and the search goes on to the next four when verification refuses a
pattern, through every four-star set of the search stars (the paper stops at
the brightest four; with false stars among them, the first set of true stars
can be far down the list: 200 sets identified 8 of 100 frames with 10 false
stars on a 15 deg sensor, every set 99).
"""
from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field

import numpy as np

from startrack.identify.algorithm import Algorithm, Proposal

MAX_CANDIDATES = 4096      # catalog triangles kept per look-up


def _quadruples(n: int):
    """Four-star sets of the ``n`` brightest stars, those made of brighter stars first (the paper's four first).

    Generated lazily in the order of ``sorted(combinations(range(n), 4), key=reversed)``: the faintest star of
    a set decides, then the next, ...
    """
    for r in range(3, n):
        for k in range(2, r):
            for j in range(1, k):
                for i in range(j):
                    yield i, j, k, r


def _sides_ok(b, stars, cos_max) -> bool:
    return all(float(b[p] @ b[q]) >= cos_max for p, q in itertools.combinations(stars, 2))


def iter_modified_pyramid(b, db, eps, max_quadruples: int = 0, quadratic: bool = True):
    """Proposals of paper 000's modified pyramid, in its order (``patterns``: four-star sets tried so far).

    Parameters
    ----------
    b : ndarray, shape (n, 3)
        Unit vectors of the measured stars (camera frame), brightest first.
    db : TriangleDatabase
    eps : float
        Tolerance of an inter-star angle (radians).
    max_quadruples : int
        Four-star sets tried (0: every one).
    quadratic : bool
        Paper 000's quadratic range search (Eqs. 10-12); ``False``: Mortari's line.
    """
    from startrack._kernels.triangles import triangle_candidates

    b = np.ascontiguousarray(b, dtype=np.float64)
    n = len(b)
    if n < 4:
        return
    cos_max = math.cos(math.radians(db.max_separation_deg))
    head = (db.tri_key, db.tri_stars, db.tri_angles, db.tri_hand, db.kquad, *db.quad)
    tail = (db.kvector, *db.line, quadratic)
    trials = 0
    for count, (i, j, k, r) in enumerate(_quadruples(n)):
        if max_quadruples and count >= max_quadruples:
            return
        # A base triangle and a confirming triangle, each with every side in the database's range.
        bases = [(i, j, k, r), (i, j, r, k), (i, k, r, j), (j, k, r, i)]
        base = next((q for q in bases if _sides_ok(b, q[:3], cos_max)), None)
        if base is None:
            continue
        p0, p1, p2, p3 = base
        confirm = next(((x, y) for x, y in ((p0, p1), (p0, p2), (p1, p2)) if _sides_ok(b, (x, y, p3), cos_max)),
                       None)
        if confirm is None:
            continue
        cands, _ = triangle_candidates(b, p0, p1, p2, *head, eps, db.star_vector, MAX_CANDIDATES, *tail)
        trials += len(cands)
        if len(cands) == 0:
            continue
        x, y = confirm
        fourth, _ = triangle_candidates(b, x, y, p3, *head, eps, db.star_vector, MAX_CANDIDATES, *tail)
        trials += len(fourth)
        if len(fourth) == 0:
            continue
        pos = {p0: 0, p1: 1, p2: 2}
        other = ({p0, p1, p2} - {x, y}).pop()
        theta_other = math.acos(min(1.0, max(-1.0, float(b[other] @ b[p3]))))
        for c in cands:
            cx, cy, co = c[pos[x]], c[pos[y]], c[pos[other]]
            for f in fourth:
                if f[0] != cx or f[1] != cy or f[2] in (c[0], c[1], c[2]):
                    continue
                cr = f[2]
                theta = math.acos(min(1.0, max(-1.0, float(db.star_vector[co] @ db.star_vector[cr]))))
                if abs(theta - theta_other) > eps:
                    continue
                # ``patterns``: the four-star sets compared with the database so far (look-elsewhere).
                yield Proposal([int(p0), int(p1), int(p2), int(p3)], [int(c[0]), int(c[1]), int(c[2]), int(cr)],
                               count + 1, {"triangles": trials})


def propose_modified_pyramid(b, db, eps, params, stars, camera):
    """The first proposal (the shared driver verifies it)."""
    for proposal in iter_modified_pyramid(b, db, eps, params.max_triads):
        return proposal
    return Proposal([], [], 0, {"reason": "no confirmed four-star pattern in the triangle database"})


@dataclass(frozen=True)
class ModifiedPyramidConfig:
    """Settings of paper 000's modified pyramid."""

    max_quadruples: int = field(default=0, metadata={
        "help": "Four-star sets tried, brightest first (0: every set of the search stars; the driver's time "
                "budget bounds the search)."})
    range_search: str = field(default="quadratic", metadata={
        "help": "Smallest-angle look-up: 'quadratic' (paper 000 Eqs. 10-12) or 'line' (Mortari's k-vector)."})


def search_modified_pyramid(ctx, config: ModifiedPyramidConfig):
    """Paper 000's modified pyramid proposals for the shared driver."""
    if config.range_search not in ("quadratic", "line"):
        from startrack.errors import ParameterError

        raise ParameterError("range_search", f"must be 'quadratic' or 'line', got {config.range_search!r}")
    yield from iter_modified_pyramid(ctx.b, ctx.db, ctx.eps, config.max_quadruples,
                                     config.range_search == "quadratic")


MODIFIED_PYRAMID = Algorithm("modified-pyramid", search_modified_pyramid, ModifiedPyramidConfig, "triangles",
                             "Paper 000's modified pyramid on the triangle database (build-triangles).")
