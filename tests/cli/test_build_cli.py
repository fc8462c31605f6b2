import os

import numpy as np
import pytest
from conftest import assert_refused, run_cli


def test_build_kvector_and_labels(tmp_path):
    out = tmp_path / "db.h5"
    proc = run_cli("build-kvector", "--fov-deg", "20", "--mag-max", "4.0", "-o", out, check=True)
    assert "pairs" in proc.stderr and out.exists()
    from startrack.kvector import load_kvector

    db = load_kvector(str(out))
    assert db.params["fov_deg"] == 20 and db.star_mag.max() <= 4.0 and db.params["n_stars"] == db.n_stars
    lab = tmp_path / "labels.h5"
    run_cli("build-labels", "--fov-deg", "24", "--mag-max", "4.5", "--step-deg", "3", "-o", lab, check=True)
    assert lab.exists()


@pytest.mark.parametrize("fov", ["0", "-3", "95"])
def test_bad_fov(tmp_path, fov):
    for cmd in ("build-kvector", "build-labels"):
        out = tmp_path / "x.h5"
        assert_refused(run_cli(cmd, "--fov-deg", fov, "-o", out), "--fov-deg")
        assert not out.exists()


def test_wrong_catalog_format_and_empty_catalog(tmp_path):
    from startrack.formats.hdf5 import write_hdf5

    bogus = tmp_path / "bogus.h5"
    write_hdf5(str(bogus), "startrack.labels/1", {}, {"x": np.arange(3)})
    out = tmp_path / "x.h5"
    assert_refused(run_cli("build-kvector", "--catalog", bogus, "--fov-deg", "10", "-o", out), "bogus.h5", "format")
    assert_refused(run_cli("build-kvector", "--fov-deg", "10", "--mag-max", "-3", "-o", out), "nothing to pair")
    assert_refused(run_cli("build-labels", "--fov-deg", "10", "--mag-max", "-3", "-o", out), "no star")
    assert_refused(run_cli("build-kvector", "--fov-deg", "10", "-o", tmp_path / "x.txt"), "HDF5")
    assert os.listdir(tmp_path) == ["bogus.h5"]
