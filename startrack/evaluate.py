"""Monte Carlo comparison of identification algorithms (the papers' tables).

For every condition (centroid noise, false stars, magnitude noise, focal-length
error, dropped stars) ``n`` random attitudes are drawn from the same seed, so
every algorithm and every condition sees the same skies.  Star lists come from
:func:`startrack.render.star_list`; each frame is scored against its truth:

* **success**: identified, and every reported match is the true star;
* **bad match**: identified, but at least one match is wrong (a false star
  matched to a catalog star counts as wrong);
* **ID failure**: no identification returned.

Times are the identification time per frame as each algorithm reports it
(``time_ms``: pattern search, verification and confidence).
"""
from __future__ import annotations

import itertools
import math
import os
from dataclasses import asdict, dataclass

import numpy as np

from startrack.errors import BadInputError, ParameterError

__all__ = ["Condition", "Tally", "conditions_grid", "make_frames", "score", "evaluate", "summarise", "wilson_interval",
           "with_intervals"]

#: z of a two-sided 95 % interval (the normal distribution's 97.5 % point)
Z95 = 1.959963984540054


def wilson_interval(k: int, n: int, z: float = Z95) -> tuple[float, float]:
    """Wilson's score interval of a binomial proportion ``k / n`` (95 % by default).

    Unlike the normal (Wald) interval it stays inside [0, 1] and is not of zero width at 0 or ``n``
    successes: 1000 of 1000 gives [0.99617, 1], 0 of 1000 gives [0, 0.00383] (E. B. Wilson, "Probable
    inference, the law of succession, and statistical inference", J. Am. Stat. Assoc. 22, 209-212, 1927).
    ``n = 0`` gives ``(nan, nan)``.
    """
    k, n = int(k), int(n)
    if n <= 0:
        return float("nan"), float("nan")
    if not 0 <= k <= n:
        raise ParameterError("k", f"must be in [0, n = {n}], got {k}")
    p = k / n
    z2 = z * z
    centre = (p + z2 / (2 * n)) / (1 + z2 / n)
    half = z / (1 + z2 / n) * math.sqrt(p * (1 - p) / n + z2 / (4 * n * n))
    # exact at the ends (0 or n successes), where rounding could leave the bound a hair inside
    lo = 0.0 if k == 0 else max(0.0, centre - half)
    hi = 1.0 if k == n else min(1.0, centre + half)
    return lo, hi


#: Row fields (``evaluate --json``) that are numbers, and the conditions a chart may sweep.
_ROW_COUNTS = ("frames", "success", "failure", "bad")
_ROW_NUMBERS = ("success_rate", "success_rate_low", "success_rate_high", "mean_ms", "median_ms", "p95_ms",
                "false_stars", "focal_error_pct", "sigma_px", "sigma_arcsec", "mag_noise", "drop_fraction", "min_stars")


def validate_rows(rows, source: str) -> list:
    """Check the ``rows`` of an ``evaluate --json`` document before they are drawn or tabled.

    Raises :class:`BadInputError` naming ``source``, the row and the field: a list of objects, each with an
    ``algorithm`` name, whole counts (``success`` and ``bad`` at most ``frames``), finite numbers, rates in [0, 1]
    with ``success_rate_low <= success_rate <= success_rate_high``.
    """
    if not isinstance(rows, list) or not rows:
        raise BadInputError(source, "rows", "must be a non-empty list of rows")
    for i, row in enumerate(rows):
        where = f"rows[{i}]"
        if not isinstance(row, dict):
            raise BadInputError(source, where, "must be a JSON object")
        if not isinstance(row.get("algorithm"), str):
            raise BadInputError(source, f"{where}.algorithm", "must be an algorithm name")
        for name in _ROW_COUNTS:
            v = row.get(name)
            if name in ("frames", "success", "bad") or v is not None:
                if isinstance(v, bool) or not isinstance(v, int) or v < 0:
                    raise BadInputError(source, f"{where}.{name}", f"must be a whole number >= 0, got {v!r}"[:120])
        if row["success"] > row["frames"] or row["bad"] > row["frames"]:
            raise BadInputError(source, f"{where}.success", "success and bad must be at most frames")
        for name in _ROW_NUMBERS:
            v = row.get(name)
            if (v is not None or name == "success_rate") and (isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v)):
                raise BadInputError(source, f"{where}.{name}", f"must be a finite number, got {v!r}"[:120])
        rates = [row.get(k) for k in ("success_rate_low", "success_rate", "success_rate_high")]
        if any(r is not None and not 0 <= r <= 1 for r in rates) or (
                None not in rates and not rates[0] <= rates[1] <= rates[2]):
            raise BadInputError(source, f"{where}.success_rate", "must lie in [0, 1], within its interval "
                                                                 "success_rate_low .. success_rate_high")
    return rows


