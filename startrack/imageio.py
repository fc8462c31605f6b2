"""Reading and writing images: PNG, TIFF, JPEG (read only) and FITS.

Writing chooses the format by extension and is atomic.  Reading returns a 2-D
array (colour converted to luminance) and refuses what it cannot read with one
line naming the file.
"""
from __future__ import annotations

import os

import numpy as np

from startrack.errors import BadInputError
from startrack.formats.atomic import atomic_path, check_writable

__all__ = [
    "IMAGE_WRITE_EXTENSIONS",
    "MAX_IMAGE_PIXELS",
    "captured_stderr",
    "check_fits_output",
    "check_image_output",
    "check_plot_output",
    "image_size_from_header",
    "max_image_pixels",
    "read_image",
    "write_image",
]

IMAGE_WRITE_EXTENSIONS = (".png", ".tif", ".tiff", ".fits", ".fit", ".fts")


def check_image_output(path: str) -> str:
    """Refuse an output name whose extension we cannot write; return the extension."""
    ext = os.path.splitext(path)[1].lower()
    if ext not in IMAGE_WRITE_EXTENSIONS:
        raise BadInputError(path, None, f"unknown image extension {ext or '(none)'!r}: use "
                            + ", ".join(IMAGE_WRITE_EXTENSIONS))
    check_writable(path)
    return ext


#: Picture formats, by the output's suffix: PNG (raster), PDF and SVG (charts as vectors; an annotated image as
#: its raster with the drawing on it, embedded at one image pixel per point).
PLOT_EXTENSIONS = (".png", ".pdf", ".svg")


def check_plot_output(path: str | None) -> None:
    """Refuse a picture name that is not ``.png``, ``.pdf`` or ``.svg`` (the format follows the name: no PNG
    named ``.txt``)."""
    if path is None:
        return
    ext = os.path.splitext(path)[1].lower()
    if ext not in PLOT_EXTENSIONS:
        raise BadInputError(path, None, f"unknown picture extension {ext or '(none)'!r}: pictures are PNG, PDF "
                            "or SVG, name it .png, .pdf or .svg")
    check_writable(path)


FITS_EXTENSIONS = (".fits", ".fit", ".fts")


def check_fits_output(path: str | None) -> None:
    """Refuse a FITS output (a WCS header) whose name is not ``.fits``, ``.fit`` or ``.fts``."""
    if path is None:
        return
    ext = os.path.splitext(path)[1].lower()
    if ext not in FITS_EXTENSIONS:
        raise BadInputError(path, None, f"unknown FITS extension {ext or '(none)'!r}: name it .fits")
    check_writable(path)


def write_image(path: str, image: np.ndarray, header: dict | None = None) -> None:
    """Write a 2-D uint8/uint16 image atomically; FITS gets ``header`` as keywords, a TIFF file is not compressed."""
    ext = check_image_output(path)
    with atomic_path(path) as tmp:
        if ext in (".fits", ".fit", ".fts"):
            from astropy.io import fits

            hdu = fits.PrimaryHDU(image)
            for key, value in (header or {}).items():
                hdu.header[key[:8].upper()] = value
            hdu.writeto(tmp, overwrite=True)
        else:
            import cv2

            if image.dtype not in (np.uint8, np.uint16):
                raise BadInputError(path, None, f"cannot write {image.dtype} pixels to {ext}")
            # TIFF not compressed (OpenCV's default is LZW): a 1024 x 768 16-bit frame is written in ~1 ms instead of
            # ~16 and read in ~0.2 ms instead of ~8 (startrack.tifffast), for twice the disk (a 12 Mpx frame: 35
            # against 265 ms written, 16 against 103 ms read, 24 against 17 MB).
            params = [cv2.IMWRITE_TIFF_COMPRESSION, 1] if ext in (".tif", ".tiff") else []
            if not cv2.imwrite(tmp, image, params):
                raise BadInputError(path, None, "OpenCV could not write the image")


