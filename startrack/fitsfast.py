"""A FITS image and its header read without astropy, for the files that need nothing more (FITS 4.0, Sect. 4-5, 7.1).

``astropy.io.fits`` costs a process ~130 ms to import (astropy 8 loads ``astropy.units`` on the way): more than a
whole solve of a one-megapixel frame.  A camera's FITS file is mostly the simplest kind: a primary header of 80-byte
cards in 2880-byte blocks, then the pixels, big-endian, of one ``BITPIX``.  This module reads that kind, and the
same kind in the first ``IMAGE`` extension after an empty primary, and says ``None`` for anything else (compressed
images, which are binary tables; random groups; scaled integers other than the standard unsigned offsets; ``BLANK``;
a header or data it does not follow): the caller then reads the file with astropy, as before.  Its answers are
astropy's, value for value (``tests/test_fitsfast.py`` holds them side by side).
"""
from __future__ import annotations

import os

import numpy as np

__all__ = ["read_header", "read_image"]

_BLOCK = 2880
_CARD = 80
# BITPIX -> big-endian dtype of the stored values (FITS 4.0 Table 8).
_STORED = {8: ">u1", 16: ">i2", 32: ">i4", 64: ">i8", -32: ">f4", -64: ">f8"}
# The unsigned integers FITS stores as signed ones with an offset (FITS 4.0 Table 11), as astropy returns them.
_UNSIGNED = {16: (32768, np.uint16), 32: (2**31, np.uint32), 64: (2**63, np.uint64)}
# Header blocks read before giving up on finding END (a header of 36 x 200 cards is far beyond a camera's).
_MAX_BLOCKS = 200


def _value(text: str):
    """A card's value field (columns 11-80) as astropy gives it, or a ``ValueError`` when this reader cannot
    tell: a string (quotes doubled inside, trailing blanks dropped), a logical, an integer or a float."""
    body = text.strip()
    if body.startswith("'"):
        out, i = [], 1
        while i < len(body):
            ch = body[i]
            if ch == "'":
                if i + 1 < len(body) and body[i + 1] == "'":
                    out.append("'")
                    i += 2
                    continue
                rest = body[i + 1:].strip()
                if rest and not rest.startswith("/"):
                    raise ValueError(text)
                return "".join(out).rstrip()
            out.append(ch)
            i += 1
        raise ValueError(text)      # no closing quote
    field = body.split("/", 1)[0].strip()
    if field == "T":
        return True
    if field == "F":
        return False
    if not field:
        raise ValueError(text)      # an undefined value: astropy's own object
    try:
        return int(field)
    except ValueError:
        pass
    if field.upper().strip("+-.0123456789ED") == "":
        return float(field.upper().replace("D", "E"))
    raise ValueError(text)          # a complex value, or something this reader does not parse


def _header(fh):
    """The next header of ``fh``: ``(cards {keyword: value}, bytes read)``, or None when this reader cannot parse
    it (a keyword repeated with another value, ``CONTINUE``, a value it cannot tell, no ``END``)."""
    cards: dict = {}
    for block in range(_MAX_BLOCKS):
        raw = fh.read(_BLOCK)
        if len(raw) != _BLOCK:
            return None
        try:
            text = raw.decode("ascii")
        except UnicodeDecodeError:
            return None
        for k in range(0, _BLOCK, _CARD):
            card = text[k:k + _CARD]
            key = card[:8].rstrip()
            if key == "END":
                return cards, (block + 1) * _BLOCK
            if key in ("", "COMMENT", "HISTORY") or card[8:10] != "= ":
                if key == "CONTINUE" or (key.startswith("HIERARCH")):
                    return None
                continue
            try:
                value = _value(card[10:])
            except ValueError:
                return None
            if key in cards and cards[key] != value:
                return None         # astropy keeps both cards; a dict of the header would keep the last
            cards[key] = value
    return None


def _image_size(cards) -> tuple | None:
    """``(shape (NAXISn ... NAXIS1), dtype)`` of the image a header describes, or None when it is not a plain one."""
    bitpix, naxis = cards.get("BITPIX"), cards.get("NAXIS")
    if type(bitpix) is not int or bitpix not in _STORED or type(naxis) is not int or not 0 <= naxis <= 999:
        return None
    shape = []
    for n in range(naxis, 0, -1):
        v = cards.get(f"NAXIS{n}")
        if type(v) is not int or v < 0:
            return None
        shape.append(v)
    if cards.get("GROUPS") is True or cards.get("PCOUNT", 0) != 0 or cards.get("GCOUNT", 1) != 1:
        return None
    return tuple(shape), np.dtype(_STORED[bitpix])


def read_header(path: str) -> dict | None:
    """The primary header of the FITS file ``path`` as ``{keyword: value}`` (what ``dict(astropy.io.fits
    .getheader(path))`` holds for the keywords with values), or None when this reader cannot parse it."""
    try:
        with open(path, "rb") as fh:
            got = _header(fh)
    except OSError:
        return None
    if got is None or got[0].get("SIMPLE") is not True:
        return None
    return got[0]


def read_image(path: str):
    """``(data, header)``: the first HDU's image with at least two axes (the primary's, or the first ``IMAGE``
    extension's after a primary without data), as astropy returns it (native byte order; the unsigned offsets
    applied), or None when this reader leaves the file to astropy (see the module's note)."""
    try:
        size = os.path.getsize(path)
        with open(path, "rb") as fh:
            got = _header(fh)
            if got is None or got[0].get("SIMPLE") is not True:
                return None
            cards, at = got
            for hdu in range(2):
                plain = _image_size(cards)
                if plain is None:
                    return None
                shape, stored = plain
                count = int(np.prod(shape)) if shape else 0
                nbytes = count * stored.itemsize
                if len(shape) >= 2 and count > 0:
                    return _pixels(fh, at, shape, stored, cards, size)
                if hdu == 1 or nbytes:
                    return None     # data of fewer than two axes, or an extension without an image: astropy's
                # An empty primary: the first extension, when it is an image.
                fh.seek(at)
                got = _header(fh)
                if got is None or got[0].get("XTENSION") != "IMAGE":
                    return None
                cards, read = got
                at += read
    except (OSError, ValueError):
        return None
    return None


def _pixels(fh, at, shape, stored, cards, size):
    """The image of a header read: ``(data, primary or extension cards)``, or None (scaled, BLANK, cut short)."""
    bitpix = cards["BITPIX"]
    zero, scale = cards.get("BZERO", 0), cards.get("BSCALE", 1)
    if "BLANK" in cards or type(scale) not in (int, float) or type(zero) not in (int, float) or scale != 1:
        return None
    count = int(np.prod(shape))
    if at + count * stored.itemsize > size:
        return None                 # the data cut short: astropy's message
    fh.seek(at)
    data = np.fromfile(fh, dtype=stored, count=count)
    if data.size != count:
        return None
    data = data.reshape(shape)
    if zero == 0:
        return data.astype(stored.newbyteorder("="), copy=False), cards
    unsigned = _UNSIGNED.get(bitpix)
    if unsigned is None or zero != unsigned[0]:
        return None
    # Signed storage plus the offset: the unsigned values, as astropy gives them (the top bit flipped).
    native = data.astype(stored.newbyteorder("="))
    return (native.view(native.dtype.str.replace("i", "u")) ^ np.array(unsigned[0], dtype=unsigned[1])
            ).astype(unsigned[1], copy=False), cards