def with_intervals(row: dict) -> dict:
    """``row`` with the Wilson 95 % intervals of its success and bad-match rates (from its counts).

    Rows written before the intervals existed (an old ``evaluate --json``, a checkpoint) get them here.
    """
    if "success_rate_low" in row:
        return row
    n = int(row["frames"])
    s_lo, s_hi = wilson_interval(row["success"], n)
    b_lo, b_hi = wilson_interval(row["bad"], n)
    return {**row, "success_rate_low": s_lo, "success_rate_high": s_hi,
            "bad_rate": row["bad"] / n if n else float("nan"), "bad_rate_low": b_lo, "bad_rate_high": b_hi}


@dataclass(frozen=True)
class Condition:
    """One cell of the comparison."""

    sigma_px: float = 0.1
    false_stars: int = 0
    mag_noise: float = 0.0
    focal_error_pct: float = 0.0
    drop_fraction: float = 0.0
    min_stars: int = 0
    max_stars: int | None = None
    min_catalog_stars: int = 0
    #: the same noise as the user gave it, in arcseconds (``--sigma-arcsec``); labels then speak arcseconds
    sigma_arcsec: float | None = None

    def label(self) -> str:
        parts = [f"sigma {self.sigma_arcsec:g} arcsec" if self.sigma_arcsec is not None else f"sigma {self.sigma_px:g}px"]
        if self.false_stars:
            parts.append(f"{self.false_stars} false")
        if self.mag_noise:
            parts.append(f"mag noise {self.mag_noise:g}")
        if self.focal_error_pct:
            parts.append(f"focal {self.focal_error_pct:g}%")
        if self.drop_fraction:
            parts.append(f"drop {self.drop_fraction:g}")
        if self.min_stars:
            parts.append(f">= {self.min_stars} stars")
        if self.min_catalog_stars:
            parts.append(f">= {self.min_catalog_stars} catalog stars")
        return ", ".join(parts)


def conditions_grid(**lists) -> list:
    """All combinations of the given value lists, e.g. ``false_stars=[0, 1, 2]``."""
    keys = [k for k, v in lists.items() if v is not None]
    values = [lists[k] for k in keys]
    return [Condition(**dict(zip(keys, combo))) for combo in itertools.product(*values)]


#: Random attitudes drawn for one frame before a condition's ``min_stars``/``min_catalog_stars`` is declared unmet.
MAX_ATTITUDE_TRIES = 1000


