"""Grid identification (Padgett & Kreutz-Delgado 1997, "A grid algorithm for autonomous star identification").

Pattern of a reference star: its neighbours between the buffer radius ``br``
and the pattern radius ``pr`` are projected on the tangent plane at the star
(gnomonic), the plane is turned so that the nearest neighbour outside ``br``
lies on the +x axis, and a ``g x g`` grid over ``[-pr, pr]^2`` marks the cells
holding a neighbour.  The pattern is the set of on-cells.

Matching: each sensor pattern votes, through an inverted index cell -> catalog
stars, for the catalog patterns sharing its on-cells (bit overlap); the best
is taken when its overlap reaches ``min_overlap`` and beats the runner-up.
Confirmation: several reference stars (those nearest the image centre) are
matched independently and the largest set whose catalog angles agree with the
measured angles (within ``eps``) is kept as the proposal.

The catalog patterns are computed from the k-vector database's star table and
neighbour lists the first time they are needed (1.2-1.6 s for a 4534-star database, 25 MB, at
5 orientations and g = 124; once per database, sensor and tolerance) and cached, so
that the grid needs no database of its own and always matches the sensor's
``g``, ``pr`` and ``br``.

Extensions (not in the paper), each for a reason any sensor shares:

* the catalog patterns are stored oriented by each star's 1st to 5th nearest neighbour
  (``catalog_orientations``): the database is deeper than what the sensor detects (here
  Hp <= 6 against stars to 5.5) and a reference off centre has catalog neighbours outside
  the field, so the image's nearest neighbour is often not the catalog's and the paper's
  single orientation turns the pattern (15 deg 1280x960 sensor, 0.3 px, 300 frames: the
  image's nearest true neighbour is the catalog's 1st for 47 % of the references, among
  the first 3 for 81 %, 5 for 91 %, 7 for 95 %);
* the image patterns are oriented by the 2nd to 5th nearest neighbours too
  (``orientations``): a false star nearer than the true one;
* each reference keeps its ``matches_per_reference`` best catalog patterns instead of
  the unique best, and the confirmation between references (catalog angles agreeing
  with the image) chooses: false stars add cells that chance patterns share, so the
  true pattern is often not the unique best;
* when the groups of the references nearest the centre are rejected, every search
  star becomes a reference (among false stars the first ones hold too few true
  references to confirm each other); every agreeing pair of references seeds a group;
* the proposal holds, beside the confirmed references, the neighbours whose angles to
  every reference match exactly one catalog star: two references alone are a pair
  pattern, which in a 4-6 star field the shared verification rightly finds too common
  by chance to accept;
* when every confirmed group is rejected, each reference match is proposed alone
  (``single_references``; the way geometric voting's every-candidate search validates
  each candidate, ``voting.py``): the grid match pairs the image pattern's orientation
  star with the catalog pattern's, and the neighbours whose angles to both name one
  catalog star join them; in 4-5 star fields often only one reference has its true
  pattern among the best (15 deg sensor, 0.3 px: 9 of 1000 frames);
* the pattern radius defaults to the field's diagonal, the farthest two stars of one image
  can be apart, so that every star of the image is a neighbour of every reference wherever
  it lies (was the half-diagonal, the reach of a reference at the centre: in a 4-6 star
  field the references off centre then lacked ``min_overlap`` neighbours, 26 of 1000
  frames of the 15 deg 1280x960 sensor had fewer than two references with three);
* the grid size follows from the database's density (``grid_geometry``): ``g`` such that
  a catalog pattern marks about ``cell_fill`` (1 %) of the cells within ``pr``, i.e. the
  chance that a random catalog pattern holds a given image cell stays the same for any
  pattern radius, sensor and catalog depth (the previous fixed ``g = 40`` at the
  half-diagonal marked 2.4 % on that sensor; doubling ``pr`` with a fixed ``g`` would
  have made it 4x that).

Other defaults (from the 24 deg / magnitude 5.2 sensor of paper 004; the paper's own
values are not in our sources): ``br`` = 6 px (at least 3 eps), 12 reference stars, an
overlap of at least 3 cells.  The paper's confirmation needs two reference stars
with three neighbours each whose true pattern is among the best
(``benchmarks/studies/grid_reasons.py`` counts the frames that have fewer); ``single_references``
proposes a reference without a second one.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from startrack.identify.algorithm import Algorithm, Proposal


@dataclass(frozen=True)
class GridConfig:
    """Settings of the grid algorithm (Padgett & Kreutz-Delgado 1997)."""

    grid_size: int | None = field(default=None, metadata={
        "help": "Cells per side of the pattern grid (g); default from the database's density (cell_fill)."})
    pattern_radius_deg: float | None = field(default=None, metadata={
        "help": "Pattern radius pr (deg); default the field's diagonal (the farthest two stars of one image can be)."})
    cell_fill: float = field(default=0.01, metadata={
        "help": "Without grid_size: the fraction of the cells within pr that a catalog pattern marks on average "
                "(sets g from the database's stars per solid angle)."})
    buffer_px: float = field(default=6.0, metadata={"help": "Buffer radius br (px; at least 3 tolerances)."})
    min_overlap: int = field(default=3, metadata={"help": "On-cells a catalog pattern must share."})
    references: int = field(default=12, metadata={
        "help": "Reference stars (nearest the centre) matched first; every search star follows when their "
                "groups are rejected."})
    orientations: int = field(default=5, metadata={
        "help": "Orientation neighbours tried per reference when the search goes on (1: the paper's nearest)."})
    matches_per_reference: int = field(default=4, metadata={
        "help": "Catalog patterns kept per reference star, most shared cells first (1: the paper's unique best); "
                "the confirmation between references chooses."})
    single_references: bool = field(default=True, metadata={
        "help": "When every confirmed group is rejected, propose each reference match alone with the "
                "neighbours its orientation pair names (the verification decides)."})
    catalog_orientations: int = field(default=5, metadata={
        "help": "Patterns stored per catalog star, oriented by its 1st, 2nd, ... nearest neighbour (1: the "
                "paper's nearest; a database deeper than the sensor holds neighbours it does not detect)."})


def _tangent_basis(v):
    x, y, z = float(v[0]), float(v[1]), float(v[2])
    # e1 = a x v with a = +z (or +x near the poles), normalised; e2 = v x e1 (np.cross's numbers, without its cost)
    e1 = (-y, x, 0.0) if abs(z) < 0.9 else (0.0, -z, y)
    n = math.sqrt(e1[0] ** 2 + e1[1] ** 2 + e1[2] ** 2)
    e1 = (e1[0] / n, e1[1] / n, e1[2] / n)
    e2 = (y * e1[2] - z * e1[1], z * e1[0] - x * e1[2], x * e1[1] - y * e1[0])
    return np.array(e1), np.array(e2)


def _patterns(centre, neighbours, pr, br, g, count=1, first=0):
    """On-cell indices of the patterns of one star oriented by its ``first``-th, ..., ``first + count - 1``-th
    nearest neighbour outside ``br`` (0: the paper's nearest), each with the index (into ``neighbours``)
    of its orientation star: a list of ``(cells, index)``, shorter when there are fewer neighbours.  The
    projection is computed once for all orientations."""
    if len(neighbours) < 2:
        return []
    cosang = neighbours @ centre
    ang = np.arccos(np.clip(cosang, -1.0, 1.0))
    keep = (ang >= br) & (ang <= pr)
    if keep.sum() < 2:
        return []
    idx = np.flatnonzero(keep)
    e1, e2 = _tangent_basis(centre)
    x = (neighbours[idx] @ e1) / cosang[idx]
    y = (neighbours[idx] @ e2) / cosang[idx]
    by_distance = np.argsort(ang[idx], kind="stable")
    half = math.tan(pr)
    out = []
    for which in range(first, min(first + count, len(idx))):
        nearest = int(by_distance[which])
        phi = math.atan2(y[nearest], x[nearest])
        c, s = math.cos(-phi), math.sin(-phi)
        ix = np.floor(((c * x - s * y) + half) / (2 * half) * g).astype(np.int64)
        iy = np.floor(((s * x + c * y) + half) / (2 * half) * g).astype(np.int64)
        ok = (ix >= 0) & (ix < g) & (iy >= 0) & (iy < g)
        out.append((np.unique(iy[ok] * g + ix[ok]), int(idx[nearest])))
    return out


def _pattern(centre, neighbours, pr, br, g, which=0):
    """On-cell indices of one pattern and the index (into ``neighbours``) of the orientation star
    (the nearest neighbour outside ``br``; ``which`` > 0: the next nearest instead); ``(None, -1)``
    when there are not enough neighbours."""
    got = _patterns(centre, neighbours, pr, br, g, 1, which)
    return got[0] if got else (None, -1)


def catalog_patterns(db, pr, br, g, orientations=1):
    """Patterns of every database star: ``(ptr, inv_ptr, inv_stars, orient)``: pattern ``t`` has
    ``ptr[t + 1] - ptr[t]`` on-cells; the patterns holding cell ``c`` are ``inv_stars[inv_ptr[c]:inv_ptr[c + 1]]``
    (ascending); ``orient[t]`` is its orientation star (-1: no pattern).

    Pattern ``s * orientations + w`` is star ``s``'s oriented by its ``w``-th nearest
    neighbour outside ``br`` (empty when it has fewer).
    """
    key = (round(pr, 9), round(br, 9), g, int(orientations))
    # Kept on the database object itself (dropped with it), keyed by (pr, br, g, orientations).
    per_db = db.__dict__.setdefault("_grid_patterns", {})
    if key in per_db:
        return per_db[key]
    n = db.n_stars
    k_or = int(orientations)
    ptr = np.zeros(n * k_or + 1, dtype=np.int64)
    cells_all = []
    orient = np.full(n * k_or, -1, dtype=np.int64)
    for s in range(n):
        nb = db.neighbor_idx[db.neighbor_ptr[s]:db.neighbor_ptr[s + 1]]
        got = _patterns(db.star_vector[s], db.star_vector[nb], pr, br, g, k_or)
        for w in range(k_or):
            t = s * k_or + w
            if w >= len(got):
                ptr[t + 1] = ptr[t]
                continue
            cells, k = got[w]
            cells_all.append(cells.astype(np.int32))
            orient[t] = nb[k]
            ptr[t + 1] = ptr[t] + len(cells)
    # int32: cell numbers below g^2 and pattern numbers below n * orientations (half the memory of int64).
    # Only the inverted index is kept (the search looks patterns up by cell; each pattern's cells are
    # not needed again): half the memory of keeping both.
    cells = np.concatenate(cells_all) if cells_all else np.zeros(0, dtype=np.int32)
    del cells_all
    owner = np.repeat(np.arange(n * k_or, dtype=np.int32), np.diff(ptr))
    inv_stars = owner[np.argsort(cells, kind="stable")]
    del owner
    inv_ptr = np.zeros(g * g + 1, dtype=np.int64)
    np.cumsum(np.bincount(cells, minlength=g * g), out=inv_ptr[1:])
    if len(per_db) > 4:
        per_db.clear()
    per_db[key] = (ptr, inv_ptr, inv_stars, orient)
    return per_db[key]


def _best(cells, inv_ptr, inv_stars, n_patterns, k_or, min_overlap, keep):
    """Catalog stars whose pattern (any of its orientations) shares the most on-cells, at least
    ``min_overlap``: with ``keep`` = 1 the paper's unique best (none when the runner-up ties), else the
    ``keep`` best, most shared cells first.  Returns a list of (star, shared cells, pattern index)."""
    votes = np.bincount(np.concatenate([inv_stars[inv_ptr[c]:inv_ptr[c + 1]] for c in cells]), minlength=n_patterns)
    hit = np.flatnonzero(votes >= min_overlap)           # only these can be kept
    if len(hit) == 0:
        return []
    star = hit // k_or
    v = votes[hit]
    order = np.lexsort((star, -v))                      # most votes first, then by star
    star, v, hit = star[order], v[order], hit[order]
    first = np.unique(star, return_index=True)[1]      # each star's best orientation
    first.sort()
    star, v, hit = star[first], v[first], hit[first]
    if keep <= 1:
        if len(v) > 1 and v[1] == v[0]:
            return []
        return [(int(star[0]), int(v[0]), int(hit[0]))]
    return [(int(a), int(c), int(t)) for a, c, t in zip(star[:keep], v[:keep], hit[:keep])]


def grid_geometry(camera, db, config: GridConfig, eps: float):
    """``(pr, br, g)``: pattern radius and buffer radius (rad) and cells per side of the grid.

    ``pr`` defaults to the field's diagonal (at most the database's largest pair angle): every
    other star of the image is then a neighbour of every reference, wherever it lies in the
    field.  ``g`` defaults to the grid whose cells within ``pr`` a catalog pattern marks in the
    fraction ``cell_fill``: a catalog pattern holds ``N (1 - cos pr) / 2`` neighbours on average
    (``N`` database stars over the sphere) in ``pi g^2 / 4`` cells, so a chance pattern shares a
    given image cell with probability ``cell_fill`` whatever the sensor and database depth.
    """
    pr = math.radians(config.pattern_radius_deg) if config.pattern_radius_deg is not None else \
        math.radians(camera.diagonal_fov_deg)
    pr = min(pr, math.radians(db.max_angle_deg))
    # At least three tolerances; above the configured buffer, rounded up to a power of sqrt(2) times
    # it, so that frames whose tolerance differs a little (each frame's own star sigmas) share one
    # set of catalog patterns instead of building their own.
    buffer = float(config.buffer_px) / camera.focal_length_px
    br = buffer if 3 * eps <= buffer else buffer * 2.0 ** (math.ceil(2.0 * math.log2(3 * eps / buffer)) / 2.0)
    if config.grid_size is not None:
        g = int(config.grid_size)
    else:
        neighbours = db.n_stars * (1.0 - math.cos(pr)) / 2.0
        g = max(8, int(math.ceil(math.sqrt(4.0 * neighbours / (math.pi * float(config.cell_fill))))))
    return pr, br, g


def search_grid(ctx, config: GridConfig):
    """Grid matches of the reference stars; the confirmed groups, largest first."""
    b, db, eps, camera = ctx.b, ctx.db, ctx.eps, ctx.camera
    pr, br, g = grid_geometry(camera, db, config, eps)
    min_overlap = int(config.min_overlap)
    n_refs = int(config.references)
    k_or = max(1, int(config.catalog_orientations))
    keep = max(1, int(config.matches_per_reference))
    ptr, inv_ptr, inv_stars, orient = catalog_patterns(db, pr, br, g, k_or)
    n_patterns = len(ptr) - 1
    boresight = np.array([0.0, 0.0, 1.0])
    # Reference stars: nearest the image centre first.
    order = np.argsort(-(b @ boresight))
    refs = []
    named = set()           # (reference, catalog star) pairs in refs
    done = set()
    # The references nearest the centre first; when all their groups are rejected, every search star
    # (false stars among the first ones leave too few true references to confirm each other).
    for batch in ([order[:n_refs], order] if len(order) > n_refs else [order]):
        for which in range(int(config.orientations)):
            # The search goes on (Padgett & Kreutz-Delgado orient by the nearest neighbour; a false
            # star nearer than the true one turns the whole pattern): each reference's pattern
            # oriented by its next nearest neighbours, the new matches added to the references.
            more = list(refs)
            for r in batch:
                if (int(r), which) in done:
                    continue
                done.add((int(r), which))
                others = np.delete(np.arange(len(b)), r)
                cells, k = _pattern(b[r], b[others], pr, br, g, which)
                if cells is None or len(cells) < min_overlap:
                    continue
                for best, votes, t in _best(cells, inv_ptr, inv_stars, n_patterns, k_or, min_overlap, keep):
                    if (int(r), best) not in named:
                        named.add((int(r), best))
                        more.append((int(r), best, int(others[k]), int(orient[t]), votes))
            if not refs or len(more) > len(refs):
                refs = more
                yield from _confirmed(ctx, b, db, refs, which + 1)
    if config.single_references:
        yield from _single(ctx, b, db, refs)


def _single(ctx, b, db, refs):
    """Each reference match alone, most shared cells first, as a proposal of the reference, its
    orientation star and the neighbours whose angles to both name one catalog star
    (:func:`_with_neighbours`; a mirror-image neighbour makes the verification reject the proposal).

    The grid's match pairs the image pattern oriented by the reference's orientation star with the
    catalog pattern oriented by the catalog star's: the two orientation stars correspond (when
    their angles to the references agree).  A reference whose match no other reference confirms
    (fewer than two references with their true pattern among the best, e.g. a 4-5 star field
    with the nearest neighbours of the catalog stars outside the field) is then still proposed,
    and the shared verification decides, as for every proposal.
    """
    sv = db.star_vector
    for i in np.argsort([-v for *_, v in refs], kind="stable"):
        r, c, o, co, _ = refs[i]
        if co < 0 or co == c or o == r:
            continue
        th = math.acos(min(1.0, float(b[r] @ b[o])))
        tc = math.acos(min(1.0, float(sv[c] @ sv[co])))
        if abs(th - tc) > ctx.pair_eps(r, o):
            continue
        img, cat = _with_neighbours(ctx, b, db, [r, o], [c, co])
        if len(img) < 3:
            continue
        yield Proposal(img, cat, len(refs), {"grid_votes": [refs[i][-1]], "grid_references": 1})


def _confirmed(ctx, b, db, refs, rounds):
    """Groups of references whose catalog angles agree with the image, largest first, as proposals."""
    if not refs:
        return
    # Confirmation: groups of references whose catalog angles agree with the image (one catalog star per
    # image star and one image star per catalog star).  Each agreeing pair of references seeds a group,
    # grown greedily with the references agreeing with every member (most votes first): a chance
    # reference that agrees with one true reference cannot then keep the true ones out of every group.
    img = np.array([r for r, *_ in refs])
    cat = np.array([c for _, c, *_ in refs])
    th = np.arccos(np.clip(b[img] @ b[img].T, -1.0, 1.0))
    tc = np.arccos(np.clip(db.star_vector[cat] @ db.star_vector[cat].T, -1.0, 1.0))
    tol = np.hypot(ctx.tol[img][:, None], ctx.tol[img][None, :]) + ctx.margin
    agree = (np.abs(th - tc) <= tol) & (img[:, None] != img[None, :]) & (cat[:, None] != cat[None, :])
    by_votes = np.argsort([-v for *_, v in refs], kind="stable")
    groups = {}
    for i in range(len(refs)):
        for j in np.flatnonzero(agree[i]):
            if j < i:
                continue
            members = [i, int(j)]
            mask = agree[i] & agree[j]          # the references agreeing with every member so far
            for h in by_votes[mask[by_votes]]:
                if mask[h]:
                    members.append(int(h))
                    mask &= agree[h]
            group = [refs[m] for m in members]
            key = frozenset((r, c) for r, c, *_ in group)
            if key not in groups:
                groups[key] = group
    # The confirmed reference stars are the proposal, with the neighbours whose angles to all of them
    # name one catalog star (_with_neighbours).  (Not their orientation neighbours: the image's nearest
    # neighbour need not be the catalog's -- a missing or extra star changes it.)
    for group in sorted(groups.values(), key=lambda g: (-len(g), -sum(v for *_, v in g))):
        img_g, cat_g = _with_neighbours(ctx, b, db, [r for r, *_ in group], [c for _, c, *_ in group])
        yield Proposal(img_g, cat_g, len(refs),
                       {"grid_votes": [v for *_, v in group], "grid_orientations": rounds,
                        "grid_references": len(group)})


def _with_neighbours(ctx, b, db, img, cat):
    """The confirmed references and the image stars whose angles to every one of them match exactly one
    catalog neighbour of the first reference's catalog star (within the pair tolerances).

    The grid's pattern match names the reference; its neighbours follow from the same angle
    confirmation as the references (two or more references: a triangle or more per neighbour).  A
    proposal of two references alone is a pair pattern, too common by chance in a sparse field for
    the shared verification to accept; with its confirmed neighbours it is a pattern of four or more.
    """
    if len(img) < 2:
        return img, cat
    c0 = cat[0]
    nb = np.asarray(db.neighbor_idx[db.neighbor_ptr[c0]:db.neighbor_ptr[c0 + 1]], dtype=np.int64)
    nb = nb[~np.isin(nb, cat)]
    if len(nb) == 0:
        return img, cat
    rest = np.setdiff1d(np.arange(len(b)), img)
    if len(rest) == 0:
        return img, cat
    ri = np.asarray(img)
    th = np.arccos(np.clip(b[rest] @ b[ri].T, -1.0, 1.0))                        # (rest, refs)
    tc = np.arccos(np.clip(db.star_vector[nb] @ db.star_vector[np.asarray(cat)].T, -1.0, 1.0))   # (nb, refs)
    tol = np.hypot(ctx.tol[rest][:, None], ctx.tol[ri][None, :]) + ctx.margin   # (rest, refs)
    ok = (np.abs(th[:, None, :] - tc[None, :, :]) <= tol[:, None, :]).all(axis=2)  # (rest, nb)
    img, cat = list(img), list(cat)
    taken = set(cat)
    for a in range(len(rest)):
        hit = np.flatnonzero(ok[a])
        if len(hit) == 1 and int(nb[hit[0]]) not in taken and np.count_nonzero(ok[:, hit[0]]) == 1:
            img.append(int(rest[a]))
            cat.append(int(nb[hit[0]]))
            taken.add(int(nb[hit[0]]))
    return img, cat


def prepare_grid(config: GridConfig, camera, db, eps: float) -> bool:
    """Build (once per database, camera and buffer radius) the catalog patterns a frame will need.

    The driver calls it before it starts the frame's clock: the patterns are the database's,
    made for this sensor (like loading it), not part of identifying the frame.  True when it
    built them now.
    """
    pr, br, g = grid_geometry(camera, db, config, eps)
    k_or = max(1, int(config.catalog_orientations))
    key = (round(pr, 9), round(br, 9), g, k_or)
    if key in db.__dict__.get("_grid_patterns", {}):
        return False
    catalog_patterns(db, pr, br, g, k_or)
    return True


GRID = Algorithm("grid", search_grid, GridConfig, "kvector",
                 "Padgett & Kreutz-Delgado's grid patterns, built from the k-vector database's neighbour lists.",
                 prepare=prepare_grid)
