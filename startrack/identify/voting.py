"""Geometric voting (Kolomenkin, Pollak, Shimshoni & Lindenbaum 2008).

Two voting steps (kernel :func:`startrack._kernels.identify.geometric_voting`)
and the validation: the stars whose verification votes reach three quarters of
the largest count are clustered greedily, strongest first, keeping only stars
whose angles to every star already in the cluster agree with the catalog within
``eps``.  The cluster (at least three stars) is the proposal.
"""
from __future__ import annotations

import math

import numpy as np

from startrack.identify.base import Proposal


def propose_voting(b, db, eps, params, stars, camera):
    from startrack._kernels.identify import geometric_voting

    identity, votes1, votes2 = geometric_voting(b, db.star_vector, db.n_stars, db.pair_i, db.pair_j, db.pair_cos,
                                                db.kvector, np.array(db.line), eps)
    n = len(b)
    if votes2.max(initial=0) < 2:
        return Proposal([], [], n * (n - 1) // 2, {"reason": "no verification votes"})
    threshold = max(2, int(math.ceil(0.75 * votes2.max())))
    order = [int(i) for i in np.argsort(-votes2, kind="stable") if votes2[i] >= threshold and identity[i] >= 0]
    cluster = []
    for i in order:
        ok = True
        for j in cluster:
            if identity[i] == identity[j]:
                ok = False
                break
            th = math.acos(min(1.0, float(b[i] @ b[j])))
            tc = math.acos(min(1.0, float(db.star_vector[identity[i]] @ db.star_vector[identity[j]])))
            if abs(th - tc) > eps:
                ok = False
                break
        if ok:
            cluster.append(i)
    if len(cluster) < 3:
        return Proposal([], [], n * (n - 1) // 2, {"reason": f"largest consistent cluster has {len(cluster)} stars"})
    cluster = cluster[:4] + sorted(cluster[4:])
    # One hypothesis per image star (its most-voted identity): n trials.
    return Proposal(cluster, [int(identity[i]) for i in cluster], n,
                    {"votes": [int(votes2[i]) for i in cluster]})
