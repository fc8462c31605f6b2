"""evaluate's report (issue 40 item 3): per-frame progress, Wilson 95 % intervals in rows and table, and a
success axis that does not make 99.9 % look like a crash."""
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from startrack.evaluate import summarise


def wilson_interval(k, n):
    from startrack.evaluate import wilson_interval

    return wilson_interval(k, n)


@pytest.mark.parametrize("k,n,low,high", [
    # Newcombe, "Two-sided confidence intervals for the single proportion", Stat. Med. 17, 857 (1998), Table I,
    # method 3 (score interval without continuity correction)
    (81, 263, 0.2553, 0.3662), (15, 148, 0.0624, 0.1605), (0, 20, 0.0, 0.1611), (1, 29, 0.0061, 0.1718)])
def test_wilson_interval_matches_newcombes_table(k, n, low, high):
    lo, hi = wilson_interval(k, n)
    assert lo == pytest.approx(low, abs=5e-5) and hi == pytest.approx(high, abs=5e-5)


@settings(max_examples=200, deadline=None)
@given(st.integers(1, 10**7), st.data())
def test_wilson_bounds_solve_the_score_equation(n, data):
    """Each bound p is a root of (k/n - p)^2 = z^2 p (1 - p) / n (the score test at 95 %), and the interval
    holds k/n; at k = 0 or n the bound at that end is exactly 0 or 1."""
    from startrack.evaluate import Z95

    k = data.draw(st.integers(0, n))
    lo, hi = wilson_interval(k, n)
    p_hat = k / n
    assert 0.0 <= lo <= p_hat <= hi <= 1.0
    for p, end in ((lo, 0), (hi, n)):
        if k == end:
            assert p == float(end > 0)
            continue
        residual = (p_hat - p) ** 2 - Z95**2 * p * (1 - p) / n
        assert abs(residual) <= 1e-9 * max(1e-12, Z95**2 * p * (1 - p) / n) + 1e-15, (k, n, p, residual)


def test_rows_and_table_carry_the_intervals():
    from startrack.evaluate import with_intervals

    row = {"algorithm": "pyramid", "condition": "sigma 0.1px", "frames": 150000, "success": 149703, "failure": 297,
           "bad": 0, "success_rate": 149703 / 150000, "mean_ms": 0.05, "median_ms": 0.02, "p95_ms": 0.04}
    full = with_intervals(row)
    assert (full["success_rate_low"], full["success_rate_high"]) == wilson_interval(149703, 150000)
    assert full["bad_rate"] == 0 and full["bad_rate_low"] == 0 and full["bad_rate_high"] == wilson_interval(0, 150000)[1]
    table = summarise([row])
    assert "success 95% CI" in table and "bad 95% CI" in table
    # 0 bad matches in 150,000 frames is a rate below 0.0026 %: printed with the digits that show it, not 0.00
    assert "[99.78, 99.82]%" in table and "[0, 0.003]%" in table, table


def test_progress_counts_frames_not_conditions(catalog):
    """main: the progress callback was called once per chunk of 1,000 frames (a 20,000-frame condition sat at 0 %
    for 34 s).  Now once per identified frame and algorithm, monotonic, ending at the total."""
    from startrack.camera import Camera
    from startrack.evaluate import conditions_grid, evaluate
    from startrack.identify import IdentifyParams
    from startrack.kvector import build_kvector, max_separation_deg

    cam = Camera.from_fov(20, 512, 512)
    cat = catalog.filter_magnitude(None, 4.0)
    db = build_kvector(cat, max_separation_deg(camera=cam))
    calls = []
    rows = evaluate(["pyramid", "voting"], conditions_grid(sigma_px=[0.1], false_stars=[0, 1]), 25, {"kvector": db},
                    cam, cat, seed=3, params=IdentifyParams(sigma_px=0.1), mag_limit=4.0,
                    progress=lambda done, total: calls.append((done, total)))
    assert len(rows) == 4
    done = [d for d, _ in calls]
    assert {t for _, t in calls} == {2 * 2 * 25}
    assert done == sorted(done) and done[-1] == 100
    assert len(set(done)) >= 100, f"{len(set(done))} distinct progress steps for 100 identified frames"


