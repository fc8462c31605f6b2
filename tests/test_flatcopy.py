"""A k-vector database's flat copy in the cache (startrack.formats.flatcopy): the HDF5 file's database, value for
value, read without h5py; a copy that does not match its checksum is never read; a changed file gets its own."""
import dataclasses
import json
import os
import subprocess
import sys

import numpy as np
import pytest

from startrack.formats import flatcopy
from startrack.kvector import KVECTOR_FORMAT, build_kvector, load_kvector, save_kvector


def _same(a, b):
    for f in dataclasses.fields(a):
        x, y = getattr(a, f.name), getattr(b, f.name)
        if isinstance(x, np.ndarray):
            assert x.dtype == y.dtype and x.shape == y.shape and np.array_equal(x, y), f.name
        else:
            assert x == y, f.name


@pytest.fixture()
def db_file(catalog, tmp_path, monkeypatch):
    monkeypatch.setenv("STARTRACK_CACHE", str(tmp_path / "cache"))
    path = tmp_path / "db.h5"
    save_kvector(build_kvector(catalog.filter_magnitude(None, 4.0), 12.0), str(path))
    return str(path)


def _copies(db_file):
    return sorted(p for p in os.listdir(os.path.join(os.path.dirname(db_file), "cache")) if p.endswith(".bin"))


def test_the_copy_is_the_files_database(db_file):
    first = load_kvector(db_file)           # the HDF5 file, and its copy written
    assert len(_copies(db_file)) == 1
    again = load_kvector(db_file)           # the copy
    _same(first, again)
    assert again.path == db_file
    assert again.star_vector.flags.writeable and type(again.pair_cos) is np.ndarray


def test_a_process_reads_the_copy_without_h5py(db_file):
    load_kvector(db_file)
    code = ("import sys, json; from startrack.kvector import load_kvector; db = load_kvector(sys.argv[1]); "
            "print(json.dumps({'h5py': 'h5py' in sys.modules, 'pairs': int(db.n_pairs)}))")
    proc = subprocess.run([sys.executable, "-c", code, db_file], capture_output=True, text=True, timeout=300,
                          env=dict(os.environ))
    assert proc.returncode == 0, proc.stderr
    out = json.loads(proc.stdout)
    assert out == {"h5py": False, "pairs": int(load_kvector(db_file).n_pairs)}


@pytest.mark.parametrize("damage", ["data", "truncate", "header"])
def test_a_damaged_copy_is_never_read(db_file, damage):
    want = load_kvector(db_file)
    (name,) = _copies(db_file)
    copy = os.path.join(os.path.dirname(db_file), "cache", name)
    data = bytearray(open(copy, "rb").read())
    if damage == "data":
        data[-100] ^= 0xFF                  # a value in the last array, the file's size the same
    elif damage == "truncate":
        data = data[: len(data) // 2]
    else:
        data[16] = ord("#")                 # the JSON header's first character
    with open(copy, "wb") as fh:
        fh.write(data)
    assert flatcopy.read_copy(copy) is None
    _same(load_kvector(db_file), want)      # from the HDF5 file again, and the copy written anew
    assert flatcopy.read_copy(copy) is not None


def test_a_damaged_copy_is_caught_even_with_its_stamp_rewritten(db_file):
    """The stamp names the copy's inode, size and times: a copy changed in place (its change time moves) is checked
    against its sha256 again, whatever its stamp says."""
    load_kvector(db_file)
    (name,) = _copies(db_file)
    copy = os.path.join(os.path.dirname(db_file), "cache", name)
    stamp = open(copy + ".checked").read()
    with open(copy, "r+b") as fh:
        fh.seek(-200, os.SEEK_END)
        fh.write(b"\x7f" * 8)
    with open(copy + ".checked", "w") as fh:
        fh.write(stamp)                     # the old stamp back: the change time no longer matches it
    assert flatcopy.read_copy(copy) is None


def test_a_changed_file_gets_its_own_copy(db_file, catalog):
    first = load_kvector(db_file)
    save_kvector(build_kvector(catalog.filter_magnitude(None, 3.5), 12.0), db_file)
    again = load_kvector(db_file)
    assert len(_copies(db_file)) == 2
    _same(again, load_kvector(db_file))
    assert again.n_stars < first.n_stars


def test_without_a_writable_cache_the_file_is_read(db_file, monkeypatch):
    monkeypatch.setenv("STARTRACK_CACHE", "/proc/no-such-cache")
    db = load_kvector(db_file)
    assert db.n_pairs > 0
    assert flatcopy.copy_path(db_file, KVECTOR_FORMAT) is None
