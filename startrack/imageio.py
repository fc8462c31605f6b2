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

__all__ = ["IMAGE_WRITE_EXTENSIONS", "check_image_output", "write_image", "read_image"]

IMAGE_WRITE_EXTENSIONS = (".png", ".tif", ".tiff", ".fits", ".fit", ".fts")
IMAGE_READ_EXTENSIONS = IMAGE_WRITE_EXTENSIONS + (".jpg", ".jpeg", ".bmp", ".pgm", ".ppm")


def check_image_output(path: str) -> str:
    """Refuse an output name whose extension we cannot write; return the extension."""
    ext = os.path.splitext(path)[1].lower()
    if ext not in IMAGE_WRITE_EXTENSIONS:
        raise BadInputError(path, None, f"unknown image extension {ext or '(none)'!r}: use "
                            + ", ".join(IMAGE_WRITE_EXTENSIONS))
    check_writable(path)
    return ext


def write_image(path: str, image: np.ndarray, header: dict | None = None) -> None:
    """Write a 2-D uint8/uint16 image atomically; FITS gets ``header`` as keywords."""
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
            if not cv2.imwrite(tmp, image):
                raise BadInputError(path, None, "OpenCV could not write the image")


def read_image(path: str):
    """Read an image as a 2-D float32 array of DN.

    Returns
    -------
    image : ndarray (height, width) of float32
    info : dict
        ``bit_depth`` (8 or 16 as stored; 12-bit data arrive in 16-bit files),
        ``channels`` of the file, ``saturation`` (the largest DN the file can hold).
    """
    if not os.path.exists(path):
        raise BadInputError(path, None, "no such file")
    if os.path.isdir(path):
        raise BadInputError(path, None, "is a directory, expected an image")
    if os.path.getsize(path) == 0:
        raise BadInputError(path, None, "is empty (0 bytes)")
    ext = os.path.splitext(path)[1].lower()
    if ext in (".fits", ".fit", ".fts"):
        from astropy.io import fits

        try:
            with fits.open(path, memmap=False) as hdul:
                data = next((h.data for h in hdul if getattr(h, "data", None) is not None and h.data.ndim >= 2), None)
        except Exception as exc:  # astropy raises many types for broken files
            raise BadInputError(path, None, f"is not a readable FITS file ({type(exc).__name__})") from None
        if data is None:
            raise BadInputError(path, None, "holds no 2-D image")
        data = np.asarray(data)
        if data.ndim == 3:
            data = data.mean(axis=0) if data.shape[0] in (3, 4) else data[0]
        bit_depth = 8 if data.dtype == np.uint8 else 16
        img = np.ascontiguousarray(data, dtype=np.float32)
        channels = 1
        saturation = float(np.nanmax(img)) if data.dtype.kind == "f" else float(np.iinfo(data.dtype).max)
    else:
        import cv2

        raw = cv2.imread(path, cv2.IMREAD_UNCHANGED | cv2.IMREAD_ANYDEPTH)
        if raw is None:
            raise BadInputError(path, None, "is not a readable image (truncated or unknown format)")
        channels = 1 if raw.ndim == 2 else raw.shape[2]
        if raw.dtype not in (np.uint8, np.uint16, np.float32):
            raise BadInputError(path, None, f"has unsupported pixel type {raw.dtype}")
        if raw.ndim == 3:
            if channels == 4:
                raw = raw[:, :, :3]
            # ITU-R BT.601 luminance; OpenCV stores BGR.
            raw = raw.astype(np.float32) @ np.array([0.114, 0.587, 0.299], dtype=np.float32)
            img = np.ascontiguousarray(raw)
        else:
            img = raw.astype(np.float32)
        bit_depth = 8 if raw.dtype == np.uint8 else 16
        saturation = 255.0 if bit_depth == 8 else 65535.0
    if img.ndim != 2 or img.shape[0] == 0 or img.shape[1] == 0:
        raise BadInputError(path, None, f"has no pixels (shape {img.shape})")
    if not np.all(np.isfinite(img)):
        img = np.nan_to_num(img, nan=0.0, posinf=0.0, neginf=0.0)
    return img, {"bit_depth": bit_depth, "channels": channels, "saturation": saturation}
