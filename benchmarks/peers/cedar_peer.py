"""Main-venv client for cedar_runner.py (cedar-solve lives in ``.venv-cedar``).  Bench-only.

Keeps one ``.venv-cedar/bin/python cedar_runner.py`` process alive and talks JSON Lines to
it, so per-request timings exclude interpreter start-up and database loading::

    from cedar_peer import CedarSolver
    with CedarSolver(db="default") as cs:            # or db=path.npz, or build_fov=20, mag=5
        r = cs.solve_centroids(xy, 1024, 768, 11.4)   # xy: [[x, y], ...] startrack convention
        r = cs.solve_image("/path/img.tiff", 11.4)

Results are cedar_runner's dicts (``ra``, ``dec``, ``roll`` in startrack's convention,
``fov``, ``matches``, ``t_solve_ms``, ``status``, ...).  ``t_solve_ms`` is cedar's own
``T_solve``; ``t_wall_ms`` the runner-side wall time of the call.
"""
from __future__ import annotations

import json
import os
import subprocess

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(os.path.dirname(HERE))
CEDAR_PY = os.environ.get("CEDAR_PYTHON", os.path.join(ROOT, ".venv-cedar", "bin", "python"))
RUNNER = os.path.join(HERE, "cedar_runner.py")


def is_available() -> bool:
    return os.path.exists(CEDAR_PY)


class CedarSolver:
    def __init__(self, db="default", *, build_fov=None, build_min_fov=None, mag=None,
                 timeout_ms=5000, stderr=subprocess.DEVNULL, epoch=None):
        if not is_available():
            raise RuntimeError(f"{CEDAR_PY} missing: run bash benchmarks/peers/setup_peers.sh")
        cmd = [CEDAR_PY, RUNNER, "--warmup", "--db", str(db), "--timeout-ms", str(timeout_ms)]
        if build_fov:
            cmd += ["--build-fov", f"{build_fov:g}"]
            if build_min_fov:
                cmd += ["--build-min-fov", f"{build_min_fov:g}"]
            if mag is not None:
                cmd += ["--mag", f"{mag:g}"]
            if epoch is not None:
                cmd += ["--epoch", f"{epoch:g}"]
        self._p = subprocess.Popen(cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                   stderr=stderr, text=True, bufsize=1)
        self._n = 0

    def request(self, req: dict) -> dict:
        self._n += 1
        req = dict(req)
        req.setdefault("id", self._n)
        self._p.stdin.write(json.dumps(req) + "\n")
        self._p.stdin.flush()
        line = self._p.stdout.readline()
        if not line:
            raise RuntimeError(f"cedar_runner exited (code {self._p.poll()})")
        return json.loads(line)

    def solve_centroids(self, centroids_xy, width, height, fov_deg, **kw):
        """``centroids_xy``: (N, 2) ``[x, y]`` in startrack's convention, brightest first."""
        yx = np.asarray(centroids_xy, dtype=np.float64).reshape(-1, 2)[:, ::-1]
        return self.request({"centroids": yx.tolist(), "size": [int(height), int(width)],
                             "fov_deg": float(fov_deg), **kw})

    def solve_image(self, path, fov_deg, **kw):
        return self.request({"image": os.path.abspath(path), "fov_deg": float(fov_deg), **kw})

    def close(self):
        if self._p and self._p.poll() is None:
            self._p.stdin.close()
            try:
                self._p.wait(timeout=30)
            except subprocess.TimeoutExpired:
                self._p.kill()
                self._p.wait()
        self._p = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
