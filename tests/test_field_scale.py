"""The field's focal-length scale: its tentative matches are those of a scan of every star."""
import numpy as np
import pytest

from startrack._kernels.common import pixels_to_unit

FOCAL, CX, CY = 6000.0, 639.5, 479.5


@pytest.mark.parametrize("n, m", [(6, 20), (40, 300)])     # every star looked at; columns of stars
def test_field_tentative_matches_are_the_brute_force_ones(n, m):
    """The field's tentative matches (each detection's one projected star within its widened radius, none
    when two are; a star once) are those of a scan of every star, also when the stars are looked up by
    columns (many detections and stars): some detections near a star, some between two, some far."""
    from startrack._kernels.focal import field_tentative_matches

    rng = np.random.default_rng(4)
    dcm = np.eye(3)
    for _ in range(30):
        u = rng.uniform(-50, 1330, m)
        v = rng.uniform(-50, 1010, m)
        stars = pixels_to_unit(u, v, FOCAL, CX, CY)
        pick = rng.choice(m, size=n, replace=False)
        xs = u[pick] + rng.normal(0, rng.choice([0.3, 3.0, 30.0]), n)
        ys = v[pick] + rng.normal(0, 0.5, n)
        xs[:2] = rng.uniform(0, 1279, 2)                  # two anywhere
        radius = rng.uniform(1.0, 3.0, n)
        core = np.arange(min(4, n), dtype=np.int64)
        front = np.arange(m, dtype=np.int64)
        got = field_tentative_matches(xs, ys, stars, dcm, FOCAL, CX, CY, 0.0, 0.0, core, radius, 0.02, front, m)
        # The scan of every star.
        allowed = radius + 0.02 * np.hypot(xs - xs[core].mean(), ys - ys[core].mean())
        d = np.hypot(xs[:, None] - u[None, :], ys[:, None] - v[None, :])
        srt = np.sort(d, axis=1)
        img, cat = [], []
        for i in range(n):
            if srt[i, 0] <= allowed[i] and srt[i, 1] > allowed[i]:
                s = int(np.argmin(d[i]))
                if s not in cat:
                    img.append(i)
                    cat.append(s)
        assert got[0].tolist() == img and got[1].tolist() == cat