def make_frames(catalog, camera, condition: Condition, n: int, seed: int, sensor=None, mag_limit=None, vectors=None,
                start: int = 0):
    """``n`` star-list frames for ``condition``; frame k uses attitude seed (seed, k), retried (seed, k, t)
    until it has ``min_stars`` stars (paper 003's "at least 4 stars including one false star") and
    ``min_catalog_stars`` stars of the catalog (false stars not counted).

    When no attitude of ``MAX_ATTITUDE_TRIES`` meets the condition, :class:`ParameterError` (``min_stars`` or
    ``min_catalog_stars``) names it: a frame that does not meet it is never returned.

    ``start`` gives the frames ``start .. start + n - 1`` of the same sequence (chunks of a large set).
    """
    from startrack.render import Scene, Sensor, star_list
    from startrack.rotations import quaternion_to_dcm, random_quaternions

    sensor = sensor or Sensor()
    scene = Scene(mag_limit=mag_limit, mag_noise=condition.mag_noise, false_stars=condition.false_stars,
                  focal_error_pct=condition.focal_error_pct)
    vectors = catalog.vectors() if vectors is None else vectors
    frames = []
    for k in range(start, start + n):
        most, most_catalog = 0, 0
        for t in range(MAX_ATTITUDE_TRIES):
            frame_seed = [int(seed), int(k), int(t)]
            rng = np.random.default_rng(frame_seed)
            dcm = quaternion_to_dcm(random_quaternions(1, rng)[0])
            stars, truth = star_list(catalog, camera, dcm, sensor, scene, rng, condition.sigma_px,
                                     condition.max_stars, condition.drop_fraction, vectors)
            n_catalog = sum(1 for i in truth["star_ids"] if i is not None)
            if len(stars) >= condition.min_stars and n_catalog >= condition.min_catalog_stars:
                break
            most, most_catalog = max(most, len(stars)), max(most_catalog, n_catalog)
        else:
            # Never a frame that does not meet the condition: the table would print the condition over
            # frames that do not have it (issue 41).
            if most < condition.min_stars:
                raise ParameterError("min_stars", f"no frame with at least {condition.min_stars} stars in "
                                     f"{MAX_ATTITUDE_TRIES} random attitudes (frame {k}; the most was {most}): "
                                     "lower it, or widen the field or the magnitude limit")
            raise ParameterError("min_catalog_stars", f"no frame with at least {condition.min_catalog_stars} "
                                 f"catalog stars in {MAX_ATTITUDE_TRIES} random attitudes (frame {k}; the most "
                                 f"was {most_catalog}): lower it, or widen the field or the magnitude limit")
        frames.append((stars, truth, frame_seed))
    return frames


def score(result, truth) -> str:
    """``"success"``, ``"bad"`` or ``"failure"`` for one identification against its truth."""
    if result.status != "ok":
        return "failure"
    ids = truth["star_ids"]
    for m in result.matches:
        # A blend of unresolved stars is the star the sensor sees: its truth id is
        # the brightest component's (render), as in a database built for the
        # sensor (Catalog.merge_close); naming a fainter component is wrong.
        if ids[m.star] != m.id:
            return "bad"
    return "success"


_WORKER = {}


def _worker_init(databases, camera, params, configs=None):
    _WORKER.update(databases=databases, camera=camera, params=params, configs=dict(configs or {}))


def _identify_chunk(args, on_frame=None):
    """``(outcome, ms, stars, frame_seed, wrong, double)`` of every frame; ``on_frame()`` after each one."""
    from startrack.identify import database_kind, identify_stars

    algorithm, frames = args
    db = _WORKER["databases"][database_kind(algorithm)]
    config = _WORKER.get("configs", {}).get(algorithm)
    if frames and not _WORKER.get(("warm", algorithm)):
        # The first call in a process loads the compiled kernels: keep it out of the timings.
        identify_stars(frames[0][0], _WORKER["camera"], db, algorithm, _WORKER["params"], config)
        _WORKER[("warm", algorithm)] = True
    out = []
    for stars, truth, frame_seed in frames:
        res = identify_stars(stars, _WORKER["camera"], db, algorithm, _WORKER["params"], config)
        outcome = score(res, truth)
        wrong = [{"star": m.star, "id": m.id, "true_id": truth["star_ids"][m.star]} for m in res.matches
                 if truth["star_ids"][m.star] != m.id][:3] if outcome == "bad" else []
        listed = set(truth["star_ids"])
        double = any(s.get("blended") and s["id"] in listed for s in truth.get("stars", ()))
        out.append((outcome, res.time_ms, len(stars), frame_seed, wrong, double))
        if on_frame is not None:
            on_frame()
    return out


