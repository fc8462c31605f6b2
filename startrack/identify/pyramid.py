"""Pyramid identification (Mortari, Samaan, Bruccoleri & Junkins 2004) and paper 000's quadratic variant.

The kernel (:func:`startrack._kernels.identify.pyramid_search`) walks the
smart triad sequence, finds catalog triangles through k-vector range look-ups
on the three inter-star angles with tolerance ``eps`` and the specular
(handedness) test, and confirms a unique triangle with a fourth star.
``pyramid-quadratic`` replaces the k-vector range by paper 000's quadratic
search (Eqs. 10-12), clipped to the k-vector range.
"""
from __future__ import annotations

import numpy as np

from startrack.identify.base import Proposal


def _propose(b, db, eps, params, stars, camera, quadratic):
    from startrack._kernels.identify import pyramid_search

    status, idx, cat, tried, _ = pyramid_search(
        b, db.star_vector, db.pair_i, db.pair_j, db.pair_cos, db.kvector, np.array(db.line), db.kquad,
        np.array(db.quad), quadratic, eps, params.max_triads, float(params.extra.get("relative_tolerance", 0.0)))
    if status == 0:
        return Proposal([], [], int(tried), {"reason": f"no unique pyramid among {tried} triads"})
    keep = [k for k in range(4) if idx[k] >= 0]
    return Proposal([int(idx[k]) for k in keep], [int(cat[k]) for k in keep], int(tried))


def propose_pyramid(b, db, eps, params, stars, camera):
    return _propose(b, db, eps, params, stars, camera, False)


def propose_pyramid_quadratic(b, db, eps, params, stars, camera):
    return _propose(b, db, eps, params, stars, camera, True)
