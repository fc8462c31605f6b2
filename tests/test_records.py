"""Typed records and their frame-document sections (startrack.records, startrack.formats.sections)."""
import json
import pathlib

import numpy as np
import pytest
from conftest import assert_same_record

from startrack.errors import BadInputError
from startrack.formats.sections import (
    from_section,
    stars_from_section,
    to_section,
    update_docs,
)
from startrack.records import Attitude, Identification, Match, ReasonCode, StarTable, Status, TrackState
from startrack.rotations import _radec_roll_to_dcm_rad, radec_roll_to_dcm

ROOT = pathlib.Path(__file__).resolve().parents[1]


def test_status_and_reason_code_are_the_file_strings():
    assert Status.OK == "ok" and Status.FAILED == "failed"
    assert json.dumps({"s": Status.FAILED, "c": ReasonCode.NO_PATTERN}) == '{"s": "failed", "c": "no_pattern"}'
    assert str(ReasonCode.TIMEOUT) == "timeout"
    assert all(code.description for code in ReasonCode)


def test_attitude_section_round_trip_keeps_the_rotation():
    dcm = radec_roll_to_dcm(83.8, -1.2, 30.0)
    att = Attitude.from_dcm(dcm, "quest", n_stars=7, rms_residual_arcsec=1.5)
    assert att.ra == pytest.approx(83.8) and att.dec == pytest.approx(-1.2) and att.roll == pytest.approx(30.0)
    section = json.loads(json.dumps(to_section(att)))
    assert section["status"] == "ok" and section["method"] == "quest" and len(section["quaternion"]) == 4
    back = from_section(Attitude, section, "x.json", "attitude")
    np.testing.assert_allclose(back.dcm, dcm, atol=1e-12)
    assert back.n_stars == 7 and back.status is Status.OK


def test_estimate_attitude_section_reads_as_an_attitude_record():
    from startrack.attitude import estimate_attitude

    rng = np.random.default_rng(3)
    truth = _radec_roll_to_dcm_rad(1.0, 0.3, 0.2)
    ref = rng.normal(size=(6, 3))
    ref /= np.linalg.norm(ref, axis=1)[:, None]
    body = ref @ truth.T
    section = estimate_attitude(body, ref, np.full(6, 1e-5)).section()
    att = from_section(Attitude, json.loads(json.dumps(section)), "<test>", "attitude")
    np.testing.assert_allclose(att.dcm, truth, atol=1e-9)
    assert att.covariance_arcsec2.shape == (3, 3)
    # Fields without a place of their own are kept and written back; every figure has its attribute (issue 40).
    assert "dcm" in att.details and to_section(att)["dcm"] == section["dcm"]
    assert att.euler123_deg == section["euler123_deg"] and to_section(att)["euler123_deg"] == section["euler123_deg"]
    assert att.sigma_roll_arcsec == section["sigma_roll_arcsec"]
    assert to_section(att) == json.loads(json.dumps(section))


def test_identification_round_trip_and_reason_code():
    ident = Identification.failed("pyramid", "no consistent star pattern found", ReasonCode.NO_PATTERN, time_ms=2.5)
    section = to_section(ident)
    assert section == {"status": "failed", "algorithm": "pyramid", "matches": [], "time_ms": 2.5,
                       "reason": "no consistent star pattern found", "reason_code": "no_pattern"}
    ok = from_section(Identification, {"status": "ok", "algorithm": "voting", "matches": [{"star": 0, "id": 32349}],
                                       "votes": 12, "reason_code": "a_code_of_a_later_version"})
    assert ok.matches == [Match(0, 32349)] and ok.details == {"votes": 12}
    assert ok.reason_code == "a_code_of_a_later_version"


@pytest.mark.parametrize("section, field, problem", [
    ({"algorithm": "pyramid", "matches": []}, "identification.status", "missing"),
    ({"status": "fine", "algorithm": "pyramid", "matches": []}, "identification.status", "'ok' or 'failed'"),
    ({"status": "ok", "algorithm": "pyramid", "matches": [{"star": 0}]}, "identification.matches[0]", "'star'"),
    ({"status": "ok", "algorithm": "pyramid", "matches": [], "time_ms": float("nan")}, "identification.time_ms",
     "finite"),
])
def test_bad_identification_sections_name_the_field(section, field, problem):
    with pytest.raises(BadInputError) as info:
        from_section(Identification, section, "frames.jsonl:3", "identification")
    assert info.value.field == field and problem in info.value.problem
    assert str(info.value).startswith("frames.jsonl:3: ")


def test_attitude_refuses_a_non_unit_quaternion():
    with pytest.raises(BadInputError, match="unit quaternion"):
        from_section(Attitude, {"status": "ok", "method": "quest", "quaternion": [1, 1, 1, 1]}, "a", "attitude")


