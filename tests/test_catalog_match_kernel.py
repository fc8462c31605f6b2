"""The final match's kernel (startrack._kernels.catalog_match.match_detections) decides as the numpy pass it
replaced (issue 38): nearest star, ambiguity, unresolved pairs, chance, ids taken, one detection per star; and
the magnitude-limited cone of CatalogStars.in_cone is the whole catalog's cone cut at the limit."""
import math

import numpy as np
import pytest

from startrack._kernels.catalog_match import match_detections
from startrack.identify.catalog_match import CatalogStars


def _numpy_decisions(dots, pc, r, sigma, idx, mag, ids, taken, max_chance, focal, width, height):
    """The numpy form of the decisions (startrack before the kernel): ``(detections, predicted stars)``."""
    rows = np.arange(dots.shape[0])
    if dots.shape[1] > 1:
        two = np.argpartition(-dots, 1, axis=1)[:, :2]
        flip = dots[rows, two[:, 1]] > dots[rows, two[:, 0]]
        best = np.where(flip, two[:, 1], two[:, 0])
        other = np.where(flip, two[:, 0], two[:, 1])
    else:
        best = other = np.zeros(dots.shape[0], dtype=np.intp)
    cos_r = np.cos(r)
    lam_floor = dots.shape[1] * math.pi * (r * focal) ** 2 / float(width * height)
    n_local = np.count_nonzero(dots >= np.cos(10 * r)[:, None], axis=1) - 1
    ok = dots[rows, best] >= cos_r
    if dots.shape[1] > 1:
        near2 = dots[rows, other] >= np.cos(2 * r)
        distinct = np.einsum("ij,ij->i", pc[best], pc[other]) < cos_r
        ok &= ~(near2 & distinct)
        pair = near2 & ~distinct & (mag[idx[other]] < mag[idx[best]])
        best = np.where(pair, other, best)
    dot = dots[rows, best]
    offset = np.arccos(np.minimum(1.0, dot))
    closest = np.maximum(offset, sigma) / r
    chance = 1.0 - np.exp(-np.maximum(n_local / 100.0, lam_floor) * np.minimum(1.0, closest) ** 2)
    ok &= ~(chance > max_chance)
    cids = ids[idx[best]]
    ok &= ~np.isin(cids, taken)
    sel = np.flatnonzero(ok)
    order = np.lexsort((sel, -dot[sel], cids[sel]))
    sel = sel[order]
    first = np.ones(len(sel), dtype=bool)
    first[1:] = cids[sel[1:]] != cids[sel[:-1]]
    sel = np.sort(sel[first])
    return sel, best[sel]


def _unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _case(rng):
    """A field of predicted stars (some in close pairs) and detections near them, between them and nowhere."""
    focal = 2000.0
    k = int(rng.integers(1, 40))
    xy = rng.uniform(-400, 400, (k, 2))
    twins = rng.random(k) < 0.3            # a star with a close neighbour (unresolved or ambiguous)
    xy = np.concatenate([xy, xy[twins] + rng.normal(0, 2.5, (int(twins.sum()), 2))])
    pc = _unit(np.column_stack([xy / focal, np.ones(len(xy))]))
    n = int(rng.integers(1, 25))
    pick = rng.integers(0, len(xy), n)
    det = xy[pick] + rng.normal(0, rng.choice([0.3, 1.5, 4.0]), (n, 2))
    nowhere = rng.random(n) < 0.2
    det[nowhere] = rng.uniform(-400, 400, (int(nowhere.sum()), 2))
    b = _unit(np.column_stack([det / focal, np.ones(n)]))
    dots = b @ pc.T
    r = rng.choice([1.5, 2.0, 3.0], n) / focal
    sigma = r if rng.random() < 0.3 else np.full(n, 0.3 / focal)
    idx = np.sort(rng.choice(5000, len(xy), replace=False)).astype(np.int64)
    mag = rng.uniform(2.0, 9.0, 5000)
    ids = rng.permutation(100000)[:5000].astype(np.int64)
    taken = ids[rng.choice(idx, int(rng.integers(0, 3)))] if len(idx) else np.zeros(0, np.int64)
    return dots, pc, r, sigma, idx, mag, ids, np.asarray(taken, dtype=np.int64), focal


@pytest.mark.parametrize("max_chance", [1e-3, 0.05, 1.0])
def test_kernel_decides_as_the_numpy_pass(max_chance):
    rng = np.random.default_rng(380)
    seen = {"pair": 0, "ambiguous": 0, "shared": 0, "taken": 0, "matched": 0}
    for _ in range(400):
        dots, pc, r, sigma, idx, mag, ids, taken, focal = _case(rng)
        want = _numpy_decisions(dots, pc, r, sigma, idx, mag, ids, taken, max_chance, focal, 800, 800)
        got = match_detections(dots, pc, r, sigma, idx, mag, ids, taken, max_chance, focal, 800.0 * 800.0)
        np.testing.assert_array_equal(got[0], want[0])
        np.testing.assert_array_equal(got[1], want[1])
        # which branches the case went through (so that the comparison covers them)
        near = np.argmax(dots, axis=1)
        seen["pair"] += int(np.count_nonzero(want[1] != near[want[0]]))
        seen["ambiguous"] += int(np.count_nonzero((np.sort(dots, axis=1)[:, -2:] >= np.cos(2 * r)[:, None]).all(1)))
        seen["shared"] += int(len(near) - len(set(near.tolist())))
        seen["taken"] += int(np.isin(ids[idx[near]], taken).sum())
        seen["matched"] += len(want[0])
    assert all(v > 0 for v in seen.values()), seen


