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
