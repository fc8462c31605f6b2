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


def test_a_pairs_subset_is_kept_beside_its_database(db_file):
    """cached_subset: a subset of a file's database (the pyramid's first tier) is made once, kept in the cache and
    read back by the next process (a fresh database object), the same arrays, sharing the database's stars; a subset
    that is none is kept as none; a damaged copy is made again; a database held in memory only makes it every time."""
    from startrack.kvector import cached_subset

    calls = []

    def make(db):
        calls.append(db)
        return db.pairs_subset(np.asarray(db.star_mag)[db.pair_i] + np.asarray(db.star_mag)[db.pair_j] < 5.0)

    first = load_kvector(db_file)
    made = cached_subset(first, "test|5.0", make)
    assert len(calls) == 1 and 0 < made.n_pairs < first.n_pairs
    again_db = load_kvector(db_file)
    again = cached_subset(again_db, "test|5.0", make)
    assert len(calls) == 1                  # read from the cache
    _same(made, again)
    assert again.star_vector is again_db.star_vector
    # Another kind is another subset.
    cached_subset(again_db, "test|other", make)
    assert len(calls) == 2
    # None is kept as none.
    assert cached_subset(again_db, "test|none", lambda db: calls.append(db)) is None
    assert cached_subset(again_db, "test|none", make) is None and len(calls) == 3
    # A damaged copy (a neighbour index beyond the stars, the sha256 written to match) is made again.
    copy = flatcopy.copy_path(db_file, f"{KVECTOR_FORMAT}|subset|test|5.0")
    header, arrays = flatcopy.read_copy(copy)
    arrays = {k: np.array(v) for k, v in arrays.items()}
    arrays["neighbor_idx"][3] = first.n_stars + 5
    os.remove(copy)
    assert flatcopy.write_copy(copy, {k: v for k, v in header.items() if k not in ("arrays", "data_sha256")}, arrays)
    remade = cached_subset(load_kvector(db_file), "test|5.0", make)
    assert len(calls) == 4
    _same(made, remade)
    # A database in memory only (no file): made every time.
    memory = dataclasses.replace(first, path="")
    cached_subset(memory, "test|5.0", make)
    cached_subset(memory, "test|5.0", make)
    assert len(calls) == 6


def test_a_copy_of_no_array_holds_its_header(tmp_path):
    """A copy without arrays (a subset that is none) reads back its header: the header's text is written even when
    no array's offset depends on it."""
    path = str(tmp_path / "empty.bin")
    assert flatcopy.write_copy(path, {"none": True}, {})
    header, arrays = flatcopy.read_copy(path)
    assert header["none"] is True and arrays == {}