def test_one_predicted_star_and_none():
    pc = np.array([[0.0, 0.0, 1.0]])
    b = np.array([[1e-4, 0.0, math.sqrt(1 - 1e-8)], [0.1, 0.0, math.sqrt(1 - 0.01)]])
    dots = b @ pc.T
    r = np.full(2, 1e-3)
    args = (np.array([3], dtype=np.int64), np.zeros(5), np.arange(5, dtype=np.int64), np.zeros(0, dtype=np.int64))
    det, cand = match_detections(dots, pc, r, r, *args, 1.0, 1000.0, 1e6)
    assert det.tolist() == [0] and cand.tolist() == [0]
    want = _numpy_decisions(dots, pc, r, r, *args, 1.0, 1000.0, 1000, 1000)
    assert want[0].tolist() == [0] and want[1].tolist() == [0]
    det, cand = match_detections(np.empty((2, 0)), np.empty((0, 3)), r, r, *args, 1.0, 1000.0, 1e6)
    assert len(det) == 0 and len(cand) == 0
    # two detections at the same place take the same star: the earlier keeps it (a tie of their cosines)
    twin = np.array([b[0], b[0]]) @ pc.T
    det, cand = match_detections(twin, pc, r, r, *args, 1.0, 1000.0, 1e6)
    assert det.tolist() == [0] and cand.tolist() == [0]
    assert _numpy_decisions(twin, pc, r, r, *args, 1.0, 1000.0, 1000, 1000)[0].tolist() == [0]


@pytest.mark.parametrize("limit", [3.0, 5.5, 6.44, 8.0, 12.0, float("nan")])
def test_magnitude_limited_cone_is_the_cut_cone(catalog, limit):
    stars = CatalogStars.from_catalog(catalog)
    rng = np.random.default_rng(int(limit * 10) if limit == limit else 1)
    vec = catalog.vectors()
    for axis in list(_unit(rng.normal(size=(6, 3)))) + [np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.0, 0.0])]:
        for radius in (2.0, 12.0, 40.0):
            c = math.cos(math.radians(radius))
            whole = np.flatnonzero(vec @ axis > c)
            want = whole[catalog.mag[whole] <= limit]
            np.testing.assert_array_equal(stars.in_cone(axis, c, limit), want)
            np.testing.assert_array_equal(stars.in_cone(axis, c), whole)
    # a limit that keeps few stars looks them up in a smaller index than the catalog's
    if limit <= 6.5:
        assert stars._bright and max(len(rows) for rows, _ in stars._bright.values()) < len(vec)


def _types(args):
    """What an ahead-of-time entry is chosen by: each array's dtype, dimensions, layout, writability, alignment."""
    return tuple((a.dtype.str, a.ndim, "C" if a.flags.c_contiguous else "F" if a.flags.f_contiguous else "A",
                  a.flags.writeable, a.flags.aligned) if isinstance(a, np.ndarray) else type(a) for a in args)


def test_warm_up_calls_the_final_match_kernels_with_their_real_argument_types(catalog, monkeypatch):
    """identify's warm-up (and so the ahead-of-time build) has the final match's kernels for the argument types a
    real match gives them: else a process's first final match imports numba (~0.3 s inside its time_ms)."""
    from startrack._kernels import _jit
    from startrack.camera import Camera
    from startrack.identify.catalog_match import match_catalog, warm_final_match
    from startrack.identify.verify import _geometry
    from startrack.records import Match
    from startrack.rotations import radec_roll_to_dcm

    seen = {}
    call = _jit.LazyKernel.__call__

    def spy(self, *args):
        seen.setdefault(self.qualname, set()).add(_types(args))
        return call(self, *args)

    monkeypatch.setattr(_jit.LazyKernel, "__call__", spy)
    warm_final_match()
    warm, seen = seen, {}
    cam = Camera.from_fov(15.0, 1280, 960)
    dcm = radec_roll_to_dcm(80.0, 20.0, 30.0)
    vec = catalog.vectors()
    body = vec @ dcm.T
    front = np.flatnonzero((body[:, 2] > 0.9) & (catalog.mag <= 6.5))
    x, y = cam.vectors_to_pixels(body[front])
    rows = front[cam.in_image(x, y, margin=3.0)][:40]
    b = vec[rows] @ dcm.T
    matches = [Match(k, int(catalog.id[rows[k]])) for k in range(4)]
    radius = np.full(len(rows), 2.0 / cam.focal_length_px)
    got, q = match_catalog(matches, vec[rows[:4]], dcm, b, radius, cam, CatalogStars.from_catalog(catalog), 1e-3,
                           _geometry(cam)[0], 6.5, radius / 4)
    assert q is not None and len(got) > 4           # the match added stars: every kernel of it ran
    names = [n for n in seen if n.endswith(("match_detections", "quest"))]
    assert len(names) == 2, sorted(seen)
    for name in names:
        assert seen[name] <= warm.get(name, set()), (name, seen[name], warm.get(name))
