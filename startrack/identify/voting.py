"""Geometric voting (Kolomenkin, Pollak, Shimshoni & Lindenbaum 2008).

Two voting steps (kernel :func:`startrack._kernels.identify.geometric_voting`)
and the validation: the stars whose verification votes reach
``vote_fraction`` of the largest count are clustered greedily, strongest
first, keeping only stars whose angles to every star already in the cluster
agree with the catalog within the pair tolerance.  The cluster (at least three
stars) is the first proposal; when the verification rejects it, the clusters
grown from each next-strongest star follow.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from startrack.identify.base import Algorithm, Proposal


@dataclass(frozen=True)
class VotingConfig:
    """Settings of geometric voting."""

    vote_fraction: float = field(default=0.75, metadata={
        "help": "Stars whose verification votes reach this fraction of the largest count form clusters."})


def _cluster(seed_order, identity, b, star_vec, ctx):
    cluster = []
    for i in seed_order:
        ok = True
        for j in cluster:
            if identity[i] == identity[j]:
                ok = False
                break
            th = float(np.arccos(min(1.0, float(b[i] @ b[j]))))
            tc = float(np.arccos(min(1.0, float(star_vec[identity[i]] @ star_vec[identity[j]]))))
            if abs(th - tc) > ctx.pair_eps(i, j):
                ok = False
                break
        if ok:
            cluster.append(i)
    return cluster


def search_voting(ctx, config: VotingConfig):
    """Voting clusters, the strongest first."""
    from startrack._kernels.identify import geometric_voting

    db = ctx.db
    b = ctx.b
    identity, votes1, votes2 = geometric_voting(b, db.star_vector, db.n_stars, db.pair_i, db.pair_j, db.pair_cos,
                                                db.kvector, np.asarray(db.line, dtype=np.float64), ctx.eps)
    n = len(b)
    if votes2.max(initial=0) < 2:
        return
    threshold = max(2, int(np.ceil(config.vote_fraction * votes2.max())))
    order = [int(i) for i in np.argsort(-votes2, kind="stable") if votes2[i] >= threshold and identity[i] >= 0]
    seen = set()
    for start in range(len(order)):
        cluster = _cluster(order[start:] + order[:start], identity, b, db.star_vector, ctx)
        key = frozenset(cluster)
        if len(cluster) < 3 or key in seen:
            continue
        seen.add(key)
        cluster = cluster[:4] + sorted(cluster[4:])
        # One hypothesis per image star (its most-voted identity): n patterns.
        yield Proposal(cluster, [int(identity[i]) for i in cluster], n,
                       {"votes": [int(votes2[i]) for i in cluster]})


VOTING = Algorithm("voting", search_voting, VotingConfig, "kvector",
                   "Kolomenkin et al.'s geometric voting on the k-vector pair database.")
