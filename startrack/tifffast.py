"""A plain TIFF image read without OpenCV, for the files that need nothing more (TIFF 6.0, Part 1: baseline).

``import cv2`` costs a process ~17 ms, and ``cv2.imread`` a one-megapixel 16-bit frame ~0.6 ms more than reading its
bytes.  A star camera's TIFF file is mostly the simplest kind: one grey sample per pixel of 8 or 16 bits, not
compressed, in strips.  This module reads that kind (the file's first image, as ``cv2.imread`` does) and says
``None`` for anything else: compression, tiles, colour or extra samples, a palette, ``WhiteIsZero``, an orientation
other than the first row at the top (OpenCV turns such an image), signed or floating-point samples, other bit depths, BigTIFF, a directory or strip it does not follow, a file cut short.  The
caller then decodes the file with OpenCV, as before (and OpenCV names what is wrong with a broken file).  Its pixels
are OpenCV's, value for value (``tests/test_tifffast.py`` holds them side by side).
"""
from __future__ import annotations

import os
import struct

import numpy as np

__all__ = ["directory", "read_image"]

# TIFF 6.0 field types -> struct code of one value (BYTE, ASCII, SHORT, LONG; others are not needed here).
_CODES = {1: "B", 2: "B", 3: "H", 4: "I", 13: "I"}
# The tags of a baseline image this reader needs, and those whose presence (other than the baseline value) sends a
# file to OpenCV: compression, photometric interpretation, samples per pixel, planar configuration, sample format,
# extra samples, fill order, tiles.
_WIDTH, _HEIGHT, _BITS, _COMPRESSION, _PHOTOMETRIC = 256, 257, 258, 259, 262
_STRIP_OFFSETS, _SAMPLES, _ROWS_PER_STRIP, _STRIP_BYTES = 273, 277, 278, 279
# FillOrder, Orientation (OpenCV turns an image whose first row is not the top one), PlanarConfiguration,
# SampleFormat (unsigned).
_PLAIN = {266: 1, 274: 1, 284: 1, 339: 1}
_TILES = (322, 323, 324, 325)
_EXTRA_SAMPLES = 338


def directory(fh, order: str, offset: int) -> dict:
    """The TIFF directory at ``offset`` of the binary file ``fh`` (byte order ``order``, ``"<"`` or ``">"``):
    ``{tag: (type, count, the entry's 4-byte value field)}``.  Raises ``ValueError`` when it lies beyond the file."""
    fh.seek(offset)
    head = fh.read(2)
    if len(head) < 2:
        raise ValueError("a TIFF directory lies beyond the file")
    (n,) = struct.unpack(order + "H", head)
    raw = fh.read(12 * n)
    if len(raw) < 12 * n:
        raise ValueError("a TIFF directory lies beyond the file")
    return {tag: (kind, count, value) for tag, kind, count, value in
            (struct.unpack_from(order + "HHI4s", raw, 12 * k) for k in range(n))}


def _values(fh, order: str, entry) -> tuple | None:
    """The numbers of a SHORT or LONG entry (read from the file when they do not fit its value field); None for
    another type or when they lie beyond the file."""
    kind, count, value = entry
    code = _CODES.get(kind)
    if code is None or kind == 2 or count < 1:
        return None
    size = struct.calcsize(code) * count
    if size <= 4:
        raw = value[:size]
    else:
        fh.seek(struct.unpack(order + "I", value)[0])
        raw = fh.read(size)
        if len(raw) < size:
            return None
    return struct.unpack(f"{order}{count}{code}", raw)


def _one(fh, order, entries, tag, default=None):
    """The single number of ``tag`` (``default`` when absent; None when it is not one SHORT or LONG)."""
    entry = entries.get(tag)
    if entry is None:
        return default
    got = _values(fh, order, entry)
    return got[0] if got is not None and len(got) == 1 else None


def read_image(path: str, max_pixels: int | None = None):
    """``(pixels, bits)`` of a plain TIFF file's first image: a 2-D uint8 or uint16 array (native byte order) and 8
    or 16; ``None`` when the file is not one this module reads (see the module's note), and when the image has more
    than ``max_pixels`` pixels or more bytes than the file holds (nothing that large is allocated here)."""
    with open(path, "rb") as fh:
        head = fh.read(8)
        if len(head) < 8 or head[:4] not in (b"II*\0", b"MM\0*"):
            return None
        order = "<" if head[:2] == b"II" else ">"
        try:
            entries = directory(fh, order, struct.unpack(order + "I", head[4:8])[0])
        except ValueError:
            return None
        width = _one(fh, order, entries, _WIDTH)
        height = _one(fh, order, entries, _HEIGHT)
        bits = _one(fh, order, entries, _BITS)
        if (not width or not height or bits not in (8, 16) or _one(fh, order, entries, _COMPRESSION, 1) != 1
                or _one(fh, order, entries, _PHOTOMETRIC) != 1 or _one(fh, order, entries, _SAMPLES, 1) != 1
                or any(_one(fh, order, entries, tag, value) != value for tag, value in _PLAIN.items())
                or _EXTRA_SAMPLES in entries or any(tag in entries for tag in _TILES)):
            return None
        offsets = _values(fh, order, entries[_STRIP_OFFSETS]) if _STRIP_OFFSETS in entries else None
        counts = _values(fh, order, entries[_STRIP_BYTES]) if _STRIP_BYTES in entries else None
        rows = _one(fh, order, entries, _ROWS_PER_STRIP, height)
        if not offsets or counts is None or len(counts) != len(offsets) or not rows:
            return None
        rows = min(rows, height)
        row_bytes = width * bits // 8
        if (len(offsets) != -(-height // rows) or (max_pixels is not None and width * height > max_pixels)
                or height * row_bytes > os.fstat(fh.fileno()).st_size):
            return None
        dtype = np.dtype(np.uint8 if bits == 8 else order + "u2")
        out = np.empty((height, width), dtype=dtype)
        flat = memoryview(out.reshape(-1)).cast("B")
        at = 0
        for k, (start, count) in enumerate(zip(offsets, counts, strict=True)):
            need = min(rows, height - k * rows) * row_bytes
            if count < need:
                return None
            fh.seek(start)
            if fh.readinto(flat[at:at + need]) != need:
                return None         # cut short: OpenCV says so
            at += need
    if not out.dtype.isnative:
        out = out.byteswap(inplace=True).view(out.dtype.newbyteorder("="))
    return out, bits
