"""Slow, obviously correct reference implementations that the kernels are checked against."""
import math

import numpy as np


def pairs_within_naive(vectors, max_angle):
    """All pairs (i < j) with angle <= max_angle, by the full O(n^2) scan."""
    cos = vectors @ vectors.T
    i, j = np.nonzero(np.triu(cos >= np.cos(max_angle), k=1))
    return set(zip(i.tolist(), j.tolist()))


def count_in_fov_naive(vectors, mags, dcm, camera):
    """Stars of a catalog inside the camera image at attitude ``dcm``."""
    cam_vec = vectors @ dcm.T
    # A pinhole sees the front hemisphere; a fisheye's model says itself where it ends (NaN beyond).
    front = cam_vec[:, 2] > 0 if camera.projection == "pinhole" else np.ones(len(cam_vec), dtype=bool)
    x, y = camera.vectors_to_pixels(cam_vec[front])
    inside = camera.in_image(x, y) & np.isfinite(x)
    m = mags[front][inside]
    return int(inside.sum()), (float(m.min()) if m.size else np.nan)


def label_naive(mask):
    """8-connected component labels by breadth-first search (0 = background)."""
    from collections import deque

    h, w = mask.shape
    labels = np.zeros((h, w), dtype=np.int64)
    n = 0
    for y in range(h):
        for x in range(w):
            if mask[y, x] and labels[y, x] == 0:
                n += 1
                labels[y, x] = n
                queue = deque([(y, x)])
                while queue:
                    cy, cx = queue.popleft()
                    for dy in (-1, 0, 1):
                        for dx in (-1, 0, 1):
                            yy, xx = cy + dy, cx + dx
                            if 0 <= yy < h and 0 <= xx < w and mask[yy, xx] and labels[yy, xx] == 0:
                                labels[yy, xx] = n
                                queue.append((yy, xx))
    return labels, n


def centre_of_mass_naive(values, labels, lab):
    """Paper 000 Eq. 1 over one blob's positive pixels."""
    ys, xs = np.nonzero(labels == lab)
    v = np.clip(values[ys, xs].astype(np.float64), 0, None)
    return float((v * xs).sum() / v.sum()), float((v * ys).sum() / v.sum()), float(v.sum())


def split_blob_naive(residual, labels, lab, stats_row, min_separation=2.5, saddle_ratio=0.7):
    """The deblend of :func:`startrack._kernels.centroid.split_blob` in numpy and Python: the separate peaks of a blob
    (local maxima whose saddle lies below ``saddle_ratio`` times the lower peak)."""
    left, top, bw, bh = (int(v) for v in stats_row[:4])
    sub = residual[top:top + bh, left:left + bw]
    mask = labels[top:top + bh, left:left + bw] == lab
    if mask.sum() < 6:
        return []
    inside = np.where(mask, sub, -np.inf)
    pad = np.full((bh + 2, bw + 2), -np.inf, dtype=inside.dtype)
    pad[1:-1, 1:-1] = inside
    # The largest of the eight neighbours, window by window (np.pad and np.stack cost ~10x more on these small blobs).
    neigh = pad[0:bh, 0:bw].copy()
    for j in range(3):
        for i in range(3):
            if (i, j) not in ((0, 0), (1, 1)):
                np.maximum(neigh, pad[j:j + bh, i:i + bw], out=neigh)
    peaks = np.argwhere(mask & (sub > neigh))
    if len(peaks) < 2:
        return []
    heights = sub[peaks[:, 0], peaks[:, 1]]
    order = np.argsort(-heights)
    # Python ints and floats in the loop (numpy scalars cost ~1 us an operation): the same integer and
    # double arithmetic; pixel values convert exactly, so comparisons between them do not change.
    pts = peaks.tolist()
    rows = sub.tolist()
    kept = []
    for k in order.tolist():
        py, px = pts[k]
        ok = True
        for (qy, qx) in kept:
            dist = math.hypot(px - qx, py - qy)
            if dist < min_separation:
                ok = False
                break
            n = int(math.ceil(dist * 2))
            lowest = min(rows[int(round(py + (qy - py) * t / n))][int(round(px + (qx - px) * t / n))]
                         for t in range(n + 1))
            # the saddle limit in the residual's precision, as before
            if lowest > float(saddle_ratio * min(sub[py, px], sub[qy, qx])):
                ok = False
                break
        if ok:
            kept.append((py, px))
    if len(kept) < 2:
        return []
    return [(left + px, top + py) for (py, px) in kept]


def cone_naive(vectors, axis, cos_radius):
    """Rows whose unit vector is within the cone (``v . axis > cos_radius``), ascending: every row tested,
    the dot product summed x, y, z as the index's kernel sums it."""
    import numpy as np

    v = np.asarray(vectors, dtype=np.float64)
    dot = v[:, 0] * axis[0] + v[:, 1] * axis[1] + v[:, 2] * axis[2]
    return np.flatnonzero(dot > cos_radius)


def allsky_match_naive(xs, ys, radius, px, py):
    """startrack.allsky._match by the full distance matrix: each detection's nearest predicted star within its
    radius, none when the second is within 1.5 radii, a predicted star taken twice given to neither."""
    import numpy as np

    det, cat = [], []
    for i in range(len(xs)):
        if not np.isfinite(radius[i]) or len(px) == 0:
            continue
        d = np.hypot(px - xs[i], py - ys[i])
        order = np.argsort(d)
        second = d[order[1]] if len(d) > 1 else np.inf
        if d[order[0]] <= radius[i] and second > 1.5 * radius[i]:
            det.append(i)
            cat.append(int(order[0]))
    keep = [k for k in range(len(cat)) if cat.count(cat[k]) == 1]
    return np.array([det[k] for k in keep], dtype=np.int64), np.array([cat[k] for k in keep], dtype=np.int64)


def subtract_background_naive(image, level_mesh, threshold_mesh, cell):
    """``image - level`` and ``residual > threshold``, the two maps bilinear between tile centres (as
    ``cv2.resize``), row by row in numpy: the reference of the background pass
    (``startrack._kernels.centroid.subtract_background_rows``), the same operations in the same order."""
    h, w = image.shape
    ny, nx = level_mesh.shape
    fx = np.minimum(np.maximum((np.arange(w) + 0.5) / cell - 0.5, 0.0), nx - 1.0)
    a = np.minimum(fx.astype(np.int64), nx - 2) if nx > 1 else np.zeros(w, dtype=np.int64)
    b = np.minimum(a + 1, nx - 1)
    tx = fx - a
    residual = np.empty(image.shape, dtype=np.float32)
    mask = np.empty(image.shape, dtype=np.uint8)
    for y in range(h):
        fy = min(max((y + 0.5) / cell - 0.5, 0.0), ny - 1.0)
        j0 = min(int(fy), ny - 2) if ny > 1 else 0
        j1 = min(j0 + 1, ny - 1)
        ty = fy - j0
        lrow = level_mesh[j0] * (1.0 - ty) + level_mesh[j1] * ty
        trow = threshold_mesh[j0] * (1.0 - ty) + threshold_mesh[j1] * ty
        la, ta = lrow[a], trow[a]
        r = image[y].astype(np.float64) - (la + (lrow[b] - la) * tx)
        residual[y] = r
        mask[y] = r > ta + (trow[b] - ta) * tx
    return residual, mask
