"""The per-star centroid sigma rule of identification (startrack.identify.params.star_sigmas_px)."""
import numpy as np

from startrack.identify import IdentifyParams
from startrack.identify.params import _table_arrays, star_sigmas_px
from startrack.records import StarTable


def _stars(sigmas):
    return [{"x": 10.0 * i, "y": 5.0 * i, "flux": 100.0 - i, **({} if s is ... else {"sigma_px": s})}
            for i, s in enumerate(sigmas)]


def test_a_fixed_sigma_applies_to_every_star():
    got = star_sigmas_px(_stars([0.1, None, ...]), IdentifyParams(sigma_px=0.3))
    assert got.dtype == np.float64 and got.tolist() == [0.3, 0.3, 0.3]


def test_reported_sigmas_are_scaled_and_clipped():
    params = IdentifyParams(reported_sigma_factor=1.5)
    got = star_sigmas_px(_stars([0.2, 0.01, 3.0, 1.0]), params)
    assert np.allclose(got, [0.3, 0.05, 2.0, 1.5], rtol=0, atol=1e-15)


def test_a_star_without_a_usable_sigma_gets_the_median_of_the_others():
    params = IdentifyParams(reported_sigma_factor=1.0)
    # None, a string, a missing key, zero, a negative, NaN and infinity are no sigma.
    sig = [0.2, None, 0.4, "0.3", ..., 0.0, -1.0, float("nan"), float("inf"), 1.0]
    got = star_sigmas_px(_stars(sig), params)
    assert got[[0, 2, 9]].tolist() == [0.2, 0.4, 1.0]
    assert got[[1, 3, 4, 5, 6, 7, 8]].tolist() == [0.4] * 7        # median of 0.2, 0.4, 1.0


def test_without_any_sigma_every_star_gets_half_a_pixel():
    for sig in ([..., ..., ...], [None, 0.0, float("nan")]):
        assert star_sigmas_px(_stars(sig), IdentifyParams()).tolist() == [0.5, 0.5, 0.5]


def test_a_star_table_gives_what_star_dicts_give():
    params = IdentifyParams()
    dicts = _stars([0.2, 0.01, 3.0, 1.0])
    table = StarTable.from_list(dicts)
    table.sigma_px[1] = np.nan      # a missing value in the column
    dicts[1]["sigma_px"] = None
    assert _table_arrays(table, params)[3].tolist() == star_sigmas_px(dicts, params).tolist()
    assert _table_arrays(StarTable.from_list(_stars([..., ..., ...])), params)[3].tolist() == [0.5, 0.5, 0.5]
