"""The shipped catalog's cache file (startrack.catalog._cached_catalog): the HDF5 file's catalog, value for value,
read without h5py, and a cache file that does not read is replaced, never believed."""
import os
import subprocess
import sys

import numpy as np
import pytest

import startrack.catalog as C


def _same(a, b):
    for name in C._COLUMNS:
        x, y = getattr(a, name), getattr(b, name)
        assert x.dtype == y.dtype and np.array_equal(x, y, equal_nan=True), name
    assert (a.epoch, a.params, a.source, a.merged) == (b.epoch, b.params, b.source, b.merged)
    assert list(a.merged) == list(b.merged)


@pytest.fixture()
def cache(tmp_path, monkeypatch):
    monkeypatch.setenv("STARTRACK_CACHE", str(tmp_path))
    return tmp_path


@pytest.mark.parametrize("mag_max", [None, 2.0, 6.5, 30.0])
def test_the_cached_catalog_is_the_files(cache, mag_max):
    path = C.default_catalog_path()
    first = C.load_catalog(None, mag_max)          # reads the HDF5 file, writes the cache
    assert [p.name for p in cache.glob("catalog-*.bin")]
    again = C.load_catalog(None, mag_max)          # from the cache
    want = C._read_catalog(path, mag_max, 0.0)
    _same(first, want)
    _same(again, want)
    assert all(getattr(again, n).flags.writeable and type(getattr(again, n)) is np.ndarray for n in C._COLUMNS)


