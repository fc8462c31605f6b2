"""Astronomers' tables of a solved image as FITS binary tables, anchored on astrometry.net's files.

* :func:`corr_table` / :func:`write_corr`: the matched stars, one row per identified detection, with the
  columns of astrometry.net's ``corr.fits`` (``field_x``, ``field_y``, ``field_ra``, ``field_dec``,
  ``index_x``, ``index_y``, ``index_ra``, ``index_dec``, ``index_id``, ``field_id``, ``match_weight``,
  ``FLUX``) and two of ours (``index_mag``, ``residual_arcsec``).
* :func:`axy_table` / :func:`write_axy`: every detection, brightest first, as astrometry.net's ``.axy``
  (``X``, ``Y``, ``FLUX``), with ``IMAGEW``/``IMAGEH`` in the header.

Pixel positions in these files follow astrometry.net's (FITS) convention: 1-based, the centre of the
top-left pixel is ``(1, 1)``, i.e. ours plus one; ``field_id`` is the 0-based index into the ``stars``
section.  ``match_weight`` is 1 for a star the attitude used and 0 for one it rejected (astrometry.net's
weight is a probability; ours is that yes/no).  astropy is imported here only.
"""
from __future__ import annotations

import numpy as np

__all__ = ["axy_table", "corr_table", "write_axy", "write_corr"]


def corr_table(result):
    """The matched stars of a solved :class:`~startrack.records.SolveResult` as an ``astropy.table.Table``."""
    from astropy import units as u
    from astropy.coordinates import SkyCoord
    from astropy.table import Table

    m = result.matches
    wcs = result.wcs
    ix, iy = wcs.world_to_pixel(SkyCoord(np.asarray(m["ra"], float), np.asarray(m["dec"], float), unit="deg"))
    used = np.isfinite(np.asarray(m["residual"], float))
    flux = result.stars.flux[np.asarray(m["star"], dtype=np.int64)] if len(m) else np.zeros(0)
    table = Table()
    table["field_x"] = (np.asarray(m["x"], float) + 1.0) * u.pix
    table["field_y"] = (np.asarray(m["y"], float) + 1.0) * u.pix
    table["field_ra"] = m["field_ra"]
    table["field_dec"] = m["field_dec"]
    table["index_x"] = (np.asarray(ix, float) + 1.0) * u.pix
    table["index_y"] = (np.asarray(iy, float) + 1.0) * u.pix
    table["index_ra"] = m["ra"]
    table["index_dec"] = m["dec"]
    table["index_id"] = np.asarray(m["catalog_id"], dtype=np.int64)
    table["field_id"] = np.asarray(m["star"], dtype=np.int32)
    table["match_weight"] = used.astype(np.float64)
    table["FLUX"] = flux
    table["index_mag"] = m["mag"]
    table["residual_arcsec"] = m["residual"]
    table.meta.update(_provenance(result))
    return table


def axy_table(result):
    """Every detection of a :class:`~startrack.records.SolveResult` as an ``astropy.table.Table`` (``X``, ``Y``,
    ``FLUX``; 1-based pixels, brightest first)."""
    from astropy import units as u
    from astropy.table import Table

    stars = result.stars
    table = Table()
    table["X"] = (stars.x + 1.0) * u.pix
    table["Y"] = (stars.y + 1.0) * u.pix
    table["FLUX"] = stars.flux
    meta = _provenance(result)
    if result.camera is not None:
        meta.update(IMAGEW=int(result.camera.width), IMAGEH=int(result.camera.height))
    table.meta.update(meta)
    return table


def _provenance(result) -> dict:
    from startrack._version import __version__

    meta = {"CREATOR": f"startrack {__version__}"}
    if result.image is not None and result.image.get("path"):
        meta["IMAGE"] = str(result.image["path"])[-68:]
    return meta


def _write(path, table, suffix):
    from astropy.io import fits

    from startrack.formats.atomic import atomic_path

    hdu = fits.table_to_hdu(table)
    with atomic_path(path, suffix=suffix) as tmp:
        fits.HDUList([fits.PrimaryHDU(), hdu]).writeto(tmp, overwrite=True)


def write_corr(path: str, result) -> None:
    """Write :func:`corr_table` as a FITS binary table (extension 1), atomically."""
    _write(path, corr_table(result), ".fits")


def write_axy(path: str, result) -> None:
    """Write :func:`axy_table` as a FITS binary table (extension 1), atomically."""
    _write(path, axy_table(result), ".axy")
