"""Pyramid identification (Mortari, Samaan, Bruccoleri & Junkins 2004).

Triads of image stars are taken in Mortari's smart index sequence (every
triad once, bright stars early, spikes spread out); for each, the kernel
(:func:`startrack._kernels.identify.pyramid_candidates`) finds the catalog
triangles through k-vector range look-ups on the inter-star angles, the
third angle and the specular (handedness) test, and confirms each triangle
with a fourth image star matching exactly one catalog star (the pyramid).
Every confirmed pyramid is a proposal, the triad's in the order found: where
Mortari's pyramid stops at the first triad with a *unique* triangle, this
search also proposes the pyramids of ambiguous triads and goes on after a
rejected one (the shared verification decides), which is what a sparse field
of four or five stars needs.  Paper 000's quadratic search on its triangle
database is :mod:`startrack.identify.modified_pyramid`.
"""
from __future__ import annotations

import itertools
from dataclasses import dataclass, field

import numpy as np

from startrack.identify.base import Algorithm, Proposal


@dataclass(frozen=True)
class PyramidConfig:
    """Settings of the pyramid search."""

    max_triads: int = field(default=300, metadata={"help": "Triads of image stars tried (smart index order)."})
    max_triangles: int = field(default=64, metadata={
        "help": "Catalog triangles of one triad beyond which the triad is skipped as uninformative."})


_TRIADS: dict = {}      # smart index sequence per number of search stars


def _search(ctx, config, quadratic):
    from startrack._kernels.identify import pyramid_candidates, smart_triads

    db = ctx.db
    n = len(ctx.b)
    arrays = db.__dict__.get("_pyramid_arrays")
    if arrays is None:
        arrays = db.__dict__["_pyramid_arrays"] = (np.asarray(db.line, dtype=np.float64),
                                                   np.asarray(db.quad, dtype=np.float64))
    line, quad = arrays
    tol = np.ascontiguousarray(ctx.tol, dtype=np.float64)
    triads = _TRIADS.get(n)
    if triads is None:
        if len(_TRIADS) > 64:
            _TRIADS.clear()
        triads = _TRIADS[n] = [tuple(r) for r in smart_triads(n).tolist()]
    seen = set()
    for t, (i, j, k) in enumerate(itertools.islice(triads, config.max_triads), start=1):
        out, n_tri = pyramid_candidates(ctx.b, tol, ctx.margin, i, j, k, db.star_vector, db.pair_i, db.pair_j,
                                        db.pair_cos, db.kvector, line, db.kquad, quad, quadratic,
                                        config.max_triangles, 256)
        for r, I, J, K, R in out.tolist():
            key = (i, j, k, I, J, K)
            if key in seen:
                continue
            seen.add(key)
            if r < 0:
                yield Proposal([i, j, k], [I, J, K], t, {"triangles": int(n_tri)})
            else:
                yield Proposal([i, j, k, r], [I, J, K, R], t, {"triangles": int(n_tri)})


def search_pyramid(ctx, config: PyramidConfig):
    """Pyramid proposals with k-vector range look-ups."""
    return _search(ctx, config, False)


PYRAMID = Algorithm("pyramid", search_pyramid, PyramidConfig, "kvector",
                    "Mortari's pyramid on the k-vector pair database.")
