"""Slow, obviously correct reference implementations that the kernels are checked against."""
import numpy as np


def pairs_within_naive(vectors, max_angle):
    """All pairs (i < j) with angle <= max_angle, by the full O(n^2) scan."""
    cos = vectors @ vectors.T
    i, j = np.nonzero(np.triu(cos >= np.cos(max_angle), k=1))
    return set(zip(i.tolist(), j.tolist()))


def count_in_fov_naive(vectors, mags, dcm, camera):
    """Stars of a catalog inside the camera image at attitude ``dcm``."""
    cam_vec = vectors @ dcm.T
    front = cam_vec[:, 2] > 0
    x, y = camera.vectors_to_pixels(cam_vec[front])
    inside = camera.in_image(x, y)
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
