"""-v/--verbose and -q through the real entry point (issue 20: log levels on stderr; -q hides progress, never errors)."""
import json
import re
import subprocess
import sys

import numpy as np
import pytest
from conftest import run_cli

LOG_LINE = re.compile(r"^startrack: (INFO|DEBUG): startrack\.[\w.]+: ", re.MULTILINE)


def _log_lines(stderr, level=None):
    return [l for l in stderr.splitlines() if LOG_LINE.match(l) and (level is None or f": {level}: " in l)]


def test_verbose_shows_the_library_log_and_quiet_default_shows_none(tmp_path):
    out = tmp_path / "bright.csv"
    for flags in (["-v"], ["--verbose"]):
        proc = run_cli(*flags, "catalog-filter", "--mag-max", "1.0", "-o", out, check=True)
        lines = _log_lines(proc.stderr, "INFO")
        # the catalog module's own line: which file, how many stars, how long
        assert any(re.search(r"startrack\.catalog: catalog \S+hip2\.h5: \d+ stars.* read in \d+ ms", l)
                   for l in lines), proc.stderr
    # -v after the command name works too
    after = run_cli("catalog-filter", "--mag-max", "1.0", "-o", out, "-v", check=True)
    assert any("startrack.catalog:" in l for l in _log_lines(after.stderr, "INFO")), after.stderr
    plain = run_cli("catalog-filter", "--mag-max", "1.0", "-o", out, check=True)
    assert _log_lines(plain.stderr) == [] and "INFO" not in plain.stderr, plain.stderr
    assert "kept" in plain.stderr        # the ordinary summary is still there


@pytest.fixture(scope="module")
def star_frame(tmp_path_factory):
    """A small k-vector database and one rendered star list (no image)."""
    d = tmp_path_factory.mktemp("verbose")
    db = d / "db.h5"
    run_cli("build-kvector", "--fov-deg", "20", "--size", "1024x1024", "--mag-max", "5.0", "-o", db, "-q", check=True)
    frame = run_cli("render", "--stars-only", "--fov-deg", "20", "--size", "1024x1024", "--ra", "83.8", "--dec",
                    "-1.2", "--mag-max", "5.5", "--seed", "3", check=True).stdout
    return db, frame


def test_verbose_identify_says_what_the_search_did(star_frame):
    db, frame = star_frame
    info = run_cli("identify", "-d", db, "-v", input=frame, check=True)
    lines = _log_lines(info.stderr, "INFO")
    assert any(re.search(r"startrack\.kvector: k-vector database \S+db\.h5: \d+ stars, \d+ pairs", l)
               for l in lines), info.stderr
    assert any(re.search(r"startrack\.identify\.driver: pyramid: \d+ of \d+ stars identified at proposal \d+", l)
               for l in lines), info.stderr
    assert any(re.search(r"startrack\.cli\.batch: frame 1 \(<stdin>[^)]*\): ok", l) for l in lines), info.stderr
    assert _log_lines(info.stderr, "DEBUG") == []
    debug = run_cli("identify", "-d", db, "-vv", input=frame, check=True)
    assert any(re.search(r"DEBUG: startrack\.identify\.driver: pyramid: \d+ stars .*tolerance", l)
               for l in _log_lines(debug.stderr, "DEBUG")), debug.stderr
    quiet = run_cli("identify", "-d", db, input=frame, check=True)
    assert _log_lines(quiet.stderr) == [], quiet.stderr
    assert json.loads(quiet.stdout)["identification"]["status"] == "ok"


def test_verbose_tells_why_a_frame_failed(star_frame):
    db, frame = star_frame
    doc = json.loads(frame)
    rng = np.random.default_rng(1)
    # stars scattered at random: no pattern of the sky
    doc["stars"] = [{"x": float(x), "y": float(y), "flux": 1000.0 - k}
                    for k, (x, y) in enumerate(rng.uniform(50, 970, (8, 2)))]
    proc = run_cli("identify", "-d", db, "-v", "--max-proposals", "50", input=json.dumps(doc))
    assert proc.returncode == 1, proc.stderr
    lines = _log_lines(proc.stderr, "INFO")
    assert any(re.search(r"pyramid: not identified after \d+ proposal\(s\).*: \S", l) for l in lines), proc.stderr
    assert any(re.search(r"frame 1 \(<stdin>[^)]*\): failed: \S", l) for l in lines), proc.stderr


def test_the_library_never_installs_a_handler():
    code = ("import logging, startrack\n"
            "from startrack.catalog import load_catalog\n"
            "load_catalog(mag_max=2.0)\n"
            "print(len(logging.getLogger('startrack').handlers), len(logging.getLogger().handlers))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["0", "0"] and out.stderr == ""


def test_quiet_batch_with_one_failed_frame_still_says_so(star_frame):
    """-q hides progress and the summary of a clean run, never a failure: one line for the frame, exit 1."""
    db, frame = star_frame
    bad = json.loads(frame)
    rng = np.random.default_rng(2)
    bad["stars"] = [{"x": float(x), "y": float(y), "flux": 1000.0 - k}
                    for k, (x, y) in enumerate(rng.uniform(50, 970, (8, 2)))]
    batch = frame.strip() + "\n" + json.dumps(bad) + "\n" + frame.strip() + "\n"
    proc = run_cli("identify", "-d", db, "-q", "--max-proposals", "50", input=batch)
    assert proc.returncode == 1, proc.stderr
    docs = [json.loads(l) for l in proc.stdout.splitlines()]
    assert [d["identification"]["status"] for d in docs] == ["ok", "failed", "ok"]
    lines = [l for l in proc.stderr.splitlines() if l.strip()]
    errors = [l for l in lines if l.startswith("startrack identify: ")]
    assert len(errors) == 1 and "<stdin>:2" in errors[0] and "identification failed: " in errors[0], proc.stderr
    assert docs[1]["identification"]["reason"] in errors[0]
    assert "Traceback" not in proc.stderr and _log_lines(proc.stderr) == []
    # besides the failure, only the summary line (kept by -q because the batch did not succeed)
    assert [l for l in lines if l not in errors] == ["identify: 3 frame(s), 2 ok, 1 failed, 0 bad input"], lines
    clean = run_cli("identify", "-d", db, "-q", input=frame.strip() + "\n" + frame.strip() + "\n")
    assert clean.returncode == 0 and clean.stderr == "", clean.stderr
