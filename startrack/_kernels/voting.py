"""Geometric voting with every candidate identity (Kolomenkin, Pollak, Shimshoni & Lindenbaum 2008, extended).

The paper's two steps, on all candidates instead of each star's single vote winner:

1. *voting*: every image pair ``(i, j)`` votes, once per pair, for both stars of every
   catalog pair whose angle agrees with the image angle within the pair's tolerance;
2. *validation*: a hypothesis ``(i, c)`` (image star ``i`` is catalog star ``c``) gets a
   vote from every other image star ``j`` that has a candidate ``d`` with the angle
   ``(c, d)`` equal to the image angle ``(i, j)`` within the tolerance (counted once per
   ``j``).  The validation walks the same k-vector ranges as the voting (a candidate is a
   table look-up), so it costs what the voting costs however many candidates there are.

A hypothesis of a consistent cluster of ``k + 1`` image stars has at least ``k`` votes
in each step from the cluster alone, so only hypotheses with fewer than ``k`` votes are
dropped: no member of such a cluster is lost, whatever the false stars and however many
chance candidates share its vote count.  The agreeing pairs of the validation are the
edges of a graph on the hypotheses, in which a consistent cluster is a clique; the
validation is then carried one step further, to pairs of supporters that agree with
each other (the triangles through a hypothesis), which chance pairs rarely do, and
the clusters are grown greedily from the hypotheses with the most triangles.
"""
import math

import numpy as np

from startrack._kernels._jit import njit
from startrack._kernels.common import _angle, _cos_window
from startrack._kernels.database import kvector_range


@njit(cache=True)
def _windows(b, tol, margin, kvector, line):
    """Per image pair (i < j, row-major): ``i``, ``j``, ``cos`` window ``lo``/``hi`` and the k-vector range."""
    n = b.shape[0]
    npairs = n * (n - 1) // 2
    pi = np.empty(npairs, dtype=np.int64)
    pj = np.empty(npairs, dtype=np.int64)
    lo = np.empty(npairs)
    hi = np.empty(npairs)
    s = np.empty(npairs, dtype=np.int64)
    e = np.empty(npairs, dtype=np.int64)
    p = 0
    for i in range(n):
        for j in range(i + 1, n):
            d = b[i, 0] * b[j, 0] + b[i, 1] * b[j, 1] + b[i, 2] * b[j, 2]
            th = math.acos(max(-1.0, min(1.0, d)))
            eps = math.sqrt(tol[i] * tol[i] + tol[j] * tol[j]) + margin
            pi[p] = i
            pj[p] = j
            lo[p] = math.cos(th + eps)
            hi[p] = math.cos(max(th - eps, 0.0))
            s[p], e[p] = kvector_range(kvector, line[0], line[1], lo[p], hi[p])
            p += 1
    return pi, pj, lo, hi, s, e


@njit(cache=True)
def _adjacent(ptr, adj, u, v):
    lo = ptr[u]
    hi = ptr[u + 1]
    while lo < hi:
        mid = (lo + hi) // 2
        if adj[mid] < v:
            lo = mid + 1
        else:
            hi = mid
    return lo < ptr[u + 1] and adj[lo] == v