#: Frames made and identified at once per condition: memory is bounded by this, whatever ``n``.
CHUNK_FRAMES = 1000
#: Identification times kept exactly per row; beyond, a histogram of 0.1 % wide log bins (median, p95 within 0.1 %).
EXACT_TIMES = 100_000
_LOG_BIN = math.log(1.001)
_LOG_T0 = math.log(1e-4)  # ms


class Tally:
    """The running counts of one table row (algorithm, condition), in memory independent of the frames' number.

    ``add`` takes ``(outcome, ms, stars, frame_seed, wrong, double)`` per frame; ``row`` gives the table row;
    ``to_dict``/``from_dict`` carry it through a checkpoint (``evaluate --resume``).
    """

    def __init__(self):
        self.n = 0
        self.counts = {"success": 0, "failure": 0, "bad": 0}
        self.sum_ms = 0.0
        self.sum_stars = 0
        self.double = [0, 0, 0]  # frames, success, bad
        self.bad_seeds: list = []
        self.times: list | None = []
        self.hist: dict[int, int] = {}

    def add(self, results) -> None:
        for outcome, ms, stars, frame_seed, wrong, double in results:
            self.n += 1
            self.counts[outcome] += 1
            self.sum_ms += float(ms)
            self.sum_stars += int(stars)
            if double:
                self.double[0] += 1
                self.double[1] += outcome == "success"
                self.double[2] += outcome == "bad"
            if outcome == "bad" and len(self.bad_seeds) < 20:
                self.bad_seeds.append({"frame_seed": frame_seed, "wrong": wrong})
            if self.times is not None:
                self.times.append(float(ms))
                if len(self.times) > EXACT_TIMES:
                    for t in self.times:
                        self._bin(t)
                    self.times = None
            else:
                self._bin(float(ms))

    def _bin(self, ms: float) -> None:
        k = int(math.floor((math.log(max(ms, 1e-4)) - _LOG_T0) / _LOG_BIN))
        self.hist[k] = self.hist.get(k, 0) + 1

    def _quantile(self, q: float) -> float:
        if self.times is not None:
            return float(np.percentile(np.array(self.times), q)) if self.times else float("nan")
        target = q / 100 * (self.n - 1)
        seen = 0
        for k in sorted(self.hist):
            seen += self.hist[k]
            if seen > target:
                return float(math.exp(_LOG_T0 + (k + 0.5) * _LOG_BIN))
        return float("nan")

    def row(self, algorithm, cond, n) -> dict:
        c = self.counts
        s_lo, s_hi = wilson_interval(c["success"], n)
        b_lo, b_hi = wilson_interval(c["bad"], n)
        return {
            "algorithm": algorithm, "condition": cond.label(), **asdict(cond), "frames": n,
            "success": c["success"], "failure": c["failure"], "bad": c["bad"],
            "success_rate": c["success"] / n,
            "success_rate_low": s_lo, "success_rate_high": s_hi,
            "bad_rate": c["bad"] / n, "bad_rate_low": b_lo, "bad_rate_high": b_hi,
            "mean_ms": self.sum_ms / self.n if self.n else float("nan"),
            "median_ms": self._quantile(50), "p95_ms": self._quantile(95),
            "mean_stars": self.sum_stars / self.n if self.n else float("nan"),
            # Frames with an unresolved double among their stars (render's blends).
            "double_frames": self.double[0], "double_success": self.double[1], "double_bad": self.double[2],
            "bad_seeds": self.bad_seeds[:20],
        }

    def to_dict(self) -> dict:
        """A copy of the state, JSON-able (later frames do not change it)."""
        return {"n": self.n, "counts": dict(self.counts), "sum_ms": self.sum_ms, "sum_stars": self.sum_stars,
                "double": list(self.double), "bad_seeds": list(self.bad_seeds),
                "times": None if self.times is None else list(self.times),
                "hist": {str(k): v for k, v in self.hist.items()}}

    @classmethod
    def from_dict(cls, d: dict) -> Tally:
        t = cls()
        t.n, t.counts, t.sum_ms, t.sum_stars = int(d["n"]), dict(d["counts"]), float(d["sum_ms"]), int(d["sum_stars"])
        t.double, t.bad_seeds = list(d["double"]), list(d["bad_seeds"])
        t.times = None if d["times"] is None else [float(v) for v in d["times"]]
        t.hist = {int(k): int(v) for k, v in d["hist"].items()}
        return t


