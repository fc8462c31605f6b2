"""The command line, through the real entry point in subprocesses."""
import json
import os
import subprocess
import sys

import numpy as np
from conftest import assert_refused, run_cli


def test_help_lists_commands_and_is_fast():
    proc = run_cli("--help", check=True)
    for name in ("catalog-filter", "catalog-stats"):
        assert name in proc.stdout
    # Heavy libraries stay out of `startrack --help`.
    code = ("import sys, startrack.cli.main as m; "
            "[m.COMMANDS and m.cli.get_command(None, n) for n in m.COMMANDS]; "
            "print(sorted(k for k in ('numba', 'cv2', 'astropy', 'h5py') if k in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "[]"


def test_every_command_help_has_an_example():
    from startrack.cli.main import COMMANDS

    for name in COMMANDS:
        proc = run_cli(name, "--help", check=True)
        assert "Example" in proc.stdout and f"startrack {name}" in proc.stdout, name


def test_version():
    from startrack import __version__

    assert run_cli("--version", check=True).stdout.strip().endswith(__version__)


def test_catalog_filter_hdf5_and_csv(tmp_path):
    out = tmp_path / "p000.h5"
    proc = run_cli("catalog-filter", "--mag-min", "2.5", "--mag-max", "6.59", "--epoch", "2026.9", "-o", out, check=True)
    assert "kept 8752 of 117955" in proc.stderr
    from startrack.catalog import load_catalog

    cat = load_catalog(str(out))
    assert len(cat) == 8752 and cat.epoch == 2026.9
    assert cat.params["mag_min"] == 2.5
    proc = run_cli("catalog-filter", "--mag-max", "1.0", "-q", check=True)
    rows = [l for l in proc.stdout.splitlines() if l and not l.startswith("#")]
    assert rows[0].startswith("id,") and len(rows) - 1 == int(np.sum(load_catalog().mag <= 1.0))
    assert proc.stderr == ""


def test_catalog_stats_json():
    proc = run_cli("catalog-stats", "--fov-deg", "20", "--size", "1024x1024", "--mag-max", "5.0",
                   "-n", "20000", "--seed", "4", "--json", check=True)
    doc = json.loads(proc.stdout)
    assert doc["boresights"] == 20000 and doc["catalog_stars"] == 1471
    assert 10 < doc["mean"] < 20
    assert doc["fraction_at_least"]["3"] > 0.95
    again = json.loads(run_cli("catalog-stats", "--fov-deg", "20", "--size", "1024x1024", "--mag-max", "5.0",
                               "-n", "20000", "--seed", "4", "--json", check=True).stdout)
    assert again == doc




def test_refuses_missing_catalog(tmp_path):
    out = tmp_path / "o.h5"
    assert_refused(run_cli("catalog-filter", "--catalog", tmp_path / "nope.h5", "-o", out), "nope.h5", "no such file")
    assert not out.exists()


def test_refuses_wrong_format_tag(tmp_path):
    from startrack.formats.hdf5 import write_hdf5

    db = tmp_path / "db.h5"
    write_hdf5(str(db), "startrack.kvector/1", {}, {"id": np.arange(3)})
    out = tmp_path / "o.h5"
    assert_refused(run_cli("catalog-filter", "--catalog", db, "-o", out), "db.h5", "format", "startrack.catalog/1")
    assert not out.exists()


def test_refuses_nan_field(tmp_path):
    from startrack.formats.hdf5 import write_hdf5

    bad = tmp_path / "bad.h5"
    write_hdf5(str(bad), "startrack.catalog/1", {}, {"id": np.arange(3), "ra": np.array([1.0, np.nan, 2.0]),
                                                     "dec": np.zeros(3), "mag": np.ones(3)})
    out = tmp_path / "o.h5"
    assert_refused(run_cli("catalog-filter", "--catalog", bad, "-o", out), "bad.h5", "ra", "non-finite")
    assert not out.exists()
    cam = tmp_path / "cam.json"
    cam.write_text('{"format": "startrack.camera/1", "width": 100, "height": 100, "focal_length_px": NaN, "cx": 1, "cy": 1}')
    assert_refused(run_cli("catalog-stats", "--camera", cam), "cam.json")
    cam.write_text('{"format": "startrack.camera/1", "width": 100, "height": 100, "focal_length_px": null, "cx": 1, "cy": 1}')
    assert_refused(run_cli("catalog-stats", "--camera", cam), "cam.json", "camera.focal_length_px")


def test_refuses_inverted_magnitude_range(tmp_path):
    out = tmp_path / "o.h5"
    assert_refused(run_cli("catalog-filter", "--mag-min", "6", "--mag-max", "3", "-o", out), "--mag-min", "larger")
    assert not out.exists()


def test_refuses_unknown_option():
    assert_refused(run_cli("catalog-filter", "--frobnicate", "3"), "--frobnicate")


def test_refuses_unwritable_output(tmp_path):
    out = tmp_path / "no-such-dir" / "o.h5"
    assert_refused(run_cli("catalog-filter", "--mag-max", "3", "-o", out), str(out), "does not exist")
    assert not out.exists()
    if os.geteuid() != 0:  # root can write anywhere
        ro = tmp_path / "ro"
        ro.mkdir()
        ro.chmod(0o500)
        assert_refused(run_cli("catalog-filter", "--mag-max", "3", "-o", ro / "o.h5"), "not writable")


def test_refuses_empty_selection(tmp_path):
    out = tmp_path / "o.h5"
    assert_refused(run_cli("catalog-filter", "--mag-min", "15", "-o", out), "no star is left")
    assert not out.exists()


def test_refuses_bad_camera_options():
    assert_refused(run_cli("catalog-stats", "--fov-deg", "0", "--size", "100x100"), "--fov-deg")
    assert_refused(run_cli("catalog-stats", "--fov-deg", "10", "--size", "0x100"), "--size")