@njit(cache=True)
def voting_clusters(b, tol, margin, n_cat, pair_i, pair_j, pair_cos, kvector, line, k_min, max_clusters):
    """Both voting steps on every candidate, the triangle votes and the clusters, strongest first.

    ``tol`` (rad, per image star) and ``margin`` give each image pair its window
    ``sqrt(tol_i^2 + tol_j^2) + margin``.  Hypotheses with fewer than ``k_min`` first-step
    votes or validation votes (distinct supporting stars) are dropped; each survivor's
    triangle votes are the agreeing pairs among its supporters; clusters are grown from
    every hypothesis with a triangle, most triangles first: the seed, then its supporters
    (most triangles first) that agree with every member, one per image star and catalog
    star.

    Returns ``(stars, cats, sizes, score, n_hyp, n_edges)``: row ``r`` of ``stars``/``cats``
    (first ``sizes[r]`` entries) is a cluster, ``score[r]`` its seed's triangle votes.
    """
    n = b.shape[0]
    pi, pj, lo, hi, s, e = _windows(b, tol, margin, kvector, line)
    votes1 = np.zeros((n, n_cat), dtype=np.int32)
    stamp = np.full((n, n_cat), -1, dtype=np.int64)
    for p in range(pi.shape[0]):
        i = pi[p]
        j = pj[p]
        for t in range(s[p], e[p]):
            c = pair_cos[t]
            if c < lo[p] or c > hi[p]:
                continue
            k = pair_i[t]
            l = pair_j[t]
            vote_once(votes1, stamp, i, k, p)
            vote_once(votes1, stamp, i, l, p)
            vote_once(votes1, stamp, j, k, p)
            vote_once(votes1, stamp, j, l, p)
    # Validation votes (distinct supporting stars) of the hypotheses with k_min first-step votes.
    votes2 = np.zeros((n, n_cat), dtype=np.int32)
    stamp[:, :] = -1
    for p in range(pi.shape[0]):
        i = pi[p]
        j = pj[p]
        for t in range(s[p], e[p]):
            c = pair_cos[t]
            if c < lo[p] or c > hi[p]:
                continue
            k = pair_i[t]
            l = pair_j[t]
            if votes1[i, k] >= k_min and votes1[j, l] >= k_min:
                vote_once(votes2, stamp, i, k, p)
                vote_once(votes2, stamp, j, l, p)
            if votes1[i, l] >= k_min and votes1[j, k] >= k_min:
                vote_once(votes2, stamp, i, l, p)
                vote_once(votes2, stamp, j, k, p)
    hid = np.full((n, n_cat), -1, dtype=np.int64)
    nh = 0
    for i in range(n):
        for c in range(n_cat):
            if votes1[i, c] >= k_min and votes2[i, c] >= k_min:
                hid[i, c] = nh
                nh += 1
    hstar = np.empty(nh, dtype=np.int64)
    hcat = np.empty(nh, dtype=np.int64)
    for i in range(n):
        for c in range(n_cat):
            h = hid[i, c]
            if h >= 0:
                hstar[h] = i
                hcat[h] = c
    # The graph: agreeing pairs among the survivors (CSR, sorted neighbour lists).
    deg = np.zeros(nh + 1, dtype=np.int64)
    for sweep in range(2):
        if sweep == 1:
            ptr = np.zeros(nh + 1, dtype=np.int64)
            for h in range(nh):
                ptr[h + 1] = ptr[h] + deg[h]
            adj = np.empty(ptr[nh], dtype=np.int64)
            fill = ptr[:nh].copy()
        for p in range(pi.shape[0]):
            i = pi[p]
            j = pj[p]
            for t in range(s[p], e[p]):
                c = pair_cos[t]
                if c < lo[p] or c > hi[p]:
                    continue
                k = pair_i[t]
                l = pair_j[t]
                for o in range(2):
                    a = hid[i, k] if o == 0 else hid[i, l]
                    g = hid[j, l] if o == 0 else hid[j, k]
                    if a < 0 or g < 0:
                        continue
                    if sweep == 0:
                        deg[a] += 1
                        deg[g] += 1
                    else:
                        adj[fill[a]] = g
                        fill[a] += 1
                        adj[fill[g]] = a
                        fill[g] += 1
    n_edges = 0
    for h in range(nh):
        adj[ptr[h]:ptr[h + 1]] = np.sort(adj[ptr[h]:ptr[h + 1]])
        n_edges += ptr[h + 1] - ptr[h]
    n_edges //= 2
    # Triangle votes: common neighbours of the two ends of every edge (sorted merge).
    tri = np.zeros(nh, dtype=np.int64)
    for u in range(nh):
        for x in range(ptr[u], ptr[u + 1]):
            v = adj[x]
            if v <= u:
                continue
            a = ptr[u]
            bb = ptr[v]
            cnt = 0
            while a < ptr[u + 1] and bb < ptr[v + 1]:
                if adj[a] < adj[bb]:
                    a += 1
                elif adj[a] > adj[bb]:
                    bb += 1
                else:
                    cnt += 1
                    a += 1
                    bb += 1
            tri[u] += cnt
            tri[v] += cnt
    # Seeds: hypotheses with a triangle, most triangles first (then validation, first-step votes).
    ns = 0
    for h in range(nh):
        if tri[h] > 0:
            ns += 1
    seeds = np.empty(ns, dtype=np.int64)
    key = np.empty(ns)
    t = 0
    for h in range(nh):
        if tri[h] > 0:
            seeds[t] = h
            key[t] = -(tri[h] * 1e6 + votes2[hstar[h], hcat[h]] * 1e3 + votes1[hstar[h], hcat[h]])
            t += 1
    seeds = seeds[np.argsort(key, kind="mergesort")]
    out_s = np.full((max_clusters, n), -1, dtype=np.int64)
    out_c = np.full((max_clusters, n), -1, dtype=np.int64)
    sizes = np.zeros(max_clusters, dtype=np.int64)
    score = np.zeros(max_clusters, dtype=np.int64)
    nc = 0
    members = np.empty(n, dtype=np.int64)
    for si in range(ns):
        if nc >= max_clusters:
            break
        h0 = seeds[si]
        members[0] = h0
        m = 1
        deg0 = ptr[h0 + 1] - ptr[h0]
        nb = adj[ptr[h0]:ptr[h0 + 1]].copy()
        nkey = np.empty(deg0)
        for x in range(deg0):
            nkey[x] = -(tri[nb[x]] * 1e6 + votes2[hstar[nb[x]], hcat[nb[x]]] * 1e3 + votes1[hstar[nb[x]], hcat[nb[x]]])
        nb = nb[np.argsort(nkey, kind="mergesort")]
        for x in range(deg0):
            g = nb[x]
            ok = True
            for y in range(m):
                if hstar[members[y]] == hstar[g] or hcat[members[y]] == hcat[g] or not _adjacent(ptr, adj, g, members[y]):
                    ok = False
                    break
            if ok:
                members[m] = g
                m += 1
        if m < 3:
            continue
        # The same cluster grown from another of its members: skip.
        dup = False
        for r in range(nc):
            if sizes[r] != m:
                continue
            same = True
            for y in range(m):
                found = False
                for z in range(m):
                    if out_s[r, z] == hstar[members[y]] and out_c[r, z] == hcat[members[y]]:
                        found = True
                        break
                if not found:
                    same = False
                    break
            if same:
                dup = True
                break
        if dup:
            continue
        for y in range(m):
            out_s[nc, y] = hstar[members[y]]
            out_c[nc, y] = hcat[members[y]]
        sizes[nc] = m
        score[nc] = tri[h0]
        nc += 1
    return out_s[:nc], out_c[:nc], sizes[:nc], score[:nc], nh, n_edges


