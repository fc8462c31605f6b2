"""Catalog loading, feeds catalogs/README.md's loading times: the deep shipped file vs a Hp <= 8 file, side by side.

    python benchmarks/catalog_bench.py [--repeats 9]

Each case is timed in turn, round-robin, so machine load hits all of them alike;
the table gives the median and the fastest of the repeats (warm file cache).
"""
from __future__ import annotations

import argparse
import os
import tempfile
import time

import numpy as np

from startrack.catalog import default_catalog_path, load_catalog, write_catalog


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeats", type=int, default=9)
    args = ap.parse_args(argv)
    deep = default_catalog_path()
    with tempfile.TemporaryDirectory() as tmp:
        shallow = os.path.join(tmp, "hip2-hp8.h5")
        write_catalog(load_catalog(deep, mag_max=8.0), shallow)
        cases = {
            "Hp <= 8 file, load_catalog()": lambda: load_catalog(shallow),
            "deep file, load_catalog()": lambda: load_catalog(deep),
            "deep file, load_catalog(mag_max=8)": lambda: load_catalog(deep, mag_max=8.0),
            "deep file, load_catalog(mag_max=6)": lambda: load_catalog(deep, mag_max=6.0),
        }
        times = {k: [] for k in cases}
        stars = {}
        for _ in range(args.repeats):
            for name, fn in cases.items():
                t0 = time.perf_counter()
                cat = fn()
                times[name].append(time.perf_counter() - t0)
                stars[name] = len(cat)
    print("| case | stars | median ms | fastest ms |")
    print("| --- | ---: | ---: | ---: |")
    for name, t in times.items():
        print(f"| {name} | {stars[name]:,} | {1000 * np.median(t):.1f} | {1000 * min(t):.1f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
