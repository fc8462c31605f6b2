"""Grid identification (Padgett & Kreutz-Delgado 1997, "A grid algorithm for autonomous star identification").

Pattern of a reference star: its neighbours between the buffer radius ``br``
and the pattern radius ``pr`` are projected on the tangent plane at the star
(gnomonic), the plane is turned so that the nearest neighbour outside ``br``
lies on the +x axis, and a ``g x g`` grid over ``[-pr, pr]^2`` marks the cells
holding a neighbour.  The pattern is the set of on-cells.

Matching: each sensor pattern votes, through an inverted index cell -> catalog
stars, for the catalog patterns sharing its on-cells (bit overlap); the best
is taken when its overlap reaches ``min_overlap`` and beats the runner-up.
Confirmation: several reference stars (those nearest the image centre, whose
pattern disc lies inside the field) are matched independently and the largest
set whose catalog angles agree with the measured angles (within ``eps``) is
kept as the proposal.

The catalog patterns are computed from the k-vector database's star table and
neighbour lists the first time they are needed (milliseconds) and cached, so
that the grid needs no database of its own and always matches the sensor's
``g``, ``pr`` and ``br``.

Defaults (tuned on the 24 deg / magnitude 5.2 sensor of paper 004; the
paper's own values are not in our sources): ``g = 40``, ``pr`` = 0.6 of the
narrower field, ``br`` = 6 px (at least 3 eps), 12 reference stars, an
overlap of at least 3 cells.  With only ~20 stars per field the patterns are
sparse, which limits the method (Padgett & Kreutz-Delgado simulated an 8 deg
field with a much deeper catalog).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from startrack.identify.base import Algorithm, Proposal


@dataclass(frozen=True)
class GridConfig:
    """Settings of the grid algorithm (Padgett & Kreutz-Delgado 1997)."""

    grid_size: int = field(default=40, metadata={"help": "Cells per side of the pattern grid (g)."})
    pattern_radius_deg: float | None = field(default=None, metadata={
        "help": "Pattern radius pr (deg); default 0.6 of the narrower field."})
    buffer_px: float = field(default=6.0, metadata={"help": "Buffer radius br (px; at least 3 tolerances)."})
    min_overlap: int = field(default=3, metadata={"help": "On-cells a catalog pattern must share."})
    references: int = field(default=12, metadata={"help": "Reference stars (nearest the centre) matched."})
    orientations: int = field(default=3, metadata={
        "help": "Orientation neighbours tried per reference when the search goes on (1: the paper's nearest)."})


def _tangent_basis(v):
    a = np.array([0.0, 0.0, 1.0]) if abs(v[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    e1 = np.cross(a, v)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(v, e1)
    return e1, e2


def _pattern(centre, neighbours, pr, br, g, which=0):
    """On-cell indices of one pattern and the index (into ``neighbours``) of the orientation star
    (the nearest neighbour outside ``br``; ``which`` > 0: the next nearest instead)."""
    if len(neighbours) == 0:
        return None, -1
    cosang = neighbours @ centre
    ang = np.arccos(np.clip(cosang, -1.0, 1.0))
    keep = (ang >= br) & (ang <= pr)
    if keep.sum() < 2:
        return None, -1
    idx = np.flatnonzero(keep)
    e1, e2 = _tangent_basis(centre)
    x = (neighbours[idx] @ e1) / cosang[idx]
    y = (neighbours[idx] @ e2) / cosang[idx]
    if which >= len(idx):
        return None, -1
    nearest = int(np.argsort(ang[idx], kind="stable")[which]) if which else int(np.argmin(ang[idx]))
    phi = math.atan2(y[nearest], x[nearest])
    c, s = math.cos(-phi), math.sin(-phi)
    xr = c * x - s * y
    yr = s * x + c * y
    half = math.tan(pr)
    ix = np.floor((xr + half) / (2 * half) * g).astype(np.int64)
    iy = np.floor((yr + half) / (2 * half) * g).astype(np.int64)
    ok = (ix >= 0) & (ix < g) & (iy >= 0) & (iy < g)
    cells = np.unique(iy[ok] * g + ix[ok])
    return cells, int(idx[nearest])


def catalog_patterns(db, pr, br, g):
    """Patterns of every database star: CSR (ptr, cells), inverted index (cell -> stars), orientation stars."""
    key = (round(pr, 9), round(br, 9), g)
    # Kept on the database object itself (dropped with it), keyed by (pr, br, g).
    per_db = db.__dict__.setdefault("_grid_patterns", {})
    if key in per_db:
        return per_db[key]
    n = db.n_stars
    ptr = np.zeros(n + 1, dtype=np.int64)
    cells_all = []
    orient = np.full(n, -1, dtype=np.int64)
    for s in range(n):
        nb = db.neighbor_idx[db.neighbor_ptr[s]:db.neighbor_ptr[s + 1]]
        cells, k = _pattern(db.star_vector[s], db.star_vector[nb], pr, br, g)
        if cells is None:
            ptr[s + 1] = ptr[s]
            continue
        cells_all.append(cells)
        orient[s] = nb[k]
        ptr[s + 1] = ptr[s] + len(cells)
    cells = np.concatenate(cells_all) if cells_all else np.zeros(0, dtype=np.int64)
    owner = np.repeat(np.arange(n), np.diff(ptr))
    order = np.argsort(cells, kind="stable")
    inv_stars = owner[order]
    inv_ptr = np.searchsorted(cells[order], np.arange(g * g + 1))
    per_db.clear()
    per_db[key] = (ptr, cells, inv_ptr, inv_stars, orient)
    return per_db[key]


def search_grid(ctx, config: GridConfig):
    """Grid matches of the reference stars; the confirmed groups, largest first."""
    b, db, eps, camera = ctx.b, ctx.db, ctx.eps, ctx.camera
    g = int(config.grid_size)
    fov = math.radians(min(camera.fov_deg))
    pr = math.radians(config.pattern_radius_deg) if config.pattern_radius_deg is not None else 0.6 * fov
    pr = min(pr, math.radians(db.max_angle_deg))
    br = max(float(config.buffer_px) / camera.focal_length_px, 3 * eps)
    min_overlap = int(config.min_overlap)
    n_refs = int(config.references)
    ptr, cells_db, inv_ptr, inv_stars, orient = catalog_patterns(db, pr, br, g)
    boresight = np.array([0.0, 0.0, 1.0])
    # Reference stars: nearest the image centre first.
    order = np.argsort(-(b @ boresight))
    refs = []
    for r in order[:n_refs]:
        others = np.delete(np.arange(len(b)), r)
        cells, k = _pattern(b[r], b[others], pr, br, g)
        if cells is None or len(cells) < min_overlap:
            continue
        votes = np.zeros(db.n_stars, dtype=np.int64)
        for c in cells:
            votes[inv_stars[inv_ptr[c]:inv_ptr[c + 1]]] += 1
        top = np.argsort(-votes)[:2]
        best, second = int(top[0]), int(top[1]) if len(top) > 1 else -1
        if votes[best] < min_overlap or (second >= 0 and votes[second] == votes[best]):
            continue
        refs.append((int(r), best, int(others[k]), int(orient[best]), int(votes[best])))
    yield from _confirmed(ctx, b, db, refs, 1)
    # The search goes on (Padgett & Kreutz-Delgado orient by the nearest neighbour; a false
    # star nearer than the true one turns the whole pattern): each reference's pattern
    # oriented by its next nearest neighbours, the new matches added to the references.
    for which in range(1, int(config.orientations)):
        more = list(refs)
        for r in order[:n_refs]:
            others = np.delete(np.arange(len(b)), r)
            cells, k = _pattern(b[r], b[others], pr, br, g, which)
            if cells is None or len(cells) < min_overlap:
                continue
            votes = np.zeros(db.n_stars, dtype=np.int64)
            for c in cells:
                votes[inv_stars[inv_ptr[c]:inv_ptr[c + 1]]] += 1
            top = np.argsort(-votes)[:2]
            best, second = int(top[0]), int(top[1]) if len(top) > 1 else -1
            if votes[best] < min_overlap or (second >= 0 and votes[second] == votes[best]):
                continue
            if any(x[0] == int(r) and x[1] == best for x in more):
                continue
            more.append((int(r), best, int(others[k]), int(orient[best]), int(votes[best])))
        if len(more) > len(refs):
            refs = more
            yield from _confirmed(ctx, b, db, refs, which + 1)


def _confirmed(ctx, b, db, refs, rounds):
    """Groups of references whose catalog angles agree with the image, largest first, as proposals."""
    if not refs:
        return
    # Confirmation: groups of references whose catalog angles agree with the image, largest first.
    groups = []
    for i in range(len(refs)):
        group = [refs[i]]
        for j in range(len(refs)):
            if j == i:
                continue
            ok = True
            for rr in group:
                th = math.acos(min(1.0, float(b[refs[j][0]] @ b[rr[0]])))
                tc = math.acos(min(1.0, float(db.star_vector[refs[j][1]] @ db.star_vector[rr[1]])))
                if abs(th - tc) > ctx.pair_eps(refs[j][0], rr[0]) or refs[j][1] == rr[1]:
                    ok = False
                    break
            if ok:
                group.append(refs[j])
        key = frozenset(r for r, *_ in group)
        if len(group) >= 2 and key not in {k for k, _ in groups}:
            groups.append((key, group))
    # The confirmed reference stars are the proposal.  (Their orientation
    # neighbours are not added: the image's nearest neighbour need not be the
    # catalog's -- a missing or extra star changes it -- and one wrong pair in
    # the proposal can pull the attitude onto the wrong member of a close pair.)
    for _, group in sorted(groups, key=lambda kg: -len(kg[1])):
        if any(r == r2 for i, (r, *_) in enumerate(group) for (r2, *_) in group[i + 1:]):
            continue    # one image star proposed as two catalog stars (two orientations)
        yield Proposal([r for r, *_ in group], [c for _, c, *_ in group], len(refs),
                       {"grid_votes": [v for *_, v in group], "grid_orientations": rounds})


GRID = Algorithm("grid", search_grid, GridConfig, "kvector",
                 "Padgett & Kreutz-Delgado's grid patterns, built from the k-vector database's neighbour lists.")
