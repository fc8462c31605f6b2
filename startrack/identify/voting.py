"""Geometric voting (Kolomenkin, Pollak, Shimshoni & Lindenbaum 2008), extended to every candidate.

The paper: every image pair votes for both stars of each catalog pair at its angle
(kernel :func:`startrack._kernels.voting.geometric_voting_top`), each image star takes
its most-voted identity, and a validation vote (pairs of identities whose catalog angle
agrees with the image angle support each other) separates the correct identities, which
support each other, from the wrong ones; the stars whose validation votes reach
``vote_fraction`` of the largest count are clustered greedily, strongest first, keeping
only stars whose angles to every star already in the cluster agree with the catalog
within the pair tolerance.  The cluster (at least three stars) is the first proposal;
when the verification rejects it, the clusters grown from each next-strongest star
follow (``identities_per_star`` > 1 keeps more identities per star than the paper).

Extension (not in the paper; ``every_candidate``): when all these are rejected, both
steps run on every candidate identity with enough votes to belong to a cluster of the
needed size (:mod:`startrack._kernels.voting`), and the validation is carried to pairs
of supporters that agree with each other (triangles).  The paper's single winner is
right when true identities out-vote chance ones; with a catalog of a few thousand stars
and 4-6 stars in the field, or among false stars, hundreds of chance identities tie
with or beat the true one (measured on the 15 deg 1280x960 sensor, Hp <= 6: 1 px
noise or 10 false stars), and its clusters never form.  The verification of every
proposal stays the shared one (:mod:`startrack.identify.verify`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from startrack.identify.algorithm import Algorithm, Proposal


@dataclass(frozen=True)
class VotingConfig:
    """Settings of geometric voting."""

    vote_fraction: float = field(default=0.0, metadata={
        "help": "Hypotheses whose verification votes reach this fraction of the largest count seed clusters."})
    identities_per_star: int = field(default=8, metadata={
        "help": "Most-voted catalog identities kept per image star (1: the paper's single vote winner)."})
    every_candidate: bool = field(default=True, metadata={
        "help": "When every cluster is rejected, vote again with every catalog star of enough votes as a candidate "
                "of each image star, clusters by triangle votes (sparse fields, false stars); off: the paper's "
                "single vote."})
    max_clusters: int = field(default=200, metadata={
        "help": "Clusters of every candidate proposed at most (strongest first)."})


def search_voting(ctx, config: VotingConfig):
    """Voting clusters: the paper's (most-voted identities) first, then those of every candidate.

    Each image star keeps its ``identities_per_star`` most-voted catalog
    stars; the second voting step scores every such hypothesis; clusters are
    grown greedily from each hypothesis whose score reaches ``vote_fraction``
    of the best (strongest first), adding the hypotheses of other stars whose
    catalog angles to every member agree with the image within the pair
    tolerance.  Each cluster of at least three stars is a proposal.

    When every one is rejected (``every_candidate``), both steps run again on
    every catalog star with at least ``k`` first-step votes as a candidate of
    each image star (:func:`startrack._kernels.voting.voting_clusters`; ``k`` =
    the matches needed less one, the votes every member of a cluster of ``k +
    1`` stars gets from the cluster alone) and the clusters follow, most
    triangle votes first.  In a sparse field or among false stars the true
    identity shares its first-step vote count with hundreds of chance
    candidates (a 4-star frame at 1 px: ~700 catalog stars with the maximal 3
    votes; ten false stars: the true one ranks in the hundreds), which the
    paper's single winner, or any fixed list, misses; the clusters of every
    candidate hold it.
    """
    from startrack._kernels.voting import geometric_voting_top

    db = ctx.db
    top = max(1, int(config.identities_per_star))
    line = db.__dict__.get("_line_array")
    if line is None:
        line = db.__dict__["_line_array"] = np.asarray(db.line, dtype=np.float64)
    n = len(ctx.b)
    keep = np.arange(n)
    seen = set()
    # Look-elsewhere: the votes compare every group of four image stars with the catalog.
    patterns = max(1, math.comb(n, 4))
    b = np.ascontiguousarray(ctx.b)
    identity, _, votes2 = geometric_voting_top(b, db.n_stars, db.pair_i, db.pair_j, db.pair_cos, db.kvector,
                                               line, ctx.eps, db.star_vector, top)
    yield from _clusters(ctx, config, b, keep, identity, votes2, top, seen, patterns)
    if not config.every_candidate or n < 3 or ctx.expired():
        return
    from startrack._kernels.voting import voting_clusters

    k_min = max(2, min(int(ctx.params.min_matches), n) - 1)
    stars, cats, sizes, score, n_hyp, n_edges = voting_clusters(
        b, np.ascontiguousarray(ctx.tol, dtype=np.float64), float(ctx.margin), db.n_stars, db.pair_i, db.pair_j,
        db.pair_cos, db.kvector, line, k_min, int(config.max_clusters))
    for r in range(len(sizes)):
        img = [int(v) for v in stars[r, :sizes[r]]]
        cat = [int(v) for v in cats[r, :sizes[r]]]
        key = frozenset(zip(img, cat))
        if key in seen:
            continue
        seen.add(key)
        yield Proposal(img, cat, patterns, {"triangle_votes": int(score[r]), "hypotheses": int(n_hyp),
                                            "agreeing_pairs": int(n_edges)})


def _clusters(ctx, config, b, keep, identity, votes2, top, seen, patterns):
    """Proposals grown from the voted hypotheses, strongest first (indices mapped back through ``keep``).

    The clusters grow in a kernel (:func:`startrack._kernels.voting.grow_clusters`), a
    few seeds a call (the driver may accept the first), until the driver's deadline.
    """
    from startrack._kernels.voting import grow_clusters

    db = ctx.db
    best = int(votes2.max(initial=0))
    if best < 2:
        return
    threshold = max(2, int(np.ceil(config.vote_fraction * best)))
    # The hypotheses with support, strongest first (ties: image star, then rank): seeds and members.
    ii, aa = np.nonzero((identity >= 0) & (votes2 >= 1))
    fv = votes2[ii, aa].astype(np.int64)
    order = np.lexsort((ii, -fv))
    fi = np.ascontiguousarray(ii[order], dtype=np.int64)
    fc = np.ascontiguousarray(identity[ii, aa][order], dtype=np.int64)
    fv = np.ascontiguousarray(fv[order])
    keep = np.ascontiguousarray(keep, dtype=np.int64)
    tol = np.ascontiguousarray(ctx.tol, dtype=np.float64)
    start = 0
    while start < len(fi) and not ctx.expired():
        members, sizes, end = grow_clusters(b, keep, tol, float(ctx.margin), db.star_vector, fi, fc, fv, start,
                                            start + 16, threshold)
        for row in range(end - start):
            cluster = [(int(fi[r]), int(fc[r])) for r in members[row, :sizes[row]]]
            key = frozenset((int(keep[i]), c) for i, c in cluster)
            if len(cluster) < 3 or key in seen:
                continue
            seen.add(key)
            yield Proposal([int(keep[i]) for i, _ in cluster], [c for _, c in cluster], patterns,
                           {"votes": [int(votes2[i, list(identity[i]).index(c)]) for i, c in cluster]})
        if end < start + 16:
            break
        start = end


VOTING = Algorithm("voting", search_voting, VotingConfig, "kvector",
                   "Kolomenkin et al.'s geometric voting on the k-vector pair database.",
                   focal_sweep=True)
