"""In-process A/B on the 8 ESA images: per image, the fastest of 9 runs (wall ms) and the median CPU ms.

    PYTHONPATH=TREE python benchmarks/blind_ab.py NAME      # startrack of TREE (solve_image, decoded image)
    CEDAR_PYTHON=... python benchmarks/blind_ab.py cedar    # cedar-solve solve_from_image (FOV 11.4 given)

Prints one JSON line.  Run two trees and cedar-solve alternately (see results-blind-speed-2026-12-02.md):
on a shared machine the minimum of repeated runs is the figure least moved by other processes.
"""
import glob
import json
import os
import sys
import time

import numpy as np

R = 9
HERE = os.path.dirname(os.path.abspath(__file__))
esa = sorted(glob.glob(os.path.join(os.path.dirname(HERE), "tests", "data", "real", "*.tiff")))
if sys.argv[1] == "cedar":
    sys.path.insert(0, os.path.join(HERE, "peers"))
    import cedar_peer
    with cedar_peer.CedarSolver(db="default") as cs:
        mins = []
        for p in esa:
            cs.solve_image(p, 11.4)
            mins.append(min(cs.solve_image(p, 11.4)["t_wall_ms"] for _ in range(R)))
    print(json.dumps({"who": "cedar", "min_wall": mins}))
else:
    from startrack.imageio import read_image
    from startrack.patterns import default_index
    from startrack.solve import SolveOptions, solve_image
    index = default_index()
    images = [read_image(p) for p in esa]
    for im, meta in images:
        solve_image(im, options=SolveOptions(), saturation=meta["saturation"], index=index)
    mins, cpus = [], []
    for im, meta in images:
        ws, cs = [], []
        for _ in range(R):
            t0, c0 = time.perf_counter(), time.process_time()
            out = solve_image(im, options=SolveOptions(), saturation=meta["saturation"], index=index)
            ws.append((time.perf_counter() - t0) * 1000); cs.append((time.process_time() - c0) * 1000)
            assert out.status == "ok"
        mins.append(min(ws)); cpus.append(float(np.median(cs)))
    print(json.dumps({"who": sys.argv[1], "min_wall": mins, "median_cpu": cpus}))