MAX_IMAGE_PIXELS = 200_000_000
"""Default largest image read, in pixels (200 megapixels: 800 MB as float32).

Checked from the file's header before any pixel is decoded; raise it with the
environment variable ``STARTRACK_MAX_IMAGE_PIXELS`` or the ``max_pixels``
argument of :func:`read_image`."""


def max_image_pixels() -> int:
    """The image size limit in pixels: ``STARTRACK_MAX_IMAGE_PIXELS`` or :data:`MAX_IMAGE_PIXELS`."""
    value = os.environ.get("STARTRACK_MAX_IMAGE_PIXELS")
    if value is None:
        return MAX_IMAGE_PIXELS
    try:
        limit = int(value)
    except ValueError:
        raise BadInputError("STARTRACK_MAX_IMAGE_PIXELS", None, f"must be a whole number, got {value!r}") from None
    if limit < 1:
        raise BadInputError("STARTRACK_MAX_IMAGE_PIXELS", None, f"must be positive, got {limit}")
    return limit


def _tiff_size(head: bytes):
    import struct

    order = {b"II": "<", b"MM": ">"}.get(head[:2])
    if order is None:
        return None
    magic = struct.unpack(order + "H", head[2:4])[0]
    if magic == 42:
        off = struct.unpack(order + "I", head[4:8])[0]
        if off + 2 > len(head):
            return None
        n = struct.unpack(order + "H", head[off:off + 2])[0]
        size, entry, count_fmt = 12, off + 2, "I"
    elif magic == 43:  # BigTIFF
        off = struct.unpack(order + "Q", head[8:16])[0]
        if off + 8 > len(head):
            return None
        n = struct.unpack(order + "Q", head[off:off + 8])[0]
        size, entry, count_fmt = 20, off + 8, "Q"
    else:
        return None
    dims = {}
    for i in range(min(n, 4096)):
        e = entry + i * size
        if e + size > len(head):
            break
        tag, typ = struct.unpack(order + "HH", head[e:e + 4])
        if tag in (256, 257):
            value_at = e + 4 + struct.calcsize(count_fmt)
            fmt = {3: "H", 4: "I", 16: "Q"}.get(typ)
            if fmt is None:
                return None
            dims[tag] = struct.unpack(order + fmt, head[value_at:value_at + struct.calcsize(fmt)])[0]
    if 256 in dims and 257 in dims:
        return dims[256], dims[257]
    return None


def _jpeg_size(head: bytes):
    i = 2
    while i + 9 < len(head):
        if head[i] != 0xFF:
            return None
        marker = head[i + 1]
        if marker in (0xD8, 0x01) or 0xD0 <= marker <= 0xD7:
            i += 2
            continue
        length = int.from_bytes(head[i + 2:i + 4], "big")
        if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):
            h = int.from_bytes(head[i + 5:i + 7], "big")
            w = int.from_bytes(head[i + 7:i + 9], "big")
            return w, h
        i += 2 + length
    return None


def image_size_from_header(path: str):
    """``(width, height)`` read from the file's header without decoding pixels, or ``None`` if unknown.

    Understands PNG, JPEG, TIFF/BigTIFF, BMP, PGM/PPM and FITS headers.
    """
    with open(path, "rb") as handle:
        head = handle.read(1 << 16)
    if head[:8] == b"\x89PNG\r\n\x1a\n" and len(head) >= 24:
        return int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")
    if head[:2] == b"\xff\xd8":
        return _jpeg_size(head)
    if head[:2] in (b"II", b"MM"):
        return _tiff_size(head)
    if head[:2] == b"BM" and len(head) >= 26:
        return abs(int.from_bytes(head[18:22], "little", signed=True)), abs(
            int.from_bytes(head[22:26], "little", signed=True))
    if head[:1] == b"P" and head[1:2] in b"123456":
        import re

        m = re.match(rb"P[1-6](?:\s+|#[^\n]*\n)+(\d+)(?:\s+|#[^\n]*\n)+(\d+)", head)
        return (int(m.group(1)), int(m.group(2))) if m else None
    if head[:9] == b"SIMPLE  =":
        cards = {}
        for k in range(0, min(len(head), 36 * 80 * 4), 80):
            card = head[k:k + 80].decode("ascii", "replace")
            key = card[:8].strip()
            if key == "END":
                break
            if card[8:10] == "= ":
                cards[key] = card[10:].split("/")[0].strip()
        try:
            naxis = int(cards.get("NAXIS", "0"))
            if naxis >= 2:
                return int(cards["NAXIS1"]), int(cards["NAXIS2"])
        except (KeyError, ValueError):
            return None
    return None


