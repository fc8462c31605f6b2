"""The blind solve's look-elsewhere split: the false-match limit shared among the searches a frame can get."""
import numpy as np
import pytest

import startrack.patterns as patterns
import startrack.solve as solve
from startrack.patterns import BlindOptions
from startrack.solve import SolveOptions, solve_image


def _spots(n, seed):
    """A 640x480 frame of ``n`` Gaussian spots (PSF sigma 1.2 px, well apart) on a noisy background."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:480, 0:640]
    image = rng.normal(200.0, 5.0, size=(480, 640))
    xy = np.column_stack([rng.permutation(np.arange(30, 610, 20))[:n], rng.uniform(30, 450, n)])
    for k, (x, y) in enumerate(xy):
        image += (4000.0 - 40 * k) * np.exp(-((xx - x) ** 2 + (yy - y) ** 2) / (2 * 1.2**2))
    return image.astype(np.float32)


@pytest.mark.parametrize("n", [12, 28])
def test_a_detection_pass_that_cannot_run_takes_no_share(monkeypatch, n):
    """Each parity and detection depth of a pinhole blind solve spends a share of the limit; a frame of at least
    BlindOptions.max_pattern_stars detections gets no deeper (matched-filter) pass, so its pattern searches each get
    half the limit instead of a quarter (a frame of fewer keeps the quarter)."""
    seen = []

    def search(stars, width, height, index, options):       # solve_blind's arguments as solve passes them
        assert width == 640 and height == 480 and index is not None
        seen.append((len(stars), options.max_false_probability))
        return None, patterns._blind_result(None, 0.0, "no star pattern identified"), \
            {"patterns": 0, "candidates": 0, "verified": 0}

    monkeypatch.setattr(patterns, "solve_blind", search)
    monkeypatch.setattr(solve, "_warm", lambda _index: None)
    solve_image(_spots(n, n), SolveOptions(projection="pinhole", max_false_probability=1e-6), index=object())
    assert [k for k, _ in seen] == [n, n], seen         # both parities searched, every spot detected
    shares = 2 * (1 if n >= BlindOptions.max_pattern_stars else 2)       # parities x detection depths
    assert [p for _, p in seen] == [pytest.approx(1e-6 / shares, rel=1e-12)] * 2
