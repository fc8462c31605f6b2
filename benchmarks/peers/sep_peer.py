"""SEP (Source Extractor as a Python library, PyPI ``sep``) as a benchmark peer.  Bench-only.

    from sep_peer import extract
    x, y, flux, ms = extract(image_float32, thresh_sigma=5.0)

Pixel convention (measured, see README.md): SEP's ``x`` is the column and ``y`` the row,
with ``(0, 0)`` the centre of the top-left pixel -- exactly startrack's, so no conversion.
Sources are returned brightest (largest ``flux``) first.
"""
from __future__ import annotations

import time

import numpy as np


def _sep():
    import sep

    return sep


def extract(image: np.ndarray, thresh_sigma: float, *, minarea: int = 5,
            deblend_cont: float = 0.005, filter_kernel="default", bw: int = 64, bh: int = 64,
            fw: int = 3, fh: int = 3, mask=None):
    """Background-subtract and extract sources from a 2-D image with SEP.

    Detection threshold: ``thresh_sigma`` x the global background RMS (``sep.Background``'s
    ``globalrms``).  Returns ``(x, y, flux, elapsed_ms)``: float64 arrays sorted by flux,
    brightest first, and the wall time of ``sep.Background`` + background subtraction +
    ``sep.extract`` only (the float32/contiguous copy made beforehand is not timed).
    Other keyword arguments are SEP's own (``filter_kernel=None`` disables filtering).
    """
    sep = _sep()
    data = np.array(image, dtype=np.float32, order="C", copy=True)  # native, contiguous
    if data.ndim != 2:
        raise ValueError(f"image must be 2-D, got shape {data.shape}")
    kw = dict(minarea=minarea, deblend_cont=deblend_cont)
    if filter_kernel is None:
        kw["filter_kernel"] = None
    elif not (isinstance(filter_kernel, str) and filter_kernel == "default"):
        kw["filter_kernel"] = np.asarray(filter_kernel, dtype=np.float32)
    t0 = time.perf_counter()
    bkg = sep.Background(data, mask=mask, bw=bw, bh=bh, fw=fw, fh=fh)
    bkg.subfrom(data)
    try:
        objs = sep.extract(data, float(thresh_sigma), err=bkg.globalrms, mask=mask, **kw)
    except Exception as exc:  # SEP's default pixel stack (300k) can overflow on busy frames
        msg = str(exc).lower()
        if "pixel" not in msg or sep.get_extract_pixstack() >= data.size:
            raise
        # Raising the stack for every call would cost ~13 ms a 1024x768 frame (it is
        # allocated per call), so only on overflow; the retry stays inside the timing.
        old = sep.get_extract_pixstack()
        sep.set_extract_pixstack(int(data.size))
        try:
            objs = sep.extract(data, float(thresh_sigma), err=bkg.globalrms, mask=mask, **kw)
        finally:  # restore, so later calls keep the fast default
            sep.set_extract_pixstack(old)
    elapsed_ms = (time.perf_counter() - t0) * 1000.0
    order = np.argsort(-objs["flux"], kind="stable")
    objs = objs[order]
    return (objs["x"].astype(np.float64), objs["y"].astype(np.float64),
            objs["flux"].astype(np.float64), elapsed_ms)


def is_available() -> bool:
    try:
        _sep()
        return True
    except ImportError:
        return False