def test_star_table_round_trip_keeps_columns_and_other_fields():
    stars = [{"x": 1.5, "y": 2.0, "flux": 100.0, "sigma_px": 0.1, "snr": 40.0, "saturated": False},
             {"x": -0.5, "y": 7.25, "flux": 50.0, "sigma_px": 0.2, "snr": 20.0, "saturated": True}]
    table = stars_from_section(stars)
    assert len(table) == 2
    np.testing.assert_array_equal(table.xy, [[1.5, 2.0], [-0.5, 7.25]])
    np.testing.assert_array_equal(table.sigma_px, [0.1, 0.2])
    assert table.to_list() == stars
    with pytest.raises(BadInputError) as info:
        stars_from_section([{"x": 1.0, "y": None}], "f.json")
    assert info.value.field == "stars[0].y"
    with pytest.raises(ValueError, match="column 'y'"):
        StarTable([1.0, 2.0], [1.0], None)


def test_track_state_round_trip():
    section = {"mode": "track", "dt_s": 0.1, "found": 9, "rate_deg_s": [0.0, 0.1, 0.0], "window_px": 8}
    state = from_section(TrackState, section, "t", "track")
    assert state.mode == "track" and state.found == 9
    assert to_section(state) == {"mode": "track", "dt_s": 0.1, "window_px": 8.0, "found": 9,
                                 "rate_deg_s": [0.0, 0.1, 0.0]}


def test_docs_formats_field_tables_are_generated_from_the_schema():
    text = (ROOT / "docs" / "formats.md").read_text(encoding="utf-8")
    assert update_docs(text) == text, "run: python -m startrack.formats.sections docs/formats.md"


def test_own_attitude_section_read_without_checks_is_the_checked_record():
    """``from_section(..., validate=False)`` (the solver's own attitude) gives the record the checked read gives."""
    from startrack.attitude import estimate_attitude

    rng = np.random.default_rng(3)
    dcm = radec_roll_to_dcm(40.0, -20.0, 15.0)
    ref = rng.normal(size=(12, 3)) * 0.05 + np.array([0.0, 0.0, 1.0]) @ dcm
    ref /= np.linalg.norm(ref, axis=1, keepdims=True)
    body = ref @ dcm.T + rng.normal(size=(12, 3)) * 1e-5
    body[3] += 0.01                                          # one outlier: a rejected star
    res = estimate_attitude(body, ref, np.full(12, 1e-5), labels=[(i, 1000 + i) for i in range(12)])
    section = res.section()
    checked = from_section(Attitude, section, "attitude")
    own = from_section(Attitude, section, "attitude", validate=False)
    assert_same_record(own, checked)
    assert own.rejected and own.covariance_arcsec2 is not None and "dcm" in own.details


def test_star_table_of_stars_with_the_same_keys_is_the_general_ones():
    """StarTable.from_list's path for stars that share their keys (column by column) makes the table of the
    general path (star by star): the same columns, dtypes, NaN fluxes, numeric columns and other keys."""
    import random

    rng = random.Random(3)
    names = ["flux", "peak", "sigma_px", "npix", "snr", "mag", "name", "saturated", "fwhm_px", "cov_px2"]
    checked = 0
    for _ in range(600):
        keys = ["x", "y"] + rng.sample(names, rng.randint(0, 7))
        rng.shuffle(keys)
        stars = []
        for _ in range(rng.randint(1, 6)):
            star = {}
            for k in keys:
                r = rng.random()
                star[k] = (rng.uniform(0, 99) if k in "xy" else None if r < 0.05 else rng.randint(0, 9) if r < 0.2
                           else r < 0.23 if r < 0.25 else "a" if k == "name" and r < 0.3 else [[r]] if k == "cov_px2"
                           else rng.uniform(-5, 5))
            stars.append(star)
        fast = StarTable.from_list(stars)
        # The general path: one more star with the keys in another order, dropped from the table after.
        if len(keys) < 2:
            continue
        general = StarTable.from_list(stars + [dict(reversed(list(stars[0].items())))])
        n = len(stars)
        for name in ("x", "y", "flux"):
            assert getattr(fast, name).tobytes() == getattr(general, name)[:n].tobytes(), name
        assert (fast.sigma_px is None) == (general.sigma_px is None)
        if fast.sigma_px is not None:
            assert fast.sigma_px.tobytes() == general.sigma_px[:n].tobytes()
        assert list(fast.columns) == list(general.columns)
        for name, col in fast.columns.items():
            assert col.dtype == np.float64 and col.tobytes() == general.columns[name][:n].tobytes(), name
        assert fast.other == (general.other[:n] if general.other is not None else None)
        checked += 1
    assert checked > 500
