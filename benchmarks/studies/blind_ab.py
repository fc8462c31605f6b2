"""Study (issue 15), recorded in 84dbd40:benchmarks/results-blind-speed-2026-12-02.md: in-process A/B of two trees.

On the 8 ESA images: per image, the fastest of 9 runs (wall ms) and the median CPU ms.

    PYTHONPATH=TREE python benchmarks/studies/blind_ab.py NAME      # startrack of TREE (solve_image, decoded image)
    CEDAR_PYTHON=... python benchmarks/studies/blind_ab.py cedar    # cedar-solve solve_from_image (FOV 11.4 given)

Prints one JSON line.  Run two trees and cedar-solve alternately (see the file above):
on a shared machine the minimum of repeated runs is the figure least moved by other processes.
"""
import json
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # benchmarks/: common, the tools
from common import esa_images  # noqa: E402

R = 9


def main(who):
    esa = esa_images()
    if who == "cedar":
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
        print(json.dumps({"who": who, "min_wall": mins, "median_cpu": cpus}))


if __name__ == "__main__":
    main(sys.argv[1])
