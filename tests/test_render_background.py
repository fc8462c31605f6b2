"""The background noise table of render (render.background_dn_cdf)."""
import math
from types import SimpleNamespace

import numpy as np
import pytest

from startrack.render import background_dn_cdf


def _dense(lam, g, bias, rn):
    """The table from its definition, every count against every DN (small backgrounds only)."""
    kmax = int(lam + 12.0 * math.sqrt(lam) + 12.0)
    k = np.arange(kmax + 1, dtype=np.float64)
    pk = np.exp(-lam + k * math.log(lam) - np.array([math.lgamma(v + 1.0) for v in k]))
    lo = int(math.floor((-9.0 * rn) / g + bias)) - 1
    hi = int(math.ceil((kmax + 9.0 * rn) / g + bias)) + 1
    d = np.arange(lo, hi + 1, dtype=np.float64)
    z = (g * (d + 0.5 - bias))[:, None] - k[None, :]
    if rn > 0:
        phi = 0.5 * (1.0 + np.vectorize(math.erf)(z / (math.sqrt(2.0) * rn)))
    else:
        phi = (z > 0).astype(np.float64)
    cdf = phi @ pk
    return cdf / cdf[-1], lo


@pytest.mark.parametrize("lam,g,bias,rn", [(3.0, 1.0, 10.0, 2.0), (40.0, 0.7, 100.0, 5.0), (400.0, 2.3, 50.0, 8.0),
                                            (25.0, 1.0, 10.0, 0.0), (900.0, 1.5, 0.0, 0.5)])
def test_table_is_the_definition(lam, g, bias, rn):
    cdf, lo = background_dn_cdf(SimpleNamespace(background_e=lam, gain=g, bias=bias, read_noise_e=rn))
    ref, ref_lo = _dense(lam, g, bias, rn)
    # The same DN values (the fast table starts where the counts carry probability).
    ref = ref[lo - ref_lo:lo - ref_lo + len(cdf)] if lo >= ref_lo else np.r_[np.zeros(ref_lo - lo), ref]
    assert np.max(np.abs(cdf - ref[:len(cdf)])) < 1e-12


@pytest.mark.parametrize("lam", [3.0e4, 1.0e6])
def test_daylight_background_is_cheap_and_has_the_right_moments(lam):
    """A daylight sky (1e6 electrons a pixel) used to need a dense ~1e5 x 1e6 matrix ('out of memory')."""
    g, bias, rn = 1.7, 100.0, 12.0
    cdf, lo = background_dn_cdf(SimpleNamespace(background_e=lam, gain=g, bias=bias, read_noise_e=rn))
    assert len(cdf) < 30 * math.sqrt(lam) / g + 40
    p = np.diff(np.r_[0.0, cdf])
    dn = lo + np.arange(len(cdf))
    mean = float(p @ dn)
    var = float(p @ (dn - mean) ** 2)
    assert mean == pytest.approx(lam / g + bias, abs=0.01)
    assert var == pytest.approx((lam + rn**2) / g**2 + 1.0 / 12.0, rel=1e-3)
