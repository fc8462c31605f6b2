"""HDF5 catalogs and databases: every file carries its format, version and parameters.

Root attributes of every startrack HDF5 file (``docs/formats.md``):

``format``
    e.g. ``"startrack.kvector/1"``.
``startrack_version``
    the version that wrote it.
``params``
    JSON string of every parameter that built it.
``catalog_sha256`` (databases)
    checksum of the star table they were built from
    (:meth:`startrack.catalog.Catalog.checksum`).
"""
from __future__ import annotations

import contextlib
import json
import logging
import os
import time

import numpy as np

from startrack._version import __version__
from startrack.errors import BadInputError, reading
from startrack.formats.atomic import atomic_path, deferred_signals
from startrack.formats.frame import check_format_tag

__all__ = ["CHECKSUM_ATTR", "HDF5File", "build_lock", "cached_database", "corrupt_hdf5", "read_format_tag", "read_hdf5", "verify_dataset", "write_hdf5"]

log = logging.getLogger(__name__)


def write_hdf5(path: str, format_tag: str, params: dict, datasets: dict, attrs: dict | None = None,
               compress: bool = True) -> None:
    """Write datasets and root attributes atomically.

    Parameters
    ----------
    path : str
        Destination; written to a temporary file beside it and renamed.
    format_tag : str
        The ``format`` attribute, e.g. ``"startrack.catalog/1"``.
    params : dict
        Every parameter that built the file; stored as a JSON string.
    datasets : dict of str -> ndarray
        Root datasets.  A value may be ``(array, {attr: value})`` to attach
        attributes such as ``unit``.
    attrs : dict, optional
        Extra root attributes (strings or numbers).
    """
    import h5py

    with atomic_path(path, suffix=".h5") as tmp, deferred_signals(), h5py.File(tmp, "w") as h5:
        h5.attrs["format"] = format_tag
        h5.attrs["startrack_version"] = __version__
        h5.attrs["params"] = json.dumps(params, sort_keys=True)
        for key, value in (attrs or {}).items():
            h5.attrs[key] = value
        sums = {ATTRS_KEY: _attrs_sha256({k: _attr(v) for k, v in h5.attrs.items()})}
        for name, value in datasets.items():
            dattrs = {}
            if isinstance(value, tuple):
                value, dattrs = value
            value = np.asarray(value)
            sums[name] = _array_sha256(value)
            kwargs = {}
            if compress and value.size > 1024:
                kwargs = {"compression": "gzip", "compression_opts": 4, "shuffle": True}
            if value.ndim >= 1 and value.size > 0 and value.dtype.kind not in "OUS":
                # A checksum per chunk, verified by HDF5 on every read (a corrupted file is noticed).
                kwargs["fletcher32"] = True
            ds = h5.create_dataset(name, data=value, **kwargs)
            for key, attr in dattrs.items():
                ds.attrs[key] = attr
        h5.attrs[CHECKSUM_ATTR] = json.dumps(sums, sort_keys=True)


#: Root attribute of every startrack HDF5 file written since issue 41: JSON ``{dataset: sha256, "@attrs": sha256}``
#: of each dataset's dtype, shape and bytes and of the other root attributes, checked by :func:`read_hdf5` (HDF5's
#: own fletcher32 covers only chunked datasets, and nothing an editor rewrites whole).
CHECKSUM_ATTR = "sha256"
ATTRS_KEY = "@attrs"


def _array_sha256(value) -> str:
    import hashlib

    value = np.ascontiguousarray(value)
    h = hashlib.sha256(f"{value.dtype.str}{value.shape}".encode())
    if value.dtype.kind == "O":
        h.update(json.dumps([str(v) for v in value.ravel()]).encode())
    else:
        h.update(memoryview(value).cast("B"))
    return h.hexdigest()


def _attrs_sha256(attrs: dict) -> str:
    import hashlib

    rest = {k: np.asarray(v).tolist() if not isinstance(v, str) else v for k, v in attrs.items() if k != CHECKSUM_ATTR}
    return hashlib.sha256(json.dumps(rest, sort_keys=True, default=str).encode()).hexdigest()


def _checksums(path: str, attrs: dict) -> dict | None:
    """The file's ``sha256`` map (None for a file written before checksums), its attributes checked."""
    text = attrs.get(CHECKSUM_ATTR)
    if text is None:
        return None
    try:
        sums = json.loads(text)
    except (TypeError, ValueError):
        sums = None
    if not isinstance(sums, dict) or ATTRS_KEY not in sums:
        raise BadInputError(path, CHECKSUM_ATTR, "is not a checksum map: the file is damaged")
    if sums[ATTRS_KEY] != _attrs_sha256(attrs):
        raise BadInputError(path, CHECKSUM_ATTR, "does not match the root attributes: the file is damaged "
                                                 "(or was edited): build it again")
    return sums


def verify_dataset(path: str, sums: dict | None, name: str, value) -> None:
    """Refuse a dataset whose bytes are not those the file's checksum map records."""
    if sums is None:
        return
    if sums.get(name) != _array_sha256(value):
        raise BadInputError(path, name, "does not match the file's sha256: the file is damaged (or was edited): "
                                        "build it again")


