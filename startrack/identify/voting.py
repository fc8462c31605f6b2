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
    revote: bool = field(default=True, metadata={
        "help": "When every cluster is rejected, keep more identities per star, then vote again without the "
                "least supported star, and so on (false stars); off: the paper's single vote."})


def search_voting(ctx, config: VotingConfig):
    """Voting clusters, the strongest first.

    Each image star keeps its ``identities_per_star`` most-voted catalog
    stars; the second voting step scores every such hypothesis; clusters are
    grown greedily from each hypothesis whose score reaches ``vote_fraction``
    of the best (strongest first), adding the hypotheses of other stars whose
    catalog angles to every member agree with the image within the pair
    tolerance.  Each cluster of at least three stars is a proposal.  When
    every cluster is rejected (``revote``), the hypotheses are widened (4 and
    16 times ``identities_per_star`` while affordable), then the star whose
    best hypothesis the second step supports least is left out and the stars
    vote again, and so on down to four stars (within the driver's budget): a
    false star's votes are noise, and each one left out lowers the noise under
    the true identities.
    """
    from startrack._kernels.identify import geometric_voting_top

    db = ctx.db
    top = max(1, int(config.identities_per_star))
    line = np.asarray(db.line, dtype=np.float64)
    keep = np.arange(len(ctx.b))
    seen = set()
    rounds = 0
    n = len(keep)
    b = np.ascontiguousarray(ctx.b)
    base = None
    # Wider identity lists next (few stars: the true identity's votes hardly exceed the
    # noise's), as long as the second step stays affordable (n^2 top^2 angle tests).
    for width in [top] + ([top * 4, top * 16] if config.revote else []):
        if width > top and n * n * width * width > 4_000_000:
            break
        identity, _, votes2 = geometric_voting_top(b, db.n_stars, db.pair_i, db.pair_j, db.pair_cos, db.kvector,
                                                   line, ctx.eps, db.star_vector, width)
        if base is None:
            base = votes2
        rounds += 1
        yield from _clusters(ctx, config, b, keep, identity, votes2, width, seen, rounds)
    if not config.revote:
        return
    votes2 = base
    while len(keep) > 4:
        # Vote again without the star the second step supports least (a false star's votes
        # are noise everywhere): fewer stars, less noise for the others.  Ties: the faintest.
        support = votes2.max(axis=1)
        keep = np.delete(keep, len(keep) - 1 - int(np.argmin(support[::-1])))
        b = np.ascontiguousarray(ctx.b[keep])
        identity, _, votes2 = geometric_voting_top(b, db.n_stars, db.pair_i, db.pair_j, db.pair_cos, db.kvector,
                                                   line, ctx.eps, db.star_vector, top)
        rounds += 1
        yield from _clusters(ctx, config, b, keep, identity, votes2, top, seen, rounds)


def _clusters(ctx, config, b, keep, identity, votes2, top, seen, rounds):
    """Proposals grown from the voted hypotheses, strongest first (indices mapped back through ``keep``)."""
    db = ctx.db
    n = len(b)
    best = int(votes2.max(initial=0))
    if best < 2:
        return
    threshold = max(2, int(np.ceil(config.vote_fraction * best)))
    flat = [(int(votes2[i, a]), i, int(identity[i, a])) for i in range(n) for a in range(top)
            if identity[i, a] >= 0 and votes2[i, a] >= 1]
    flat.sort(key=lambda t: (-t[0], t[1]))
    sv = db.star_vector
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
                if abs(th - tc) > ctx.pair_eps(int(keep[i]), int(keep[m])):
                    ok = False
                    break
            if ok:
                cluster.append((i, c))
        key = frozenset((int(keep[i]), c) for i, c in cluster)
        if len(cluster) < 3 or key in seen:
            continue
        seen.add(key)
        # One hypothesis per image star and identity kept: n * top patterns per round.
        yield Proposal([int(keep[i]) for i, _ in cluster], [c for _, c in cluster], rounds * n * top,
                       {"votes": [int(votes2[i, list(identity[i]).index(c)]) for i, c in cluster],
                        "voting_round": rounds})


VOTING = Algorithm("voting", search_voting, VotingConfig, "kvector",
                   "Kolomenkin et al.'s geometric voting on the k-vector pair database.")
