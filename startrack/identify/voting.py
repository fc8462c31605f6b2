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

    vote_fraction: float = field(default=0.0, metadata={
        "help": "Hypotheses whose verification votes reach this fraction of the largest count seed clusters."})
    identities_per_star: int = field(default=8, metadata={
        "help": "Most-voted catalog identities kept per image star (1: the paper's single vote winner)."})


def search_voting(ctx, config: VotingConfig):
    """Voting clusters, the strongest first.

    Each image star keeps its ``identities_per_star`` most-voted catalog
    stars; the second voting step scores every such hypothesis; clusters are
    grown greedily from each hypothesis whose score reaches ``vote_fraction``
    of the best (strongest first), adding the hypotheses of other stars whose
    catalog angles to every member agree with the image within the pair
    tolerance.  Each cluster of at least three stars is a proposal.
    """
    from startrack._kernels.identify import geometric_voting_top

    db = ctx.db
    b = ctx.b
    top = max(1, int(config.identities_per_star))
    identity, _, votes2 = geometric_voting_top(b, db.n_stars, db.pair_i, db.pair_j, db.pair_cos, db.kvector,
                                               np.asarray(db.line, dtype=np.float64), ctx.eps, db.star_vector, top)
    n = len(b)
    best = int(votes2.max(initial=0))
    if best < 2:
        return
    threshold = max(2, int(np.ceil(config.vote_fraction * best)))
    flat = [(int(votes2[i, a]), i, int(identity[i, a])) for i in range(n) for a in range(top)
            if identity[i, a] >= 0 and votes2[i, a] >= 1]
    flat.sort(key=lambda t: (-t[0], t[1]))
    sv = db.star_vector
    seen = set()
    for v0, i0, c0 in flat:
        if v0 < threshold:
            break
        cluster = [(i0, c0)]
        for _, i, c in flat:
            if any(i == m for m, _ in cluster) or any(c == k for _, k in cluster):
                continue
            ok = True
            for m, k in cluster:
                th = float(np.arccos(min(1.0, float(b[i] @ b[m]))))
                tc = float(np.arccos(min(1.0, float(sv[c] @ sv[k]))))
                if abs(th - tc) > ctx.pair_eps(i, m):
                    ok = False
                    break
            if ok:
                cluster.append((i, c))
        key = frozenset(cluster)
        if len(cluster) < 3 or key in seen:
            continue
        seen.add(key)
        # One hypothesis per image star and identity kept: n * top patterns.
        yield Proposal([i for i, _ in cluster], [c for _, c in cluster], n * top,
                       {"votes": [int(votes2[i, list(identity[i]).index(c)]) for i, c in cluster]})


VOTING = Algorithm("voting", search_voting, VotingConfig, "kvector",
                   "Kolomenkin et al.'s geometric voting on the k-vector pair database.")