@njit(cache=True, inline="always")
def vote_once(votes, stamp, i, c, key):
    """One vote for hypothesis ``(i, c)`` per ``key`` (an image pair): ``stamp`` remembers the last key."""
    if stamp[i, c] != key:
        stamp[i, c] = key
        votes[i, c] += 1


@njit(cache=True)
def geometric_voting_top(b, n_cat, pair_i, pair_j, pair_cos, kvector, line, eps, star_vec, top):
    """Kolomenkin et al. (2008) voting, keeping each image star's ``top`` most-voted identities.

    First step (each image pair votes for both
    stars of every catalog pair at its angle within ``eps``, once per image
    pair).  Each image star keeps its ``top`` most-voted catalog stars (ties
    by index).  Second (verification) step over these hypotheses: hypothesis
    ``(i, a)`` gets a vote from every hypothesis ``(j, c)`` of another star
    whose catalog angle agrees with the image angle within ``eps``.

    Returns ``(identity[n, top], votes1[n, top], votes2[n, top])``, identity -1
    where fewer candidates were voted for.
    """
    n = b.shape[0]
    votes = np.zeros((n, n_cat), dtype=np.int32)
    stamp = np.full((n, n_cat), -1, dtype=np.int64)
    pair_id = 0
    for i in range(n):
        for j in range(i + 1, n):
            th = _angle(b[i], b[j])
            lo, hi = _cos_window(th, eps)
            s, e = kvector_range(kvector, line[0], line[1], lo, hi)
            for t in range(s, e):
                c = pair_cos[t]
                if c < lo or c > hi:
                    continue
                k = pair_i[t]
                l = pair_j[t]
                vote_once(votes, stamp, i, k, pair_id)
                vote_once(votes, stamp, i, l, pair_id)
                vote_once(votes, stamp, j, k, pair_id)
                vote_once(votes, stamp, j, l, pair_id)
            pair_id += 1
    identity = np.full((n, top), -1, dtype=np.int64)
    votes1 = np.zeros((n, top), dtype=np.int64)
    for i in range(n):
        for c in range(n_cat):
            v = votes[i, c]
            if v == 0 or v <= votes1[i, top - 1]:
                continue
            # insert into the sorted top list
            p = top - 1
            while p > 0 and votes1[i, p - 1] < v:
                votes1[i, p] = votes1[i, p - 1]
                identity[i, p] = identity[i, p - 1]
                p -= 1
            votes1[i, p] = v
            identity[i, p] = c
    votes2 = np.zeros((n, top), dtype=np.int64)
    for i in range(n):
        for a in range(top):
            ci = identity[i, a]
            if ci < 0:
                continue
            for j in range(i + 1, n):
                th = _angle(b[i], b[j])
                for c in range(top):
                    cj = identity[j, c]
                    if cj < 0 or cj == ci:
                        continue
                    if abs(_angle(star_vec[ci], star_vec[cj]) - th) <= eps:
                        votes2[i, a] += 1
                        votes2[j, c] += 1
    return identity, votes1, votes2