def test_success_axis_is_zero_based_or_broken_with_room():
    from startrack.plot import BROKEN_AXIS_ABOVE, success_axis_range

    # anything reaching below BROKEN_AXIS_ABOVE: one axis from 0
    assert success_axis_range([0.5, 0.999]) is None
    assert success_axis_range([BROKEN_AXIS_ABOVE - 1e-6]) is None
    for lows in ([0.999], [0.9986, 0.9991], [0.97, 0.999], [0.85], [1.0]):
        bottom, top = success_axis_range(lows)
        assert top == 100.0 and 100 * BROKEN_AXIS_ABOVE <= bottom <= 100 * min(lows)
        # at least one percentage point shown: 99.9 % sits in the top tenth of the band, never at its floor
        assert top - bottom >= 1.0
        assert (100 * min(lows) - bottom) / (top - bottom) >= 0.05


def test_chart_draws_error_bars_and_writes_pdf_and_svg(tmp_path):
    """The chart in every format its suffix names (main: PNG bytes whatever the name); an unknown suffix is
    refused naming the file."""
    from startrack.errors import BadInputError
    from startrack.plot import plot_results

    rows = [{"algorithm": a, "condition": "", "sigma_px": 0.1, "sigma_arcsec": None, "false_stars": f, "mag_noise": 0,
             "focal_error_pct": 0, "drop_fraction": 0, "min_stars": 0, "frames": 1000, "success": s, "failure": 1000 - s,
             "bad": 0, "success_rate": s / 1000, "median_ms": 0.1 + f} for a, ss in (("pyramid", (999, 998)),
                                                                                   ("voting", (999, 990)))
            for f, s in enumerate(ss)]
    plot_results(rows, str(tmp_path / "c.pdf"))
    plot_results(rows, str(tmp_path / "c.svg"))
    plot_results(rows, str(tmp_path / "c.png"))
    assert (tmp_path / "c.pdf").read_bytes()[:5] == b"%PDF-"
    svg = (tmp_path / "c.svg").read_text()
    assert "<svg" in svg[:500] and "axis broken" in svg
    assert (tmp_path / "c.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    with pytest.raises(BadInputError, match=r"c\.jpg.*\.png, \.pdf or \.svg"):
        plot_results(rows, str(tmp_path / "c.jpg"))
    assert not (tmp_path / "c.jpg").exists()


def test_error_bars_are_drawn_at_the_intervals(tmp_path):
    """The success panel's error bars span each row's Wilson interval (read back from the SVG's paths would be
    brittle: the figure's own Line2D data are checked through matplotlib's object model instead)."""
    import startrack.plot as plot

    rows = [{"algorithm": "pyramid", "condition": "", "sigma_px": 0.1, "sigma_arcsec": None, "false_stars": f,
             "mag_noise": 0, "focal_error_pct": 0, "drop_fraction": 0, "min_stars": 0, "frames": 200, "success": s,
             "failure": 200 - s, "bad": 0, "success_rate": s / 200, "median_ms": 1.0} for f, s in ((0, 120), (1, 60))]
    saved = {}
    real = plot._save
    plot._save = lambda fig, path: saved.update(fig=fig) or real(fig, path)
    try:
        plot.plot_results(rows, str(tmp_path / "e.png"))
    finally:
        plot._save = real
    ax = saved["fig"].axes[0]
    # zero-based: the rates are 60 % and 30 %
    assert ax.get_ylim()[0] == 0
    segments = [np.asarray(seg) for coll in ax.collections for seg in coll.get_segments()]
    spans = sorted((float(s[:, 1].min()), float(s[:, 1].max())) for s in segments if len(s) == 2)
    want = sorted((100 * lo, 100 * hi) for lo, hi in (wilson_interval(120, 200), wilson_interval(60, 200)))
    assert len(spans) == 2 and np.allclose(spans, want, atol=1e-9), (spans, want)