class HDF5File:
    """What :func:`read_hdf5` returns: root attributes, parsed params and datasets."""

    def __init__(self, path: str, attrs: dict, datasets: dict):
        self.path = path
        self.attrs = attrs
        self.datasets = datasets
        try:
            self.params = json.loads(attrs.get("params", "{}"))
        except (ValueError, TypeError):
            raise BadInputError(path, "params", "is not a JSON string") from None
        if not isinstance(self.params, dict):
            raise BadInputError(path, "params", "is not a JSON object")

    def __getitem__(self, name):
        try:
            return self.datasets[name]
        except KeyError:
            raise BadInputError(self.path, name, "dataset is missing") from None

    def __contains__(self, name):
        return name in self.datasets

    def array(self, name: str, dtype, shape: tuple = (None,), finite: bool = False, index_of: int | None = None,
              within: tuple | None = None, ascending: bool = False) -> np.ndarray:
        """Dataset ``name`` as a contiguous array of ``dtype``, checked before any kernel trusts it.

        ``shape``: the expected shape, ``None`` for any length (``(n, 3)``: n rows of 3).  ``finite``: no NaN or
        infinity.  ``index_of``: every value indexes an array of that length (``0 <= v < index_of``).
        ``within``: every value in ``[lo, hi]``.  ``ascending``: sorted, non-decreasing.  Anything else is a
        :class:`BadInputError` naming the file and the dataset.
        """
        raw = np.asarray(self[name])
        want = np.dtype(dtype)
        ok_kinds = "iub" if want.kind in "iu" else "iubf" if want.kind == "f" else want.kind
        if raw.dtype.kind not in ok_kinds:
            raise BadInputError(self.path, name, f"holds {raw.dtype} values, expected {want.name}")
        if raw.ndim != len(shape) or any(w is not None and w != h for w, h in zip(shape, raw.shape)):
            expected = " x ".join("n" if w is None else str(w) for w in shape)
            raise BadInputError(self.path, name, f"has shape {raw.shape}, expected ({expected})")
        if want.kind in "iu" and raw.size and (raw.min() < np.iinfo(want).min or raw.max() > np.iinfo(want).max):
            raise BadInputError(self.path, name, f"holds values outside the range of {want.name}")
        out = np.ascontiguousarray(raw, dtype=want)
        if (finite or index_of is not None or within is not None) and want.kind == "f" and not np.isfinite(out).all():
            raise BadInputError(self.path, name, f"has {int((~np.isfinite(out)).sum())} non-finite values")
        if index_of is not None and out.size and (out.min() < 0 or out.max() >= index_of):
            raise BadInputError(self.path, name, f"holds indices outside 0..{index_of - 1}: the file is damaged")
        if within is not None and out.size and (out.min() < within[0] or out.max() > within[1]):
            raise BadInputError(self.path, name, f"holds values outside [{within[0]}, {within[1]}]: the file is "
                                                 "damaged")
        if ascending and out.size > 1 and not np.all(out[1:] >= out[:-1]):
            raise BadInputError(self.path, name, "is not sorted ascending: the file is damaged")
        return out

    def numbers(self, name: str, count: int | None = None, positive: bool = False) -> tuple:
        """Root attribute ``name``: ``count`` finite numbers (one number when ``count`` is None)."""
        if name not in self.attrs:
            raise BadInputError(self.path, name, "attribute is missing")
        try:
            values = np.asarray(self.attrs[name], dtype=np.float64).ravel()
        except (TypeError, ValueError):
            raise BadInputError(self.path, name, "attribute is not numeric") from None
        if len(values) != (count or 1) or not np.isfinite(values).all() or (positive and not (values > 0).all()):
            raise BadInputError(self.path, name, f"attribute must be {count or 1} finite{' positive' if positive else ''} "
                                                 f"number(s), got {values.tolist()[:6]}")
        return tuple(float(v) for v in values) if count else float(values[0])


def _attr(value):
    if isinstance(value, bytes):
        return value.decode()
    if isinstance(value, np.generic):
        return value.item()
    return value


class corrupt_hdf5(contextlib.AbstractContextManager):  # noqa: N801 - used as a context manager
    """Turn what h5py raises on a damaged file (``OSError``, ``KeyError``, ``ValueError`` ...) into a
    :class:`BadInputError` naming the file and the dataset being read (set ``.field`` as reading goes on).

    Example: ``with corrupt_hdf5(path) as where: where.field = "ra"; h5["ra"][()]``.
    """

    def __init__(self, path: str, field: str | None = None):
        self.path, self.field = path, field

    def __exit__(self, exc_type, exc, tb):
        if exc is None or isinstance(exc, BadInputError) or not isinstance(
                exc, (OSError, KeyError, ValueError, RuntimeError, TypeError, AttributeError, IndexError)):
            return False
        text = str(exc).strip("'\"").splitlines()[0][:100] if str(exc) else type(exc).__name__
        raise BadInputError(self.path, self.field, f"is corrupt (HDF5: {text})") from None