def _magic(path: str) -> bytes:
    with open(path, "rb") as handle:
        return handle.read(9)


_STDERR_LOCK = None


def _stderr_lock():
    global _STDERR_LOCK
    if _STDERR_LOCK is None:
        import threading

        _STDERR_LOCK = threading.Lock()
    return _STDERR_LOCK


def _scratch_file():
    """An anonymous read-write binary file: in memory where the system has ``memfd_create`` (Linux), else a
    temporary file (an image read no longer imports :mod:`tempfile`, with :mod:`shutil` and :mod:`random`,
    nor creates a file in the temporary directory)."""
    if hasattr(os, "memfd_create"):
        try:
            return open(os.memfd_create("startrack-stderr", os.MFD_CLOEXEC), "w+b")
        except OSError:
            pass
    import tempfile

    return tempfile.TemporaryFile()


class captured_stderr:
    """Catch what C libraries (OpenCV, libpng, libtiff, CFITSIO) print to file descriptor 2.

    ``with captured_stderr() as cap: ...`` then ``cap.text``: the chatter, to be
    folded into a one-line message (or dropped when all went well).
    """

    def __enter__(self):
        import sys

        self.text = ""
        self._lock = _stderr_lock()
        self._lock.acquire()
        self._saved = None
        try:
            sys.stderr.flush()
            self._tmp = _scratch_file()
            self._saved = os.dup(2)
            os.dup2(self._tmp.fileno(), 2)
        except (OSError, ValueError, AttributeError):
            self._saved = None
        return self

    def __exit__(self, *exc):
        try:
            if self._saved is not None:
                os.dup2(self._saved, 2)
                os.close(self._saved)
                self._tmp.seek(0)
                self.text = self._tmp.read(1 << 16).decode("utf-8", "replace")
                self._tmp.close()
        finally:
            self._lock.release()
        return False

    @property
    def first_line(self) -> str:
        """The first line of chatter without OpenCV's log prefix (``[ WARN:0@0.1] global file.cpp:123``)."""
        import re

        for line in self.text.splitlines():
            line = re.sub(r"^\[\s*\w+:\d+@[\d.]+\]\s*(global\s+\S+\s+)?", "", line.strip())
            if line:
                return line[:160]
        return ""


def _with_chatter(problem: str, cap) -> str:
    line = cap.first_line
    return f"{problem} ({line})" if line else problem


