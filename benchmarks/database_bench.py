"""Databases, feeds `make bench` section databases (results/results-2026-11-22.md).

Build time, size and entries; range and label query throughput; paper 000 Table 5 recomputed."""
from __future__ import annotations

import math
import os
import tempfile
import time

import numpy as np
from numba import njit

from startrack._kernels.database import kvector_range, label_search, quadratic_range


@njit(cache=True)
def _many_linear(kvector, m, q, lo, hi):
    total = 0
    for i in range(lo.shape[0]):
        s, e = kvector_range(kvector, m, q, lo[i], hi[i])
        total += e - s
    return total


@njit(cache=True)
def _many_quadratic(kquad, p1, p2, p3, lo, hi):
    total = 0
    for i in range(lo.shape[0]):
        s, e = quadratic_range(kquad, p1, p2, p3, lo[i], hi[i])
        total += e - s
    return total


@njit(cache=True)
def _many_binary(values, lo, hi):
    total = 0
    for i in range(lo.shape[0]):
        s = np.searchsorted(values, lo[i], side="left")
        e = np.searchsorted(values, hi[i], side="right")
        total += e - s
    return total


@njit(cache=True)
def _many_labels(labels, queries, guesses, radius):
    total = 0
    for i in range(queries.shape[0]):
        s, e = label_search(labels, queries[i], guesses[i], radius)
        total += e - s
    return total


def builds():
    from startrack.catalog import load_catalog
    from startrack.kvector import build_kvector, max_separation_deg, save_kvector
    from startrack.labels import build_labels, save_labels

    cat = load_catalog()
    rows = []
    dbs = {}
    with tempfile.TemporaryDirectory() as tmp:
        for name, fov, lo, hi, paper in (("(a) 20 deg, mag <= 5.0 (paper 003)", 20.0, None, 5.0,
                                          "1604 BSC stars -> 44,234 pairs (pairs < 20 deg)"),
                                         ("(b) 8 deg, mag 2.5-6.59 (paper 000)", 8.0, 2.5, 6.59,
                                          "triangle database 1.12 MB (Table 3)")):
            c = cat.filter_magnitude(lo, hi)
            build_kvector(c, max_separation_deg(fov))  # warm the JIT cache
            t0 = time.perf_counter()
            db = build_kvector(c, max_separation_deg(fov))
            dt = time.perf_counter() - t0
            p = os.path.join(tmp, "db.h5")
            save_kvector(db, p)
            size = os.path.getsize(p) / 1e6
            n20 = int(np.sum(db.pair_cos >= math.cos(math.radians(fov))))
            rows.append([name, f"{dt:.2f} s", f"{size:.2f} MB", f"{db.n_stars} stars, {db.n_pairs} pairs "
                         f"(< {db.max_angle_deg:.1f} deg); {n20} pairs < {fov:g} deg", paper])
            dbs[name[:3]] = db
        c = cat.filter_magnitude(None, 5.2)
        t0 = time.perf_counter()
        lab = build_labels(c, 24.0)
        dt = time.perf_counter() - t0
        p = os.path.join(tmp, "labels.h5")
        save_labels(lab, p)
        rows.append(["(c) labels 24 deg, mag 5.2, 8 stars, groups of 4, r = 2, 1 deg", f"{dt:.2f} s",
                     f"{os.path.getsize(p) / 1e6:.2f} MB",
                     f"{lab.params['combinations']} groups ({lab.params['distinct_labels']} distinct labels) of "
                     f"{lab.n_stars if hasattr(lab, 'n_stars') else len(lab.star_id)} stars, "
                     f"{lab.params['boresights']} boresights",
                     "258,474 combinations, 4.1 MB (2055 stars)"])
        dbs["labels"] = lab
    return rows, dbs


def queries(db, n=200000, seed=0, eps_arcsec=15.0):
    rng = np.random.default_rng(seed)
    ang = np.radians(rng.uniform(0.2, db.max_angle_deg - 0.2, n))
    eps = math.radians(eps_arcsec / 3600)
    lo = np.cos(ang + eps)
    hi = np.cos(ang - eps)
    out = []
    for name, fn, args in (
        ("k-vector (linear)", _many_linear, (db.kvector, db.line[0], db.line[1], lo, hi)),
        ("quadratic (paper 000)", _many_quadratic, (db.kquad, *db.quad, lo, hi)),
        ("binary search (np.searchsorted)", _many_binary, (db.pair_cos, lo, hi)),
    ):
        fn(*args)
        t0 = time.perf_counter()
        scanned = fn(*args)
        dt = time.perf_counter() - t0
        out.append([name, f"{n / dt / 1e6:.2f} M/s", f"{scanned / n:.2f}"])
    truth = _many_binary(db.pair_cos, lo, hi) / n
    return out, truth


def label_queries(lab, n=200000, seed=1):
    rng = np.random.default_rng(seed)
    pick = rng.integers(0, len(lab.label), n)
    q = lab.label[pick]
    t0 = time.perf_counter()
    guesses = np.rint(np.polyval(lab.trend, q / lab.trend_scale)).astype(np.int64)
    _many_labels(lab.label, q, guesses, lab.trend_radius)
    t0 = time.perf_counter()
    guesses = np.rint(np.polyval(lab.trend, q / lab.trend_scale)).astype(np.int64)
    found = _many_labels(lab.label, q, guesses, lab.trend_radius)
    dt = time.perf_counter() - t0
    return n / dt, found / n


def table5(db, eps_deg=0.6, n=20000, seed=2):
    """Paper 000 Table 5 on our database: scanned interval for a query of +-eps around random angles."""
    rng = np.random.default_rng(seed)
    ang = rng.uniform(eps_deg, db.max_angle_deg - eps_deg, n)
    lin, quad, pure, true = [], [], [], []
    for a in ang:
        lo, hi = math.cos(math.radians(a + eps_deg)), math.cos(math.radians(a - eps_deg))
        s, e = db.range_linear(lo, hi)
        lin.append(e - s)
        s, e = db.range_quadratic_pure(lo, hi)
        pure.append(e - s)
        s, e = db.range_quadratic(lo, hi)
        quad.append(e - s)
        true.append(int(np.sum((db.pair_cos >= lo) & (db.pair_cos <= hi))))
    return np.mean(true), np.mean(lin), np.mean(pure), np.mean(quad)