def read_hdf5(path: str, expected_format: str, names=None) -> HDF5File:
    """Open a startrack HDF5 file, check its format tag and read its datasets.

    Parameters
    ----------
    path : str
    expected_format : str
        e.g. ``"startrack.catalog/1"``; another family or major version is refused.
    names : iterable of str, optional
        Datasets to read (default all root datasets).

    Raises
    ------
    BadInputError
        Missing file, not HDF5, wrong or missing ``format``, missing dataset.
    """
    import h5py

    if not os.path.exists(path):
        raise BadInputError(path, None, "no such file")
    if os.path.isdir(path):
        raise BadInputError(path, None, "is a directory")
    try:
        h5 = h5py.File(path, "r")
    except OSError:
        raise BadInputError(path, None, f"is not an HDF5 file or is corrupt (expected {expected_format})") from None
    with h5, corrupt_hdf5(path) as where, reading(path) as what:
        try:
            attrs = {k: _attr(v) for k, v in h5.attrs.items()}
        except (OSError, KeyError, ValueError, RuntimeError):
            raise BadInputError(path, None, "is corrupt (its attributes cannot be read)") from None
        check_format_tag(attrs, expected_format, path)
        sums = _checksums(path, attrs)
        present = [k for k in h5 if isinstance(h5[k], h5py.Dataset)]
        if sums is not None:
            extra = sorted(set(present) - set(sums))
            if extra:
                raise BadInputError(path, extra[0], "is not in the file's sha256 map: the file was edited")
        wanted = list(names) if names is not None else present
        datasets = {}
        for name in wanted:
            where.field = what.field = name
            if name not in h5:
                raise BadInputError(path, name, "dataset is missing")
            datasets[name] = h5[name][()]
            verify_dataset(path, sums, name, datasets[name])
    return HDF5File(path, attrs, datasets)


@contextlib.contextmanager
def build_lock(path: str):
    """Hold an exclusive lock (``fcntl``) on ``path + ".lock"`` while a cached file is checked or built.

    A second process that needs the same file waits, then finds it built.
    """
    try:
        import fcntl
    except ImportError:  # not POSIX: no lock, builds may race (each is still atomic)
        yield
        return
    lock_path = path + ".lock"
    try:
        handle = open(lock_path, "a+")  # noqa: SIM115 - held for the whole block
    except OSError:
        yield
        return
    with handle:
        try:
            fcntl.flock(handle.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            log.warning("waiting for another process building %s", path)
            fcntl.flock(handle.fileno(), fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(handle.fileno(), fcntl.LOCK_UN)


def cached_database(path: str, load, save, build, valid=lambda db: True):  # noqa: ARG005 - the caller's signature
    """A database from its cache file, else built and saved; a corrupt or stale file is rebuilt.

    Parameters
    ----------
    path : str
        The cache file.
    load, save : callable
        ``load(path) -> db`` (raises ``BadInputError`` for a corrupt file, e.g. a
        failed HDF5 checksum) and ``save(db, path)`` (atomic).
    build : callable
        ``build() -> db``.
    valid : callable
        ``valid(db) -> bool``: False for a file built from another catalog.

    Holds :func:`build_lock` so two processes never build the same file at once;
    a file without the ``sha256`` map (:data:`CHECKSUM_ATTR`, checked by :func:`read_hdf5`) is rebuilt, and
    a corrupt file gets a one-line warning (logger ``startrack.formats.hdf5``) and is rebuilt.
    """
    with build_lock(path):
        db = None
        if os.path.exists(path):
            try:
                if not _has_checksum(path):
                    raise BadInputError(path, CHECKSUM_ATTR, "is missing (a file from before checksums)")
                db = load(path)
                if not valid(db):
                    log.info("cached database %s was built from another catalog: rebuilding it", path)
                    db = None
            except BadInputError as exc:
                log.warning("cached database %s: %s%s: rebuilding it", path,
                            f"{exc.field}: " if exc.field else "", exc.problem)
                db = None
        if db is None:
            log.info("building the cached database %s", path)
            t0 = time.perf_counter()
            db = build()
            save(db, path)
            db.path = path
            log.info("built %s in %.1f s", path, time.perf_counter() - t0)
    return db


def _has_checksum(path: str) -> bool:
    """Whether an HDF5 file carries the ``sha256`` map (False for a file that is not HDF5: its loader says why)."""
    import h5py

    try:
        with h5py.File(path, "r") as h5:
            return CHECKSUM_ATTR in h5.attrs
    except (OSError, KeyError, ValueError, RuntimeError):
        return True


def read_format_tag(path: str) -> str:
    """The ``format`` attribute of a startrack HDF5 file (``BadInputError`` when missing or not HDF5)."""
    import h5py

    if not os.path.exists(path):
        raise BadInputError(path, None, "no such file")
    try:
        with h5py.File(path, "r") as h5:
            tag = _attr(h5.attrs.get("format"))
    except OSError:
        raise BadInputError(path, None, "is not an HDF5 file") from None
    if not isinstance(tag, str) or not tag.startswith("startrack."):
        raise BadInputError(path, "format", f"{tag!r} is not a startrack file")
    return tag