def read_image(path: str, max_pixels: int | None = None, whole_dn: bool = False):
    """Read an image as a 2-D float32 array of DN.

    Parameters
    ----------
    path : str
        PNG, JPEG, TIFF, BMP, PGM/PPM or FITS file.
    max_pixels : int, optional
        Refuse (``BadInputError``) an image with more pixels than this, checked
        from the header before decoding; default :func:`max_image_pixels`.
    whole_dn : bool
        Return a single-channel 8- or 16-bit file (a FITS file of unsigned 8- or 16-bit pixels too) as decoded
        (uint8 or uint16: the same values in a quarter or half of float32's memory; issue 41) instead of as
        float32.

    Returns
    -------
    image : ndarray (height, width) of float32 (uint8 or uint16 with ``whole_dn``, as above)
    info : dict
        ``bit_depth`` (8 or 16 as stored, 32 for floating-point files; 12-bit
        data arrive in 16-bit files), ``channels`` of the file, ``saturation``
        (the largest DN the decoded type can hold: 255 for 8-bit files, also
        colour ones, 65535 for 16-bit; None for floating point, whose type says
        nothing: :func:`startrack.centroid.find_stars` reads a clip from the
        pixels, as it does for an array handed to the Python API).
    """
    if not isinstance(path, str) or not path:
        raise BadInputError(str(path), None, "is not an image path")
    if not os.path.exists(path):
        raise BadInputError(path, None, "no such file")
    if os.path.isdir(path):
        raise BadInputError(path, None, "is a directory, expected an image")
    try:
        if os.path.getsize(path) == 0:
            raise BadInputError(path, None, "is empty (0 bytes)")
        size = image_size_from_header(path)
    except OSError as exc:
        raise BadInputError(path, None, f"cannot read: {exc.strerror or exc}") from None
    limit = max_image_pixels() if max_pixels is None else int(max_pixels)
    if size is not None:
        width, height = size
        if width * height > limit:
            raise BadInputError(path, None, f"is {width}x{height} pixels, more than the limit of {limit} "
                                "(STARTRACK_MAX_IMAGE_PIXELS)")
        if width == 0 or height == 0:
            raise BadInputError(path, None, f"has no pixels ({width}x{height})")
    from startrack.errors import reading

    ext = os.path.splitext(path)[1].lower()
    with reading(path):   # an unexpected exception of a decoder names the image
        magic = _magic(path)
        if ext in (".fits", ".fit", ".fts") or magic == b"SIMPLE  =":
            img, bit_depth, channels, saturation = _read_fits(path, limit, whole_dn)
        else:
            plain = _read_tiff(path, limit, whole_dn) if magic[:4] in (b"II*\0", b"MM\0*") else None
            img, bit_depth, channels, saturation = plain or _read_cv2(path, limit, whole_dn)
    if img.ndim != 2 or img.shape[0] == 0 or img.shape[1] == 0:
        raise BadInputError(path, None, f"has no pixels (shape {img.shape})")
    if img.dtype.kind == "f" and not np.all(np.isfinite(img)):
        img = np.nan_to_num(img, nan=0.0, posinf=0.0, neginf=0.0)
    return img, {"bit_depth": bit_depth, "channels": channels, "saturation": saturation}


def _read_fits(path, limit, whole_dn=False):
    from startrack.fitsfast import read_image as read_plain

    plain = read_plain(path)        # a plain image without astropy's import (startrack.fitsfast), else astropy
    if plain is not None:
        data = plain[0]
        if int(np.prod(data.shape[-2:])) > limit:
            raise BadInputError(path, None, f"is {data.shape[-1]}x{data.shape[-2]} pixels, more than the "
                                f"limit of {limit} (STARTRACK_MAX_IMAGE_PIXELS)")
        return _fits_pixels(data, whole_dn)
    from astropy.io import fits

    with captured_stderr() as cap:
        try:
            with fits.open(path, memmap=False) as hdul:
                data = None
                for h in hdul:
                    shape = tuple(int(v) for v in (getattr(h, "shape", None) or ()))
                    if len(shape) < 2:
                        continue
                    if int(np.prod(shape[-2:])) > limit:
                        raise BadInputError(path, None, f"is {shape[-1]}x{shape[-2]} pixels, more than the "
                                            f"limit of {limit} (STARTRACK_MAX_IMAGE_PIXELS)")
                    data = h.data
                    if data is not None:
                        break
        except BadInputError:
            raise
        except Exception as exc:  # noqa: BLE001 - astropy raises many types for broken files
            raise BadInputError(path, None, _with_chatter(f"is not a readable FITS file ({type(exc).__name__})",
                                                          cap)) from None
    if data is None:
        raise BadInputError(path, None, "holds no 2-D image")
    return _fits_pixels(np.asarray(data), whole_dn)


