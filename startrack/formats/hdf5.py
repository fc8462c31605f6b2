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
from startrack.errors import BadInputError
from startrack.formats.atomic import atomic_path, deferred_signals
from startrack.formats.frame import check_format_tag

__all__ = ["HDF5File", "build_lock", "cached_database", "corrupt_hdf5", "read_format_tag", "read_hdf5", "write_hdf5"]

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
        for name, value in datasets.items():
            dattrs = {}
            if isinstance(value, tuple):
                value, dattrs = value
            value = np.asarray(value)
            kwargs = {}
            if compress and value.size > 1024:
                kwargs = {"compression": "gzip", "compression_opts": 4, "shuffle": True}
            if value.ndim >= 1 and value.size > 0 and value.dtype.kind not in "OUS":
                # A checksum per chunk, verified by HDF5 on every read (a corrupted file is noticed).
                kwargs["fletcher32"] = True
            ds = h5.create_dataset(name, data=value, **kwargs)
            for key, attr in dattrs.items():
                ds.attrs[key] = attr


class HDF5File:
    """What :func:`read_hdf5` returns: root attributes, parsed params and datasets."""

    def __init__(self, path: str, attrs: dict, datasets: dict):
        self.path = path
        self.attrs = attrs
        self.datasets = datasets
        try:
            self.params = json.loads(attrs.get("params", "{}"))
        except ValueError:
            raise BadInputError(path, "params", "is not a JSON string") from None

    def __getitem__(self, name):
        try:
            return self.datasets[name]
        except KeyError:
            raise BadInputError(self.path, name, "dataset is missing") from None

    def __contains__(self, name):
        return name in self.datasets


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
    with h5, corrupt_hdf5(path) as where:
        try:
            attrs = {k: _attr(v) for k, v in h5.attrs.items()}
        except (OSError, KeyError, ValueError, RuntimeError):
            raise BadInputError(path, None, "is corrupt (its attributes cannot be read)") from None
        check_format_tag(attrs, expected_format, path)
        wanted = list(names) if names is not None else [k for k in h5 if isinstance(h5[k], h5py.Dataset)]
        datasets = {}
        for name in wanted:
            where.field = name
            if name not in h5:
                raise BadInputError(path, name, "dataset is missing")
            datasets[name] = h5[name][()]
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
    a corrupt file gets a one-line warning (logger ``startrack.formats.hdf5``) and is rebuilt.
    """
    with build_lock(path):
        db = None
        if os.path.exists(path):
            try:
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