@pytest.mark.parametrize("damage", ["truncate", "magic", "header"])
def test_a_cache_file_that_does_not_read_is_replaced(cache, damage):
    want = C.load_catalog()
    (cache_file,) = cache.glob("catalog-*.bin")
    data = cache_file.read_bytes()
    if damage == "truncate":
        cache_file.write_bytes(data[: len(data) // 2])
    elif damage == "magic":
        cache_file.write_bytes(b"XXXXXXX\n" + data[8:])
    else:
        cache_file.write_bytes(data[:16] + b"{not json" + data[25:])
    assert C._cached_catalog(C.default_catalog_path()) is None
    _same(C.load_catalog(), want)                   # read from the file again, and the cache written anew
    assert C._cached_catalog(C.default_catalog_path()) is not None


def test_a_changed_catalog_file_gets_its_own_cache(cache, tmp_path, monkeypatch):
    import shutil

    copy = tmp_path / "hip2.h5"
    shutil.copy(C.default_catalog_path(), copy)
    monkeypatch.setenv("STARTRACK_CATALOG", str(copy))
    C.load_catalog()
    os.utime(copy, ns=(1, 1))                       # the file "changed": another name, not the old file's copy
    C.load_catalog()
    assert len(list(cache.glob("catalog-*.bin"))) == 2


def test_a_process_reads_the_cached_catalog_without_h5py(cache):
    C.load_catalog()
    code = ("import sys; from startrack.catalog import load_catalog; c = load_catalog(); "
            "print(len(c), 'h5py' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                         env={**os.environ, "STARTRACK_CACHE": str(cache)})
    assert out.returncode == 0, out.stderr
    n, h5 = out.stdout.split()
    assert int(n) == len(C.load_catalog()) and h5 == "False"


def test_a_cache_that_cannot_be_written_leaves_nothing_behind(cache, monkeypatch):
    """A full disk (the rename fails): the catalog is read as ever, and no partial cache file stays."""
    def full(*_args):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(C.os, "replace", full)
    cat = C.load_catalog()
    assert len(cat) > 100_000
    assert not list(cache.glob("catalog-*"))


def test_without_a_writable_cache_a_few_rows_are_read_alone(cache, monkeypatch):
    """Where no cache file can be written, a read of the brightest stars reads those rows alone, as before the
    cache (not the whole file for a copy that cannot be kept)."""
    monkeypatch.setattr(C, "_cache_writable", lambda: False)
    read = []
    real = C._read_catalog

    def spy(path, mag_max, t0):
        read.append(mag_max)
        return real(path, mag_max, t0)

    monkeypatch.setattr(C, "_read_catalog", spy)
    bright = C.load_catalog(None, 3.0)
    assert read == [3.0] and len(bright) < 200
    assert not list(cache.glob("catalog-*"))


def test_band_databases_are_cached_uncompressed(catalog, tmp_path, monkeypatch):
    """A FOV band's k-vector database goes to the cache without compression (every `solve --camera` process reads
    it: half the time of a gzipped read), loads as it was built, and a file cached gzipped before still loads."""
    import h5py

    from startrack import solve
    from startrack.kvector import load_kvector, save_kvector

    monkeypatch.setenv("STARTRACK_CACHE", str(tmp_path))
    small = catalog.filter_magnitude(None, 4.0)
    built = solve.band_database(2, catalog=small)
    assert os.path.dirname(built.path) == str(tmp_path)
    with h5py.File(built.path, "r") as h5:
        assert h5["pair_cos"].size > 1024 and all(h5[name].compression is None for name in h5)
    again = solve.band_database(2, catalog=small)
    for name in ("star_id", "star_vector", "pair_i", "pair_j", "pair_cos", "kvector", "kquad", "neighbor_idx"):
        np.testing.assert_array_equal(getattr(again, name), getattr(built, name))
    save_kvector(built, built.path)                 # as a cache written before: gzipped
    with h5py.File(built.path, "r") as h5:
        assert h5["pair_cos"].compression == "gzip"
    np.testing.assert_array_equal(load_kvector(built.path).pair_cos, built.pair_cos)
    np.testing.assert_array_equal(solve.band_database(2, catalog=small).kvector, built.kvector)


@pytest.mark.usefixtures("cache")
@pytest.mark.parametrize("mag_max", [None, 2.0, 6.5])
def test_the_cached_catalog_holds_its_unit_vectors(mag_max):
    """The cache file holds the stars' unit vectors (a process then never computes them: ~22 ms of the shipped
    catalog's): the vectors its ra and dec give, bit for bit, for the whole catalog and its brightest rows; a catalog
    made from it (a subset) computes its own."""
    from startrack.rotations import radec_to_vector

    C.load_catalog()                                # writes the cache
    again = C.load_catalog(None, mag_max)           # from the cache
    held = again.__dict__["_cache_vectors"][1]      # kept, not computed
    want = radec_to_vector(again.ra, again.dec)
    assert again.vectors() is held
    assert held.shape == (len(again), 3) and held.flags.c_contiguous and held.flags.writeable
    assert np.array_equal(held, want)               # bit for bit (no NaN: every star has a position)
    sub = again.subset(np.arange(0, len(again), 7))
    assert "_cache_vectors" not in sub.__dict__ and np.array_equal(sub.vectors(), want[::7])


@pytest.mark.usefixtures("cache")
def test_the_cached_catalog_holds_its_sky_index():
    """The cache file holds the sky index of the whole catalog (~12 ms a process would spend): the arrays a new
    SkyIndex of its vectors makes, and the same cones."""
    from startrack.skyindex import SkyIndex

    C.load_catalog()
    again = C.load_catalog()
    sky = again.sky_index()
    assert again.__dict__["_cache_sky_index"][1] is sky         # kept, not built
    fresh = SkyIndex(again.vectors())
    assert np.array_equal(sky.cells, fresh.cells) and np.array_equal(sky.ra, fresh.ra)
    rng = np.random.default_rng(5)
    for axis in rng.normal(size=(20, 3)):
        axis /= np.linalg.norm(axis)
        assert np.array_equal(sky.cone(axis, np.cos(0.2)), fresh.cone(axis, np.cos(0.2)))


@pytest.mark.parametrize("damage", ["cut", "row", "offset"])
def test_a_cache_file_whose_derived_arrays_do_not_hold_is_replaced(cache, damage):
    """A cache file cut short in its last derived array, or whose sky index names a row beyond the stars or a band
    beyond them (a cone query would read outside the vectors), is not read, and the catalog file is read again."""
    want = C.load_catalog()
    (cache_file,) = cache.glob("catalog-*.bin")
    data = bytearray(cache_file.read_bytes())
    head = C.json.loads(bytes(data[16:16 + int.from_bytes(data[8:16], "little")]))
    _, _, shape, at = next(d for d in head["arrays"] if d[0] == "sky_cells")
    nb = int(np.frombuffer(bytes(data[at:at + 8]), "<i8")[0])
    if damage == "cut":
        data = data[:-8]
    elif damage == "row":
        data[at + 8 * (nb + 2 + 5):at + 8 * (nb + 2 + 6)] = np.int64(len(want) + 3).tobytes()
    else:
        data[at + 8 * 3:at + 8 * 4] = np.int64(len(want) * 2).tobytes()
    cache_file.write_bytes(bytes(data))
    assert C._cached_catalog(C.default_catalog_path()) is None
    _same(C.load_catalog(), want)
    assert C._cached_catalog(C.default_catalog_path()) is not None