def _fits_pixels(data, whole_dn=False):
    """:func:`_read_fits`' image, bit depth, channels and saturation of a FITS HDU's data (``whole_dn``: a 2-D image of
    8- or 16-bit unsigned integers as it is, in native byte order, instead of float32)."""
    if data.ndim == 3:
        data = data.mean(axis=0) if data.shape[0] in (3, 4) else data[0]
    dtype = data.dtype
    if whole_dn and data.ndim == 2 and dtype.kind == "u" and dtype.itemsize <= 2:
        img = np.ascontiguousarray(data, dtype=dtype.newbyteorder("="))
        return img, 8 * dtype.itemsize, 1, float(np.iinfo(dtype).max)
    img = np.ascontiguousarray(data, dtype=np.float32)
    if dtype.kind == "f":
        return img, 32, 1, None
    bit_depth = 8 if dtype.itemsize == 1 else 16
    return img, bit_depth, 1, float(np.iinfo(dtype).max) if dtype.itemsize <= 2 else None


def _read_tiff(path, limit, whole_dn=False):
    """:func:`_read_cv2`'s answer for a plain TIFF file (:mod:`startrack.tifffast`: one grey 8- or 16-bit sample
    per pixel, not compressed) without OpenCV's import; None for any other TIFF file, and for one of more than
    ``limit`` pixels (OpenCV reads it, and the limit refuses it as before)."""
    from startrack.tifffast import read_image as read_plain

    plain = read_plain(path, limit)
    if plain is None:
        return None
    raw, bits = plain
    img = raw if whole_dn else raw.astype(np.float32)
    return img, bits, 1, 255.0 if bits == 8 else 65535.0


def _read_cv2(path, limit, whole_dn=False):
    import cv2

    with captured_stderr() as cap:
        try:
            raw = cv2.imread(path, cv2.IMREAD_UNCHANGED | cv2.IMREAD_ANYDEPTH)
        except cv2.error as exc:
            msg = str(exc).strip().splitlines()[-1] if str(exc).strip() else "OpenCV error"
            raise BadInputError(path, None, f"is not a readable image ({msg[:160]})") from None
    if raw is None:
        raise BadInputError(path, None, _with_chatter("is not a readable image (truncated or unknown format)", cap))
    if raw.shape[0] * raw.shape[1] > limit:
        raise BadInputError(path, None, f"is {raw.shape[1]}x{raw.shape[0]} pixels, more than the limit of {limit} "
                            "(STARTRACK_MAX_IMAGE_PIXELS)")
    channels = 1 if raw.ndim == 2 else raw.shape[2]
    dtype = raw.dtype
    if dtype not in (np.uint8, np.uint16, np.float32):
        raise BadInputError(path, None, f"has unsupported pixel type {dtype} (read: 8/16-bit integer, 32-bit float)")
    if raw.ndim == 3:
        if channels == 4:
            raw = raw[:, :, :3]
        if channels == 1:
            img = raw[:, :, 0].astype(np.float32)
        else:
            # ITU-R BT.601 luminance; OpenCV stores BGR.
            img = np.ascontiguousarray(raw.astype(np.float32) @ np.array([0.114, 0.587, 0.299], dtype=np.float32))
    elif whole_dn and dtype in (np.uint8, np.uint16):
        img = np.ascontiguousarray(raw)
    else:
        img = raw.astype(np.float32)
    del raw             # before the caller's next step: a large frame's decoded copy is not kept
    # Bit depth and saturation from the decoded type, before any conversion to float.
    if dtype == np.uint8:
        return img, 8, channels, 255.0
    if dtype == np.uint16:
        return img, 16, channels, 65535.0
    return img, 32, channels, None
