"""Flat, memory-mapped copies of a file's arrays in the cache, checked once.

A database read from HDF5 costs a process h5py's import (~20 ms), the decompression and the sha256 of every
dataset; its copy here is a flat file (this magic, the JSON header's length as a little-endian uint64, the JSON
header, then each array at a 64-byte boundary) that a later process maps in about a millisecond.  The header
holds the sha256 of everything after it: a copy is checked against it the first time it is opened after it was
written or changed (its inode, size, modification and change times, kept in ``PATH.checked``, as the pattern
index's), so a damaged copy is never read (:func:`read_copy` returns None and the caller reads the original).
"""
from __future__ import annotations

import hashlib
import json
import os

import numpy as np

__all__ = ["copy_path", "is_checked", "mark_checked", "read_copy", "stamp", "write_copy"]

MAGIC = b"STFLAT1\n"
_ALIGN = 64


def copy_path(source: str, kind: str) -> str | None:
    """The cache file of the copy of ``source`` (named by its path, inode, size and modification time, and ``kind``:
    the reader's format), or None when ``source`` cannot be looked at."""
    from startrack.cachedir import cache_dir

    try:
        st = os.stat(source)
        where = cache_dir()
    except OSError:         # (a cache directory that cannot be made: no copy)
        return None
    stamp = f"{os.path.abspath(source)}|{st.st_ino}|{st.st_size}|{st.st_mtime_ns}|{kind}|{MAGIC.decode()}"
    return os.path.join(where, f"copy-{hashlib.sha256(stamp.encode()).hexdigest()[:16]}.bin")


def write_copy(path: str, header: dict, arrays: dict) -> bool:
    """Write ``arrays`` (name -> numeric ndarray) and the JSON-able ``header`` to ``path`` atomically, and its
    ``.checked`` stamp; False (nothing left behind) when the cache cannot take it."""
    try:
        items = [(name, np.ascontiguousarray(a)) for name, a in arrays.items()]
        if any(a.dtype.kind not in "biuf" for _, a in items):
            return False
        digest = hashlib.sha256()
        for _, a in items:
            digest.update(a.data)
            digest.update(b"\0" * _pad(a.nbytes))
        head = dict(header, arrays=None, data_sha256=digest.hexdigest())      # (None: the first pass writes the text)
        text = b""
        for _ in range(5):      # the offsets follow the header's length, which holds them: until they stay put
            offset = -(-(16 + len(text)) // _ALIGN) * _ALIGN
            table = []
            for name, a in items:
                table.append([name, a.dtype.str, list(a.shape), offset])
                offset += a.nbytes + _pad(a.nbytes)
            if table == head["arrays"]:
                break
            head["arrays"] = table
            text = json.dumps(head).encode()
        start = table[0][3] if table else -(-(16 + len(text)) // _ALIGN) * _ALIGN
        if 16 + len(text) > start:
            return False
        os.makedirs(os.path.dirname(path), exist_ok=True)
        tmp = f"{path}.{os.getpid()}.tmp"
    except (OSError, TypeError, ValueError):
        return False
    try:
        with open(tmp, "wb") as fh:
            fh.write(MAGIC + len(text).to_bytes(8, "little") + text)
            fh.write(b"\0" * (start - fh.tell()))
            for _, a in items:
                fh.write(a.data)
                fh.write(b"\0" * _pad(a.nbytes))
        os.replace(tmp, path)
    except OSError:         # a full disk, a cache that cannot be written: no copy, nor a partial one
        try:
            os.remove(tmp)
        except OSError:
            pass
        return False
    mark_checked(path, stamp(path, head["data_sha256"]))
    return True


def _pad(nbytes: int) -> int:
    """The zeros after an array of ``nbytes`` bytes to the next 64-byte boundary."""
    return -nbytes % _ALIGN


def read_copy(path: str) -> tuple | None:
    """``(header, arrays)`` of the copy at ``path``, its arrays mapped copy-on-write (writable, as the kernels' builds
    take them), or None: no copy, or one that does not read or whose data does not match its sha256."""
    try:
        before = os.stat(path)
        size = before.st_size
        with open(path, "rb") as fh:
            head = fh.read(16)
            if len(head) != 16 or head[:8] != MAGIC:
                return None
            header = json.loads(fh.read(int.from_bytes(head[8:], "little")))
        taken = stamp(path, header["data_sha256"])
        if taken is None or taken["ino"] != before.st_ino:
            return None         # (replaced while it was opened)
        arrays = {}
        ends = []
        for name, dtype, shape, offset in header["arrays"]:
            dt = np.dtype(dtype)
            shape = tuple(int(v) for v in shape)
            nbytes = int(np.prod(shape)) * dt.itemsize
            if dt.kind not in "biuf" or offset < 0 or offset + nbytes > size:
                return None
            ends.append(offset + nbytes + _pad(nbytes))
            arrays[name] = np.asarray(np.memmap(path, dtype=dt, mode="c", offset=offset, shape=shape)) \
                if nbytes else np.zeros(shape, dtype=dt)
        if not is_checked(path, taken):
            start = header["arrays"][0][3] if header["arrays"] else size
            whole = np.memmap(path, dtype=np.uint8, mode="r") if size else np.zeros(0, np.uint8)
            if max(ends, default=start) > size or hashlib.sha256(whole[start:max(ends, default=start)]).hexdigest() \
                    != header["data_sha256"]:
                return None
            mark_checked(path, taken)
    except (OSError, ValueError, KeyError, TypeError, IndexError):
        return None
    return header, arrays


def stamp(path: str, checksum: str) -> dict | None:
    """What ``PATH.checked`` holds once ``path`` is found to match ``checksum`` (taken before it is read: a file
    replaced meanwhile is checked again next time): its inode, size and times (any write changes its change time),
    and the checksum; None when ``path`` cannot be looked at."""
    try:
        st = os.stat(path)
    except OSError:
        return None
    return {"ino": st.st_ino, "size": st.st_size, "mtime_ns": st.st_mtime_ns, "ctime_ns": st.st_ctime_ns,
            "data_sha256": checksum}


def is_checked(path: str, taken: dict | None) -> bool:
    """Whether ``path``'s ``.checked`` record is ``taken`` (:func:`stamp`): it was checked and has not changed since."""
    try:
        with open(path + ".checked", encoding="utf-8") as fh:
            return taken is not None and json.load(fh) == taken
    except (OSError, ValueError):
        return False


def mark_checked(path: str, taken: dict | None) -> None:
    """Record ``taken`` (:func:`stamp`) in ``PATH.checked``, atomically; nothing when it cannot be written."""
    if taken is None:
        return
    tmp = f"{path}.checked.{os.getpid()}"
    try:
        with open(tmp, "w", encoding="utf-8") as fh:
            json.dump(taken, fh)
        os.replace(tmp, path + ".checked")
    except OSError:
        try:
            os.remove(tmp)
        except OSError:
            pass