@njit(cache=True)
def grow_clusters(b, keep, tol, margin, star_vec, fi, fc, fv, start, stop, threshold):
    """Geometric voting's clusters (:func:`startrack.identify.voting._clusters`) of seeds ``start`` to ``stop``.

    ``fi``, ``fc``, ``fv``: the hypotheses (image star, catalog star, support), strongest
    first.  Each seed with support >= ``threshold`` grows greedily through the list: a
    hypothesis joins when neither its image star nor its catalog star is in the cluster
    and its image angle to every member agrees with the catalog angle within the pair
    tolerance ``hypot(tol[keep[i]], tol[keep[m]]) + margin``.

    Returns ``(members, sizes, end)``: row ``s - start`` of ``members`` holds the flat
    indices of seed ``s``'s cluster (its first ``sizes`` entries); ``end`` the first seed
    not grown (below the threshold, or ``stop``).
    """
    nf = fi.shape[0]
    n = b.shape[0]
    stop = min(stop, nf)
    members = np.full((max(stop - start, 0), n), -1, dtype=np.int64)
    sizes = np.zeros(max(stop - start, 0), dtype=np.int64)
    end = start
    for s in range(start, stop):
        if fv[s] < threshold:
            break
        end = s + 1
        row = s - start
        members[row, 0] = s
        k = 1
        for f in range(nf):
            i = fi[f]
            c = fc[f]
            clash = False
            for u in range(k):
                g = members[row, u]
                if fi[g] == i or fc[g] == c:
                    clash = True
                    break
            if clash:
                continue
            ok = True
            for u in range(k):
                g = members[row, u]
                m = fi[g]
                th = math.acos(min(1.0, b[i, 0] * b[m, 0] + b[i, 1] * b[m, 1] + b[i, 2] * b[m, 2]))
                d = fc[g]
                tc = math.acos(min(1.0, star_vec[c, 0] * star_vec[d, 0] + star_vec[c, 1] * star_vec[d, 1]
                                   + star_vec[c, 2] * star_vec[d, 2]))
                if abs(th - tc) > math.hypot(tol[keep[i]], tol[keep[m]]) + margin:
                    ok = False
                    break
            if ok and k < n:
                members[row, k] = f
                k += 1
        sizes[row] = k
    return members, sizes, end
