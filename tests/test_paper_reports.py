"""examples/paper_reports.py: every report is written, and says what was not measured."""
import json
import os
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _reports():
    sys.path.insert(0, os.path.join(ROOT, "examples"))
    try:
        import paper_reports
    finally:
        sys.path.pop(0)
    return paper_reports


def test_reports_without_measurements_say_so(tmp_path):
    pr = _reports()
    assert "Not measured" in pr.report_000(str(tmp_path))
    assert "No data" in pr.report_003(str(tmp_path)) and "p003-scope.json missing" in pr.report_003(str(tmp_path))
    assert "p004-table2.json missing" in pr.report_004(str(tmp_path))
    assert "Cannot be run as published" in pr.report_001(str(tmp_path))


def test_scope_claim_follows_the_measurement(tmp_path):
    pr = _reports()

    def write(b_ms, p_ms):
        mode = {"frames": 10, "mean_ms": 1.0, "mean_search_ms": b_ms, "mean_scope": 10.0, "mean_unnarrowed": 60.0}
        row = {"frames": 10, "success": 10, "failure": 0, "bad": 0, "mean_ms": 1.0, "median_ms": 1.0,
               "mean_scope": 10.0, "mean_unnarrowed": 60.0}
        doc = {"command": "examples/p003_scope.py", "sensor": "s", "calibration": "3:1", "calibration_samples": 5,
               "rows": {"brightness (calibrated)": {**row, "median_search_ms": b_ms, "mean_search_ms": b_ms,
                                                    "modes": {"reference-star": mode}},
                        "pyramid": {**row, "median_search_ms": p_ms, "mean_search_ms": p_ms, "mean_unnarrowed": None,
                                    "modes": {"none": {**mode, "mean_unnarrowed": None}}}}}
        (tmp_path / "p003-scope.json").write_text(json.dumps(doc))
        return pr.report_003(str(tmp_path))

    assert "**not reproduced**" in write(0.08, 0.025)
    text = write(0.01, 0.05)
    assert "speed-up is reproduced" in text and "6.0x fewer" in text