def evaluate(algorithms, conditions, n, databases: dict, camera, catalog, seed: int = 0, jobs: int = 1,
             params=None, mag_limit=None, progress=None, scheduler: str | None = None, catalog_path=None,
             configs: dict | None = None, resume: dict | None = None, checkpoint=None):
    """Run every algorithm on every condition.

    Frames are made and identified ``CHUNK_FRAMES`` at a time and reduced into one :class:`Tally` per
    row as they finish, so memory does not grow with ``n``.

    Parameters
    ----------
    databases : dict
        Database kind (``"kvector"``, ``"labels"``, ...) -> loaded database.
    scheduler : str or None
        A Dask scheduler (``"local"`` or an address): the frames are made and
        identified by the workers in chunks, each worker loading the databases
        (from their files) and the catalog (``catalog_path``, None for the
        shipped one) once, and the results are reduced as the chunks arrive, so
        the client holds no frame.
    configs : dict, optional
        Algorithm name -> its configuration (:func:`startrack.identify.make_config`);
        the defaults for the others.
    progress : callable, optional
        ``progress(done, total)``: frames identified (each algorithm's) of ``len(conditions) * n *
        len(algorithms)``, called as they finish (per frame on one process, per piece with ``jobs`` or a
        cluster).
    resume, checkpoint : optional
        ``checkpoint(state)`` is called after every chunk with a JSON-able ``state`` (rows done, the
        condition under way, its frames done and tallies); ``resume=state`` goes on from it, with the
        same frames (frame k's attitude depends on ``seed`` and k only), on one machine or a cluster alike
        (a checkpoint of either resumes on the other).

    Returns
    -------
    list of dict
        One row per (algorithm, condition) with the counts, rates and times,
        and the frame seeds of any bad match (to reproduce it).
    """
    from startrack.identify import IdentifyParams, database_kind

    for a in algorithms:
        kind = database_kind(a)
        if kind not in databases:
            raise ParameterError("database", f"{a} needs a {kind} database")
    params = params or IdentifyParams()
    if scheduler is not None:
        return _evaluate_on_cluster(algorithms, conditions, n, databases, camera, catalog_path, seed, jobs, params,
                                    mag_limit, progress, scheduler, configs, resume, checkpoint)
    vectors = catalog.vectors()
    state = resume or {"rows": [], "condition": 0, "frames_done": 0, "tallies": None}
    rows = list(state["rows"])
    total = len(conditions) * len(algorithms)
    pool = None
    if jobs > 1:
        import multiprocessing as mp

        # spawn, not fork: numba's OpenMP threading layer must not be forked.
        pool = mp.get_context("spawn").Pool(jobs, _worker_init, (databases, camera, params, configs))
    else:
        _worker_init(databases, camera, params, configs)
    try:
        for ci in range(int(state["condition"]), len(conditions)):
            cond = conditions[ci]
            if resume is not None and ci == int(state["condition"]) and state["tallies"]:
                start = int(state["frames_done"])
                tallies = {a: Tally.from_dict(state["tallies"][a]) for a in algorithms}
            else:
                start, tallies = 0, {a: Tally() for a in algorithms}
            for a0 in range(start, n, CHUNK_FRAMES):
                frames = make_frames(catalog, camera, cond, min(CHUNK_FRAMES, n - a0), seed, mag_limit=mag_limit,
                                     vectors=vectors, start=a0)
                # Progress counts identified frames (each algorithm's), as they finish: a bar that moves
                # with the frames and gives tqdm its rate and ETA, not one step per condition.
                counted = [len(rows) * n + a0 * len(algorithms)]

                def tick(k=1, counted=counted):
                    counted[0] += k
                    if progress:
                        progress(counted[0], total * n)

                for algorithm in algorithms:
                    if pool is not None:
                        size = max(1, min(50, len(frames) // (jobs * 4)))
                        chunks = [(algorithm, frames[i:i + size]) for i in range(0, len(frames), size)]
                        results = []
                        for part in pool.imap(_identify_chunk, chunks):
                            results += part
                            tick(len(part))
                    else:
                        results = _identify_chunk((algorithm, frames), tick)
                    tallies[algorithm].add(results)
                done_frames = a0 + len(frames)
                if checkpoint is not None and done_frames < n:
                    checkpoint({"rows": list(rows), "condition": ci, "frames_done": done_frames,
                                "tallies": {a: t.to_dict() for a, t in tallies.items()}})
            rows += [tallies[a].row(a, cond, n) for a in algorithms]
            if checkpoint is not None:
                checkpoint({"rows": list(rows), "condition": ci + 1, "frames_done": 0, "tallies": None})
    finally:
        if pool is not None:
            pool.close()
            pool.join()
    return rows


def _row(algorithm, cond, n, results) -> dict:
    """One table row from ``(outcome, ms, stars, frame_seed, wrong, double)`` per frame."""
    tally = Tally()
    tally.add(results)
    return tally.row(algorithm, cond, n)


def _load_database(path):
    """A database of any kind from its file (the kind is its format tag)."""
    from startrack.formats.hdf5 import read_format_tag

    kind = read_format_tag(path).split(".")[1].split("/")[0]
    if kind == "labels":
        from startrack.labels import load_labels

        return kind, load_labels(path)
    if kind == "triangles":
        from startrack.triangles import load_triangles

        return kind, load_triangles(path)
    from startrack.kvector import load_kvector

    return kind, load_kvector(path)


def _cluster_chunk(spec):
    """Dask task: frames ``start .. stop`` of one condition, made here and identified by every algorithm.

    The worker loads the databases and the catalog once (:func:`startrack.cluster.worker_cache`) and
    returns only the per-frame outcomes, so a task's result is small whatever the chunk.
    """
    from startrack.camera import Camera
    from startrack.catalog import load_catalog
    from startrack.cluster import worker_cache

    paths, catalog_path, mag_limit, camera_doc, params, cond, algorithms, seed, start, stop, configs = spec
    cache = worker_cache()
    key = ("evaluate", tuple(sorted(paths.items())), catalog_path, mag_limit)
    if key not in cache:
        dbs = dict(_load_database(p) for p in paths.values())
        cat = load_catalog(catalog_path, mag_max=mag_limit).filter_magnitude(None, mag_limit)
        cache[key] = (dbs, cat, cat.vectors())
    dbs, cat, vectors = cache[key]
    camera = Camera.from_dict(camera_doc)
    frames = make_frames(cat, camera, cond, stop - start, seed, mag_limit=mag_limit, vectors=vectors, start=start)
    _worker_init(dbs, camera, params, configs)
    return {algorithm: _identify_chunk((algorithm, frames)) for algorithm in algorithms}


def _evaluate_on_cluster(algorithms, conditions, n, databases, camera, catalog_path, seed, jobs, params, mag_limit,
                         progress, scheduler, configs=None, resume=None, checkpoint=None):
    """:func:`evaluate` on a Dask cluster: the chunks' outcomes reduced in input order, so a checkpoint after a chunk
    is the one-process path's state after the same frames, and ``resume`` sends only the frames not yet tallied."""
    from startrack.cluster import TaskFailure, chunks, default_chunk, ordered_map

    paths = {}
    for kind, db in databases.items():
        if not getattr(db, "path", ""):
            raise BadInputError("databases", None, f"the {kind} database has no file: a cluster loads it by path")
        paths[kind] = os.path.abspath(db.path)
    if catalog_path is not None:
        catalog_path = os.path.abspath(catalog_path)
    state = resume or {"rows": [], "condition": 0, "frames_done": 0, "tallies": None}
    rows = list(state["rows"])
    first = int(state["condition"])
    start = int(state["frames_done"]) if resume is not None and state["tallies"] else 0
    tallies = {a: Tally.from_dict(state["tallies"][a]) if start else Tally() for a in algorithms}
    size = default_chunk(n, jobs)
    spans = [(ci, max(a, start) if ci == first else a, b) for ci in range(first, len(conditions))
             for a, b in chunks(n, size) if ci > first or b > start]
    specs = [(paths, catalog_path, mag_limit, camera.to_dict(), params, conditions[ci], list(algorithms), seed, a, b,
              configs) for ci, a, b in spans]
    done = len(rows) * n + start * len(algorithms)
    for i, part in ordered_map(_cluster_chunk, specs, jobs=jobs, scheduler=scheduler):
        if isinstance(part, TaskFailure):
            raise BadInputError("scheduler", None, f"a chunk of frames failed on the cluster: {part.error}")
        ci, _, stop = spans[i]
        for algorithm, res in part.items():
            tallies[algorithm].add(res)
            done += len(res)
        # frames identified (each algorithm's), as the one-machine path counts them
        if progress:
            progress(done, len(conditions) * n * len(algorithms))
        if stop < n:
            if checkpoint is not None:
                checkpoint({"rows": list(rows), "condition": ci, "frames_done": stop,
                            "tallies": {a: t.to_dict() for a, t in tallies.items()}})
            continue
        rows += [tallies[a].row(a, conditions[ci], n) for a in algorithms]
        tallies = {a: Tally() for a in algorithms}
        if checkpoint is not None:
            checkpoint({"rows": list(rows), "condition": ci + 1, "frames_done": 0, "tallies": None})
    return rows


def summarise(rows) -> str:
    """The papers' table: per algorithm and condition, with the Wilson 95 % intervals of the success and
    bad-match rates (``[low, high]`` in per cent: 0 bad matches in 1,000 frames is a rate below 0.38 %)."""
    rows = [with_intervals(r) for r in rows]
    headers = ["algorithm", "condition", "frames", "success", "success 95% CI", "ID failure", "bad match",
               "bad 95% CI", "mean ms", "median ms", "p95 ms"]
    body = [[r["algorithm"], r["condition"], str(r["frames"]), f"{100 * r['success_rate']:.2f}%",
             _interval(r["success_rate_low"], r["success_rate_high"]), str(r["failure"]), str(r["bad"]),
             _interval(r["bad_rate_low"], r["bad_rate_high"]), f"{r['mean_ms']:.3f}", f"{r['median_ms']:.3f}",
             f"{r['p95_ms']:.3f}"] for r in rows]
    widths = [max(len(h), *(len(b[i]) for b in body)) for i, h in enumerate(headers)]
    lines = ["  ".join(h.ljust(w) for h, w in zip(headers, widths)), "  ".join("-" * w for w in widths)]
    lines += ["  ".join(c.ljust(w) for c, w in zip(b, widths)) for b in body]
    return "\n".join(lines)


def _interval(lo: float, hi: float) -> str:
    return f"[{_percent(lo)}, {_percent(hi)}]%"


def _percent(v: float) -> str:
    """A rate in per cent with two decimals, more when two would round it to 0 or 100 (0.0026, 99.9974)."""
    x = 100 * v
    if not math.isfinite(x) or x in (0.0, 100.0):
        return f"{x:g}"
    d = 2
    while d < 6 and round(x, d) in (0.0, 100.0):
        d += 1
    return f"{x:.{d}f}"
